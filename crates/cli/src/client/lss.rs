//! A CiA 305 LSS master: switch state, configure node-id / bit timing, store, inquire,
//! identify and fastscan, on 0x7E5 (master → slaves) / 0x7E4 (slaves → master).

use std::fmt;
use std::io;
use std::time::{Duration, Instant};

use canpos_host::transport::Transport;
use canpos_stack::lss::{
    cs, LssRequest, LssResponse, Part, FASTSCAN_CONFIRM, MODE_CONFIGURATION, MODE_WAITING,
    STATUS_MANUFACTURER, STATUS_OK, STATUS_REFUSED, STATUS_STORAGE_ERROR,
};
use canpos_stack::{cob, Frame};

/// LSS master → slave COB-ID.
pub const LSS_TX: u16 = cob::LSS_RX;
/// LSS slave → master COB-ID.
pub const LSS_RX: u32 = cob::LSS_TX as u32;

/// Index in CiA 305 bit-timing table 0 of a bit rate in kbit/s (the slave's own table).
pub fn bit_timing_index(kbps: u32) -> Option<u8> {
    let kbps = u16::try_from(kbps).ok().filter(|&k| k != 0)?;
    (0..=u8::MAX).find(|&i| canpos_stack::lss::bit_timing_kbps(i) == Some(kbps))
}

/// The 128-bit LSS address (0x1018 sub 1…4).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LssAddress {
    /// Vendor-id.
    pub vendor: u32,
    /// Product code.
    pub product: u32,
    /// Revision number.
    pub revision: u32,
    /// Serial number.
    pub serial: u32,
}

impl LssAddress {
    /// The four parts in LSS sub order (0 vendor … 3 serial).
    pub fn parts(&self) -> [u32; 4] {
        [self.vendor, self.product, self.revision, self.serial]
    }

    fn from_parts(p: [u32; 4]) -> Self {
        LssAddress {
            vendor: p[0],
            product: p[1],
            revision: p[2],
            serial: p[3],
        }
    }
}

impl fmt::Display for LssAddress {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "vendor 0x{:08X} product 0x{:08X} revision 0x{:08X} serial 0x{:08X} ({})",
            self.vendor, self.product, self.revision, self.serial, self.serial
        )
    }
}

/// What [`LssMaster::inquire`] asks for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Inquire {
    /// Vendor-id (0x5A).
    Vendor,
    /// Product code (0x5B).
    Product,
    /// Revision number (0x5C).
    Revision,
    /// Serial number (0x5D).
    Serial,
    /// Node-id (0x5E).
    NodeId,
}

impl Inquire {
    /// The request as the stack's LSS vocabulary names it.
    pub fn wire(self) -> canpos_stack::lss::Inquire {
        use canpos_stack::lss::Inquire as W;
        match self {
            Inquire::Vendor => W::Identity(Part::Vendor),
            Inquire::Product => W::Identity(Part::Product),
            Inquire::Revision => W::Identity(Part::Revision),
            Inquire::Serial => W::Identity(Part::Serial),
            Inquire::NodeId => W::NodeId,
        }
    }

    /// The command specifier.
    pub fn cs(self) -> u8 {
        self.wire().cs()
    }
}

/// Why an LSS service failed.
#[derive(Debug)]
pub enum LssError {
    /// No slave answered within the timeout.
    Timeout,
    /// The transport failed.
    Io(io::Error),
}

impl fmt::Display for LssError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            LssError::Timeout => f.write_str(
                "LSS timeout: no answer (is a node in LSS configuration state? \
                 use `canpos lss switch-global config` or `switch-selective` first)",
            ),
            LssError::Io(e) => write!(f, "CAN transport error: {e}"),
        }
    }
}

impl std::error::Error for LssError {}

impl From<io::Error> for LssError {
    fn from(e: io::Error) -> Self {
        LssError::Io(e)
    }
}

/// The answer of a configure / store service: status and the manufacturer's error byte.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LssStatus {
    /// Error code (0 = success).
    pub code: u8,
    /// Manufacturer-specific error, meaningful when `code` is 0xFF.
    pub spec: u8,
}

