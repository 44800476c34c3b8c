//! SDO command bytes (CiA 301 §7.2.4.3): decoding of client requests, encoding of server
//! responses, and the block-transfer CRC. Pure functions over 8-byte payloads, so a host-side
//! SDO client can reuse them.

/// Multiplexor of an SDO transfer: the object it addresses.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Mux {
    /// Object index.
    pub index: u16,
    /// Sub-index.
    pub sub: u8,
}

impl Mux {
    /// The multiplexor in bytes 1…3 of a frame.
    pub const fn from_frame(f: &[u8; 8]) -> Mux {
        Mux {
            index: u16::from_le_bytes([f[1], f[2]]),
            sub: f[3],
        }
    }
}

/// Largest block size (segments per block) CiA 301 allows.
pub const MAX_BLKSIZE: u8 = 127;

/// Bytes of data an SDO segment carries.
pub const SEGMENT_DATA: usize = 7;

/// The command byte of a client request (byte 0), read field by field (CiA 301 §7.2.4.3): the
/// one place the bits of a request are named. [`Request::parse`] is built from it, and the
/// server reads it where it dispatches, without a [`Request`] in between.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Command(pub u8);

impl Command {
    /// ccs, the client command specifier (bits 5…7).
    #[inline]
    pub const fn ccs(self) -> u8 {
        self.0 >> 5
    }
    /// cs of a block command (ccs 5: bits 0…1, 0 initiate, 1 end, 2 acknowledge, 3 start;
    /// ccs 6: bit 0, 0 initiate, 1 end).
    #[inline]
    pub const fn block_cs(self) -> u8 {
        self.0 & 0x03
    }
    /// s of a download initiate (bit 0): the size is indicated.
    #[inline]
    pub const fn size_indicated(self) -> bool {
        self.0 & 0x01 != 0
    }
    /// c of a download segment (bit 0): the last one.
    #[inline]
    pub const fn last(self) -> bool {
        self.0 & 0x01 != 0
    }
    /// e of a download initiate (bit 1): expedited.
    #[inline]
    pub const fn expedited(self) -> bool {
        self.0 & 0x02 != 0
    }
    /// s of a block download initiate (bit 1): the size is indicated.
    #[inline]
    pub const fn block_size_indicated(self) -> bool {
        self.0 & 0x02 != 0
    }
    /// cc of a block initiate (bit 2): the client takes part in the CRC.
    #[inline]
    pub const fn crc(self) -> bool {
        self.0 & 0x04 != 0
    }
    /// t of a segment (bit 4).
    #[inline]
    pub const fn toggle(self) -> bool {
        self.0 & 0x10 != 0
    }
    /// The data length of an expedited download with its size indicated: 4 − n (n: bits 2…3).
    #[inline]
    pub const fn expedited_len(self) -> u32 {
        4 - ((self.0 >> 2) & 0x03) as u32
    }
    /// n of a download segment (bits 1…3): bytes of the segment that carry no data.
    #[inline]
    pub const fn segment_unused(self) -> u8 {
        (self.0 >> 1) & 0x07
    }
    /// n of a block download end (bits 2…4): bytes of the last segment that carried no data.
    #[inline]
    pub const fn end_unused(self) -> u8 {
        (self.0 >> 2) & 0x07
    }
    /// Whether the command is one of a block transfer (specifier 5 or 6, in either direction).
    #[inline]
    pub const fn is_block(self) -> bool {
        matches!(self.ccs(), 5 | 6)
    }
    /// Whether the request starts a new transfer: download, upload, block upload and block
    /// download initiates (as [`Request::is_initiate`]).
    #[inline]
    pub const fn is_initiate(self) -> bool {
        let ccs = self.ccs();
        matches!(ccs, 1 | 2)
            || (ccs == 5 && self.block_cs() == 0)
            || (ccs == 6 && self.block_cs() & 0x01 == 0)
    }
}

