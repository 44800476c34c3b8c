//! The FMI-LS-BUS 1.0 CAN operations (the layered standard's `fmi3LsBusCan.h` layout): parsed
//! with bounds from an `Rx_Data` binary and emitted into a bounded `Tx_Data` buffer.
//!
//! Every operation starts with an 8-byte header: the operation code (`u32`) and the length of
//! the whole operation, header included (`u32`); all fields are packed and little-endian.
//! A buffer holds zero or more operations back to back. Parsing never reads past the buffer
//! and never trusts a length: a length shorter than the operation's fixed part, longer than
//! the bytes left, or a data length that disagrees with the length is a [`Malformed`] error
//! with its byte offset, and nothing of the buffer is taken (the caller rejects it whole).

use std::fmt;

/// Length of the operation header (op code + length).
pub const HEADER_LEN: usize = 8;
/// CAN Transmit.
pub const OP_CAN_TRANSMIT: u32 = 0x10;
/// CAN FD Transmit.
pub const OP_CANFD_TRANSMIT: u32 = 0x11;
/// CAN XL Transmit.
pub const OP_CANXL_TRANSMIT: u32 = 0x12;
/// Confirm: the frame with this identifier was carried.
pub const OP_CONFIRM: u32 = 0x20;
/// Arbitration Lost: the frame was discarded by the bus simulation.
pub const OP_ARBITRATION_LOST: u32 = 0x30;
/// Bus Error.
pub const OP_BUS_ERROR: u32 = 0x31;
/// Configuration (bit rates, arbitration-lost behaviour).
pub const OP_CONFIGURATION: u32 = 0x40;
/// Status of a node (error active / passive / bus off).
pub const OP_STATUS: u32 = 0x41;
/// Wakeup.
pub const OP_WAKEUP: u32 = 0x42;

/// Largest payload of a classic CAN frame.
pub const CAN_MAX_DATA: usize = 8;
/// Largest payload of a CAN FD frame.
pub const CANFD_MAX_DATA: usize = 64;
/// Largest payload of a CAN XL frame.
pub const CANXL_MAX_DATA: usize = 2048;

/// Bus error codes of the Bus Error operation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BusErrorCode {
    /// A sender read back a different bit.
    Bit,
    /// Six equal bits in a row.
    BitStuffing,
    /// A fixed-form field was violated.
    Form,
    /// The CRC did not match.
    Crc,
    /// No node acknowledged the frame.
    Ack,
    /// An error frame was itself disturbed.
    BrokenErrorFrame,
}

impl BusErrorCode {
    fn from_u8(v: u8) -> Option<Self> {
        Some(match v {
            1 => Self::Bit,
            2 => Self::BitStuffing,
            3 => Self::Form,
            4 => Self::Crc,
            5 => Self::Ack,
            6 => Self::BrokenErrorFrame,
            _ => return None,
        })
    }
    fn to_u8(self) -> u8 {
        match self {
            Self::Bit => 1,
            Self::BitStuffing => 2,
            Self::Form => 3,
            Self::Crc => 4,
            Self::Ack => 5,
            Self::BrokenErrorFrame => 6,
        }
    }
}

/// The error state a Status operation reports.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CanStatus {
    /// Error active.
    ErrorActive,
    /// Error passive.
    ErrorPassive,
    /// Bus off.
    BusOff,
}

impl CanStatus {
    fn from_u8(v: u8) -> Option<Self> {
        Some(match v {
            1 => Self::ErrorActive,
            2 => Self::ErrorPassive,
            3 => Self::BusOff,
            _ => return None,
        })
    }
    fn to_u8(self) -> u8 {
        match self {
            Self::ErrorActive => 1,
            Self::ErrorPassive => 2,
            Self::BusOff => 3,
        }
    }
}

/// What to do with a frame that lost arbitration (Configuration parameter 4).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ArbitrationLostBehavior {
    /// The bus simulation keeps the frame and sends it again.
    BufferAndRetransmit,
    /// The bus simulation drops the frame and sends Arbitration Lost.
    DiscardAndNotify,
}