impl LssStatus {
    /// Whether the service succeeded.
    pub fn ok(&self) -> bool {
        self.code == 0
    }
}

/// The meaning of an LSS status byte for the service with command specifier `cs`.
pub fn status_meaning(cs: u8, code: u8) -> &'static str {
    match (cs, code) {
        (_, STATUS_OK) => "success",
        (_, STATUS_MANUFACTURER) => "manufacturer-specific error",
        (cs::CONFIGURE_NODE_ID, STATUS_REFUSED) => "node-id out of range",
        (cs::CONFIGURE_BIT_TIMING, STATUS_REFUSED) => "bit timing not supported",
        (cs::STORE_CONFIGURATION, STATUS_REFUSED) => "store configuration not supported",
        (cs::STORE_CONFIGURATION, STATUS_STORAGE_ERROR) => "storage media access error",
        _ => "reserved error code",
    }
}

/// An LSS master on one bus.
pub struct LssMaster<'a> {
    bus: &'a mut dyn Transport,
    timeout: Duration,
}

impl<'a> LssMaster<'a> {
    /// A master that waits `timeout` for each confirmed service's answer.
    pub fn new(bus: &'a mut dyn Transport, timeout: Duration) -> Self {
        LssMaster { bus, timeout }
    }

    fn send(&mut self, r: LssRequest) -> io::Result<()> {
        self.bus.send(&Frame::std8(LSS_TX, r.emit()))
    }

    /// Waits until `deadline` for an LSS answer with the specifier `cs`; other frames are
    /// dropped (nothing else should answer on 0x7E4).
    fn wait(&mut self, cs: Option<u8>, deadline: Instant) -> io::Result<Option<LssResponse>> {
        loop {
            let Some(rx) = self.bus.recv_deadline(deadline)? else {
                return Ok(None);
            };
            let f = rx.frame;
            if f.is_extended() || f.is_remote() || f.id() != LSS_RX {
                continue;
            }
            // A slave always sends 8 bytes; be lenient with short frames but never index past.
            let mut d = [0u8; 8];
            let n = f.data().len().min(8);
            d[..n].copy_from_slice(&f.data()[..n]);
            if n == 0 {
                continue;
            }
            if let Some(r) = LssResponse::parse(&d).filter(|r| Some(r.cs()) == cs) {
                return Ok(Some(r));
            }
        }
    }

    fn confirmed(&mut self, req: LssRequest) -> Result<LssResponse, LssError> {
        // Drop answers that arrived late for an earlier request.
        while self.bus.try_recv()?.is_some() {}
        self.send(req)?;
        let deadline = Instant::now() + self.timeout;
        self.wait(req.answer_cs(), deadline)?
            .ok_or(LssError::Timeout)
    }

    /// A configure or store service and its answer's status.
    fn status(&mut self, req: LssRequest) -> Result<LssStatus, LssError> {
        match self.confirmed(req)? {
            LssResponse::ConfigureNodeId(s)
            | LssResponse::ConfigureBitTiming(s)
            | LssResponse::StoreConfiguration(s) => Ok(LssStatus {
                code: s.code,
                spec: s.spec,
            }),
            // `confirmed` returns only the answer the request names.
            _ => Err(LssError::Timeout),
        }
    }

    /// Switch state global: all slaves to configuration (`true`) or waiting state. Unconfirmed.
    pub fn switch_global(&mut self, configuration: bool) -> Result<(), LssError> {
        let mode = if configuration {
            MODE_CONFIGURATION
        } else {
            MODE_WAITING
        };
        Ok(self.send(LssRequest::SwitchGlobal { mode })?)
    }

    /// Switch state selective: the one slave with this address enters configuration state.
    pub fn switch_selective(&mut self, a: &LssAddress) -> Result<(), LssError> {
        for (part, value) in Part::ALL.into_iter().zip(a.parts()) {
            let req = LssRequest::SwitchSelective { part, value };
            if part != Part::Serial {
                self.send(req)?;
            } else {
                self.confirmed(req)?;
            }
        }
        Ok(())
    }

