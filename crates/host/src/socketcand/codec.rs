//! socketcand ASCII elements: incremental stream decoder, element parser and formatters.
//!
//! The wire format (see `docs/TRANSPORT.md`) is a stream of `< ... >` elements with no separators.
//! TCP may split an element over reads or put several in one, and a broken peer may send
//! anything, so the decoder is a byte-level state machine with a bounded buffer: bytes outside
//! elements are skipped, an over-long element is dropped, and a `<` inside an element restarts.

use std::io::Write as _;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use canpos_core::Frame;

use crate::transport::RxFrame;

/// Longest element body kept, in bytes; the longest legal one (`send` of an extended frame with
/// 8 bytes) is about 40.
pub const MAX_ELEMENT: usize = 256;

/// `< hi >`, sent by the server right after accepting.
pub const HI: &[u8] = b"< hi >";
/// `< ok >`, the answer to `open` and `rawmode`.
pub const OK: &[u8] = b"< ok >";
/// `< echo >`, both the request and its answer.
pub const ECHO: &[u8] = b"< echo >";
/// `< rawmode >`, the client's request to switch to raw frames.
pub const RAWMODE: &[u8] = b"< rawmode >";

/// Splits a byte stream into element bodies (the text between `<` and `>`).
#[derive(Debug, Default)]
pub struct Decoder {
    buf: Vec<u8>,
    in_element: bool,
    overflow: bool,
    skipped: u64,
}

impl Decoder {
    /// A decoder at the start of a stream.
    pub fn new() -> Self {
        Self::default()
    }

    /// Feeds bytes; calls `on_element` with each complete element body, in order.
    pub fn feed(&mut self, input: &[u8], mut on_element: impl FnMut(&[u8])) {
        for &b in input {
            if !self.in_element {
                if b == b'<' {
                    self.in_element = true;
                    self.overflow = false;
                    self.buf.clear();
                } else {
                    self.skipped += 1;
                }
                continue;
            }
            match b {
                b'>' => {
                    if self.overflow {
                        self.skipped += 1;
                    } else {
                        on_element(&self.buf);
                    }
                    self.in_element = false;
                    self.buf.clear();
                }
                b'<' => {
                    // An unterminated element followed by a new one: drop the broken part.
                    self.skipped += self.buf.len() as u64 + 1;
                    self.buf.clear();
                    self.overflow = false;
                }
                _ if self.buf.len() < MAX_ELEMENT => self.buf.push(b),
                _ => self.overflow = true,
            }
        }
    }

    /// Feeds bytes and returns the parsed elements.
    pub fn feed_parse(&mut self, input: &[u8]) -> Vec<Element> {
        let mut out = Vec::new();
        self.feed(input, |body| out.push(Element::parse(body)));
        out
    }

    /// Bytes thrown away so far (outside elements, broken or over-long elements).
    pub fn skipped(&self) -> u64 {
        self.skipped
    }

    /// Whether the decoder is in the middle of an element.
    pub fn is_partial(&self) -> bool {
        self.in_element
    }
}

/// One parsed element.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Element {
    /// `< hi >`
    Hi,
    /// `< ok >`
    Ok,
    /// `< echo >`
    Echo,
    /// `< rawmode >`
    RawMode,
    /// `< open CHANNEL >`
    Open(String),
    /// `< send ID DLC B0 .. >` from a client.
    Send(Frame),
    /// `< frame ID SEC.USEC DATA >` from a server.
    Frame(RxFrame),
    /// `< error ... >` with its text.
    Error(String),
    /// Anything else, or a malformed known element (kept for logs).
    Other(String),
}

impl Element {
    /// Parses an element body (without the angle brackets). Never panics.
    pub fn parse(body: &[u8]) -> Element {
        let Ok(text) = std::str::from_utf8(body) else {
            return Element::Other(String::from_utf8_lossy(body).into_owned());
        };
        let mut tok = text.split_ascii_whitespace();
        let other = || Element::Other(text.trim().to_string());
        match tok.next() {
            Some("hi") => Element::Hi,
            Some("ok") => Element::Ok,
            Some("echo") => Element::Echo,
            Some("rawmode") => Element::RawMode,
            Some("open") => match (tok.next(), tok.next()) {
                (Some(ch), None) => Element::Open(ch.to_string()),
                _ => other(),
            },
            Some("send") => parse_send(tok).map(Element::Send).unwrap_or_else(other),
            Some("frame") => parse_frame(tok).map(Element::Frame).unwrap_or_else(other),
            Some("error") => Element::Error(text.trim().to_string()),
            _ => other(),
        }
    }
}

