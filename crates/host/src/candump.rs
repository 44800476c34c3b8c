//! candump `-L` log lines: `(1700000000.123456) can0 123#DEADBEEF`.
//!
//! Frames: `123#DEADBEEF` (3-digit standard id, upper-case data), `12345678#..` (8-digit
//! extended id), `080#` (no data), `705#R` / `705#R1` (remote frame, with DLC when > 0). This is
//! what can-utils' `candump -L` writes and `canplayer` and python-can's `can.LogReader` read.
//!
//! Lines that hold something other than a classical frame are read as such ([`Record`]), so that
//! a player can skip them and play the rest: error frames (`20000004#0004000000000000`, an
//! 8-digit id with `CAN_ERR_FLAG` 0x20000000 and the SocketCAN error class below it) and CAN FD
//! frames (`123##1DEADBEEF`: `##`, one hex digit of FD flags, up to 64 data bytes).

use std::io::{self, BufRead, Write};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use canpos_stack::Frame;

/// SocketCAN's `CAN_EFF_FLAG`: the id is 29 bits.
pub const CAN_EFF_FLAG: u32 = 0x8000_0000;
/// SocketCAN's `CAN_RTR_FLAG`: a remote frame.
pub const CAN_RTR_FLAG: u32 = 0x4000_0000;
/// SocketCAN's `CAN_ERR_FLAG`: an error frame; the bits below it are the error class.
pub const CAN_ERR_FLAG: u32 = 0x2000_0000;
/// SocketCAN's `CAN_ERR_MASK`: the error class bits of an error frame's id.
pub const CAN_ERR_MASK: u32 = 0x1FFF_FFFF;

/// An error frame as SocketCAN reports it (`linux/can/error.h`): the error class (e.g.
/// `CAN_ERR_PROT` 0x8, `CAN_ERR_BUSOFF` 0x40) in the id below [`CAN_ERR_FLAG`], details in the
/// 8 data bytes (`data[2]` protocol error type, `data[3]` location, `data[6..8]` counters).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ErrorFrame {
    /// The error class bits (masked with [`CAN_ERR_MASK`]).
    pub class: u32,
    /// The error details (`CAN_ERR_DLC` = 8 bytes).
    pub data: [u8; 8],
}

impl ErrorFrame {
    /// An error frame of `class` (masked to [`CAN_ERR_MASK`]) with `data`.
    pub fn new(class: u32, data: [u8; 8]) -> Self {
        ErrorFrame {
            class: class & CAN_ERR_MASK,
            data,
        }
    }

    /// The SocketCAN `can_id`: [`CAN_ERR_FLAG`] | class.
    pub fn can_id(&self) -> u32 {
        CAN_ERR_FLAG | self.class
    }
}

/// A CAN FD frame as a log holds it (canpos plays only classical CAN; kept to be counted).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FdFrame {
    /// The identifier (11 or 29 bits).
    pub id: u32,
    /// A 29-bit identifier.
    pub extended: bool,
    /// The FD flags (`CANFD_BRS` 0x1, `CANFD_ESI` 0x2).
    pub flags: u8,
    /// Data length (0…64).
    pub len: u8,
    /// Data (the first `len` bytes).
    pub data: [u8; 64],
}

/// What one log line holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Record {
    /// A classical data or remote frame.
    Frame(Frame),
    /// An error frame.
    Error(ErrorFrame),
    /// A CAN FD frame.
    Fd(FdFrame),
}

impl Record {
    /// The classical frame, if this is one.
    pub fn frame(&self) -> Option<&Frame> {
        match self {
            Record::Frame(f) => Some(f),
            _ => None,
        }
    }
}

/// One log line.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct LogEntry {
    /// When the frame was seen (microsecond resolution in the file).
    pub timestamp: SystemTime,
    /// Interface name, e.g. `can0`.
    pub interface: String,
    /// What the line holds.
    pub record: Record,
}