/// A client request, decoded from its command byte. Block-download sub-block segments are not
/// decodable without the server's state (their first byte is `c | seqno`), so the server reads
/// those raw.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Request {
    /// ccs 1: initiate download. `expedited`: the data is in bytes 4…7 and `size` (if
    /// indicated) is its length; otherwise `size` is the indicated total of a segmented transfer.
    DownloadInitiate {
        /// Target object.
        mux: Mux,
        /// e bit.
        expedited: bool,
        /// Data length (expedited, s = 1) or total size (segmented, s = 1).
        size: Option<u32>,
        /// Bytes 4…7.
        data: [u8; 4],
    },
    /// ccs 0: download segment.
    DownloadSegment {
        /// t bit.
        toggle: bool,
        /// n: bytes at the end of `data` that carry no data.
        unused: u8,
        /// c bit: last segment.
        last: bool,
        /// Bytes 1…7.
        data: [u8; 7],
    },
    /// ccs 2: initiate upload.
    UploadInitiate {
        /// Source object.
        mux: Mux,
    },
    /// ccs 3: upload segment request.
    UploadSegment {
        /// t bit.
        toggle: bool,
    },
    /// ccs 4: abort transfer.
    Abort {
        /// Object of the aborted transfer.
        mux: Mux,
        /// Abort code.
        code: u32,
    },
    /// ccs 5, cs 0: initiate block upload.
    BlockUploadInitiate {
        /// Source object.
        mux: Mux,
        /// cc bit: the client wants a CRC.
        crc: bool,
        /// Segments per block.
        blksize: u8,
        /// Protocol switch threshold in bytes (0 = no switch allowed).
        pst: u8,
    },
    /// ccs 5, cs 1: end of block upload (client confirms the end frame).
    BlockUploadEnd,
    /// ccs 5, cs 2: block acknowledgement.
    BlockUploadAck {
        /// Last segment received in sequence.
        ackseq: u8,
        /// Segments per block for the next block.
        blksize: u8,
    },
    /// ccs 5, cs 3: start of the block upload.
    BlockUploadStart,
    /// ccs 6, cs 0: initiate block download.
    BlockDownloadInitiate {
        /// Target object.
        mux: Mux,
        /// cc bit: the client will send a CRC.
        crc: bool,
        /// Indicated total size.
        size: Option<u32>,
    },
    /// ccs 6, cs 1: end of block download.
    BlockDownloadEnd {
        /// n: bytes of the last segment that carried no data.
        unused: u8,
        /// CRC of the data (meaningful only if both sides agreed on CRC).
        crc: u16,
    },
    /// ccs 7: not a CiA 301 command.
    Unknown,
}

impl Request {
    /// Decodes a request frame (outside a block-download sub-block).
    pub fn parse(f: &[u8; 8]) -> Request {
        let c = Command(f[0]);
        let mux = Mux::from_frame(f);
        let le32 = u32::from_le_bytes([f[4], f[5], f[6], f[7]]);
        match c.ccs() {
            0 => {
                let mut data = [0u8; 7];
                data.copy_from_slice(&f[1..8]);
                Request::DownloadSegment {
                    toggle: c.toggle(),
                    unused: c.segment_unused(),
                    last: c.last(),
                    data,
                }
            }
            1 => {
                let expedited = c.expedited();
                let size = match (expedited, c.size_indicated()) {
                    (_, false) => None,
                    (true, true) => Some(c.expedited_len()),
                    (false, true) => Some(le32),
                };
                Request::DownloadInitiate {
                    mux,
                    expedited,
                    size,
                    data: [f[4], f[5], f[6], f[7]],
                }
            }
            2 => Request::UploadInitiate { mux },
            3 => Request::UploadSegment { toggle: c.toggle() },
            4 => Request::Abort { mux, code: le32 },
            5 => match c.block_cs() {
                0 => Request::BlockUploadInitiate {
                    mux,
                    crc: c.crc(),
                    blksize: f[4],
                    pst: f[5],
                },
                1 => Request::BlockUploadEnd,
                2 => Request::BlockUploadAck {
                    ackseq: f[1],
                    blksize: f[2],
                },
                _ => Request::BlockUploadStart,
            },
            6 => {
                if c.block_cs() & 0x01 == 0 {
                    Request::BlockDownloadInitiate {
                        mux,
                        crc: c.crc(),
                        size: c.block_size_indicated().then_some(le32),
                    }
                } else {
                    Request::BlockDownloadEnd {
                        unused: c.end_unused(),
                        crc: u16::from_le_bytes([f[1], f[2]]),
                    }
                }
            }
            _ => Request::Unknown,
        }
    }

