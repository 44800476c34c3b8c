//! A small CiA 301 SDO client: expedited and segmented upload / download with toggle checking.
//!
//! It talks to one server (`0x600 + node` → `0x580 + node`) through any [`Transport`]. Frames
//! that are not answers of the transfer in progress are either dropped or, when asked with
//! [`SdoClient::keep_other_frames`], kept for the caller (the monitor must not lose PDOs while
//! it reads a node's configuration).

use std::fmt;
use std::io;
use std::time::{Duration, Instant};

use canpos_host::transport::{RxFrame, Transport};
use canpos_stack::od::Abort;
use canpos_stack::sdo::wire::{Mux, Request, Response, SEGMENT_DATA};
use canpos_stack::{cob, Frame};

use crate::common::{parse_i64, parse_u64};

/// The SDO timeout of canpos's tools, ms: `canpos sdo --timeout`'s default and the dashboard's
/// (D45): a node that answers one answers the other.
pub const DEFAULT_TIMEOUT_MS: u64 = 1000;

/// Largest segmented upload accepted; a server that keeps sending beyond that is aborted rather
/// than letting a broken device exhaust memory.
pub const MAX_UPLOAD: usize = 1 << 20;

/// Abort codes the client itself sends (CiA 301).
mod code {
    pub const TOGGLE: u32 = 0x0503_0000;
    pub const TIMEOUT: u32 = 0x0504_0000;
    pub const INVALID_COMMAND: u32 = 0x0504_0001;
    pub const OUT_OF_MEMORY: u32 = 0x0504_0005;
}

/// Why an SDO transfer failed.
#[derive(Debug)]
pub enum SdoError {
    /// The server aborted the transfer with this CiA 301 abort code.
    Abort(u32),
    /// No answer within the timeout (the client sent abort 0x05040000).
    Timeout,
    /// The server answered something that does not fit the protocol (the client aborted).
    Protocol(String),
    /// The transport failed.
    Io(io::Error),
}

/// The CiA 301 meaning of an abort code, or a note that the code is not a standard one.
pub fn abort_meaning(code: u32) -> &'static str {
    Abort::from_code(code)
        .map(Abort::meaning)
        .unwrap_or("unknown (manufacturer-specific) abort code")
}

impl fmt::Display for SdoError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            SdoError::Abort(c) => write!(f, "SDO abort 0x{c:08X}: {}", abort_meaning(*c)),
            SdoError::Timeout => f.write_str("SDO timeout: no answer from the node"),
            SdoError::Protocol(m) => write!(f, "SDO protocol error: {m}"),
            SdoError::Io(e) => write!(f, "CAN transport error: {e}"),
        }
    }
}

impl std::error::Error for SdoError {}

impl From<io::Error> for SdoError {
    fn from(e: io::Error) -> Self {
        SdoError::Io(e)
    }
}

/// An SDO client for one node on a bus.
pub struct SdoClient<'a> {
    bus: &'a mut dyn Transport,
    node: u8,
    timeout: Duration,
    other: Option<Vec<RxFrame>>,
}

impl<'a> SdoClient<'a> {
    /// A client for `node` (1…127) that waits `timeout` for each answer.
    pub fn new(bus: &'a mut dyn Transport, node: u8, timeout: Duration) -> Self {
        SdoClient {
            bus,
            node,
            timeout,
            other: None,
        }
    }

    /// Keeps every frame received during transfers that is not an answer (see
    /// [`SdoClient::take_other_frames`]) instead of dropping it.
    pub fn keep_other_frames(mut self) -> Self {
        self.other = Some(Vec::new());
        self
    }

    /// The frames kept since the last call (empty unless [`SdoClient::keep_other_frames`]).
    pub fn take_other_frames(&mut self) -> Vec<RxFrame> {
        self.other.as_mut().map(std::mem::take).unwrap_or_default()
    }

    fn rx_id(&self) -> u32 {
        u32::from(cob::SDO_TX) + self.node as u32
    }

    fn send(&mut self, req: Request) -> io::Result<()> {
        let f = Frame::std8(cob::SDO_RX + self.node as u16, req.emit());
        self.bus.send(&f)
    }

    /// Best-effort abort: the transfer is failing anyway, so a send error is not reported over
    /// the original cause.
    fn send_abort(&mut self, index: u16, sub: u8, code: u32) {
        let mux = Mux { index, sub };
        let _ = self.send(Request::Abort { mux, code });
    }