/// Why a line could not be parsed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ParseError {
    /// Missing or malformed `(SEC.USEC)`.
    #[error("bad timestamp: expected `(SECONDS.MICROS)`")]
    Timestamp,
    /// Missing interface name.
    #[error("missing interface name")]
    Interface,
    /// Missing or malformed `ID#DATA`.
    #[error("bad frame `{0}`: expected ID#DATA, e.g. 123#DEADBEEF, 080#, 705#R")]
    Frame(String),
    /// Unexpected text after the frame.
    #[error("unexpected text after the frame")]
    Trailing,
    /// Bytes that are not UTF-8 text (a binary file, another encoding).
    #[error("not UTF-8 text")]
    NotText,
}

/// A parse error with the line it happened on (1-based), or an I/O error.
#[derive(Debug, thiserror::Error)]
pub enum LogError {
    /// A malformed line.
    #[error("line {line}: {error}")]
    Parse {
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        error: ParseError,
    },
    /// A line longer than [`MAX_LINE`]: no log line is, so the input is no log (`/dev/zero`, a
    /// binary file); reading stops there rather than hold a line without end.
    #[error("line {line}: longer than {MAX_LINE} bytes without a newline: not a log")]
    TooLong {
        /// 1-based line number.
        line: usize,
    },
    /// Reading failed.
    #[error("reading log: {0}")]
    Io(#[from] io::Error),
}

/// Longest line a log reader takes, its newline not counted: a candump line of a 64-byte CAN FD frame
/// is under 200 bytes and an ASC line under 400, so this leaves room for any real one while a
/// line without end (`/dev/zero`, a file without newlines) is found after 4 KiB, not after all
/// of it is read.
pub const MAX_LINE: usize = 4096;

/// What [`read_line_bounded`] found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LineRead {
    /// A line (in the buffer, without its newline); the last one of the input may have none.
    Line,
    /// The end of the input.
    End,
    /// More than `max` bytes without a newline; the buffer holds the first of them.
    TooLong,
}

/// Reads the next line of `input` into `line` (cleared first, newline dropped), taking no more
/// than `max` bytes besides the newline: the memory a line costs is bounded whatever the input.
pub fn read_line_bounded(
    input: &mut dyn BufRead,
    line: &mut Vec<u8>,
    max: usize,
) -> io::Result<LineRead> {
    line.clear();
    loop {
        let buf = match input.fill_buf() {
            Ok(b) => b,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e),
        };
        if buf.is_empty() {
            return Ok(if line.is_empty() {
                LineRead::End
            } else {
                LineRead::Line
            });
        }
        let (take, done) = match buf.iter().position(|&b| b == b'\n') {
            Some(i) => (i, true),
            None => (buf.len(), false),
        };
        if line.len() + take > max {
            let room = max.saturating_sub(line.len());
            line.extend_from_slice(&buf[..room.min(take)]);
            return Ok(LineRead::TooLong);
        }
        line.extend_from_slice(&buf[..take]);
        input.consume(take + usize::from(done));
        if done {
            return Ok(LineRead::Line);
        }
    }
}

/// Formats one line (without newline).
pub fn format_line(timestamp: SystemTime, interface: &str, frame: &Frame) -> String {
    format_record_line(timestamp, interface, &Record::Frame(*frame))
}