    /// Whether the request starts a new transfer.
    pub const fn is_initiate(&self) -> bool {
        matches!(
            self,
            Request::DownloadInitiate { .. }
                | Request::UploadInitiate { .. }
                | Request::BlockUploadInitiate { .. }
                | Request::BlockDownloadInitiate { .. }
        )
    }
}

impl Request {
    /// The request's 8 bytes (a client's side of [`Request::parse`]). Fields a kind does not
    /// use are sent as zero; a segmented download initiate with its size indicated carries the
    /// size in bytes 4…7 (its `data` is not sent), an expedited one `data`, its length in n
    /// when `size` is `Some(1..=4)`. [`Request::Unknown`] is sent as ccs 7.
    pub const fn emit(&self) -> [u8; 8] {
        match *self {
            Request::DownloadInitiate {
                mux,
                expedited,
                size,
                data,
            } => {
                let e = if expedited { ccs::E } else { 0 };
                match (expedited, size) {
                    (_, None) => with_mux(ccs::DOWNLOAD_INITIATE | e, mux, data),
                    (true, Some(n)) => with_mux(
                        ccs::DOWNLOAD_INITIATE | e | ccs::S | unused_of(n) << 2,
                        mux,
                        data,
                    ),
                    (false, Some(n)) => {
                        with_mux(ccs::DOWNLOAD_INITIATE | ccs::S, mux, n.to_le_bytes())
                    }
                }
            }
            Request::DownloadSegment {
                toggle,
                unused,
                last,
                data,
            } => {
                let mut r = [0u8; 8];
                r[0] = ccs::DOWNLOAD_SEGMENT | toggle_bit(toggle) | (unused & 7) << 1 | last as u8;
                let mut i = 0;
                while i < SEGMENT_DATA {
                    r[1 + i] = data[i];
                    i += 1;
                }
                r
            }
            Request::UploadInitiate { mux } => with_mux(ccs::UPLOAD_INITIATE, mux, [0; 4]),
            Request::UploadSegment { toggle } => [
                ccs::UPLOAD_SEGMENT | toggle_bit(toggle),
                0,
                0,
                0,
                0,
                0,
                0,
                0,
            ],
            Request::Abort { mux, code } => with_mux(ccs::ABORT, mux, code.to_le_bytes()),
            Request::BlockUploadInitiate {
                mux,
                crc,
                blksize,
                pst,
            } => with_mux(
                ccs::BLOCK_UPLOAD | (crc as u8) << 2,
                mux,
                [blksize, pst, 0, 0],
            ),
            Request::BlockUploadEnd => [ccs::BLOCK_UPLOAD | 1, 0, 0, 0, 0, 0, 0, 0],
            Request::BlockUploadAck { ackseq, blksize } => {
                [ccs::BLOCK_UPLOAD | 2, ackseq, blksize, 0, 0, 0, 0, 0]
            }
            Request::BlockUploadStart => [ccs::BLOCK_UPLOAD | 3, 0, 0, 0, 0, 0, 0, 0],
            Request::BlockDownloadInitiate { mux, crc, size } => {
                let (s, n) = match size {
                    Some(n) => (1u8, n),
                    None => (0, 0),
                };
                with_mux(
                    ccs::BLOCK_DOWNLOAD | (crc as u8) << 2 | s << 1,
                    mux,
                    n.to_le_bytes(),
                )
            }
            Request::BlockDownloadEnd { unused, crc } => {
                let c = crc.to_le_bytes();
                [
                    ccs::BLOCK_DOWNLOAD | (unused & 7) << 2 | 1,
                    c[0],
                    c[1],
                    0,
                    0,
                    0,
                    0,
                    0,
                ]
            }
            Request::Unknown => [ccs::UNKNOWN, 0, 0, 0, 0, 0, 0, 0],
        }
    }
}

