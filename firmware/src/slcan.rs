//! CAN frames as text lines on a serial link, in the Lawicel / SLCAN format that serial CAN
//! adapters and python-can's `slcan` interface use:
//!
//! ```text
//! tIIILDD…\r   standard data frame (3 hex id digits, DLC digit, 2 hex digits per byte)
//! TIIIIIIIILDD…\r  extended data frame
//! rIIIL\r / RIIIIIIIIL\r  remote frames
//! ```
//!
//! The firmware's UART carries this format in both directions: the host side of the QEMU
//! serial port is the rest of the CAN bus.

use embedded_can::{ExtendedId, Frame, Id, StandardId};

/// Longest line: `T`, 8 id digits, DLC, 16 data digits, `\r`.
pub const LINE_MAX: usize = 27;

const HEX: &[u8; 16] = b"0123456789ABCDEF";

fn hex_val(c: u8) -> Option<u32> {
    match c {
        b'0'..=b'9' => Some((c - b'0') as u32),
        b'A'..=b'F' => Some((c - b'A' + 10) as u32),
        b'a'..=b'f' => Some((c - b'a' + 10) as u32),
        _ => None,
    }
}

fn hex_num(digits: &[u8]) -> Option<u32> {
    digits
        .iter()
        .try_fold(0u32, |acc, &c| Some(acc << 4 | hex_val(c)?))
}

/// Parses one line (without its `\r`) into a frame; `None` for anything else.
pub fn parse<F: Frame>(line: &[u8]) -> Option<F> {
    let (&kind, rest) = line.split_first()?;
    let id_len = match kind {
        b't' | b'r' => 3,
        b'T' | b'R' => 8,
        _ => return None,
    };
    let id_digits = rest.get(..id_len)?;
    let raw = hex_num(id_digits)?;
    let id: Id = if id_len == 3 {
        StandardId::new(u16::try_from(raw).ok()?)?.into()
    } else {
        ExtendedId::new(raw)?.into()
    };
    let dlc = hex_num(rest.get(id_len..id_len + 1)?)? as usize;
    if dlc > 8 {
        return None;
    }
    let body = rest.get(id_len + 1..)?;
    if kind == b'r' || kind == b'R' {
        return if body.is_empty() {
            F::new_remote(id, dlc)
        } else {
            None
        };
    }
    if body.len() != 2 * dlc {
        return None;
    }
    let mut data = [0u8; 8];
    for (d, pair) in data.iter_mut().zip(body.chunks_exact(2)) {
        *d = hex_num(pair)? as u8;
    }
    F::new(id, data.get(..dlc)?)
}

/// Writes `f` as one line with its `\r` into `out`; returns the length.
pub fn format<F: Frame>(f: &F, out: &mut [u8; LINE_MAX]) -> usize {
    let (kind, raw, digits) = match f.id() {
        Id::Standard(s) => (b't', s.as_raw() as u32, 3),
        Id::Extended(e) => (b'T', e.as_raw(), 8),
    };
    let kind = if f.is_remote_frame() { kind - 2 } else { kind }; // t→r, T→R
    let mut n = 0;
    let mut put = |b: u8, n: &mut usize| {
        if let Some(slot) = out.get_mut(*n) {
            *slot = b;
            *n += 1;
        }
    };
    put(kind, &mut n);
    for i in (0..digits).rev() {
        put(HEX[(raw >> (4 * i) & 0xF) as usize], &mut n);
    }
    let dlc = f.dlc().min(8);
    put(HEX[dlc], &mut n);
    if !f.is_remote_frame() {
        for &b in f.data().iter().take(dlc) {
            put(HEX[(b >> 4) as usize], &mut n);
            put(HEX[(b & 0xF) as usize], &mut n);
        }
    }
    put(b'\r', &mut n);
    n
}

/// Collects received bytes into lines.
pub struct LineReader {
    buf: [u8; LINE_MAX],
    len: usize,
    /// The current line overflowed: it is dropped up to its `\r`.
    overflow: bool,
}