    /// Sends `req` and waits for the server's answer to the transfer of `index`/`sub`: its
    /// command byte (for messages) and what it says.
    ///
    /// `initiate`: the answer must carry the multiplexer (initiate responses); answers with
    /// another multiplexer are stale (e.g. a late answer to an earlier, timed-out request) and
    /// are skipped. Aborts are recognised by multiplexer (or an all-zero one, which some
    /// devices send for malformed requests).
    fn request(
        &mut self,
        req: Request,
        index: u16,
        sub: u8,
        initiate: bool,
    ) -> Result<(u8, Response), SdoError> {
        self.send(req)?;
        let deadline = Instant::now() + self.timeout;
        let ours_mux = Mux { index, sub };
        loop {
            let Some(rx) = self.bus.recv_deadline(deadline)? else {
                self.send_abort(index, sub, code::TIMEOUT);
                return Err(SdoError::Timeout);
            };
            let f = rx.frame;
            let ours = !f.is_extended() && !f.is_remote() && f.id() == self.rx_id();
            let Some(d) = ours.then(|| <[u8; 8]>::try_from(f.data()).ok()).flatten() else {
                if let Some(o) = self.other.as_mut() {
                    o.push(rx);
                }
                continue;
            };
            let mux_matches = Mux::from_frame(&d) == ours_mux;
            let r = Response::parse(&d);
            if let Response::Abort { mux, code } = r {
                if mux_matches || mux == Mux::default() {
                    return Err(SdoError::Abort(code));
                }
                continue;
            }
            if initiate && !mux_matches {
                continue;
            }
            return Ok((d[0], r));
        }
    }

    fn protocol(&mut self, index: u16, sub: u8, code: u32, msg: String) -> SdoError {
        self.send_abort(index, sub, code);
        SdoError::Protocol(msg)
    }

    /// Reads object `index`/`sub` (expedited or segmented, as the server chooses).
    pub fn upload(&mut self, index: u16, sub: u8) -> Result<Vec<u8>, SdoError> {
        let mux = Mux { index, sub };
        let (c, r) = self.request(Request::UploadInitiate { mux }, index, sub, true)?;
        let Response::UploadInitiate {
            expedited,
            size,
            data: first,
            ..
        } = r
        else {
            let m = format!("unexpected answer 0x{c:02X} to upload initiate");
            return Err(self.protocol(index, sub, code::INVALID_COMMAND, m));
        };
        if expedited {
            // Without the size bit the size is unspecified; all 4 bytes are data.
            let n = size.unwrap_or(4) as usize;
            return Ok(first[..n].to_vec());
        }
        let size = size.map(|s| s as usize);
        if size.is_some_and(|s| s > MAX_UPLOAD) {
            let m = format!("announced size {} exceeds {MAX_UPLOAD}", size.unwrap_or(0));
            return Err(self.protocol(index, sub, code::OUT_OF_MEMORY, m));
        }
        let mut data = Vec::with_capacity(size.unwrap_or(0));
        let mut toggle = false;
        loop {
            let (c, r) = self.request(Request::UploadSegment { toggle }, index, sub, false)?;
            let Response::UploadSegment {
                toggle: t,
                unused,
                last,
                data: seg,
            } = r
            else {
                let m = format!("unexpected answer 0x{c:02X} to upload segment");
                return Err(self.protocol(index, sub, code::INVALID_COMMAND, m));
            };
            if t != toggle {
                let m = "toggle bit not alternated in upload segment".to_string();
                return Err(self.protocol(index, sub, code::TOGGLE, m));
            }
            data.extend_from_slice(&seg[..SEGMENT_DATA - unused as usize]);
            if data.len() > MAX_UPLOAD {
                let m = format!("upload longer than {MAX_UPLOAD} bytes");
                return Err(self.protocol(index, sub, code::OUT_OF_MEMORY, m));
            }
            if last {
                break;
            }
            toggle = !toggle;
        }
        if let Some(s) = size {
            if s != data.len() {
                // The transfer is complete on the server's side: nothing left to abort.
                return Err(SdoError::Protocol(format!(
                    "server announced {s} bytes but sent {}",
                    data.len()
                )));
            }
        }
        Ok(data)
    }

