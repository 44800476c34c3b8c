use super::{abort_payload, ObjectAccess};
use crate::od::Abort;
use crate::wire::{Duration, Instant};

/// Time after which an unfinished segmented / block transfer is aborted (0x05040000).
pub const SDO_TIMEOUT: Duration = Duration::from_millis(1000);

/// The SDO server state machine.
#[derive(Clone, Debug, Default)]
pub struct SdoServer {
    /// Requests ignored because their DLC was not 8.
    pub bad_dlc: u32,
}

impl SdoServer {
    /// A server with no transfer in progress.
    pub fn new() -> Self {
        SdoServer::default()
    }

    /// Aborts any transfer in progress without sending anything (NMT reset).
    pub fn reset(&mut self) {}

    /// Handles one request frame's data (any length; DLC ≠ 8 is ignored and counted).
    /// Returns the response payload, if one is due.
    pub fn handle(
        &mut self,
        data: &[u8],
        _now: Instant,
        od: &mut dyn ObjectAccess,
    ) -> Option<[u8; 8]> {
        let Ok(req) = <[u8; 8]>::try_from(data) else {
            self.bad_dlc = self.bad_dlc.wrapping_add(1);
            return None;
        };
        let index = u16::from_le_bytes([req[1], req[2]]);
        let sub = req[3];
        let r = match req[0] >> 5 {
            1 => self.download_initiate(&req, index, sub, od),
            2 => self.upload_initiate(index, sub, od),
            4 => return None, // abort from the client: nothing to answer
            _ => Err(Abort::InvalidCommand),
        };
        Some(r.unwrap_or_else(|a| abort_payload(index, sub, a)))
    }

    fn upload_initiate(
        &mut self,
        index: u16,
        sub: u8,
        od: &mut dyn ObjectAccess,
    ) -> Result<[u8; 8], Abort> {
        let size = od.upload_size(index, sub)?;
        if size > 4 || size == 0 {
            return Err(Abort::UnsupportedAccess);
        }
        let mut r = [0u8; 8];
        od.read(index, sub, 0, &mut r[4..8])?;
        r[0] = 0x43 | ((4 - size as u8) << 2);
        r[1..3].copy_from_slice(&index.to_le_bytes());
        r[3] = sub;
        Ok(r)
    }

    fn download_initiate(
        &mut self,
        req: &[u8; 8],
        index: u16,
        sub: u8,
        od: &mut dyn ObjectAccess,
    ) -> Result<[u8; 8], Abort> {
        let cmd = req[0];
        if cmd & 0x02 == 0 {
            return Err(Abort::UnsupportedAccess);
        }
        let fixed = od.download_size(index, sub)?;
        let len = if cmd & 0x01 != 0 {
            4 - ((cmd >> 2) & 3) as usize
        } else {
            fixed.unwrap_or(4).min(4)
        };
        od.write(index, sub, &req[4..4 + len])?;
        let i = index.to_le_bytes();
        Ok([0x60, i[0], i[1], sub, 0, 0, 0, 0])
    }

    /// The deadline of a transfer in progress.
    pub fn poll_timeout(&self) -> Option<Instant> {
        None
    }

    /// Aborts a transfer whose deadline passed; returns the abort payload.
    pub fn handle_timeout(&mut self, _now: Instant) -> Option<[u8; 8]> {
        None
    }
}