    /// Configure node-id (1…127, or 0xFF to make the node unconfigured).
    pub fn configure_node_id(&mut self, id: u8) -> Result<LssStatus, LssError> {
        self.status(LssRequest::ConfigureNodeId { node_id: id })
    }

    /// Configure bit timing with table 0 index `index`.
    pub fn configure_bit_timing(&mut self, index: u8) -> Result<LssStatus, LssError> {
        self.status(LssRequest::ConfigureBitTiming { table: 0, index })
    }

    /// Activate bit timing: slaves switch after `delay_ms`, and talk again after another
    /// `delay_ms`. Unconfirmed.
    pub fn activate_bit_timing(&mut self, delay_ms: u16) -> Result<(), LssError> {
        Ok(self.send(LssRequest::ActivateBitTiming { delay_ms })?)
    }

    /// Store configuration (node-id and bit rate).
    pub fn store(&mut self) -> Result<LssStatus, LssError> {
        self.status(LssRequest::StoreConfiguration)
    }

    /// Inquire one identity value or the node-id of the slave in configuration state.
    pub fn inquire(&mut self, what: Inquire) -> Result<u32, LssError> {
        match self.confirmed(LssRequest::Inquire(what.wire()))? {
            LssResponse::NodeId(id) => Ok(u32::from(id)),
            LssResponse::Identity { value, .. } => Ok(value),
            // `confirmed` returns only the answer the request names.
            _ => Err(LssError::Timeout),
        }
    }

    /// Identify non-configured remote slave: whether any slave without a node-id answers.
    pub fn identify_non_configured(&mut self) -> Result<bool, LssError> {
        match self.confirmed(LssRequest::IdentifyNonConfigured) {
            Ok(_) => Ok(true),
            Err(LssError::Timeout) => Ok(false),
            Err(e) => Err(e),
        }
    }

    /// One fastscan step: whether any slave answered "identify slave" (0x4F).
    ///
    /// On a real bus the identical answers of several slaves merge into one frame; on a virtual
    /// bus each arrives separately, so after the first one the master lingers a quarter of the
    /// step time to swallow the duplicates before the next step.
    fn fastscan_step(
        &mut self,
        id: u32,
        bit: u8,
        sub: u8,
        next: u8,
        step: Duration,
    ) -> Result<bool, LssError> {
        let req = LssRequest::Fastscan {
            id_number: id,
            bit_checked: bit,
            sub,
            next,
        };
        while self.bus.try_recv()?.is_some() {}
        self.send(req)?;
        let answer = req.answer_cs();
        let got = self.wait(answer, Instant::now() + step)?.is_some();
        if got {
            let linger = Instant::now() + step / 4;
            while self.wait(answer, linger)?.is_some() {}
        }
        Ok(got)
    }

    /// CiA 305 fastscan: finds the 128-bit address of one non-configured slave bit by bit
    /// (`step` is the wait per step). The slave found is left in configuration state.
    /// `Ok(None)`: no slave answered the initial step.
    pub fn fastscan(&mut self, step: Duration) -> Result<Option<LssAddress>, LssError> {
        // Bit checked 0x80: every non-configured slave resets its scan and answers.
        if !self.fastscan_step(0, FASTSCAN_CONFIRM, 0, 0, step)? {
            return Ok(None);
        }
        let mut parts = [0u32; 4];
        for sub in 0..4u8 {
            let mut id = 0u32;
            for bit in (0..32u8).rev() {
                // Slaves whose bits bit..31 equal `id` answer; no answer means this bit is 1.
                if !self.fastscan_step(id, bit, sub, sub, step)? {
                    id |= 1 << bit;
                }
            }
            // Confirm the full value; the last confirmation (next = 0) selects the slave.
            let next = (sub + 1) % 4;
            if !self.fastscan_step(id, 0, sub, next, step)? {
                // The slave went away or two slaves disturbed each other: give up.
                return Err(LssError::Timeout);
            }
            parts[sub as usize] = id;
        }
        Ok(Some(LssAddress::from_parts(parts)))
    }
}