/// Formats one line of any record (without newline): error frames as can-utils writes them
/// (`20000004#0004000000000000`), FD frames as `123##1DEADBEEF`.
pub fn format_record_line(timestamp: SystemTime, interface: &str, record: &Record) -> String {
    let mut s = String::with_capacity(48);
    let t = timestamp.duration_since(UNIX_EPOCH).unwrap_or_default();
    use std::fmt::Write as _;
    let _ = write!(s, "({}.{:06}) {interface} ", t.as_secs(), t.subsec_micros());
    let frame = match record {
        Record::Frame(f) => f,
        Record::Error(e) => {
            let _ = write!(s, "{:08X}#", e.can_id());
            for b in e.data {
                let _ = write!(s, "{b:02X}");
            }
            return s;
        }
        Record::Fd(f) => {
            let _ = if f.extended {
                write!(s, "{:08X}##{:X}", f.id, f.flags & 0xF)
            } else {
                write!(s, "{:03X}##{:X}", f.id, f.flags & 0xF)
            };
            for b in &f.data[..f.len as usize] {
                let _ = write!(s, "{b:02X}");
            }
            return s;
        }
    };
    let _ = if frame.is_extended() {
        write!(s, "{:08X}#", frame.id())
    } else {
        write!(s, "{:03X}#", frame.id())
    };
    if frame.is_remote() {
        s.push('R');
        if frame.dlc() > 0 {
            let _ = write!(s, "{}", frame.dlc());
        }
    } else {
        for b in frame.data() {
            let _ = write!(s, "{b:02X}");
        }
    }
    s
}

fn parse_timestamp(tok: &str) -> Result<SystemTime, ParseError> {
    let inner = tok
        .strip_prefix('(')
        .and_then(|t| t.strip_suffix(')'))
        .ok_or(ParseError::Timestamp)?;
    crate::socketcand::codec::parse_timestamp(inner).ok_or(ParseError::Timestamp)
}

fn hex(s: &str) -> Option<u32> {
    if s.is_empty() || !s.bytes().all(|b| b.is_ascii_hexdigit()) {
        return None;
    }
    u32::from_str_radix(s, 16).ok()
}

/// Hex data bytes, `.` allowed between them (can-utils allows it for readability).
fn hex_bytes(s: &str, out: &mut [u8]) -> Option<usize> {
    let digits: Vec<u8> = s.bytes().filter(|&b| b != b'.').collect();
    if !digits.len().is_multiple_of(2) || digits.len() > 2 * out.len() {
        return None;
    }
    for (i, pair) in digits.chunks(2).enumerate() {
        out[i] = hex(std::str::from_utf8(pair).ok()?)? as u8;
    }
    Some(digits.len() / 2)
}

/// Parses the `ID#DATA` part of a classical frame (error and FD frames are errors here; see
/// [`parse_record`]).
pub fn parse_frame(tok: &str) -> Result<Frame, ParseError> {
    match parse_record(tok)? {
        Record::Frame(f) => Ok(f),
        _ => Err(ParseError::Frame(tok.chars().take(40).collect())),
    }
}

/// Parses the `ID#DATA` part: a classical frame, an error frame or a CAN FD frame.
pub fn parse_record(tok: &str) -> Result<Record, ParseError> {
    let bad = || ParseError::Frame(tok.chars().take(40).collect());
    let (id_s, rest) = tok.split_once('#').ok_or_else(bad)?;
    let extended = match id_s.len() {
        3 => false,
        8 => true,
        _ => return Err(bad()),
    };
    let id = hex(id_s).ok_or_else(bad)?;
    if let Some(fd) = rest.strip_prefix('#') {
        // `##F` then data; can-utils' CAN XL (`###`) is not read.
        let mut chars = fd.chars();
        let flags = chars.next().and_then(|c| c.to_digit(16)).ok_or_else(bad)? as u8;
        let mut data = [0u8; 64];
        let len = hex_bytes(chars.as_str(), &mut data).ok_or_else(bad)?;
        if id > if extended { 0x1FFF_FFFF } else { 0x7FF } {
            return Err(bad());
        }
        return Ok(Record::Fd(FdFrame {
            id,
            extended,
            flags,
            len: len as u8,
            data,
        }));
    }
    if extended && id & CAN_ERR_FLAG != 0 {
        if id & !(CAN_ERR_FLAG | CAN_ERR_MASK) != 0 {
            return Err(bad());
        }
        let mut data = [0u8; 8];
        hex_bytes(rest, &mut data).ok_or_else(bad)?;
        return Ok(Record::Error(ErrorFrame::new(id, data)));
    }
    if let Some(r) = rest.strip_prefix(['R', 'r']) {
        let dlc = match r {
            "" => 0,
            d if d.len() == 1 => hex(d).filter(|&d| d <= 8).ok_or_else(bad)? as u8,
            _ => return Err(bad()),
        };
        return Frame::remote(id, extended, dlc)
            .map(Record::Frame)
            .map_err(|_| bad());
    }
    let mut data = [0u8; 8];
    let len = hex_bytes(rest, &mut data).ok_or_else(bad)?;
    Frame::with_id(id, extended, &data[..len])
        .map(Record::Frame)
        .map_err(|_| bad())
}