    /// Writes `data` to object `index`/`sub`: expedited up to 4 bytes, segmented above.
    pub fn download(&mut self, index: u16, sub: u8, data: &[u8]) -> Result<(), SdoError> {
        let mux = Mux { index, sub };
        if (1..=4).contains(&data.len()) {
            let mut first = [0u8; 4];
            first[..data.len()].copy_from_slice(data);
            let req = Request::DownloadInitiate {
                mux,
                expedited: true,
                size: Some(data.len() as u32),
                data: first,
            };
            let (c, r) = self.request(req, index, sub, true)?;
            if !matches!(r, Response::DownloadInitiate { .. }) {
                let m = format!("unexpected answer 0x{c:02X} to download");
                return Err(self.protocol(index, sub, code::INVALID_COMMAND, m));
            }
            return Ok(());
        }
        let Ok(size) = u32::try_from(data.len()) else {
            return Err(SdoError::Protocol("value too long for SDO".into()));
        };
        let req = Request::DownloadInitiate {
            mux,
            expedited: false,
            size: Some(size),
            data: size.to_le_bytes(),
        };
        let (c, r) = self.request(req, index, sub, true)?;
        if !matches!(r, Response::DownloadInitiate { .. }) {
            let m = format!("unexpected answer 0x{c:02X} to download initiate");
            return Err(self.protocol(index, sub, code::INVALID_COMMAND, m));
        }
        // An empty value still needs one (empty, last) segment to complete the transfer.
        let chunks: Vec<&[u8]> = if data.is_empty() {
            vec![&[]]
        } else {
            data.chunks(SEGMENT_DATA).collect()
        };
        let mut toggle = false;
        for (i, chunk) in chunks.iter().enumerate() {
            let mut seg = [0u8; SEGMENT_DATA];
            seg[..chunk.len()].copy_from_slice(chunk);
            let req = Request::DownloadSegment {
                toggle,
                unused: (SEGMENT_DATA - chunk.len()) as u8,
                last: i + 1 == chunks.len(),
                data: seg,
            };
            let (c, r) = self.request(req, index, sub, false)?;
            let Response::DownloadSegment { toggle: t } = r else {
                let m = format!("unexpected answer 0x{c:02X} to download segment");
                return Err(self.protocol(index, sub, code::INVALID_COMMAND, m));
            };
            if t != toggle {
                let m = "toggle bit not alternated in download segment answer".to_string();
                return Err(self.protocol(index, sub, code::TOGGLE, m));
            }
            toggle = !toggle;
        }
        Ok(())
    }

    /// Reads an object of at most 4 bytes as an unsigned little-endian number.
    pub fn read_u32(&mut self, index: u16, sub: u8) -> Result<u32, SdoError> {
        let d = self.upload(index, sub)?;
        if d.is_empty() || d.len() > 4 {
            return Err(SdoError::Protocol(format!(
                "{index:04X}:{sub:02X} returned {} bytes, expected 1 to 4",
                d.len()
            )));
        }
        let mut b = [0u8; 4];
        b[..d.len()].copy_from_slice(&d);
        Ok(u32::from_le_bytes(b))
    }
}

/// The value types `canpos sdo` understands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum ValueType {
    /// UNSIGNED8
    U8,
    /// UNSIGNED16
    U16,
    /// UNSIGNED32
    U32,
    /// INTEGER8
    I8,
    /// INTEGER16
    I16,
    /// INTEGER32
    I32,
    /// VISIBLE_STRING
    Str,
    /// raw bytes, written and printed as hex (`DEADBEEF`, `de:ad:be:ef`, `de ad be ef`)
    Bytes,
}

impl ValueType {
    /// Size in bytes of the numeric types.
    pub fn size(self) -> Option<usize> {
        match self {
            ValueType::U8 | ValueType::I8 => Some(1),
            ValueType::U16 | ValueType::I16 => Some(2),
            ValueType::U32 | ValueType::I32 => Some(4),
            ValueType::Str | ValueType::Bytes => None,
        }
    }

