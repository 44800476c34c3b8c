//! The master side of the conformance tool: raw frames, NMT master, SYNC producer, guarding
//! requests, timestamped capture, and a full SDO client (expedited, segmented, block with
//! CRC-16) that can also send deliberately wrong frames.

use canpos_encoder::{Fault, Sample, MAX_CHANNELS};
use canpos_models::Model;
use canpos_stack::sdo::wire::crc16;
use canpos_stack::Frame;

use crate::backend::Backend;

/// SDO abort codes as numbers (CONFORMANCE.md "Abort codes used").
pub mod abort {
    /// Toggle bit not alternated.
    pub const TOGGLE: u32 = 0x0503_0000;
    /// SDO protocol timed out.
    pub const TIMEOUT: u32 = 0x0504_0000;
    /// Command specifier not valid or unknown.
    pub const BAD_COMMAND: u32 = 0x0504_0001;
    /// Invalid block size.
    pub const BAD_BLOCK_SIZE: u32 = 0x0504_0002;
    /// Invalid sequence number.
    pub const BAD_SEQUENCE: u32 = 0x0504_0003;
    /// Unsupported access.
    pub const UNSUPPORTED: u32 = 0x0601_0000;
    /// Read of a write-only object.
    pub const WRITE_ONLY: u32 = 0x0601_0001;
    /// Write of a read-only object.
    pub const READ_ONLY: u32 = 0x0601_0002;
    /// Object does not exist.
    pub const NO_OBJECT: u32 = 0x0602_0000;
    /// Object cannot be mapped.
    pub const NOT_MAPPABLE: u32 = 0x0604_0041;
    /// Mapping exceeds the PDO length.
    pub const MAPPING_LENGTH: u32 = 0x0604_0042;
    /// Length mismatch.
    pub const LENGTH: u32 = 0x0607_0010;
    /// Length too high.
    pub const LENGTH_HIGH: u32 = 0x0607_0012;
    /// Length too low.
    pub const LENGTH_LOW: u32 = 0x0607_0013;
    /// Sub-index does not exist.
    pub const NO_SUB: u32 = 0x0609_0011;
    /// Value range exceeded.
    pub const RANGE: u32 = 0x0609_0030;
    /// Value too high.
    pub const TOO_HIGH: u32 = 0x0609_0031;
    /// Value too low.
    pub const TOO_LOW: u32 = 0x0609_0032;
    /// General error.
    pub const GENERAL: u32 = 0x0800_0000;
    /// Cannot store (wrong signature).
    pub const CANNOT_STORE: u32 = 0x0800_0020;
    /// Refused in the present device state.
    pub const WRONG_STATE: u32 = 0x0800_0022;
    /// No data available.
    pub const NO_DATA: u32 = 0x0800_0024;
}

/// NMT command specifiers.
pub mod nmt {
    /// Start remote node.
    pub const START: u8 = 0x01;
    /// Stop remote node.
    pub const STOP: u8 = 0x02;
    /// Enter pre-operational.
    pub const PRE_OP: u8 = 0x80;
    /// Reset node.
    pub const RESET_NODE: u8 = 0x81;
    /// Reset communication.
    pub const RESET_COMM: u8 = 0x82;
}

/// An SDO transfer's outcome: the data, or the abort code the server sent (or
/// [`abort::TIMEOUT`] when it sent nothing, after which the client aborted).
pub type SdoResult<T> = Result<T, u32>;

/// How long the client waits for an SDO answer (the server holds "save" answers ≥ 20 ms).
pub const SDO_WAIT_MS: u64 = 1000;

/// Options of a block upload, including the deliberately wrong ones.
#[derive(Clone, Copy, Debug)]
pub struct BlockUpload {
    /// Block size the client asks for (legal: 1…127).
    pub blksize: u8,
    /// Ask for a CRC.
    pub crc: bool,
    /// Send this ackseq in the first block ack instead of the real one.
    pub forged_ackseq: Option<u8>,
}

impl Default for BlockUpload {
    fn default() -> Self {
        BlockUpload {
            blksize: 20,
            crc: false,
            forged_ackseq: None,
        }
    }
}