/// Parses one line.
pub fn parse_line(line: &str) -> Result<LogEntry, ParseError> {
    let mut tok = line.split_ascii_whitespace();
    let timestamp = parse_timestamp(tok.next().ok_or(ParseError::Timestamp)?)?;
    let interface = tok.next().ok_or(ParseError::Interface)?.to_string();
    let record = parse_record(tok.next().ok_or_else(|| ParseError::Frame(String::new()))?)?;
    // candump -L of newer can-utils may append ` T` / ` R` (tx/rx direction); accept that.
    match (tok.next(), tok.next()) {
        (None, _) | (Some("T" | "R"), None) => {}
        _ => return Err(ParseError::Trailing),
    }
    Ok(LogEntry {
        timestamp,
        interface,
        record,
    })
}

/// Writes frames as candump `-L` lines.
pub struct LogWriter<W: Write> {
    out: W,
    interface: String,
}

impl<W: Write> LogWriter<W> {
    /// A writer labelling every line with `interface` (e.g. `can0`).
    pub fn new(out: W, interface: &str) -> Self {
        LogWriter {
            out,
            interface: interface.to_string(),
        }
    }

    /// Writes one frame.
    pub fn write(&mut self, timestamp: SystemTime, frame: &Frame) -> io::Result<()> {
        let line = format_line(timestamp, &self.interface, frame);
        self.out.write_all(line.as_bytes())?;
        self.out.write_all(b"\n")
    }

    /// Writes any record (error frames included).
    pub fn write_record(&mut self, timestamp: SystemTime, record: &Record) -> io::Result<()> {
        let line = format_record_line(timestamp, &self.interface, record);
        self.out.write_all(line.as_bytes())?;
        self.out.write_all(b"\n")
    }

    /// Writes an entry with its own interface name.
    pub fn write_entry(&mut self, e: &LogEntry) -> io::Result<()> {
        let line = format_record_line(e.timestamp, &e.interface, &e.record);
        self.out.write_all(line.as_bytes())?;
        self.out.write_all(b"\n")
    }

    /// Flushes the underlying writer.
    pub fn flush(&mut self) -> io::Result<()> {
        self.out.flush()
    }

    /// Returns the underlying writer.
    pub fn into_inner(self) -> W {
        self.out
    }
}

/// Reads candump `-L` lines; an iterator of entries. Blank lines are skipped. A line longer
/// than [`MAX_LINE`] ends the iteration with [`LogError::TooLong`].
pub struct LogReader<R: BufRead> {
    input: R,
    line_no: usize,
    line: Vec<u8>,
    /// A line too long (or an I/O error) ended the log.
    done: bool,
}

impl<R: BufRead> LogReader<R> {
    /// A reader over `input`.
    pub fn new(input: R) -> Self {
        LogReader {
            input,
            line_no: 0,
            line: Vec::new(),
            done: false,
        }
    }

    /// The number of the last line read (1-based).
    pub fn line_number(&self) -> usize {
        self.line_no
    }
}

impl<R: BufRead> Iterator for LogReader<R> {
    type Item = Result<LogEntry, LogError>;

