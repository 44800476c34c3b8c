use super::wire::{self, Command, Mux, MAX_BLKSIZE, SEGMENT_DATA};
use super::{abort_payload, ObjectAccess};
use crate::od::Abort;
use crate::wire::{Duration, Instant};

/// Time after which an unfinished segmented / block transfer is aborted (0x05040000).
pub const SDO_TIMEOUT: Duration = Duration::from_millis(1000);

pub use crate::config::SDO_BUF_LEN;

/// Block size the server announces for block downloads (the CTT log's value). The buffer, not
/// the block size, bounds a transfer: data beyond [`SDO_BUF_LEN`] is refused.
pub const SERVER_BLKSIZE: u8 = MAX_BLKSIZE;

/// The transfer types a server offers beyond expedited ones (a model without one answers its
/// initiates with 0x05040001).
///
/// A node passes its model's with every request (`SdoServer::handle_as`): where the build fixes
/// the features (a firmware), they are constants and the code of a type the device lacks is not
/// linked.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Transfers {
    /// Segmented upload and download.
    pub segmented: bool,
    /// Block upload and download.
    pub block: bool,
}

impl Transfers {
    /// Every transfer type.
    pub const ALL: Transfers = Transfers {
        segmented: true,
        block: true,
    };
}

/// The kind of an unfinished transfer (for hosts' status displays and tests).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TransferKind {
    /// Segmented download (client → server).
    SegmentedDownload,
    /// Segmented upload (server → client).
    SegmentedUpload,
    /// Block download: inside a sub-block most frames get no answer.
    BlockDownload,
    /// Block upload: one request can be answered by a whole block of segments.
    BlockUpload,
}

/// Where a transfer stands between two requests.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
// A plain tag byte: every state test is one compare (no niches in the fields).
#[repr(u8)]
enum State {
    Idle,
    /// Segmented download: `buf[..len]` received so far.
    DownSeg {
        toggle: bool,
        size: Option<usize>,
    },
    /// Segmented upload: `buf[..len]` is the value, `pos` bytes sent.
    UpSeg {
        toggle: bool,
    },
    /// Block download. `raw` bytes received in order (the last segment's padding included),
    /// `seq` the last segment received in order in this block, `last` once the c-bit segment
    /// arrived (then the end frame is due).
    BlkDown {
        crc: bool,
        size: Option<usize>,
        raw: usize,
        seq: u8,
        last: bool,
    },
    /// Block upload initiated: waiting for the start request.
    BlkUpInit {
        crc: bool,
        blksize: u8,
    },
    /// Block upload: the block starting at byte `pos` has `segs` segments; `next` is the next
    /// segment [`SdoServer::poll_transmit`] emits. Waiting for the block ack.
    BlkUp {
        crc: bool,
        segs: u8,
        next: u8,
        blksize: u8,
    },
    /// Block upload end sent: waiting for the client's end response.
    BlkUpEnd,
}

/// The SDO server state machine (CiA 301 §7.2.4): expedited, segmented and block transfers in
/// both directions, with one transfer buffer of [`SDO_BUF_LEN`] bytes.
///
/// Choices where CiA 301 leaves room:
/// - An initiate request that arrives while a transfer is unfinished abandons that transfer
///   without an abort frame and is served as a new transfer: the client has evidently given the
///   old one up, and answering with an abort *and* a response would give one request two
///   answers. Inside a block-download sub-block every frame is a segment (`c | seqno`), so
///   there a frame is never read as an initiate; `0x80` (c = 1, seqno 0, invalid as a segment)
///   is read as the client's abort.
/// - Abort frames carry the multiplexor of the transfer in progress; outside a transfer they
///   echo bytes 1…3 of the request.
/// - Lengths: an indicated size that differs from the object's fixed size is 0x06070012 /
///   0x06070013 (direction known); data that then differs from the client's own indicated size
///   is 0x06070010 (length mismatch).
/// - Block download segments that arrive out of order (lost or repeated) are ignored and
///   acknowledged by the last in-order sequence number, so the client repeats from there; a
///   sequence number of 0 or above the block size is 0x05040003.
#[derive(Clone, Debug)]
// In this order: the fields every request reads sit at the start, where a Thumb load or store
// of them is a 16-bit instruction (byte offsets up to 31, word offsets up to 124).
#[repr(C)]
pub struct SdoServer {
    state: State,
    /// The transfer's multiplexor as bytes 1…3 of a frame (byte 0 zero, little endian): one
    /// word to store and load, and or'ed with a command byte it is an answer's first four bytes.
    head: u32,
    /// Valid bytes in `buf` (download: received; upload: the value's size).
    len: usize,
    /// Upload: bytes confirmed sent (segmented) or the start of the current block (block).
    pos: usize,
    /// Requests ignored because their DLC was not 8.
    pub bad_dlc: u32,
    /// What [`SdoServer::handle`] offers.
    transfers: Transfers,
    /// The transfer's deadline in µs (as [`SdoServer::due_us`]); meaningful only while a
    /// transfer is unfinished, so only a request that leaves one unfinished sets it.
    deadline: u64,
    buf: [u8; SDO_BUF_LEN],
}