/// One parameter of a Configuration operation (exactly one per operation).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Config {
    /// Classic CAN bit rate, bit/s.
    CanBaudrate(u32),
    /// CAN FD data-phase bit rate, bit/s.
    CanFdBaudrate(u32),
    /// CAN XL data-phase bit rate, bit/s.
    CanXlBaudrate(u32),
    /// Arbitration-lost behaviour.
    ArbitrationLost(ArbitrationLostBehavior),
}

/// One LS-BUS CAN operation, borrowing its payload from the parsed buffer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Op<'a> {
    /// A classic CAN frame (`ide`: 29-bit identifier; `rtr`: remote frame).
    Transmit {
        /// Identifier.
        id: u32,
        /// Extended (29-bit) identifier.
        ide: bool,
        /// Remote transmission request.
        rtr: bool,
        /// Payload (0–8 bytes; a remote frame's data length is its DLC, no bytes follow).
        data: &'a [u8],
        /// The data length field (for a remote frame: the requested DLC).
        dlc: u16,
    },
    /// A CAN FD frame (recognised; a classic CAN node does not take it).
    FdTransmit {
        /// Identifier.
        id: u32,
        /// Extended identifier.
        ide: bool,
        /// Payload.
        data: &'a [u8],
    },
    /// A CAN XL frame (recognised; a classic CAN node does not take it).
    XlTransmit {
        /// Identifier.
        id: u32,
        /// Payload.
        data: &'a [u8],
    },
    /// The frame with this identifier was carried.
    Confirm {
        /// Identifier.
        id: u32,
    },
    /// The frame with this identifier lost arbitration and was discarded.
    ArbitrationLost {
        /// Identifier.
        id: u32,
    },
    /// A bus error.
    BusError {
        /// Identifier of the frame concerned.
        id: u32,
        /// What went wrong.
        code: BusErrorCode,
        /// This node detected it first (primary error flag) or reacted to it (secondary).
        primary: bool,
        /// The error concerns a frame this node sent.
        is_sender: bool,
    },
    /// A configuration parameter.
    Configuration(Config),
    /// A node's error state.
    Status(CanStatus),
    /// A wakeup.
    Wakeup,
}

/// Why a buffer of operations was refused, with the byte offset of the operation.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Malformed {
    /// Offset of the operation's header in the buffer.
    pub offset: usize,
    /// What is wrong.
    pub reason: String,
}

impl fmt::Display for Malformed {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "malformed LS-BUS operation at byte {}: {}",
            self.offset, self.reason
        )
    }
}

impl std::error::Error for Malformed {}

fn u16_at(b: &[u8], i: usize) -> u16 {
    u16::from_le_bytes([b[i], b[i + 1]])
}
fn u32_at(b: &[u8], i: usize) -> u32 {
    u32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]])
}

/// Parses every operation of `buf`; the first malformed one refuses the whole buffer.
pub fn parse(buf: &[u8]) -> Result<Vec<Op<'_>>, Malformed> {
    let mut ops = Vec::new();
    let mut at = 0;
    while at < buf.len() {
        let (op, len) = parse_one(&buf[at..]).map_err(|reason| Malformed { offset: at, reason })?;
        ops.push(op);
        at += len;
    }
    Ok(ops)
}