/// The command bytes of both directions with their variable bits clear (CiA 301 §7.2.4.3):
/// the specifier in bits 5…7, and the flag bits the initiates share.
mod ccs {
    /// Client: download segment (ccs 0). Server: upload segment (scs 0).
    pub const DOWNLOAD_SEGMENT: u8 = 0x00;
    /// Client: initiate download (ccs 1). Server: download segment response (scs 1).
    pub const DOWNLOAD_INITIATE: u8 = 0x20;
    /// Client: initiate upload (ccs 2). Server: initiate upload response (scs 2).
    pub const UPLOAD_INITIATE: u8 = 0x40;
    /// Client: upload segment (ccs 3). Server: initiate download response (scs 3).
    pub const UPLOAD_SEGMENT: u8 = 0x60;
    /// Abort transfer (cs 4), both directions.
    pub const ABORT: u8 = 0x80;
    /// Client: block upload (ccs 5). Server: block download (scs 5).
    pub const BLOCK_UPLOAD: u8 = 0xA0;
    /// Client: block download (ccs 6). Server: block upload (scs 6).
    pub const BLOCK_DOWNLOAD: u8 = 0xC0;
    /// Specifier 7: no CiA 301 command.
    pub const UNKNOWN: u8 = 0xE0;
    /// e: expedited.
    pub const E: u8 = 0x02;
    /// s: size indicated.
    pub const S: u8 = 0x01;
}

/// t in bit 4.
const fn toggle_bit(t: bool) -> u8 {
    (t as u8) << 4
}

/// n of an expedited transfer of `len` (1…4) bytes: the bytes of 4…7 that carry no data (a
/// length outside 1…4 is sent modulo the two-bit field).
const fn unused_of(len: u32) -> u8 {
    (4u32.wrapping_sub(len) & 3) as u8
}

const fn with_mux(b0: u8, mux: Mux, tail: [u8; 4]) -> [u8; 8] {
    let i = mux.index.to_le_bytes();
    [b0, i[0], i[1], mux.sub, tail[0], tail[1], tail[2], tail[3]]
}

/// Expedited upload response (scs 2, e = 1, s = 1) with 1…4 bytes of `data`; more are cut.
pub fn expedited_upload(mux: Mux, data: &[u8]) -> [u8; 8] {
    let n = data.len().clamp(1, 4);
    let mut tail = [0u8; 4];
    let k = data.len().min(4);
    tail[..k].copy_from_slice(&data[..k]);
    with_mux(0x43 | (((4 - n) as u8) << 2), mux, tail)
}

/// Segmented upload initiate response with the size indicated (0x41).
pub fn upload_initiate_segmented(mux: Mux, size: u32) -> [u8; 8] {
    with_mux(0x41, mux, size.to_le_bytes())
}

/// Upload segment response: up to 7 bytes of `data`, n = unused bytes, c = `last`.
pub fn upload_segment(toggle: bool, data: &[u8], last: bool) -> [u8; 8] {
    let k = data.len().min(SEGMENT_DATA);
    let mut r = [0u8; 8];
    r[0] = (u8::from(toggle) << 4) | (((SEGMENT_DATA - k) as u8) << 1) | u8::from(last);
    r[1..1 + k].copy_from_slice(&data[..k]);
    r
}

/// Download initiate response (scs 3, 0x60).
pub fn download_initiate_ack(mux: Mux) -> [u8; 8] {
    with_mux(0x60, mux, [0; 4])
}

/// Download segment response (scs 1) echoing the toggle bit.
pub fn download_segment_ack(toggle: bool) -> [u8; 8] {
    [0x20 | (u8::from(toggle) << 4), 0, 0, 0, 0, 0, 0, 0]
}

/// Block download initiate response (scs 5, ss 0): server CRC support and block size.
pub fn block_download_initiate_ack(mux: Mux, crc: bool, blksize: u8) -> [u8; 8] {
    with_mux(0xA0 | (u8::from(crc) << 2), mux, [blksize, 0, 0, 0])
}

/// Block download acknowledgement (scs 5, ss 2): last segment received in order, next size.
pub fn block_download_ack(ackseq: u8, blksize: u8) -> [u8; 8] {
    [0xA2, ackseq, blksize, 0, 0, 0, 0, 0]
}

/// Block download end response (scs 5, ss 1).
pub fn block_download_end_ack() -> [u8; 8] {
    [0xA1, 0, 0, 0, 0, 0, 0, 0]
}

/// Block upload initiate response (scs 6, ss 0) with the size indicated.
pub fn block_upload_initiate(mux: Mux, crc: bool, size: u32) -> [u8; 8] {
    with_mux(0xC2 | (u8::from(crc) << 2), mux, size.to_le_bytes())
}

/// One block-upload segment: `c | seqno`, then up to 7 bytes (the rest zero).
pub fn block_segment(seq: u8, last: bool, data: &[u8]) -> [u8; 8] {
    let k = data.len().min(SEGMENT_DATA);
    let mut r = [0u8; 8];
    r[0] = (u8::from(last) << 7) | (seq & 0x7F);
    r[1..1 + k].copy_from_slice(&data[..k]);
    r
}