impl Default for SdoServer {
    fn default() -> Self {
        SdoServer::new(true, true)
    }
}

impl SdoServer {
    /// A server with no transfer in progress; `segmented` / `block` select the transfer types
    /// the model supports (a model without them answers their initiates with 0x05040001).
    pub fn new(segmented: bool, block: bool) -> Self {
        SdoServer {
            bad_dlc: 0,
            transfers: Transfers { segmented, block },
            state: State::Idle,
            head: 0,
            buf: [0; SDO_BUF_LEN],
            len: 0,
            pos: 0,
            deadline: u64::MAX,
        }
    }

    /// Aborts any transfer in progress without sending anything (NMT reset).
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    pub fn reset(&mut self) {
        // `len`, `pos` and `deadline` mean something only in a transfer, whose start sets them.
        self.state = State::Idle;
    }

    /// The transfer's multiplexor.
    #[inline]
    fn mux(&self) -> Mux {
        Mux {
            index: (self.head >> 8) as u16,
            sub: (self.head >> 24) as u8,
        }
    }

    /// Sets the transfer's multiplexor.
    #[inline]
    fn set_mux(&mut self, m: Mux) {
        self.head = (u32::from(m.index) << 8) | (u32::from(m.sub) << 24);
    }

    /// Whether a segmented or block transfer is unfinished.
    #[inline]
    pub fn busy(&self) -> bool {
        self.state != State::Idle
    }

    /// The unfinished transfer, if any: its kind and the object it addresses.
    pub fn transfer(&self) -> Option<(TransferKind, Mux)> {
        let k = match self.state {
            State::Idle => return None,
            State::DownSeg { .. } => TransferKind::SegmentedDownload,
            State::UpSeg { .. } => TransferKind::SegmentedUpload,
            State::BlkDown { .. } => TransferKind::BlockDownload,
            State::BlkUpInit { .. } | State::BlkUp { .. } | State::BlkUpEnd => {
                TransferKind::BlockUpload
            }
        };
        Some((k, self.mux()))
    }

    /// Handles one request frame's data (any length; DLC ≠ 8 is ignored and counted).
    /// Returns the response payload, if one is due. Block-upload segments are not returned
    /// here: take them with [`SdoServer::poll_transmit`] after every call.
    #[inline(always)]
    pub fn handle(
        &mut self,
        data: &[u8],
        now: Instant,
        od: &mut dyn ObjectAccess,
    ) -> Option<[u8; 8]> {
        let t = self.transfers;
        self.handle_as(data, now, od, || t)
    }