/// Parses the operation at the start of `b`: the operation and its length.
fn parse_one(b: &[u8]) -> Result<(Op<'_>, usize), String> {
    if b.len() < HEADER_LEN {
        return Err(format!(
            "{} bytes left, shorter than the 8-byte header",
            b.len()
        ));
    }
    let code = u32_at(b, 0);
    let len = u32_at(b, 4) as usize;
    if len > b.len() {
        return Err(format!(
            "length {len} runs past the buffer ({} bytes left)",
            b.len()
        ));
    }
    let b = &b[..len];
    let need = |n: usize, what: &str| {
        if len < n {
            Err(format!(
                "{what}: length {len} below its fixed part of {n} bytes"
            ))
        } else {
            Ok(())
        }
    };
    let exact = |n: usize, what: &str| {
        if len != n {
            Err(format!("{what}: length {len}, the operation has {n} bytes"))
        } else {
            Ok(())
        }
    };
    let flag = |v: u8, what: &str| match v {
        0 => Ok(false),
        1 => Ok(true),
        _ => Err(format!("{what} is {v}, neither 0 nor 1")),
    };
    let op = match code {
        OP_CAN_TRANSMIT => {
            need(16, "CAN Transmit")?;
            let id = u32_at(b, 8);
            let ide = flag(b[12], "CAN Transmit ide")?;
            let rtr = flag(b[13], "CAN Transmit rtr")?;
            let dlc = u16_at(b, 14);
            check_id(id, ide)?;
            if dlc as usize > CAN_MAX_DATA {
                return Err(format!("CAN Transmit data length {dlc} above 8"));
            }
            // A remote frame carries no data: its data length is the DLC it asks for.
            let carried = if rtr { 0 } else { dlc as usize };
            exact(16 + carried, "CAN Transmit")?;
            Op::Transmit {
                id,
                ide,
                rtr,
                data: &b[16..],
                dlc,
            }
        }
        OP_CANFD_TRANSMIT => {
            need(17, "CAN FD Transmit")?;
            let id = u32_at(b, 8);
            let ide = flag(b[12], "CAN FD Transmit ide")?;
            let dl = u16_at(b, 15) as usize;
            check_id(id, ide)?;
            if dl > CANFD_MAX_DATA {
                return Err(format!("CAN FD Transmit data length {dl} above 64"));
            }
            exact(17 + dl, "CAN FD Transmit")?;
            Op::FdTransmit {
                id,
                ide,
                data: &b[17..],
            }
        }
        OP_CANXL_TRANSMIT => {
            need(22, "CAN XL Transmit")?;
            let id = u32_at(b, 8);
            let dl = u16_at(b, 20) as usize;
            if dl > CANXL_MAX_DATA {
                return Err(format!("CAN XL Transmit data length {dl} above 2048"));
            }
            exact(22 + dl, "CAN XL Transmit")?;
            Op::XlTransmit { id, data: &b[22..] }
        }
        OP_CONFIRM => {
            exact(12, "Confirm")?;
            Op::Confirm { id: u32_at(b, 8) }
        }
        OP_ARBITRATION_LOST => {
            exact(12, "Arbitration Lost")?;
            Op::ArbitrationLost { id: u32_at(b, 8) }
        }
        OP_BUS_ERROR => {
            exact(15, "Bus Error")?;
            let code = BusErrorCode::from_u8(b[12])
                .ok_or_else(|| format!("Bus Error code {} unknown", b[12]))?;
            let primary = match b[13] {
                1 => true,
                2 => false,
                v => return Err(format!("Bus Error flag {v} unknown")),
            };
            Op::BusError {
                id: u32_at(b, 8),
                code,
                primary,
                is_sender: flag(b[14], "Bus Error isSender")?,
            }
        }
        OP_CONFIGURATION => {
            need(10, "Configuration")?;
            let kind = b[8];
            let cfg = match kind {
                1..=3 => {
                    // The union holds a u32 bit rate; 13 bytes (`fmi3LsBusCanOperationConfiguration`).
                    exact(13, "Configuration (baud rate)")?;
                    let rate = u32_at(b, 9);
                    if rate == 0 {
                        return Err("Configuration baud rate 0".into());
                    }
                    match kind {
                        1 => Config::CanBaudrate(rate),
                        2 => Config::CanFdBaudrate(rate),
                        _ => Config::CanXlBaudrate(rate),
                    }
                }
                4 => {
                    // Importers write 10 (the byte alone) or 13 (the union's size): both accepted.
                    if len != 10 && len != 13 {
                        return Err(format!(
                            "Configuration (arbitration lost behaviour): length {len}, expected 10 or 13"
                        ));
                    }
                    Config::ArbitrationLost(match b[9] {
                        1 => ArbitrationLostBehavior::BufferAndRetransmit,
                        2 => ArbitrationLostBehavior::DiscardAndNotify,
                        v => {
                            return Err(format!("arbitration lost behaviour {v} unknown"));
                        }
                    })
                }
                v => return Err(format!("Configuration parameter type {v} unknown")),
            };
            Op::Configuration(cfg)
        }
        OP_STATUS => {
            exact(9, "Status")?;
            Op::Status(
                CanStatus::from_u8(b[8]).ok_or_else(|| format!("Status kind {} unknown", b[8]))?,
            )
        }
        OP_WAKEUP => {
            exact(8, "Wakeup")?;
            Op::Wakeup
        }
        c => return Err(format!("operation code 0x{c:X} is not a CAN operation")),
    };
    Ok((op, len))
}