    fn next(&mut self) -> Option<Self::Item> {
        while !self.done {
            // Bytes, not `read_line`: a line that is not UTF-8 is one malformed line (with its
            // number), not an I/O error that ends the log.
            let read = read_line_bounded(&mut self.input, &mut self.line, MAX_LINE);
            match read {
                Ok(LineRead::End) => return None,
                Ok(LineRead::Line) => self.line_no += 1,
                Ok(LineRead::TooLong) => {
                    self.done = true;
                    self.line_no += 1;
                    return Some(Err(LogError::TooLong { line: self.line_no }));
                }
                Err(e) => {
                    self.done = true;
                    return Some(Err(LogError::Io(e)));
                }
            }
            let parsed = match std::str::from_utf8(&self.line) {
                Ok(l) if l.trim().is_empty() => continue,
                Ok(l) => parse_line(l.trim()),
                Err(_) => Err(ParseError::NotText),
            };
            return Some(parsed.map_err(|error| LogError::Parse {
                line: self.line_no,
                error,
            }));
        }
        None
    }
}

/// Microsecond-truncated timestamp, as a log stores it.
pub fn truncate_to_micros(t: SystemTime) -> SystemTime {
    let d = t.duration_since(UNIX_EPOCH).unwrap_or_default();
    UNIX_EPOCH + Duration::new(d.as_secs(), d.subsec_micros() * 1000)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn t(s: u64, us: u32) -> SystemTime {
        UNIX_EPOCH + Duration::new(s, us * 1000)
    }

    #[test]
    fn formats_exactly() {
        let ts = t(1700000000, 123456);
        let cases = [
            (
                Frame::new(0x123, &[0xDE, 0xAD, 0xBE, 0xEF]).unwrap(),
                "(1700000000.123456) can0 123#DEADBEEF",
            ),
            (
                Frame::new(0x080, &[]).unwrap(),
                "(1700000000.123456) can0 080#",
            ),
            (
                Frame::remote(0x705, false, 0).unwrap(),
                "(1700000000.123456) can0 705#R",
            ),
            (
                Frame::remote(0x705, false, 1).unwrap(),
                "(1700000000.123456) can0 705#R1",
            ),
            (
                Frame::with_id(0x12345678, true, &[1]).unwrap(),
                "(1700000000.123456) can0 12345678#01",
            ),
        ];
        for (f, s) in cases {
            assert_eq!(format_line(ts, "can0", &f), s);
            assert_eq!(
                parse_line(s).unwrap(),
                LogEntry {
                    timestamp: ts,
                    interface: "can0".into(),
                    record: Record::Frame(f)
                }
            );
        }
    }

    #[test]
    fn parses_variants() {
        assert_eq!(
            parse_frame("123#de.ad").unwrap(),
            Frame::new(0x123, &[0xDE, 0xAD]).unwrap()
        );
        assert_eq!(
            parse_line("(1.5) vcan0 123# T").unwrap().timestamp,
            t(1, 500_000)
        );
        assert_eq!(
            parse_frame("123##1DEAD"),
            Err(ParseError::Frame("123##1DEAD".into()))
        );
        // python-can's CanutilsLogWriter appends the direction.
        let e = parse_line("(1.500000) can0 705#R R").unwrap();
        assert_eq!(
            e.record,
            Record::Frame(Frame::remote(0x705, false, 0).unwrap())
        );
    }

    #[test]
    fn error_and_fd_frames() {
        let ts = t(1700000000, 5);
        // can-utils: a bus error (CAN_ERR_PROT 0x8 | CAN_ERR_BUSERROR 0x80) with a form error.
        let e = parse_line("(1700000000.000005) can0 20000088#0000020000000000").unwrap();
        let want = ErrorFrame::new(0x88, [0, 0, 2, 0, 0, 0, 0, 0]);
        assert_eq!(e.record, Record::Error(want));
        assert_eq!(want.can_id(), 0x2000_0088);
        assert_eq!(
            format_record_line(ts, "can0", &e.record),
            "(1700000000.000005) can0 20000088#0000020000000000"
        );
        let fd = parse_line("(1.0) can0 123##3DEADBEEF00112233AABB").unwrap();
        let Record::Fd(f) = fd.record else {
            panic!("{fd:?}")
        };
        assert_eq!((f.id, f.extended, f.flags, f.len), (0x123, false, 3, 10));
        assert_eq!(&f.data[..4], &[0xDE, 0xAD, 0xBE, 0xEF]);
        assert_eq!(
            format_record_line(ts, "can0", &fd.record),
            "(1700000000.000005) can0 123##3DEADBEEF00112233AABB"
        );
        let long = format!("(1.0) can0 12345678##0{}", "AB".repeat(64));
        assert!(
            matches!(parse_line(&long).unwrap().record, Record::Fd(f) if f.len == 64 && f.extended)
        );
        for bad in [
            "(1.0) can0 123##",
            "(1.0) can0 123##G00",
            "(1.0) can0 800##0",
            format!("(1.0) can0 123##0{}", "AB".repeat(65)).as_str(),
            "(1.0) can0 60000000#00",
            "(1.0) can0 20000088#000000000000000000",
        ] {
            assert!(
                matches!(parse_line(bad), Err(ParseError::Frame(_))),
                "{bad}"
            );
        }
    }

    #[test]
    fn rejects_bad_lines() {
        for (line, want) in [
            ("", ParseError::Timestamp),
            ("1.0 can0 123#", ParseError::Timestamp),
            ("(1.x) can0 123#", ParseError::Timestamp),
            ("(1.0)", ParseError::Interface),
            ("(1.0) can0", ParseError::Frame(String::new())),
            ("(1.0) can0 12#00", ParseError::Frame("12#00".into())),
            ("(1.0) can0 800#00", ParseError::Frame("800#00".into())),
            ("(1.0) can0 123#0", ParseError::Frame("123#0".into())),
            (
                "(1.0) can0 123#000000000000000000",
                ParseError::Frame("123#000000000000000000".into()),
            ),
            ("(1.0) can0 123#R9", ParseError::Frame("123#R9".into())),
            ("(1.0) can0 123#ZZ", ParseError::Frame("123#ZZ".into())),
            ("(1.0) can0 123 #00", ParseError::Frame("123".into())),
            ("(1.0) can0 123#00 extra stuff", ParseError::Trailing),
        ] {
            assert_eq!(parse_line(line), Err(want), "{line}");
        }
    }

    #[test]
    fn reader_reports_line_numbers() {
        let log = "(1.000000) can0 123#01\n\n(2.000000) can0 nonsense\n(3.000000) can0 080#\n";
        let mut r = LogReader::new(log.as_bytes());
        assert_eq!(
            r.next().unwrap().unwrap().record,
            Record::Frame(Frame::new(0x123, &[1]).unwrap())
        );
        let e = r.next().unwrap().unwrap_err();
        assert_eq!(
            e.to_string(),
            "line 3: bad frame `nonsense`: expected ID#DATA, e.g. 123#DEADBEEF, 080#, 705#R"
        );
        assert_eq!(
            r.next().unwrap().unwrap().record,
            Record::Frame(Frame::new(0x80, &[]).unwrap())
        );
        assert!(r.next().is_none());
        assert_eq!(r.line_number(), 4);
    }

    /// A line without end (`/dev/zero`, a file without newlines) is an error at [`MAX_LINE`]
    /// bytes, with its number, and reading stops: the input is not read to its end.
    #[test]
    fn a_line_without_end_stops_the_reader_at_the_limit() {
        let mut input = b"(1.000000) can0 123#01\n".to_vec();
        input.extend(std::iter::repeat_n(0u8, 10 * MAX_LINE));
        input.extend_from_slice(b"\n(2.000000) can0 123#02\n");
        let mut cursor = io::Cursor::new(&input[..]);
        let mut r = LogReader::new(io::BufReader::with_capacity(512, &mut cursor));
        assert!(r.next().unwrap().is_ok());
        let e = r.next().unwrap().unwrap_err();
        assert!(matches!(e, LogError::TooLong { line: 2 }), "{e}");
        assert_eq!(
            e.to_string(),
            "line 2: longer than 4096 bytes without a newline: not a log"
        );
        assert!(r.next().is_none());
        // Read up to the limit and a buffer more, no further.
        assert!(
            cursor.position() <= (24 + MAX_LINE + 512) as u64,
            "{}",
            cursor.position()
        );
    }

    #[test]
    fn bounded_lines_split_as_lines_do() {
        for (input, max, want) in [
            (
                &b"ab\ncd"[..],
                8,
                vec![
                    (LineRead::Line, &b"ab"[..]),
                    (LineRead::Line, b"cd"),
                    (LineRead::End, b""),
                ],
            ),
            (
                b"\n\n",
                8,
                vec![
                    (LineRead::Line, &b""[..]),
                    (LineRead::Line, b""),
                    (LineRead::End, b""),
                ],
            ),
            // Exactly `max` bytes fit, with their newline or without one at the end; one
            // more does not.
            (
                b"abcd\n",
                4,
                vec![(LineRead::Line, &b"abcd"[..]), (LineRead::End, b"")],
            ),
            (
                b"abcd",
                4,
                vec![(LineRead::Line, &b"abcd"[..]), (LineRead::End, b"")],
            ),
            (b"abcde\n", 4, vec![(LineRead::TooLong, &b"abcd"[..])]),
            (b"abcdef", 4, vec![(LineRead::TooLong, &b"abcd"[..])]),
        ] {
            // One byte at a time too: the limit holds across buffer refills.
            for cap in [1, 64] {
                let mut r = io::BufReader::with_capacity(cap, input);
                let mut line = Vec::new();
                for (kind, text) in &want {
                    assert_eq!(
                        read_line_bounded(&mut r, &mut line, max).unwrap(),
                        *kind,
                        "{input:?}"
                    );
                    assert_eq!(&line[..], *text, "{input:?}");
                }
            }
        }
    }

    fn arb_frame() -> impl Strategy<Value = Frame> {
        (
            0u32..0x2000_0000,
            any::<bool>(),
            any::<bool>(),
            proptest::collection::vec(any::<u8>(), 0..=8),
            0u8..=8,
        )
            .prop_map(|(id, ext, rtr, data, dlc)| {
                let id = if ext { id } else { id & 0x7FF };
                if rtr {
                    Frame::remote(id, ext, dlc).unwrap()
                } else {
                    Frame::with_id(id, ext, &data).unwrap()
                }
            })
    }

    proptest! {
        #[test]
        fn roundtrip(frames in proptest::collection::vec((arb_frame(), 0u64..5_000_000_000, 0u32..1_000_000), 0..20)) {
            let mut w = LogWriter::new(Vec::new(), "vcan0");
            for (f, s, us) in &frames {
                w.write(t(*s, *us), f).unwrap();
            }
            let bytes = w.into_inner();
            let got: Vec<LogEntry> = LogReader::new(&bytes[..]).collect::<Result<_, _>>().unwrap();
            prop_assert_eq!(got.len(), frames.len());
            for (e, (f, s, us)) in got.iter().zip(&frames) {
                prop_assert_eq!(e.record, Record::Frame(*f));
                prop_assert_eq!(e.timestamp, t(*s, *us));
                prop_assert_eq!(&e.interface, "vcan0");
            }
        }

        #[test]
        fn parse_never_panics(s in "\\PC{0,80}") {
            let _ = parse_line(&s);
        }
    }
}