    /// [`SdoServer::handle`] with the transfer types `t()`, which must be those the server was
    /// made with: a node passes its features' (constants where the build fixes them). On a
    /// host `t` is called only for a request that is not an expedited one outside a transfer.
    #[inline(always)]
    pub(crate) fn handle_as(
        &mut self,
        data: &[u8],
        now: Instant,
        od: &mut dyn ObjectAccess,
        t: impl Fn() -> Transfers,
    ) -> Option<[u8; 8]> {
        debug_assert_eq!(t(), self.transfers, "the server's own transfer types");
        // Expedited transfers outside a transfer are what masters mostly send (polling,
        // configuration): a host (`inline-hot-paths`) serves them without decoding a `Request`,
        // with the same checks and answers as the general path (an upload that turns out
        // segmented takes that path), inlined into the caller. A firmware takes the general
        // path for them too: one copy of each answer in flash (docs/FIRMWARE.md, "Build
        // options in figures").
        if crate::config::INLINE_HOT_PATHS && self.state == State::Idle {
            if let Ok(req) = <[u8; 8]>::try_from(data) {
                let c = Command(req[0]);
                if c.ccs() == 2 {
                    if let Some(r) = self.fast_upload(&req, od) {
                        return Some(r);
                    }
                } else if c.ccs() == 1 && c.expedited() {
                    return Some(self.fast_download(&req, od));
                }
            }
        }
        self.handle_general(data, now, od, t())
    }

    /// An expedited download initiate in state `Idle` (see [`SdoServer::handle`]).
    #[inline]
    fn fast_download(&mut self, req: &[u8; 8], od: &mut dyn ObjectAccess) -> [u8; 8] {
        let c = Command(req[0]);
        let mux = Mux::from_frame(req);
        self.reset();
        self.set_mux(mux);
        let size = c.size_indicated().then(|| c.expedited_len());
        let data = [req[4], req[5], req[6], req[7]];
        match self.download_expedited(mux, size, &data, od) {
            Ok(r) => r,
            Err(a) => {
                self.reset();
                abort_payload(mux.index, mux.sub, a)
            }
        }
    }

    // Out of line (a host keeps the fast path's caller small). Its one caller passes the same
    // `t` every time, a constant where the build fixes the features, and LTO's constant
    // propagation then drops the code of a transfer type the device lacks.
    #[inline(never)]
    fn handle_general(
        &mut self,
        data: &[u8],
        now: Instant,
        od: &mut dyn ObjectAccess,
        t: Transfers,
    ) -> Option<[u8; 8]> {
        let Ok(req) = <[u8; 8]>::try_from(data) else {
            self.bad_dlc = self.bad_dlc.wrapping_add(1);
            return None;
        };
        let r = if let State::BlkDown { last: false, .. } = self.state_as(t) {
            self.block_download_segment(&req)
        } else {
            // The command byte is read field by field where it is used (`wire::Command`),
            // without a `Request` in between: not a value built and taken apart again.
            let c = Command(req[0]);
            if c.ccs() == 4 {
                // The client's abort ends any transfer and is never answered.
                self.reset();
                return None;
            }
            if c.is_initiate() {
                // A new transfer replaces an unfinished one (see the type's docs).
                self.reset();
            }
            if self.state == State::Idle {
                // The object of a new transfer, and what an abort outside a transfer echoes
                // (the multiplexor is read only while a transfer is unfinished).
                self.set_mux(Mux::from_frame(&req));
            }
            self.dispatch(&req, od, t)
        };
        // Every answer, sub-block segments' included, leaves here: one deadline and one abort.
        match r {
            Ok(r) => {
                if self.state != State::Idle {
                    self.deadline = (now + SDO_TIMEOUT).0;
                }
                r
            }
            Err(a) => self.abort(a),
        }
    }

    /// Ends the transfer with the abort `a`, which carries the transfer's multiplexor.
    fn abort(&mut self, a: Abort) -> Option<[u8; 8]> {
        let m = self.mux();
        self.reset();
        Some(abort_payload(m.index, m.sub, a))
    }

    /// The state as far as the transfer types `t` allow: a type the device lacks never left a
    /// state of its own (its initiates are refused), and saying so lets a build with constant
    /// features drop the code of that type's states.
    #[inline(always)]
    fn state_as(&self, t: Transfers) -> State {
        match self.state {
            State::DownSeg { .. } | State::UpSeg { .. } if !t.segmented => State::Idle,
            State::BlkDown { .. }
            | State::BlkUpInit { .. }
            | State::BlkUp { .. }
            | State::BlkUpEnd
                if !t.block =>
            {
                State::Idle
            }
            s => s,
        }
    }

