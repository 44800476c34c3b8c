//! SDO server (CiA 301 §7.2.4): expedited, segmented and block transfers on 0x600+id /
//! 0x580+id, with the abort codes of SPEC §4.

mod server;
pub mod wire;

pub use server::{SdoServer, TransferKind, Transfers, SDO_BUF_LEN, SDO_TIMEOUT, SERVER_BLKSIZE};

use crate::od::types::Abort;

/// What the SDO server needs from the device: object access with every check applied.
///
/// The device implements it over its dictionary; the checks that belong to one object live in
/// the model table, those that belong to one service (PDO mapping rules, storage signatures) in
/// that service.
pub trait ObjectAccess {
    /// Checks that `index`/`sub` exists and is readable; returns its current size in bytes.
    fn upload_size(&mut self, index: u16, sub: u8) -> Result<usize, Abort>;
    /// Copies the value (from byte `offset` on) into `buf`; returns the bytes copied.
    fn read(&mut self, index: u16, sub: u8, offset: usize, buf: &mut [u8]) -> Result<usize, Abort>;
    /// Checks that `index`/`sub` exists and is writable; returns its size if fixed.
    fn download_size(&mut self, index: u16, sub: u8) -> Result<Option<usize>, Abort>;
    /// Writes a complete value (all checks, then side effects).
    fn write(&mut self, index: u16, sub: u8, data: &[u8]) -> Result<(), Abort>;
    /// An expedited download: [`ObjectAccess::download_size`], then [`ObjectAccess::write`] of
    /// the first `size` bytes of `data` (size not indicated: the object's own size, at most 4).
    /// Implementations may do both in one lookup; the checks and their order stay the same.
    #[inline]
    fn write_expedited(
        &mut self,
        index: u16,
        sub: u8,
        size: Option<u32>,
        data: &[u8; 4],
    ) -> Result<(), Abort> {
        let fixed = self.download_size(index, sub)?;
        let len = match size {
            Some(n) => n as usize,
            None => fixed.unwrap_or(4).min(4),
        };
        self.write(index, sub, data.get(..len).unwrap_or(data))
    }
}

/// Encodes an abort frame's payload.
pub fn abort_payload(index: u16, sub: u8, abort: Abort) -> [u8; 8] {
    let i = index.to_le_bytes();
    let c = abort.code().to_le_bytes();
    [0x80, i[0], i[1], sub, c[0], c[1], c[2], c[3]]
}