fn hex_u32(s: &str) -> Option<u32> {
    if s.is_empty() || s.len() > 8 || !s.bytes().all(|b| b.is_ascii_hexdigit()) {
        return None;
    }
    u32::from_str_radix(s, 16).ok()
}

/// Parses an identifier token: exactly 8 digits or a value above 0x7FF means extended.
fn parse_id(s: &str, three_digits_only_std: bool) -> Option<(u32, bool)> {
    let v = hex_u32(s)?;
    let ext = if three_digits_only_std {
        // Server frames follow python-can: anything but exactly 3 digits is extended.
        s.len() != 3
    } else {
        s.len() == 8 || v > 0x7FF
    };
    Some((v, ext))
}

fn parse_send<'a>(mut tok: impl Iterator<Item = &'a str>) -> Option<Frame> {
    let (id, ext) = parse_id(tok.next()?, false)?;
    let dlc_s = tok.next()?;
    if dlc_s.len() > 2 {
        return None;
    }
    let dlc = hex_u32(dlc_s)? as usize;
    if dlc > 8 {
        return None;
    }
    let mut data = [0u8; 8];
    let mut n = 0;
    for t in tok {
        if n == 8 || t.len() > 2 {
            return None;
        }
        data[n] = hex_u32(t)? as u8;
        n += 1;
    }
    if n != dlc {
        return None;
    }
    Frame::with_id(id, ext, &data[..n]).ok()
}

fn parse_frame<'a>(mut tok: impl Iterator<Item = &'a str>) -> Option<RxFrame> {
    let (id, ext) = parse_id(tok.next()?, true)?;
    let timestamp = parse_timestamp(tok.next()?)?;
    let hex = tok.next().unwrap_or("");
    if tok.next().is_some() || !hex.len().is_multiple_of(2) || hex.len() > 16 {
        return None;
    }
    let mut data = [0u8; 8];
    for (i, pair) in hex.as_bytes().chunks(2).enumerate() {
        let s = std::str::from_utf8(pair).ok()?;
        data[i] = hex_u32(s)? as u8;
    }
    let frame = Frame::with_id(id, ext, &data[..hex.len() / 2]).ok()?;
    Some(RxFrame { frame, timestamp })
}

/// Parses `SEC.FRACTION` (fraction of any length up to 9 digits) as a wall-clock time.
pub fn parse_timestamp(s: &str) -> Option<SystemTime> {
    let (sec, frac) = s.split_once('.').unwrap_or((s, ""));
    if sec.is_empty()
        || sec.len() > 12
        || frac.len() > 9
        || !sec.bytes().all(|b| b.is_ascii_digit())
        || !frac.bytes().all(|b| b.is_ascii_digit())
    {
        return None;
    }
    let secs: u64 = sec.parse().ok()?;
    let nanos: u32 = if frac.is_empty() {
        0
    } else {
        frac.parse::<u32>().ok()? * 10u32.pow(9 - frac.len() as u32)
    };
    UNIX_EPOCH.checked_add(Duration::new(secs, nanos))
}

fn since_epoch(ts: SystemTime) -> Duration {
    // Times before 1970 cannot be written; clamp rather than fail.
    ts.duration_since(UNIX_EPOCH).unwrap_or_default()
}

/// Appends `< frame ID SEC.USEC DATA >` (server → client).
///
/// A remote frame with DLC 0 becomes a zero-length data frame (the protocol has no RTR);
/// returns `false` and writes nothing for a remote frame with DLC > 0, which cannot be carried.
pub fn write_frame(out: &mut Vec<u8>, frame: &Frame, timestamp: SystemTime) -> bool {
    if frame.is_remote() && frame.dlc() > 0 {
        return false;
    }
    let t = since_epoch(timestamp);
    // Writing into a Vec cannot fail.
    let _ = if frame.is_extended() {
        write!(out, "< frame {:08X} ", frame.id())
    } else {
        write!(out, "< frame {:03X} ", frame.id())
    };
    let _ = write!(out, "{}.{:06} ", t.as_secs(), t.subsec_micros());
    for b in frame.data() {
        let _ = write!(out, "{b:02X}");
    }
    // Always a space before `>`: an empty frame gets the two spaces python-can requires.
    out.extend_from_slice(b" >");
    true
}