/// The conformance tool's side of the bus, driving one device.
pub struct Harness {
    be: Box<dyn Backend>,
    /// Node-id of the device under test.
    pub node_id: u8,
    /// Every frame received, with its time (µs on the harness clock).
    pub log: Vec<(u64, Frame)>,
}

impl Harness {
    /// A harness on back end `be`, addressing node-id 127 (the models' default).
    pub fn new(be: Box<dyn Backend>) -> Harness {
        Harness {
            be,
            node_id: 127,
            log: Vec::new(),
        }
    }

    /// The device's model.
    pub fn model(&self) -> &'static Model {
        self.be.model()
    }

    /// Whether the device runs on the virtual clock.
    pub fn is_virtual(&self) -> bool {
        self.be.is_virtual()
    }

    /// The harness clock in µs.
    pub fn now_us(&mut self) -> u64 {
        self.be.now_us()
    }

    // ---- raw frames -------------------------------------------------------------------

    /// Sends a data frame with any content and DLC (0…8).
    pub fn raw(&mut self, id: u16, data: &[u8]) {
        let f = Frame::new(id, data).expect("frame");
        self.be.send(&f);
    }

    /// Sends a remote frame (RTR) with DLC `dlc`.
    pub fn rtr(&mut self, id: u16, dlc: u8) {
        let f = Frame::remote(u32::from(id), false, dlc).expect("remote frame");
        self.be.send(&f);
    }

    // ---- capture ------------------------------------------------------------------------

    /// Waits `ms` milliseconds, capturing everything; returns the frames of that window.
    pub fn wait_ms(&mut self, ms: u64) -> Vec<(u64, Frame)> {
        let start = self.log.len();
        let deadline = self.be.now_us() + ms * 1000;
        while let Some(x) = self.be.recv_until(deadline) {
            self.log.push(x);
        }
        self.log[start..].to_vec()
    }

    /// Waits up to `ms` for a frame matching `pred` (capturing everything on the way); returns
    /// it as soon as it arrives.
    pub fn wait_for(&mut self, ms: u64, pred: impl Fn(&Frame) -> bool) -> Option<(u64, Frame)> {
        let deadline = self.be.now_us() + ms * 1000;
        while let Some(x) = self.be.recv_until(deadline) {
            self.log.push(x);
            if pred(&x.1) {
                return Some(x);
            }
        }
        None
    }

    /// Frames received so far (forgets them: windows are counted from here).
    pub fn take(&mut self) -> Vec<(u64, Frame)> {
        // Pick up whatever is already queued without moving the clock.
        let now = self.be.now_us();
        while let Some(x) = self.be.recv_until(now) {
            self.log.push(x);
        }
        std::mem::take(&mut self.log)
    }

    /// Drops the capture so far.
    pub fn clear(&mut self) {
        self.take();
    }

    /// Number of frames on `id` in `frames`.
    pub fn count(frames: &[(u64, Frame)], id: u16) -> usize {
        frames
            .iter()
            .filter(|(_, f)| f.std_id() == Some(id))
            .count()
    }

    // ---- NMT master ---------------------------------------------------------------------

    /// Sends NMT command `cs` to the device.
    pub fn nmt(&mut self, cs: u8) {
        let id = self.node_id;
        self.raw(0x000, &[cs, id]);
    }

    /// Reset node (or communication) and wait for the boot-up message within 5 s.
    pub fn reset(&mut self, cs: u8) {
        self.nmt(cs);
        let boot = 0x700 + u16::from(self.node_id);
        let got = self.wait_for(5000, |f| f.std_id() == Some(boot) && f.data() == [0]);
        assert!(got.is_some(), "no boot-up within 5 s after NMT {cs:02X}");
    }

    /// Power cycle through the back end; waits for the boot-up.
    pub fn power_cycle(&mut self) {
        assert!(self.be.power_cycle(), "back end cannot power-cycle");
        let boot = 0x700 + u16::from(self.node_id);
        let got = self.wait_for(5000, |f| f.std_id() == Some(boot) && f.data() == [0]);
        assert!(got.is_some(), "no boot-up after power cycle");
    }

    // ---- SYNC producer, guarding --------------------------------------------------------

    /// One SYNC without counter (0x080, DLC 0).
    pub fn sync(&mut self) {
        self.raw(0x080, &[]);
    }

    /// One SYNC with counter byte `c`.
    pub fn sync_counter(&mut self, c: u8) {
        self.raw(0x080, &[c]);
    }

    /// A guarding request (RTR, DLC 1) and the reply byte, if one came within 100 ms.
    pub fn guard(&mut self) -> Option<u8> {
        let id = 0x700 + u16::from(self.node_id);
        self.rtr(id, 1);
        self.wait_for(100, |f| f.std_id() == Some(id) && !f.is_remote())
            .map(|(_, f)| f.data().first().copied().unwrap_or(0xFF))
    }

    /// The zero-length data frame form of a guarding request (transports without RTR, D22).
    pub fn guard_zero_length(&mut self) -> Option<u8> {
        let id = 0x700 + u16::from(self.node_id);
        self.raw(id, &[]);
        self.wait_for(100, |f| f.std_id() == Some(id) && f.dlc() == 1)
            .map(|(_, f)| f.data()[0])
    }

    // ---- sensor hooks (instead of RPDO-triggered events) --------------------------------

    /// Moves magnet 1 to `mm` (one measurement cycle).
    pub fn move_magnet(&mut self, mm: f64) {
        let mut s = Sample::default();
        s.positions_nm[0] = Some((mm * 1e6) as i64);
        for (k, p) in s
            .positions_nm
            .iter_mut()
            .enumerate()
            .take(MAX_CHANNELS)
            .skip(1)
        {
            // Further magnets 100 mm apart so multi-channel units see them all.
            *p = Some(((mm + 100.0 * k as f64) * 1e6) as i64);
        }
        assert!(self.be.update_sample(&s), "back end cannot move magnets");
    }

    /// Injects (or removes) a sensor fault.
    pub fn fault(&mut self, f: Fault, active: bool) {
        assert!(
            self.be.inject_fault(f, active),
            "back end cannot inject faults"
        );
    }

    // ---- SDO client ---------------------------------------------------------------------

    fn sdo_rx(&self) -> u16 {
        0x600 + u16::from(self.node_id)
    }
    fn sdo_tx(&self) -> u16 {
        0x580 + u16::from(self.node_id)
    }

    /// Sends one SDO request frame (exactly these bytes, any length) and returns the server's
    /// next frame, if it answers within [`SDO_WAIT_MS`].
    pub fn sdo_raw(&mut self, req: &[u8]) -> Option<[u8; 8]> {
        let id = self.sdo_rx();
        self.raw(id, req);
        self.sdo_next()
    }

    /// The next frame from the SDO server (block upload segments come without a request).
    pub fn sdo_next(&mut self) -> Option<[u8; 8]> {
        let tx = self.sdo_tx();
        self.wait_for(SDO_WAIT_MS, |f| f.std_id() == Some(tx))
            .map(|(_, f)| {
                let mut b = [0u8; 8];
                b[..f.data().len()].copy_from_slice(f.data());
                b
            })
    }

    /// Sends a client abort (e.g. 0x05040000 after a timeout).
    pub fn sdo_abort(&mut self, index: u16, sub: u8, code: u32) {
        let i = index.to_le_bytes();
        let c = code.to_le_bytes();
        let id = self.sdo_rx();
        self.raw(id, &[0x80, i[0], i[1], sub, c[0], c[1], c[2], c[3]]);
    }

    /// Sends `req` and interprets the answer: `Ok(frame)`, `Err(abort code)`, or on silence a
    /// client abort 0x05040000 and `Err(TIMEOUT)`.
    fn sdo_exchange(&mut self, index: u16, sub: u8, req: [u8; 8]) -> SdoResult<[u8; 8]> {
        match self.sdo_raw(&req) {
            Some(r) if r[0] == 0x80 => Err(u32::from_le_bytes([r[4], r[5], r[6], r[7]])),
            Some(r) => Ok(r),
            None => {
                self.sdo_abort(index, sub, abort::TIMEOUT);
                Err(abort::TIMEOUT)
            }
        }
    }

    /// Upload (expedited or segmented, whatever the server chooses).
    pub fn upload(&mut self, index: u16, sub: u8) -> SdoResult<Vec<u8>> {
        let r = self.sdo_exchange(index, sub, initiate(0x40, index, sub, [0; 4]))?;
        if r[0] & 0xE0 != 0x40 {
            return Err(abort::BAD_COMMAND);
        }
        if r[0] & 0x02 != 0 {
            let n = if r[0] & 0x01 != 0 {
                4 - usize::from((r[0] >> 2) & 3)
            } else {
                4
            };
            return Ok(r[4..4 + n].to_vec());
        }
        let size = u32::from_le_bytes([r[4], r[5], r[6], r[7]]) as usize;
        let mut out = Vec::new();
        let mut toggle = 0u8;
        loop {
            let s = self.sdo_exchange(index, sub, [0x60 | toggle, 0, 0, 0, 0, 0, 0, 0])?;
            assert_eq!(s[0] & 0x10, toggle, "server toggle");
            let n = 7 - usize::from((s[0] >> 1) & 7);
            out.extend_from_slice(&s[1..1 + n]);
            toggle ^= 0x10;
            if s[0] & 1 != 0 {
                break;
            }
        }
        assert_eq!(out.len(), size, "segmented upload size");
        Ok(out)
    }

    /// Upload as an unsigned number (up to 4 bytes, little-endian).
    pub fn read(&mut self, index: u16, sub: u8) -> SdoResult<u32> {
        let d = self.upload(index, sub)?;
        let mut b = [0u8; 4];
        let n = d.len().min(4);
        b[..n].copy_from_slice(&d[..n]);
        Ok(u32::from_le_bytes(b))
    }

    /// Download: expedited up to 4 bytes, segmented beyond.
    pub fn download(&mut self, index: u16, sub: u8, data: &[u8]) -> SdoResult<()> {
        if data.len() <= 4 {
            let mut d = [0u8; 4];
            d[..data.len()].copy_from_slice(data);
            let cmd = 0x23 | (((4 - data.len()) as u8) << 2);
            let r = self.sdo_exchange(index, sub, initiate(cmd, index, sub, d))?;
            return if r[0] == 0x60 {
                Ok(())
            } else {
                Err(abort::BAD_COMMAND)
            };
        }
        self.download_segmented(index, sub, data, false)
    }

    /// Expedited download of `value` with `size` bytes (1, 2 or 4).
    pub fn write(&mut self, index: u16, sub: u8, value: u32, size: usize) -> SdoResult<()> {
        self.download(index, sub, &value.to_le_bytes()[..size])
    }

    /// Segmented download (initiate with size, then 7-byte segments). With `wrong_toggle`
    /// the first segment carries toggle 1.
    pub fn download_segmented(
        &mut self,
        index: u16,
        sub: u8,
        data: &[u8],
        wrong_toggle: bool,
    ) -> SdoResult<()> {
        let size = (data.len() as u32).to_le_bytes();
        let r = self.sdo_exchange(index, sub, initiate(0x21, index, sub, size))?;
        assert_eq!(r[0], 0x60, "segmented download initiate ack");
        let mut toggle = if wrong_toggle { 0x10 } else { 0 };
        let chunks: Vec<&[u8]> = data.chunks(7).collect();
        for (k, c) in chunks.iter().enumerate() {
            let last = k + 1 == chunks.len();
            let mut s = [0u8; 8];
            s[0] = toggle | (((7 - c.len()) as u8) << 1) | u8::from(last);
            s[1..1 + c.len()].copy_from_slice(c);
            let r = self.sdo_exchange(index, sub, s)?;
            assert_eq!(r[0], 0x20 | toggle, "segment ack");
            toggle ^= 0x10;
        }
        Ok(())
    }

    /// Block upload with the given options; returns the data after checking size and CRC.
    pub fn block_upload(&mut self, index: u16, sub: u8, o: BlockUpload) -> SdoResult<Vec<u8>> {
        let cmd = 0xA0 | if o.crc { 0x04 } else { 0 };
        let mut req = initiate(cmd, index, sub, [0; 4]);
        req[4] = o.blksize;
        // pst = 0: no switch to a normal upload.
        let r = self.sdo_exchange(index, sub, req)?;
        assert_eq!(r[0] & 0xE1, 0xC0, "block upload initiate answer {r:02X?}");
        let server_crc = r[0] & 0x04 != 0;
        let size = (r[0] & 0x02 != 0).then(|| u32::from_le_bytes([r[4], r[5], r[6], r[7]]));
        let id = self.sdo_rx();
        self.raw(id, &[0xA3, 0, 0, 0, 0, 0, 0, 0]);
        let mut data = Vec::new();
        let mut first_ack = true;
        loop {
            // One block: segments seq 1… until the block is full or the last one.
            let mut seq;
            let mut last = false;
            let mut block = Vec::new();
            loop {
                let Some(s) = self.sdo_next() else {
                    self.sdo_abort(index, sub, abort::TIMEOUT);
                    return Err(abort::TIMEOUT);
                };
                if s[0] == 0x80 {
                    return Err(u32::from_le_bytes([s[4], s[5], s[6], s[7]]));
                }
                seq = s[0] & 0x7F;
                block.extend_from_slice(&s[1..8]);
                if s[0] & 0x80 != 0 {
                    last = true;
                    break;
                }
                if seq == o.blksize {
                    break;
                }
            }
            let ackseq = match o.forged_ackseq {
                Some(a) if first_ack => a,
                _ => seq,
            };
            first_ack = false;
            let ack = [0xA2, ackseq, o.blksize, 0, 0, 0, 0, 0];
            data.extend_from_slice(&block);
            if !last {
                // The server answers this ack with the next block's segments.
                let id = self.sdo_rx();
                self.raw(id, &ack);
                continue;
            }
            let e = self.sdo_exchange(index, sub, ack)?;
            assert_eq!(e[0] & 0xE3, 0xC1, "block upload end {e:02X?}");
            let unused = usize::from((e[0] >> 2) & 7);
            data.truncate(data.len() - unused);
            if o.crc && server_crc {
                let crc = u16::from_le_bytes([e[1], e[2]]);
                assert_eq!(crc, crc16(&data), "block upload CRC");
            }
            let id = self.sdo_rx();
            self.raw(id, &[0xA1, 0, 0, 0, 0, 0, 0, 0]);
            if let Some(sz) = size {
                assert_eq!(data.len() as u32, sz, "block upload size");
            }
            return Ok(data);
        }
    }

    /// Block download of `data` (one block) with or without CRC.
    pub fn block_download(&mut self, index: u16, sub: u8, data: &[u8], crc: bool) -> SdoResult<u8> {
        let cmd = 0xC2 | if crc { 0x04 } else { 0 };
        let r = self.sdo_exchange(
            index,
            sub,
            initiate(cmd, index, sub, (data.len() as u32).to_le_bytes()),
        )?;
        assert_eq!(r[0] & 0xFB, 0xA0, "block download initiate ack {r:02X?}");
        let blksize = r[4];
        assert!((1..=127).contains(&blksize), "server blksize {blksize}");
        let chunks: Vec<&[u8]> = data.chunks(7).collect();
        let id = self.sdo_rx();
        for (k, c) in chunks.iter().enumerate() {
            let last = k + 1 == chunks.len();
            let mut s = [0u8; 8];
            s[0] = (k as u8 + 1) | if last { 0x80 } else { 0 };
            s[1..1 + c.len()].copy_from_slice(c);
            if last {
                let a = self.sdo_exchange(index, sub, s)?;
                assert_eq!(a[0], 0xA2, "block ack");
                assert_eq!(a[1], chunks.len() as u8, "ackseq");
            } else {
                self.raw(id, &s);
            }
        }
        let unused = (7 - data.len() % 7) % 7;
        let c = if crc { crc16(data) } else { 0 }.to_le_bytes();
        let end = [0xC1 | ((unused as u8) << 2), c[0], c[1], 0, 0, 0, 0, 0];
        let a = self.sdo_exchange(index, sub, end)?;
        assert_eq!(a[0], 0xA1, "block download end ack");
        Ok(blksize)
    }
}

/// An initiate frame: command, index, sub-index, 4 data bytes.
pub fn initiate(cmd: u8, index: u16, sub: u8, d: [u8; 4]) -> [u8; 8] {
    let i = index.to_le_bytes();
    [cmd, i[0], i[1], sub, d[0], d[1], d[2], d[3]]
}