    /// Encodes a command-line value (decimal, or hex with `0x`; negative for signed types).
    pub fn encode(self, s: &str) -> Result<Vec<u8>, String> {
        let t = s.trim();
        match self {
            ValueType::Str => Ok(s.as_bytes().to_vec()),
            ValueType::Bytes => parse_hex_bytes(t),
            ValueType::U8 | ValueType::U16 | ValueType::U32 => {
                let v = parse_u64(t).ok_or_else(|| format!("`{s}` is not a number"))?;
                let n = self.size().unwrap_or(4);
                if v >> (8 * n) != 0 {
                    return Err(format!("{v} does not fit {self:?}"));
                }
                Ok(v.to_le_bytes()[..n].to_vec())
            }
            ValueType::I8 | ValueType::I16 | ValueType::I32 => {
                let v = parse_i64(t).ok_or_else(|| format!("`{s}` is not a number"))?;
                let n = self.size().unwrap_or(4);
                let bits = 8 * n as u32;
                let (min, max) = (-(1i64 << (bits - 1)), (1i64 << (bits - 1)) - 1);
                // Hex input is taken as the raw bit pattern (0xFFFF for i16 = -1).
                let hex_pattern = t.starts_with("0x") || t.starts_with("0X");
                if hex_pattern && (v >> bits) == 0 && v >= 0 {
                    return Ok(v.to_le_bytes()[..n].to_vec());
                }
                if v < min || v > max {
                    return Err(format!("{v} does not fit {self:?}"));
                }
                Ok(v.to_le_bytes()[..n].to_vec())
            }
        }
    }

    /// Formats a value read from the device; `Err` when its length does not fit the type.
    pub fn decode(self, d: &[u8]) -> Result<String, String> {
        if let Some(n) = self.size() {
            if d.len() != n {
                return Err(format!(
                    "the device returned {} byte(s), a {self:?} has {n}",
                    d.len()
                ));
            }
        }
        let mut b = [0u8; 8];
        let n = d.len().min(8);
        b[..n].copy_from_slice(&d[..n]);
        let u = u64::from_le_bytes(b);
        Ok(match self {
            ValueType::U8 => format!("{u} (0x{u:02X})"),
            ValueType::U16 => format!("{u} (0x{u:04X})"),
            ValueType::U32 => format!("{u} (0x{u:08X})"),
            ValueType::I8 => format!("{}", d[0] as i8),
            ValueType::I16 => format!("{}", i16::from_le_bytes([d[0], d[1]])),
            ValueType::I32 => format!("{}", i32::from_le_bytes([d[0], d[1], d[2], d[3]])),
            ValueType::Str => String::from_utf8_lossy(d)
                .trim_end_matches('\0')
                .to_string(),
            ValueType::Bytes => hex_string(d),
        })
    }
}

/// How a value read without `--type` is shown: numbers for 1…4 bytes, text when printable,
/// hex otherwise.
pub fn format_auto(d: &[u8]) -> String {
    match d.len() {
        0 => "(empty)".to_string(),
        1..=4 => {
            let mut b = [0u8; 4];
            b[..d.len()].copy_from_slice(d);
            let u = u32::from_le_bytes(b);
            // Short strings (a device name like "C304") travel expedited too: show both.
            if d.len() > 1 && d.iter().all(|c| c.is_ascii_graphic()) {
                let t = String::from_utf8_lossy(d);
                format!("0x{u:0w$X} ({u}) {t:?}", w = d.len() * 2)
            } else {
                format!("0x{u:0w$X} ({u})", w = d.len() * 2)
            }
        }
        _ => {
            let text = d
                .iter()
                .rev()
                .skip_while(|b| **b == 0)
                .all(|b| b.is_ascii_graphic() || *b == b' ');
            if text {
                format!("{:?}", String::from_utf8_lossy(d).trim_end_matches('\0'))
            } else {
                hex_string(d)
            }
        }
    }
}

/// Bytes as upper-case hex pairs separated by spaces.
pub fn hex_string(d: &[u8]) -> String {
    d.iter()
        .map(|b| format!("{b:02X}"))
        .collect::<Vec<_>>()
        .join(" ")
}

fn parse_hex_bytes(s: &str) -> Result<Vec<u8>, String> {
    let s = s.strip_prefix("0x").unwrap_or(s);
    let digits: String = s
        .chars()
        .filter(|c| !matches!(c, ' ' | ':' | '-' | '_'))
        .collect();
    if !digits.len().is_multiple_of(2) || !digits.chars().all(|c| c.is_ascii_hexdigit()) {
        return Err(format!(
            "`{s}` is not a hex byte string (e.g. DEADBEEF or de:ad:be:ef)"
        ));
    }
    (0..digits.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&digits[i..i + 2], 16).map_err(|e| e.to_string()))
        .collect()
}