    /// The request `req` in the current state (an initiate has reset the server and set
    /// `self.mux`). Every arm of a transfer type is guarded by `t` (its later requests also by
    /// [`SdoServer::state_as`]), so that a type the device lacks is gone with its constant. The
    /// fields are those [`wire::Request::parse`] decodes.
    fn dispatch(
        &mut self,
        req: &[u8; 8],
        od: &mut dyn ObjectAccess,
        t: Transfers,
    ) -> Result<Option<[u8; 8]>, Abort> {
        let c = Command(req[0]);
        let mux = self.mux();
        let le32 = u32::from_le_bytes([req[4], req[5], req[6], req[7]]);
        // Bit 0: s of a download initiate, c of a download segment, cs of a block download end.
        let bit0 = c.size_indicated();
        let (ccs, cs, toggle, crc) = (c.ccs(), c.block_cs(), c.toggle(), c.crc());
        match (ccs, self.state_as(t)) {
            (1, _) if c.expedited() => {
                let size = bit0.then(|| c.expedited_len());
                let data = [req[4], req[5], req[6], req[7]];
                self.download_expedited(mux, size, &data, od).map(Some)
            }
            // Segmented and block download initiates share one call of the size checks.
            (1, _) | (6, _)
                if (ccs == 1 && t.segmented) || (ccs == 6 && t.block && cs & 0x01 == 0) =>
            {
                let s = if ccs == 1 {
                    bit0
                } else {
                    c.block_size_indicated()
                };
                let size = self.check_download_size(mux, s.then_some(le32), od)?;
                self.len = 0;
                Ok(Some(if ccs == 1 {
                    self.state = State::DownSeg {
                        toggle: false,
                        size,
                    };
                    wire::download_initiate_ack(mux)
                } else {
                    self.state = State::BlkDown {
                        crc,
                        size,
                        raw: 0,
                        seq: 0,
                        last: false,
                    };
                    wire::block_download_initiate_ack(mux, crc, SERVER_BLKSIZE)
                }))
            }
            (2, _) => self.upload_initiate(mux, od, t.segmented, None).map(Some),
            (5, _) if t.block && cs == 0 => {
                // blksize, pst.
                let block = Some((crc, req[4], req[5]));
                self.upload_initiate(mux, od, t.segmented, block).map(Some)
            }
            (0, State::DownSeg { toggle: tg, size }) => {
                if toggle != tg {
                    return Err(Abort::Toggle);
                }
                // Bytes 1…7 less the n unused ones.
                let k = SEGMENT_DATA - usize::from(c.segment_unused());
                self.append(req.get(1..1 + k).unwrap_or(&[]), size)?;
                if bit0 {
                    // c: the last segment.
                    self.finish_download(size, od)?;
                    self.state = State::Idle;
                } else if let State::DownSeg { toggle, .. } = &mut self.state {
                    // The next segment's t bit (the rest of the state stays).
                    *toggle = !tg;
                }
                Ok(Some(wire::download_segment_ack(tg)))
            }
            (3, State::UpSeg { toggle: tg }) => {
                if toggle != tg {
                    return Err(Abort::Toggle);
                }
                let end = self.len.min(self.pos + SEGMENT_DATA);
                let chunk = self.buf.get(self.pos..end).unwrap_or(&[]);
                let last = end >= self.len;
                let r = wire::upload_segment(tg, chunk, last);
                self.pos = end;
                self.state = if last {
                    State::Idle
                } else {
                    State::UpSeg { toggle: !tg }
                };
                Ok(Some(r))
            }
            (5, State::BlkUpInit { crc, blksize }) if t.block && cs == 3 => {
                // Start of the block upload.
                self.pos = 0;
                self.start_block(crc, blksize);
                Ok(None)
            }
            (
                5,
                State::BlkUp {
                    crc, segs, next, ..
                },
            ) if t.block && cs == 2 => {
                // Block acknowledgement: ackseq, blksize.
                let (ackseq, blksize) = (req[1], req[2]);
                // SDO-27: an ackseq beyond what was sent is a bad sequence number.
                if ackseq > segs || ackseq >= next {
                    return Err(Abort::BlockSequence);
                }
                if blksize == 0 || blksize > MAX_BLKSIZE {
                    return Err(Abort::BlockSize);
                }
                let acked = self.pos + ackseq as usize * SEGMENT_DATA;
                let last_in_block = self.pos + segs as usize * SEGMENT_DATA >= self.len;
                if last_in_block && ackseq == segs {
                    let before = self.pos + (segs as usize - 1) * SEGMENT_DATA;
                    let in_last = self.len.saturating_sub(before);
                    let unused = (SEGMENT_DATA - in_last) as u8;
                    let c = if crc {
                        wire::crc16(self.buf.get(..self.len).unwrap_or(&[]))
                    } else {
                        0
                    };
                    self.state = State::BlkUpEnd;
                    return Ok(Some(wire::block_upload_end(unused, c)));
                }
                // Repeat from the first segment the client did not confirm.
                self.pos = acked;
                self.start_block(crc, blksize);
                Ok(None)
            }
            (5, State::BlkUpEnd) if t.block && cs == 1 => {
                // The client confirms the end frame.
                self.state = State::Idle;
                Ok(None)
            }
            (
                6,
                State::BlkDown {
                    crc: use_crc,
                    size,
                    raw,
                    last: true,
                    ..
                },
            ) if t.block && bit0 => {
                // End of block download: n = bits 2…4, the CRC in bytes 1…2.
                let unused = c.end_unused();
                let crc = u16::from_le_bytes([req[1], req[2]]);
                let total = raw
                    .checked_sub(unused as usize)
                    .ok_or(Abort::LengthMismatch)?;
                if total > SDO_BUF_LEN {
                    return Err(Abort::OutOfMemory);
                }
                if size.is_some_and(|s| s != total) {
                    return Err(Abort::LengthMismatch);
                }
                let data = self.buf.get(..total).unwrap_or(&[]);
                if use_crc && wire::crc16(data) != crc {
                    return Err(Abort::Crc);
                }
                od.write(mux.index, mux.sub, data)?;
                self.state = State::Idle;
                Ok(Some(wire::block_download_end_ack()))
            }
            // Unknown specifiers and requests that do not fit the transfer's state.
            _ => Err(Abort::InvalidCommand),
        }
    }