fn check_id(id: u32, ide: bool) -> Result<(), String> {
    let max = if ide { 0x1FFF_FFFF } else { 0x7FF };
    if id > max {
        Err(format!(
            "identifier 0x{id:X} above the {}-bit range",
            if ide { 29 } else { 11 }
        ))
    } else {
        Ok(())
    }
}

/// The buffer did not have room for an operation (nothing of it was written).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Full;

/// A bounded buffer that operations are written into (the FMU's `Tx_Data`).
#[derive(Debug, Clone)]
pub struct TxBuffer {
    buf: Vec<u8>,
    cap: usize,
}

impl TxBuffer {
    /// An empty buffer that never grows past `cap` bytes.
    pub fn new(cap: usize) -> Self {
        Self {
            buf: Vec::with_capacity(cap),
            cap,
        }
    }

    /// The operations written so far.
    pub fn bytes(&self) -> &[u8] {
        &self.buf
    }

    /// No operation written.
    pub fn is_empty(&self) -> bool {
        self.buf.is_empty()
    }

    /// Forgets every operation (after the importer read them).
    pub fn clear(&mut self) {
        self.buf.clear();
    }

    /// Appends one operation whole, or nothing if it does not fit ([`Full`]).
    /// Data longer than the kind of frame carries is refused as [`Full`] too.
    pub fn push(&mut self, op: &Op<'_>) -> Result<(), Full> {
        let len = encoded_len(op).ok_or(Full)?;
        if self.buf.len() + len > self.cap {
            return Err(Full);
        }
        let start = self.buf.len();
        encode(op, len, &mut self.buf);
        debug_assert_eq!(self.buf.len() - start, len);
        Ok(())
    }
}

/// The encoded length of `op`, or `None` if its payload is too long for its kind.
pub fn encoded_len(op: &Op<'_>) -> Option<usize> {
    Some(match op {
        Op::Transmit { rtr, data, dlc, .. } => {
            if *rtr {
                if *dlc as usize > CAN_MAX_DATA || !data.is_empty() {
                    return None;
                }
                16
            } else {
                if data.len() > CAN_MAX_DATA {
                    return None;
                }
                16 + data.len()
            }
        }
        Op::FdTransmit { data, .. } if data.len() <= CANFD_MAX_DATA => 17 + data.len(),
        Op::XlTransmit { data, .. } if data.len() <= CANXL_MAX_DATA => 22 + data.len(),
        Op::FdTransmit { .. } | Op::XlTransmit { .. } => return None,
        Op::Confirm { .. } | Op::ArbitrationLost { .. } => 12,
        Op::BusError { .. } => 15,
        Op::Configuration(_) => 13,
        Op::Status(_) => 9,
        Op::Wakeup => 8,
    })
}