impl Default for LineReader {
    fn default() -> Self {
        LineReader {
            buf: [0; LINE_MAX],
            len: 0,
            overflow: false,
        }
    }
}

impl LineReader {
    /// Feeds one byte; returns a complete line (without `\r`) when `b` ends one. `\n` is
    /// ignored so `\r\n` line ends work too.
    pub fn push(&mut self, b: u8) -> Option<&[u8]> {
        match b {
            b'\r' => {
                let n = core::mem::take(&mut self.len);
                if core::mem::take(&mut self.overflow) {
                    return None;
                }
                self.buf.get(..n)
            }
            b'\n' => None,
            _ => {
                match self.buf.get_mut(self.len) {
                    Some(slot) => {
                        *slot = b;
                        self.len += 1;
                    }
                    None => self.overflow = true,
                }
                None
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use canpos_stack::Frame as CoreFrame;

    fn line_of(f: &CoreFrame) -> ([u8; LINE_MAX], usize) {
        let mut out = [0u8; LINE_MAX];
        let n = format(f, &mut out);
        (out, n)
    }

    #[test]
    fn frames_round_trip_through_lines() {
        let cases = [
            (CoreFrame::new(0x77F, &[0x05]).unwrap(), &b"t77F105\r"[..]),
            (CoreFrame::new(0x000, &[]).unwrap(), &b"t0000\r"[..]),
            (
                CoreFrame::new(0x5FF, &[0x43, 0x00, 0x10, 0x00, 0x96, 0x01, 0x08, 0x00]).unwrap(),
                &b"t5FF84300100096010800\r"[..],
            ),
            (CoreFrame::remote(0x77F, false, 1).unwrap(), &b"r77F1\r"[..]),
            (
                CoreFrame::with_id(0x1ABC_DEF0, true, &[0xFF]).unwrap(),
                &b"T1ABCDEF01FF\r"[..],
            ),
            (
                CoreFrame::remote(0x1FFF_FFFF, true, 8).unwrap(),
                &b"R1FFFFFFF8\r"[..],
            ),
        ];
        for (f, text) in cases {
            let (out, n) = line_of(&f);
            assert_eq!(&out[..n], text);
            let back: CoreFrame = parse(&text[..text.len() - 1]).unwrap();
            assert_eq!(back, f);
        }
    }

    #[test]
    fn malformed_lines_are_no_frames() {
        for bad in [
            &b""[..],
            b"t",
            b"t77",
            b"t77F",
            b"t80001",      // id above 0x7FF
            b"t77F9",       // DLC 9
            b"t77F2AA",     // one byte short
            b"t77F1AAB",    // one digit too many
            b"t77F1ZZ",     // not hex
            b"r77F1AA",     // remote frame with data
            b"T2000000000", // id above 29 bits
            b"x77F0",
        ] {
            assert!(
                parse::<CoreFrame>(bad).is_none(),
                "{:?}",
                core::str::from_utf8(bad)
            );
        }
        assert_eq!(
            parse::<CoreFrame>(b"t77f1aa"),
            CoreFrame::new(0x77F, &[0xAA]).ok()
        );
    }

    #[test]
    fn line_reader_splits_and_drops_overlong_lines() {
        let mut r = LineReader::default();
        let mut lines = 0;
        for &b in b"t0000\r\nt77F105\r" {
            if let Some(l) = r.push(b) {
                assert!(l == b"t0000" || l == b"t77F105");
                lines += 1;
            }
        }
        assert_eq!(lines, 2);
        // A line longer than any frame is dropped whole, and the next one is read.
        for _ in 0..100 {
            assert!(r.push(b'1').is_none());
        }
        assert!(r.push(b'\r').is_none());
        let got = b"t0000\r"
            .iter()
            .filter_map(|&b| r.push(b).map(|l| l.len()))
            .next();
        assert_eq!(got, Some(5));
    }
}