/// Block upload end (scs 6, ss 1): unused bytes of the last segment and the CRC.
pub fn block_upload_end(unused: u8, crc: u16) -> [u8; 8] {
    let c = crc.to_le_bytes();
    [0xC1 | ((unused & 0x07) << 2), c[0], c[1], 0, 0, 0, 0, 0]
}

/// A server response, the client's view of the bytes the functions above build (CiA 301
/// §7.2.4.3). Block-upload sub-block segments are not decodable without the client's state
/// (their first byte is `c | seqno`, see [`block_segment`]), so a client reads those raw.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Response {
    /// scs 2: initiate upload response. `expedited`: the data is in bytes 4…7 and `size` (if
    /// indicated) is its length; otherwise `size` is the indicated total of a segmented
    /// transfer.
    UploadInitiate {
        /// Source object.
        mux: Mux,
        /// e bit.
        expedited: bool,
        /// Data length (expedited, s = 1) or total size (segmented, s = 1).
        size: Option<u32>,
        /// Bytes 4…7.
        data: [u8; 4],
    },
    /// scs 0: upload segment response.
    UploadSegment {
        /// t bit.
        toggle: bool,
        /// n: bytes at the end of `data` that carry no data.
        unused: u8,
        /// c bit: last segment.
        last: bool,
        /// Bytes 1…7.
        data: [u8; 7],
    },
    /// scs 3: initiate download response.
    DownloadInitiate {
        /// Target object.
        mux: Mux,
    },
    /// scs 1: download segment response.
    DownloadSegment {
        /// t bit, echoing the segment's.
        toggle: bool,
    },
    /// cs 4: abort transfer.
    Abort {
        /// Object of the aborted transfer.
        mux: Mux,
        /// Abort code.
        code: u32,
    },
    /// scs 5, ss 0: initiate block download response.
    BlockDownloadInitiate {
        /// Target object.
        mux: Mux,
        /// sc bit: the server takes part in the CRC.
        crc: bool,
        /// Segments per block.
        blksize: u8,
    },
    /// scs 5, ss 1: end of block download response.
    BlockDownloadEnd,
    /// scs 5, ss 2: block download acknowledgement.
    BlockDownloadAck {
        /// Last segment received in sequence.
        ackseq: u8,
        /// Segments per block for the next block.
        blksize: u8,
    },
    /// scs 6, ss 0: initiate block upload response.
    BlockUploadInitiate {
        /// Source object.
        mux: Mux,
        /// sc bit: the server will send a CRC.
        crc: bool,
        /// Indicated total size.
        size: Option<u32>,
    },
    /// scs 6, ss 1: end of block upload.
    BlockUploadEnd {
        /// n: bytes of the last segment that carried no data.
        unused: u8,
        /// CRC of the data.
        crc: u16,
    },
    /// scs 7, or scs 5 with ss 3: not a CiA 301 response.
    Unknown,
}

impl Response {
    /// Decodes a response frame (outside a block-upload sub-block).
    pub fn parse(f: &[u8; 8]) -> Response {
        let c = Command(f[0]);
        let mux = Mux::from_frame(f);
        let le32 = u32::from_le_bytes([f[4], f[5], f[6], f[7]]);
        match c.ccs() {
            0 => {
                let mut data = [0u8; 7];
                data.copy_from_slice(&f[1..8]);
                Response::UploadSegment {
                    toggle: c.toggle(),
                    unused: c.segment_unused(),
                    last: c.last(),
                    data,
                }
            }
            1 => Response::DownloadSegment { toggle: c.toggle() },
            2 => {
                let expedited = c.expedited();
                let size = match (expedited, c.size_indicated()) {
                    (_, false) => None,
                    (true, true) => Some(c.expedited_len()),
                    (false, true) => Some(le32),
                };
                Response::UploadInitiate {
                    mux,
                    expedited,
                    size,
                    data: [f[4], f[5], f[6], f[7]],
                }
            }
            3 => Response::DownloadInitiate { mux },
            4 => Response::Abort { mux, code: le32 },
            5 => match c.block_cs() {
                0 => Response::BlockDownloadInitiate {
                    mux,
                    crc: c.crc(),
                    blksize: f[4],
                },
                1 => Response::BlockDownloadEnd,
                2 => Response::BlockDownloadAck {
                    ackseq: f[1],
                    blksize: f[2],
                },
                _ => Response::Unknown,
            },
            6 => {
                if c.block_cs() & 0x01 == 0 {
                    Response::BlockUploadInitiate {
                        mux,
                        crc: c.crc(),
                        size: c.block_size_indicated().then_some(le32),
                    }
                } else {
                    Response::BlockUploadEnd {
                        unused: c.end_unused(),
                        crc: u16::from_le_bytes([f[1], f[2]]),
                    }
                }
            }
            _ => Response::Unknown,
        }
    }