fn encode(op: &Op<'_>, len: usize, out: &mut Vec<u8>) {
    let code = match op {
        Op::Transmit { .. } => OP_CAN_TRANSMIT,
        Op::FdTransmit { .. } => OP_CANFD_TRANSMIT,
        Op::XlTransmit { .. } => OP_CANXL_TRANSMIT,
        Op::Confirm { .. } => OP_CONFIRM,
        Op::ArbitrationLost { .. } => OP_ARBITRATION_LOST,
        Op::BusError { .. } => OP_BUS_ERROR,
        Op::Configuration(_) => OP_CONFIGURATION,
        Op::Status(_) => OP_STATUS,
        Op::Wakeup => OP_WAKEUP,
    };
    out.extend_from_slice(&code.to_le_bytes());
    out.extend_from_slice(&(len as u32).to_le_bytes());
    match *op {
        Op::Transmit {
            id,
            ide,
            rtr,
            data,
            dlc,
        } => {
            out.extend_from_slice(&id.to_le_bytes());
            out.push(ide as u8);
            out.push(rtr as u8);
            let dl = if rtr { dlc } else { data.len() as u16 };
            out.extend_from_slice(&dl.to_le_bytes());
            out.extend_from_slice(data);
        }
        Op::FdTransmit { id, ide, data } => {
            out.extend_from_slice(&id.to_le_bytes());
            out.extend_from_slice(&[ide as u8, 0, 0]);
            out.extend_from_slice(&(data.len() as u16).to_le_bytes());
            out.extend_from_slice(data);
        }
        Op::XlTransmit { id, data } => {
            out.extend_from_slice(&id.to_le_bytes());
            out.extend_from_slice(&[0, 0, 0, 0, 0, 0, 0, 0]);
            out.extend_from_slice(&(data.len() as u16).to_le_bytes());
            out.extend_from_slice(data);
        }
        Op::Confirm { id } | Op::ArbitrationLost { id } => out.extend_from_slice(&id.to_le_bytes()),
        Op::BusError {
            id,
            code,
            primary,
            is_sender,
        } => {
            out.extend_from_slice(&id.to_le_bytes());
            out.push(code.to_u8());
            out.push(if primary { 1 } else { 2 });
            out.push(is_sender as u8);
        }
        Op::Configuration(c) => {
            let (kind, word) = match c {
                Config::CanBaudrate(r) => (1u8, r),
                Config::CanFdBaudrate(r) => (2, r),
                Config::CanXlBaudrate(r) => (3, r),
                Config::ArbitrationLost(b) => (
                    4,
                    match b {
                        ArbitrationLostBehavior::BufferAndRetransmit => 1,
                        ArbitrationLostBehavior::DiscardAndNotify => 2,
                    },
                ),
            };
            out.push(kind);
            out.extend_from_slice(&word.to_le_bytes());
        }
        Op::Status(s) => out.push(s.to_u8()),
        Op::Wakeup => {}
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn all_ops() -> Vec<Op<'static>> {
        vec![
            Op::Transmit {
                id: 0x181,
                ide: false,
                rtr: false,
                data: &[1, 2, 3, 4],
                dlc: 4,
            },
            Op::Transmit {
                id: 0x1234_5678 & 0x1FFF_FFFF,
                ide: true,
                rtr: false,
                data: &[],
                dlc: 0,
            },
            Op::Transmit {
                id: 0x701,
                ide: false,
                rtr: true,
                data: &[],
                dlc: 1,
            },
            Op::FdTransmit {
                id: 0x100,
                ide: false,
                data: &[7; 12],
            },
            Op::XlTransmit {
                id: 0x10,
                data: &[9; 20],
            },
            Op::Confirm { id: 0x181 },
            Op::ArbitrationLost { id: 0x281 },
            Op::BusError {
                id: 0x181,
                code: BusErrorCode::Ack,
                primary: true,
                is_sender: true,
            },
            Op::Configuration(Config::CanBaudrate(125_000)),
            Op::Configuration(Config::ArbitrationLost(
                ArbitrationLostBehavior::DiscardAndNotify,
            )),
            Op::Status(CanStatus::ErrorPassive),
            Op::Wakeup,
        ]
    }

    #[test]
    fn every_operation_round_trips_back_to_back() {
        let mut tx = TxBuffer::new(4096);
        for op in all_ops() {
            tx.push(&op).unwrap();
        }
        assert_eq!(parse(tx.bytes()).unwrap(), all_ops());
    }

    #[test]
    fn a_transmit_has_the_spec_layout() {
        let mut tx = TxBuffer::new(64);
        tx.push(&Op::Transmit {
            id: 0x601,
            ide: false,
            rtr: false,
            data: &[0x40, 0x18, 0x10, 0x01],
            dlc: 4,
        })
        .unwrap();
        assert_eq!(
            tx.bytes(),
            &[0x10, 0, 0, 0, 20, 0, 0, 0, 0x01, 0x06, 0, 0, 0, 0, 4, 0, 0x40, 0x18, 0x10, 0x01]
        );
    }

    #[test]
    fn the_buffer_bound_takes_whole_operations_or_none() {
        let op = Op::Confirm { id: 1 };
        let mut tx = TxBuffer::new(20);
        assert_eq!(tx.push(&op), Ok(()));
        assert_eq!(tx.push(&op), Err(Full));
        assert_eq!(tx.bytes().len(), 12);
        let long = Op::Transmit {
            id: 1,
            ide: false,
            rtr: false,
            data: &[0; 9],
            dlc: 9,
        };
        assert_eq!(TxBuffer::new(100).push(&long), Err(Full));
    }

    fn transmit(id: u32, ide: u8, rtr: u8, dl: u16, data: &[u8], len: u32) -> Vec<u8> {
        let mut v = Vec::new();
        v.extend_from_slice(&OP_CAN_TRANSMIT.to_le_bytes());
        v.extend_from_slice(&len.to_le_bytes());
        v.extend_from_slice(&id.to_le_bytes());
        v.extend_from_slice(&[ide, rtr]);
        v.extend_from_slice(&dl.to_le_bytes());
        v.extend_from_slice(data);
        v
    }

    #[test]
    fn malformed_operations_are_refused_with_their_offset() {
        let good = transmit(0x601, 0, 0, 2, &[1, 2], 18);
        assert!(parse(&good).is_ok());
        let cases: Vec<(Vec<u8>, &str)> = vec![
            (vec![0x10, 0, 0], "shorter than the 8-byte header"),
            (
                transmit(0x601, 0, 0, 2, &[1, 2], 19),
                "runs past the buffer",
            ),
            (
                transmit(0x601, 0, 0, 2, &[1, 2, 3], 19),
                "the operation has 18",
            ),
            (transmit(0x601, 0, 0, 9, &[0; 9], 25), "above 8"),
            (transmit(0x801, 0, 0, 0, &[], 16), "above the 11-bit range"),
            (transmit(0x601, 2, 0, 0, &[], 16), "neither 0 nor 1"),
            (transmit(0x601, 0, 0, 0, &[], 4), "below its fixed part"),
            (
                [0x99u32.to_le_bytes(), 8u32.to_le_bytes()].concat(),
                "not a CAN operation",
            ),
            (
                [
                    OP_STATUS.to_le_bytes().as_slice(),
                    &9u32.to_le_bytes(),
                    &[7],
                ]
                .concat(),
                "Status kind 7",
            ),
            (
                [
                    OP_CONFIGURATION.to_le_bytes().as_slice(),
                    &13u32.to_le_bytes(),
                    &[1, 0, 0, 0, 0],
                ]
                .concat(),
                "baud rate 0",
            ),
        ];
        for (bytes, why) in cases {
            let mut buf = good.clone();
            buf.extend_from_slice(&bytes);
            let err = parse(&buf).unwrap_err();
            assert_eq!(err.offset, good.len(), "{why}: {err}");
            assert!(err.reason.contains(why), "{why}: {err}");
        }
        // A zero length would loop for ever if it were taken: it is below the header.
        let zero = [OP_WAKEUP.to_le_bytes(), 0u32.to_le_bytes()].concat();
        assert!(parse(&zero).unwrap_err().reason.contains("Wakeup"));
    }

    #[test]
    fn every_truncation_of_valid_operations_is_refused_not_panicking() {
        let mut tx = TxBuffer::new(4096);
        for op in all_ops() {
            tx.push(&op).unwrap();
        }
        let all = tx.bytes();
        for cut in 0..all.len() {
            let r = parse(&all[..cut]);
            // Cuts at an operation boundary parse; every other cut is refused.
            if let Ok(ops) = r {
                let mut again = TxBuffer::new(4096);
                for op in &ops {
                    again.push(op).unwrap();
                }
                assert_eq!(again.bytes(), &all[..cut]);
            }
        }
    }
}
