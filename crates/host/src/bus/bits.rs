//! A classic CAN frame on the wire: its bits, CRC-15, stuff bits and length (ISO 11898-1).
//!
//! The stuffed part runs from SOF to the end of the CRC sequence; after five equal bits the
//! transmitter inserts one of the opposite level, and that stuff bit counts towards the next
//! run. The fixed tail is not stuffed: CRC delimiter 1, ACK slot 1, ACK delimiter 1, EOF 7,
//! intermission 3.

use canpos_stack::Frame;

/// Bits after the CRC sequence: CRC delimiter, ACK slot, ACK delimiter, EOF (7), intermission (3).
pub const TAIL_BITS: u32 = 1 + 1 + 1 + 7 + 3;
/// The intermission between frames.
pub const INTERMISSION_BITS: u32 = 3;
/// Error flag (6) plus error delimiter (8).
pub const ERROR_FRAME_BITS: u32 = 6 + 8;
/// Recessive bits an error-passive transmitter waits after its frame ("suspend transmission").
pub const SUSPEND_BITS: u32 = 8;
/// The 11 recessive bits that bus integration and bus-off recovery count.
pub const RECESSIVE_SEQUENCE_BITS: u32 = 11;
/// Sequences of 11 recessive bits a bus-off node must see before it is error active again.
pub const BUS_OFF_RECOVERY_SEQUENCES: u32 = 128;

/// The CAN CRC-15 generator x^15 + x^14 + x^10 + x^8 + x^7 + x^4 + x^3 + 1.
const CRC15_POLY: u16 = 0x4599;

/// Up to 160 bits, most significant first (the longest stuffed extended frame is below that).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Bits {
    words: [u64; 3],
    len: u32,
}

impl Bits {
    const fn new() -> Self {
        Bits {
            words: [0; 3],
            len: 0,
        }
    }

    fn push(&mut self, bit: bool) {
        if bit {
            self.words[(self.len / 64) as usize] |= 1 << (63 - self.len % 64);
        }
        self.len += 1;
    }

    fn push_field(&mut self, value: u32, width: u32) {
        for i in (0..width).rev() {
            self.push(value >> i & 1 != 0);
        }
    }

    /// Bit `i` (true = recessive).
    pub fn get(&self, i: u32) -> bool {
        self.words[(i / 64) as usize] >> (63 - i % 64) & 1 != 0
    }

    /// Number of bits.
    pub fn len(&self) -> u32 {
        self.len
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
}

/// CRC-15 over `bits` (SOF to the end of the data field, unstuffed).
pub fn crc15(bits: &Bits) -> u16 {
    let mut crc: u16 = 0;
    for i in 0..bits.len() {
        let next = bits.get(i) ^ (crc >> 14 & 1 != 0);
        crc = (crc << 1) & 0x7FFF;
        if next {
            crc ^= CRC15_POLY;
        }
    }
    crc
}

/// SOF to the end of the data field, unstuffed: what the CRC covers.
pub fn crc_covered(f: &Frame) -> Bits {
    let mut b = Bits::new();
    b.push(false); // SOF, dominant
    let rtr = f.is_remote();
    if f.is_extended() {
        b.push_field(f.id() >> 18, 11);
        b.push(true); // SRR, recessive
        b.push(true); // IDE, recessive
        b.push_field(f.id() & 0x3FFFF, 18);
        b.push(rtr);
        b.push(false); // r1
        b.push(false); // r0
    } else {
        b.push_field(f.id(), 11);
        b.push(rtr);
        b.push(false); // IDE, dominant
        b.push(false); // r0
    }
    b.push_field(u32::from(f.dlc()), 4);
    if !rtr {
        for &byte in f.data() {
            b.push_field(u32::from(byte), 8);
        }
    }
    b
}

/// The stuffed bit stream from SOF to the end of the CRC sequence, as the transmitter sends it.
pub fn stuffed(f: &Frame) -> Bits {
    let mut raw = crc_covered(f);
    let crc = crc15(&raw);
    raw.push_field(u32::from(crc), 15);
    let mut out = Bits::new();
    let (mut run, mut last) = (0u32, None);
    for i in 0..raw.len() {
        let bit = raw.get(i);
        out.push(bit);
        if Some(bit) == last {
            run += 1;
        } else {
            (run, last) = (1, Some(bit));
        }
        if run == 5 {
            out.push(!bit);
            (run, last) = (1, Some(!bit));
        }
    }
    out
}

/// How long a frame is on the bus, in bits.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FrameLength {
    /// Stuff bits in it.
    pub stuff: u32,
    /// Every bit from SOF to the end of the intermission.
    pub total: u32,
}

/// The frame's bit count on the wire, stuff bits and the intermission included.
pub fn frame_length(f: &Frame) -> FrameLength {
    let raw = crc_covered(f).len() + 15;
    let s = stuffed(f).len();
    FrameLength {
        stuff: s - raw,
        total: s + TAIL_BITS,
    }
}

/// The arbitration value of a frame: lower wins. Bit for bit what the identifier field sends:
/// 11 base bits, RTR (standard) or SRR (extended, recessive), IDE, then for extended frames
/// the 18 extension bits and RTR. So a standard data frame beats the remote frame and any
/// extended frame with the same base identifier.
pub fn arbitration_key(f: &Frame) -> u32 {
    let rtr = u32::from(f.is_remote());
    if f.is_extended() {
        (f.id() >> 18) << 21 | 1 << 20 | 1 << 19 | (f.id() & 0x3FFFF) << 1 | rtr
    } else {
        f.id() << 21 | rtr << 20
    }
}