    #[inline]
    fn download_expedited(
        &mut self,
        mux: Mux,
        size: Option<u32>,
        data: &[u8; 4],
        od: &mut dyn ObjectAccess,
    ) -> Result<[u8; 8], Abort> {
        // download_size + write (0x22, size not indicated: the object's own size, at most the
        // 4 bytes there are), in one call.
        od.write_expedited(mux.index, mux.sub, size, data)?;
        Ok(wire::download_initiate_ack(mux))
    }

    /// Initiate-time checks of a segmented / block download: the object is writable and an
    /// indicated size fits the object and the buffer.
    fn check_download_size(
        &mut self,
        mux: Mux,
        size: Option<u32>,
        od: &mut dyn ObjectAccess,
    ) -> Result<Option<usize>, Abort> {
        let fixed = od.download_size(mux.index, mux.sub)?;
        let Some(n) = size else { return Ok(None) };
        let n = usize::try_from(n).unwrap_or(usize::MAX);
        match fixed {
            Some(f) if n > f => Err(Abort::LengthTooHigh),
            Some(f) if n < f => Err(Abort::LengthTooLow),
            _ if n > SDO_BUF_LEN => Err(Abort::OutOfMemory),
            _ => Ok(Some(n)),
        }
    }

    /// Adds segment data to the buffer.
    fn append(&mut self, data: &[u8], size: Option<usize>) -> Result<(), Abort> {
        let end = self.len + data.len();
        if size.is_some_and(|s| end > s) {
            return Err(Abort::LengthMismatch);
        }
        let dst = self.buf.get_mut(self.len..end).ok_or(Abort::OutOfMemory)?;
        dst.copy_from_slice(data);
        self.len = end;
        Ok(())
    }