/// Appends `< send ID DLC B0 .. >` (client → server); same RTR rule as [`write_frame`].
pub fn write_send(out: &mut Vec<u8>, frame: &Frame) -> bool {
    if frame.is_remote() && frame.dlc() > 0 {
        return false;
    }
    let _ = if frame.is_extended() {
        write!(out, "< send {:08X} ", frame.id())
    } else {
        write!(out, "< send {:03X} ", frame.id())
    };
    let _ = write!(out, "{:x} ", frame.data().len());
    for b in frame.data() {
        let _ = write!(out, "{b:x} ");
    }
    if frame.data().is_empty() {
        // `< send 123 0  >`, as python-can writes it.
        out.push(b' ');
    }
    out.push(b'>');
    true
}

/// Appends `< open CHANNEL >`.
pub fn write_open(out: &mut Vec<u8>, channel: &str) {
    let _ = write!(out, "< open {channel} >");
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn ts(s: u64, us: u32) -> SystemTime {
        UNIX_EPOCH + Duration::new(s, us * 1000)
    }

    fn frame_str(f: &Frame, t: SystemTime) -> String {
        let mut v = Vec::new();
        assert!(write_frame(&mut v, f, t));
        String::from_utf8(v).unwrap()
    }

    fn send_str(f: &Frame) -> String {
        let mut v = Vec::new();
        assert!(write_send(&mut v, f));
        String::from_utf8(v).unwrap()
    }

    #[test]
    fn formats_frames_exactly() {
        let t = ts(1795332392, 674281);
        let f = Frame::new(0x123, &[0xDE, 0xAD, 0xBE, 0xEF]).unwrap();
        assert_eq!(frame_str(&f, t), "< frame 123 1795332392.674281 DEADBEEF >");
        let e = Frame::new(0x80, &[]).unwrap();
        assert_eq!(frame_str(&e, t), "< frame 080 1795332392.674281  >");
        let x = Frame::with_id(0x1ABCDE, true, &[1]).unwrap();
        assert_eq!(frame_str(&x, ts(5, 7)), "< frame 001ABCDE 5.000007 01 >");
        let r0 = Frame::remote(0x705, false, 0).unwrap();
        assert_eq!(frame_str(&r0, t), "< frame 705 1795332392.674281  >");
        assert!(!write_frame(
            &mut Vec::new(),
            &Frame::remote(0x705, false, 1).unwrap(),
            t
        ));
    }

    #[test]
    fn formats_sends_exactly() {
        let f = Frame::new(0x601, &[0x40, 0, 0x10, 0, 0, 0, 0, 0]).unwrap();
        assert_eq!(send_str(&f), "< send 601 8 40 0 10 0 0 0 0 0 >");
        assert_eq!(
            send_str(&Frame::new(0x123, &[]).unwrap()),
            "< send 123 0  >"
        );
        assert_eq!(
            send_str(&Frame::remote(0x77F, false, 0).unwrap()),
            "< send 77F 0  >"
        );
        let x = Frame::with_id(0x12345, true, &[0xff]).unwrap();
        assert_eq!(send_str(&x), "< send 00012345 1 ff >");
        assert!(!write_send(
            &mut Vec::new(),
            &Frame::remote(1, false, 8).unwrap()
        ));
    }

    #[test]
    fn parses_what_python_can_sends() {
        let mut d = Decoder::new();
        let els = d.feed_parse(
            b"< open can0 >< rawmode >< send 601 8 40 0 10 0 0 0 0 0 >< send 77F 0  >< echo >",
        );
        assert_eq!(
            els,
            vec![
                Element::Open("can0".into()),
                Element::RawMode,
                Element::Send(Frame::new(0x601, &[0x40, 0, 0x10, 0, 0, 0, 0, 0]).unwrap()),
                Element::Send(Frame::new(0x77F, &[]).unwrap()),
                Element::Echo,
            ]
        );
        // python-can writes extended ids zero-filled to 8 digits, data upper-case padded.
        assert_eq!(
            Element::parse(b" send 00000123 2 0A FF "),
            Element::Send(Frame::with_id(0x123, true, &[0x0A, 0xFF]).unwrap())
        );
    }

    #[test]
    fn parses_server_frames() {
        let got = Element::parse(b" frame 123 1795332392.674281 DEADBEEF ");
        let want = RxFrame {
            frame: Frame::new(0x123, &[0xDE, 0xAD, 0xBE, 0xEF]).unwrap(),
            timestamp: ts(1795332392, 674281),
        };
        assert_eq!(got, Element::Frame(want));
        match Element::parse(b" frame 0080 1.5  ") {
            Element::Frame(r) => {
                assert!(r.frame.is_extended());
                assert_eq!(r.frame.data(), &[] as &[u8]);
                assert_eq!(r.timestamp, ts(1, 500_000));
            }
            e => panic!("{e:?}"),
        }
    }

    #[test]
    fn malformed_elements_become_other() {
        for body in [
            &b" send 601 9 0 0 0 0 0 0 0 0 0 "[..],
            b" send 601 2 1 ",
            b" send 601 1 100 ",
            b" send 801x 0 ",
            b" send 1FFFFFFFF 0 ",
            b" send ",
            b" frame 123 notatime 00 ",
            b" frame 123 1.0 0 ",
            b" frame 123 1.0 000000000000000000 ",
            b" frame FFF 1.0 ",
            b" open ",
            b" open a b ",
            b"\xff\xfe",
            b"",
            b" bogus ",
        ] {
            assert!(
                matches!(Element::parse(body), Element::Other(_)),
                "{body:?}"
            );
        }
        assert!(matches!(Element::parse(b" error 123 "), Element::Error(_)));
    }

    #[test]
    fn decoder_skips_garbage_and_restarts() {
        let mut d = Decoder::new();
        let mut bodies = Vec::new();
        d.feed(b"junk<  hi ><broken <ok>x>>y", |b| bodies.push(b.to_vec()));
        assert_eq!(bodies, vec![b"  hi ".to_vec(), b"ok".to_vec()]);
        assert!(d.skipped() > 0);
        assert!(!d.is_partial());
    }

    #[test]
    fn decoder_drops_overlong_elements() {
        let mut d = Decoder::new();
        let mut long = vec![b'<'];
        long.extend(std::iter::repeat_n(b'a', 10 * MAX_ELEMENT));
        long.extend_from_slice(b">< ok >");
        assert_eq!(d.feed_parse(&long), vec![Element::Ok]);
        assert!(d.buf.capacity() <= 2 * MAX_ELEMENT);
    }

    proptest! {
        /// Any split of a valid stream decodes to the same elements.
        #[test]
        fn split_anywhere(cuts in proptest::collection::vec(0usize..200, 0..8)) {
            let stream: &[u8] = b"< hi >< frame 123 1.000001 0102 ><echo>< send 00012345 1 ff >< frame 080 2.000000  >";
            let whole = Decoder::new().feed_parse(stream);
            let mut cuts: Vec<usize> = cuts.into_iter().map(|c| c % (stream.len() + 1)).collect();
            cuts.sort();
            let mut d = Decoder::new();
            let mut got = Vec::new();
            let mut last = 0;
            for c in cuts.into_iter().chain([stream.len()]) {
                got.extend(d.feed_parse(&stream[last..c]));
                last = c;
            }
            prop_assert_eq!(got, whole);
        }

        /// Arbitrary bytes never panic and never grow the buffer past the bound.
        #[test]
        fn garbage_never_panics(chunks in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 0..600), 0..8)) {
            let mut d = Decoder::new();
            for c in &chunks {
                let _ = d.feed_parse(c);
                prop_assert!(d.buf.len() <= MAX_ELEMENT);
            }
        }

        /// Formatted frames and sends parse back to the same frame.
        #[test]
        fn format_parse_roundtrip(id in 0u32..0x2000_0000, ext in any::<bool>(), data in proptest::collection::vec(any::<u8>(), 0..=8), s in 0u64..4_000_000_000, us in 0u32..1_000_000) {
            let id = if ext { id } else { id & 0x7FF };
            let f = Frame::with_id(id, ext, &data).unwrap();
            let t = ts(s, us);
            let mut v = Vec::new();
            write_frame(&mut v, &f, t);
            write_send(&mut v, &f);
            let els = Decoder::new().feed_parse(&v);
            prop_assert_eq!(els, vec![Element::Frame(RxFrame { frame: f, timestamp: t }), Element::Send(f)]);
        }
    }
}