    /// The response's 8 bytes, as the server's builders above send them (a segmented upload
    /// initiate with its size indicated carries the size in bytes 4…7, not `data`).
    pub const fn emit(&self) -> [u8; 8] {
        match *self {
            Response::UploadInitiate {
                mux,
                expedited,
                size,
                data,
            } => {
                let e = if expedited { ccs::E } else { 0 };
                match (expedited, size) {
                    (_, None) => with_mux(ccs::UPLOAD_INITIATE | e, mux, data),
                    (true, Some(n)) => with_mux(
                        ccs::UPLOAD_INITIATE | e | ccs::S | unused_of(n) << 2,
                        mux,
                        data,
                    ),
                    (false, Some(n)) => {
                        with_mux(ccs::UPLOAD_INITIATE | ccs::S, mux, n.to_le_bytes())
                    }
                }
            }
            Response::UploadSegment {
                toggle,
                unused,
                last,
                data,
            } => {
                let mut r = [0u8; 8];
                r[0] = ccs::DOWNLOAD_SEGMENT | toggle_bit(toggle) | (unused & 7) << 1 | last as u8;
                let mut i = 0;
                while i < SEGMENT_DATA {
                    r[1 + i] = data[i];
                    i += 1;
                }
                r
            }
            Response::DownloadInitiate { mux } => with_mux(ccs::UPLOAD_SEGMENT, mux, [0; 4]),
            Response::DownloadSegment { toggle } => [
                ccs::DOWNLOAD_INITIATE | toggle_bit(toggle),
                0,
                0,
                0,
                0,
                0,
                0,
                0,
            ],
            Response::Abort { mux, code } => with_mux(ccs::ABORT, mux, code.to_le_bytes()),
            Response::BlockDownloadInitiate { mux, crc, blksize } => with_mux(
                ccs::BLOCK_UPLOAD | (crc as u8) << 2,
                mux,
                [blksize, 0, 0, 0],
            ),
            Response::BlockDownloadEnd => [ccs::BLOCK_UPLOAD | 1, 0, 0, 0, 0, 0, 0, 0],
            Response::BlockDownloadAck { ackseq, blksize } => {
                [ccs::BLOCK_UPLOAD | 2, ackseq, blksize, 0, 0, 0, 0, 0]
            }
            Response::BlockUploadInitiate { mux, crc, size } => {
                let (s, n) = match size {
                    Some(n) => (1u8, n),
                    None => (0, 0),
                };
                with_mux(
                    ccs::BLOCK_DOWNLOAD | (crc as u8) << 2 | s << 1,
                    mux,
                    n.to_le_bytes(),
                )
            }
            Response::BlockUploadEnd { unused, crc } => {
                let c = crc.to_le_bytes();
                [
                    ccs::BLOCK_DOWNLOAD | (unused & 7) << 2 | 1,
                    c[0],
                    c[1],
                    0,
                    0,
                    0,
                    0,
                    0,
                ]
            }
            Response::Unknown => [ccs::UNKNOWN, 0, 0, 0, 0, 0, 0, 0],
        }
    }
}

/// CRC-16 of block transfers: CCITT polynomial 0x1021, initial value 0, no reflection (the
/// XMODEM variant CiA 301 specifies).
#[inline(never)] // block uploads and downloads share one copy
pub fn crc16(data: &[u8]) -> u16 {
    let mut crc: u16 = 0;
    for &b in data {
        crc ^= u16::from(b) << 8;
        for _ in 0..8 {
            crc = if crc & 0x8000 != 0 {
                (crc << 1) ^ 0x1021
            } else {
                crc << 1
            };
        }
    }
    crc
}

#[cfg(test)]
mod tests;