/// The index of the first bit where two frames with the same arbitration value differ on the
/// wire (in the control or data field, or the CRC), or `None` when they are the same frame.
pub fn first_difference(a: &Frame, b: &Frame) -> Option<u32> {
    let (x, y) = (stuffed(a), stuffed(b));
    (0..x.len().min(y.len()))
        .find(|&i| x.get(i) != y.get(i))
        .or((x.len() != y.len()).then(|| x.len().min(y.len())))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn all_dominant_standard_frame() {
        // ID 0x000, DLC 0: SOF, 11 ID bits, RTR, IDE, r0, 4 DLC bits = 19 dominant bits. The
        // CRC of all-zero bits is 0, so 15 more: 34 dominant bits in a row. A stuff bit after
        // every 5: after bits 5, 10, 15, 20, 25, 30 → 6 (the last 4 make no full run).
        // 34 + 6 + 13 (CRC delimiter, ACK 2, EOF 7, intermission 3) = 53.
        let f = Frame::new(0x000, &[]).unwrap();
        assert_eq!(crc15(&crc_covered(&f)), 0);
        assert_eq!(
            frame_length(&f),
            FrameLength {
                stuff: 6,
                total: 53
            }
        );
    }

    #[test]
    fn eight_byte_frames_stay_within_the_stuffing_bounds() {
        // 8 data bytes: 34 + 64 = 98 stuffable bits, 47 + 64 = 111 bits without stuffing, and
        // at most ⌊(98 − 1) / 4⌋ = 24 stuff bits: 111 … 135 bits whatever the content.
        for (id, b) in [(0x000, 0x00), (0x181, 0xFF), (0x7EF, 0x55), (0x555, 0x0F)] {
            let len = frame_length(&Frame::new(id, &[b; 8]).unwrap());
            assert!((111..=135).contains(&len.total), "{id:#x} {b:#x}: {len:?}");
            assert_eq!(len.total, 111 + len.stuff);
        }
    }

    #[test]
    fn remote_frame_with_hand_computed_crc() {
        // Remote frame ID 0x000, DLC 0: 12 dominant (SOF + ID), RTR recessive, 6 dominant
        // (IDE, r0, DLC). CRC: zeros keep it 0; the RTR 1 gives 0x4599; then six 0 bits, each
        // a shift (and XOR 0x4599 when bit 14 was set):
        //   0x4599 → 0x4EAB → 0x58CF → 0x7407 → 0x2D97 → 0x5B2E → 0x73C5.
        // Stream: 00000 [1] 00000 [1] 00 1 00000 [1] 0 | CRC 111001111000101: 3 stuff bits.
        // 19 + 15 + 3 + 13 = 50.
        let f = Frame::remote(0x000, false, 0).unwrap();
        assert_eq!(crc15(&crc_covered(&f)), 0x73C5);
        assert_eq!(
            frame_length(&f),
            FrameLength {
                stuff: 3,
                total: 50
            }
        );
    }

    #[test]
    fn alternating_bits_need_no_stuffing() {
        // SOF 0, ID 0x555 = 10101010101, then RTR 0, IDE 0, r0 0 and DLC 0001: after the ID's
        // last 1 come six dominant bits (RTR, IDE, r0, DLC 000), so one stuff bit goes after the
        // fifth. Data 0x55 = 01010101 alternates. Whatever the CRC adds, the stuffed stream
        // never holds six equal bits in a row.
        let f = Frame::new(0x555, &[0x55]).unwrap();
        let len = frame_length(&f);
        let s = stuffed(&f);
        // No six equal bits in a row anywhere in the stuffed stream.
        let mut run = 1;
        for i in 1..s.len() {
            run = if s.get(i) == s.get(i - 1) { run + 1 } else { 1 };
            assert!(run <= 5, "run of {run} at {i}");
        }
        assert!(len.stuff >= 1);
        assert_eq!(len.total, 47 + 8 + len.stuff);
    }

    #[test]
    fn extended_frame_layout() {
        // Extended, DLC 0: SOF 1, base 11, SRR 1, IDE 1, extension 18, RTR 1, r1 r0 2, DLC 4 =
        // 39 bits covered by the CRC, + 15 CRC + 13 tail = 67 plus stuffing.
        let f = Frame::with_id(0x0AAA_AAAA & 0x1FFF_FFFF, true, &[]).unwrap();
        assert_eq!(crc_covered(&f).len(), 39);
        let len = frame_length(&f);
        assert_eq!(len.total, 67 + len.stuff);
    }

    #[test]
    fn arbitration_order() {
        let d = |id| Frame::new(id, &[]).unwrap();
        assert!(arbitration_key(&d(0x100)) < arbitration_key(&d(0x101)));
        // Data beats remote with the same identifier.
        let r = Frame::remote(0x100, false, 0).unwrap();
        assert!(arbitration_key(&d(0x100)) < arbitration_key(&r));
        // Standard beats extended with the same base identifier (IDE dominant vs recessive).
        let e = Frame::with_id(0x100 << 18, true, &[]).unwrap();
        assert!(arbitration_key(&r) < arbitration_key(&e));
        assert!(arbitration_key(&e) < arbitration_key(&d(0x101)));
    }

    #[test]
    fn difference_is_found_in_the_data() {
        let a = Frame::new(0x181, &[1, 2]).unwrap();
        let b = Frame::new(0x181, &[1, 3]).unwrap();
        assert_eq!(first_difference(&a, &a), None);
        let i = first_difference(&a, &b).unwrap();
        // After SOF..DLC (19 bits), the first data byte (8) and at least part of the second.
        assert!(i >= 19 + 8, "{i}");
    }
}