    fn finish_download(
        &mut self,
        size: Option<usize>,
        od: &mut dyn ObjectAccess,
    ) -> Result<(), Abort> {
        if size.is_some_and(|s| s != self.len) {
            return Err(Abort::LengthMismatch);
        }
        let data = self.buf.get(..self.len).unwrap_or(&[]);
        let m = self.mux();
        od.write(m.index, m.sub, data)
    }

    /// Upload initiate while idle, for values of 1…4 bytes (and refusals); `None` when the
    /// value needs a segmented transfer, which the general path then handles.
    #[inline]
    fn fast_upload(&mut self, req: &[u8; 8], od: &mut dyn ObjectAccess) -> Option<[u8; 8]> {
        let mux = Mux::from_frame(req);
        let size = od.upload_size(mux.index, mux.sub);
        if matches!(size, Ok(n) if !(1..=4).contains(&n)) {
            return None;
        }
        self.reset();
        self.set_mux(mux);
        let r = size.and_then(|_| {
            let mut b = [0u8; 4];
            let n = od.read(mux.index, mux.sub, 0, &mut b)?;
            // `b` is zero beyond the `n` bytes read: it is the response's data field as is.
            let unused = (4 - n.clamp(1, 4)) as u8;
            let i = mux.index.to_le_bytes();
            Ok([
                0x43 | unused << 2,
                i[0],
                i[1],
                mux.sub,
                b[0],
                b[1],
                b[2],
                b[3],
            ])
        });
        Some(r.unwrap_or_else(|a| {
            self.reset();
            abort_payload(mux.index, mux.sub, a)
        }))
    }

    /// An upload initiate: a plain one (`block` = `None`), where a value that needs a
    /// segmented transfer is refused unless `segmented`, or a block one (`block` = `Some((crc,
    /// blksize, pst))`). Both share the size query and the read into the buffer.
    fn upload_initiate(
        &mut self,
        mux: Mux,
        od: &mut dyn ObjectAccess,
        segmented: bool,
        block: Option<(bool, u8, u8)>,
    ) -> Result<[u8; 8], Abort> {
        if block.is_some_and(|(_, blksize, _)| blksize == 0 || blksize > MAX_BLKSIZE) {
            return Err(Abort::BlockSize);
        }
        let size = od.upload_size(mux.index, mux.sub)?;
        // Protocol switch: the client allows a plain upload for a value this small.
        let block = block.filter(|&(_, _, pst)| pst == 0 || size > pst as usize);
        if let Some((crc, blksize, _)) = block {
            self.load(mux, size, od)?;
            self.state = State::BlkUpInit { crc, blksize };
            return Ok(wire::block_upload_initiate(mux, crc, self.len as u32));
        }
        if (1..=4).contains(&size) {
            let mut b = [0u8; 4];
            let n = od.read(mux.index, mux.sub, 0, &mut b)?;
            return Ok(wire::expedited_upload(
                mux,
                b.get(..n.clamp(1, 4)).unwrap_or(&b),
            ));
        }
        // Longer (or empty) values need a segmented transfer.
        if !segmented {
            return Err(Abort::InvalidCommand);
        }
        self.load(mux, size, od)?;
        self.state = State::UpSeg { toggle: false };
        Ok(wire::upload_initiate_segmented(mux, self.len as u32))
    }

    /// Reads the whole value into the buffer, so every segment comes from one snapshot.
    fn load(&mut self, mux: Mux, size: usize, od: &mut dyn ObjectAccess) -> Result<(), Abort> {
        if size > SDO_BUF_LEN {
            return Err(Abort::OutOfMemory);
        }
        let n = od.read(mux.index, mux.sub, 0, &mut self.buf[..size])?;
        self.len = n.min(size);
        self.pos = 0;
        Ok(())
    }

    /// Sets up the block that starts at `self.pos`; `poll_transmit` emits its segments.
    // Out of line: the block-upload start and every acknowledged block share it.
    #[inline(never)]
    fn start_block(&mut self, crc: bool, blksize: u8) {
        let left = self.len.saturating_sub(self.pos);
        // An empty rest still needs one (empty, c = 1) segment.
        let needed = left.div_ceil(SEGMENT_DATA).max(1);
        let segs = needed.min(blksize as usize) as u8;
        self.state = State::BlkUp {
            crc,
            segs,
            next: 1,
            blksize,
        };
    }

    /// One frame inside a block-download sub-block.
    fn block_download_segment(&mut self, req: &[u8; 8]) -> Result<Option<[u8; 8]>, Abort> {
        let State::BlkDown {
            crc,
            size,
            raw,
            seq,
            ..
        } = self.state
        else {
            return Ok(None);
        };
        if req[0] == 0x80 {
            // c = 1 with seqno 0 is no segment: it is the client's abort.
            self.reset();
            return Ok(None);
        }
        let s = req[0] & 0x7F;
        let c = req[0] & 0x80 != 0;
        if s == 0 || s > SERVER_BLKSIZE {
            return Err(Abort::BlockSequence);
        }
        let mut raw = raw;
        let mut seq = seq;
        let mut last = false;
        if s == seq.wrapping_add(1) {
            let data = req.get(1..8).unwrap_or(&[]);
            let room = SDO_BUF_LEN.saturating_sub(self.len);
            if !c && data.len() > room {
                return Err(Abort::OutOfMemory);
            }
            if !c && size.is_some_and(|sz| raw + data.len() > sz) {
                return Err(Abort::LengthMismatch);
            }
            // The last segment's padding may not fit: its length is known only at the end.
            let k = data.len().min(room);
            if let (Some(dst), Some(src)) =
                (self.buf.get_mut(self.len..self.len + k), data.get(..k))
            {
                dst.copy_from_slice(src);
            }
            self.len += k;
            raw += data.len();
            seq = s;
            last = c;
        }
        // Out-of-order segments are dropped; the ack tells the client where to resume.
        let block_end = c || s == SERVER_BLKSIZE;
        self.state = State::BlkDown {
            crc,
            size,
            raw,
            seq: if block_end { 0 } else { seq },
            last,
        };
        Ok(block_end.then(|| wire::block_download_ack(seq, SERVER_BLKSIZE)))
    }

    /// The next block-upload segment to send, if a block is being sent. Call after
    /// [`SdoServer::handle`] until it returns `None`.
    #[inline]
    pub fn poll_transmit(&mut self) -> Option<[u8; 8]> {
        let t = self.transfers;
        self.poll_transmit_as(|| t)
    }

    /// [`SdoServer::poll_transmit`] with the transfer types `t()` (as [`SdoServer::handle_as`]).
    #[inline]
    pub(crate) fn poll_transmit_as(&mut self, t: impl Fn() -> Transfers) -> Option<[u8; 8]> {
        let State::BlkUp {
            crc,
            segs,
            next,
            blksize,
        } = self.state
        else {
            return None;
        };
        if !t().block {
            return None;
        }
        if next > segs {
            return None;
        }
        let start = self.pos + (next as usize - 1) * SEGMENT_DATA;
        let end = self.len.min(start + SEGMENT_DATA);
        let last = end >= self.len;
        let data = self.buf.get(start..end).unwrap_or(&[]);
        let f = wire::block_segment(next, last, data);
        self.state = State::BlkUp {
            crc,
            segs,
            next: next + 1,
            blksize,
        };
        Some(f)
    }

    /// The deadline of a transfer in progress.
    #[inline]
    pub fn poll_timeout(&self) -> Option<Instant> {
        (self.due_us() != u64::MAX).then_some(Instant(self.due_us()))
    }

    /// [`SdoServer::poll_timeout`] in µs, `u64::MAX` for none (the node's timer table).
    #[inline]
    pub fn due_us(&self) -> u64 {
        // While idle `deadline` is stale (nothing clears it).
        if self.state != State::Idle {
            self.deadline
        } else {
            u64::MAX
        }
    }

    /// Aborts a transfer whose deadline passed; returns the abort payload (0x05040000).
    #[inline]
    pub fn handle_timeout(&mut self, now: Instant) -> Option<[u8; 8]> {
        match self.poll_timeout() {
            Some(t) if now >= t => self.abort(Abort::Timeout),
            _ => None,
        }
    }
}
