//! Capture files `canpos record` writes and `canpos replay` reads (docs/FILES.md):
//!
//! * pcapng and pcap with `LINKTYPE_CAN_SOCKETCAN` (227): each packet is SocketCAN's 16-byte
//!   `struct can_frame` with the `can_id` (and its EFF / RTR / ERR flags) big-endian, as the
//!   link type's definition asks; Wireshark and tshark read both live from a pipe;
//! * candump `-L` logs (`canpos_host::candump`);
//! * Vector ASC (`base hex  timestamps absolute`), as python-can's `ASCWriter` and CANalyzer
//!   write it.
//!
//! Writers take [`Record`]s so that error frames (SocketCAN `CAN_ERR_FLAG` with the error class
//! in the id) are written the same way as data and remote frames once a bus delivers them.
//! Every writer flushes after each record: `canpos record - | wireshark -k -i -` is a live view.

use std::io::{self, BufRead, Write};
use std::path::Path;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use canpos_host::candump::{
    format_record_line, read_line_bounded, ErrorFrame, FdFrame, LineRead, LogError, LogReader,
    Record, CAN_EFF_FLAG, CAN_ERR_FLAG, CAN_RTR_FLAG, MAX_LINE,
};
use canpos_stack::Frame;

/// `LINKTYPE_CAN_SOCKETCAN`.
pub const LINKTYPE_CAN_SOCKETCAN: u16 = 227;

/// The file formats.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    /// pcapng (Wireshark's default), nanosecond timestamps.
    Pcapng,
    /// Classic pcap, nanosecond timestamps.
    Pcap,
    /// can-utils `candump -L` log.
    Candump,
    /// Vector ASC.
    Asc,
}

impl Format {
    /// The format a file name's extension names: `.pcapng`, `.pcap`, `.log` / `.candump`,
    /// `.asc` (case-insensitive).
    pub fn from_path(p: &Path) -> Option<Format> {
        let ext = p.extension()?.to_str()?.to_ascii_lowercase();
        Some(match ext.as_str() {
            "pcapng" => Format::Pcapng,
            "pcap" => Format::Pcap,
            "log" | "candump" => Format::Candump,
            "asc" => Format::Asc,
            _ => return None,
        })
    }
}

/// The SocketCAN `can_frame` of a record, as LINKTYPE_CAN_SOCKETCAN stores it: `can_id`
/// big-endian, `len`, three reserved bytes (`__pad`, `__res0`, `len8_dlc`), 8 data bytes.
/// CAN FD frames are not written (canpos buses carry classical CAN only).
pub fn socketcan_bytes(record: &Record) -> Option<[u8; 16]> {
    let (id, len, data) = match record {
        Record::Frame(f) => {
            let mut id = f.id();
            if f.is_extended() {
                id |= CAN_EFF_FLAG;
            }
            let mut data = [0u8; 8];
            if f.is_remote() {
                id |= CAN_RTR_FLAG;
            } else {
                data[..f.data().len()].copy_from_slice(f.data());
            }
            (id, f.dlc(), data)
        }
        // CAN_ERR_DLC: error frames always carry 8 bytes.
        Record::Error(e) => (e.can_id(), 8, e.data),
        Record::Fd(_) => return None,
    };
    let mut b = [0u8; 16];
    b[..4].copy_from_slice(&id.to_be_bytes());
    b[4] = len;
    b[8..].copy_from_slice(&data);
    Some(b)
}

/// Decodes a LINKTYPE_CAN_SOCKETCAN packet written by [`socketcan_bytes`] (for tests and for
/// tools reading canpos captures back).
pub fn parse_socketcan(b: &[u8]) -> Option<Record> {
    if b.len() < 8 {
        return None;
    }
    let id = u32::from_be_bytes(b[..4].try_into().ok()?);
    let len = b[4];
    let payload = b.get(8..8 + (len as usize).min(8))?;
    if id & CAN_ERR_FLAG != 0 {
        let mut data = [0u8; 8];
        data[..payload.len()].copy_from_slice(payload);
        return Some(Record::Error(ErrorFrame::new(id, data)));
    }
    let ext = id & CAN_EFF_FLAG != 0;
    let raw = id & if ext { 0x1FFF_FFFF } else { 0x7FF };
    let f = if id & CAN_RTR_FLAG != 0 {
        Frame::remote(raw, ext, len.min(8)).ok()?
    } else {
        Frame::with_id(raw, ext, payload).ok()?
    };
    Some(Record::Frame(f))
}

fn since_epoch(t: SystemTime) -> Duration {
    t.duration_since(UNIX_EPOCH).unwrap_or_default()
}

/// A capture writer of one of the [`Format`]s.
pub struct CaptureWriter<W: Write> {
    out: W,
    format: Format,
    /// The ASC header's time (first record's, or the end's for an empty file); `None` until
    /// written. pcapng / pcap headers are written in [`CaptureWriter::new`].
    asc_start: Option<SystemTime>,
    interface: String,
}

fn pad4(n: usize) -> usize {
    (4 - n % 4) % 4
}

/// A pcapng option: code, length, value padded to 32 bits.
fn pcapng_option(buf: &mut Vec<u8>, code: u16, value: &[u8]) {
    buf.extend_from_slice(&code.to_le_bytes());
    buf.extend_from_slice(&(value.len() as u16).to_le_bytes());
    buf.extend_from_slice(value);
    buf.extend(std::iter::repeat_n(0, pad4(value.len())));
}

/// A pcapng block: type, total length, body, total length again.
fn pcapng_block(out: &mut impl Write, block_type: u32, body: &[u8]) -> io::Result<()> {
    let total = (12 + body.len()) as u32;
    let mut b = Vec::with_capacity(total as usize);
    b.extend_from_slice(&block_type.to_le_bytes());
    b.extend_from_slice(&total.to_le_bytes());
    b.extend_from_slice(body);
    b.extend_from_slice(&total.to_le_bytes());
    out.write_all(&b)
}

impl<W: Write> CaptureWriter<W> {
    /// Starts a capture of `interface` (the name pcapng and candump record): writes the pcapng
    /// section header and interface description, or the pcap file header.
    pub fn new(mut out: W, format: Format, interface: &str) -> io::Result<Self> {
        match format {
            Format::Pcapng => {
                // Section header: byte-order magic, version 1.0, section length unknown.
                let mut shb = Vec::new();
                shb.extend_from_slice(&0x1A2B_3C4Du32.to_le_bytes());
                shb.extend_from_slice(&1u16.to_le_bytes());
                shb.extend_from_slice(&0u16.to_le_bytes());
                shb.extend_from_slice(&(-1i64).to_le_bytes());
                pcapng_option(
                    &mut shb,
                    4,
                    concat!("canpos ", env!("CARGO_PKG_VERSION")).as_bytes(),
                );
                pcapng_option(&mut shb, 0, &[]);
                pcapng_block(&mut out, 0x0A0D_0D0A, &shb)?;
                // Interface description: link type, snap length 0 (no limit), name, ns stamps.
                let mut idb = Vec::new();
                idb.extend_from_slice(&LINKTYPE_CAN_SOCKETCAN.to_le_bytes());
                idb.extend_from_slice(&0u16.to_le_bytes());
                idb.extend_from_slice(&0u32.to_le_bytes());
                pcapng_option(&mut idb, 2, interface.as_bytes());
                pcapng_option(&mut idb, 9, &[9]);
                pcapng_option(&mut idb, 0, &[]);
                pcapng_block(&mut out, 1, &idb)?;
            }
            Format::Pcap => {
                // Nanosecond-resolution magic, version 2.4, snap length 16 (a can_frame).
                let mut h = Vec::with_capacity(24);
                h.extend_from_slice(&0xA1B2_3C4Du32.to_le_bytes());
                h.extend_from_slice(&2u16.to_le_bytes());
                h.extend_from_slice(&4u16.to_le_bytes());
                h.extend_from_slice(&0i32.to_le_bytes());
                h.extend_from_slice(&0u32.to_le_bytes());
                h.extend_from_slice(&16u32.to_le_bytes());
                h.extend_from_slice(&(LINKTYPE_CAN_SOCKETCAN as u32).to_le_bytes());
                out.write_all(&h)?;
            }
            Format::Candump | Format::Asc => {}
        }
        out.flush()?;
        Ok(CaptureWriter {
            out,
            format,
            asc_start: None,
            interface: interface.to_string(),
        })
    }

    /// Writes one record stamped `t` and flushes. FD records cannot be written to pcap /
    /// pcapng / ASC here (`InvalidInput`).
    pub fn write(&mut self, t: SystemTime, record: &Record) -> io::Result<()> {
        let unsupported = || {
            io::Error::new(
                io::ErrorKind::InvalidInput,
                "CAN FD frames are not recorded",
            )
        };
        match self.format {
            Format::Pcapng => {
                let pkt = socketcan_bytes(record).ok_or_else(unsupported)?;
                let ns = since_epoch(t).as_nanos() as u64;
                let mut epb = Vec::with_capacity(20 + 16);
                epb.extend_from_slice(&0u32.to_le_bytes());
                epb.extend_from_slice(&((ns >> 32) as u32).to_le_bytes());
                epb.extend_from_slice(&(ns as u32).to_le_bytes());
                epb.extend_from_slice(&16u32.to_le_bytes());
                epb.extend_from_slice(&16u32.to_le_bytes());
                epb.extend_from_slice(&pkt);
                pcapng_block(&mut self.out, 6, &epb)?;
            }
            Format::Pcap => {
                let pkt = socketcan_bytes(record).ok_or_else(unsupported)?;
                let d = since_epoch(t);
                let mut r = Vec::with_capacity(32);
                r.extend_from_slice(&(d.as_secs() as u32).to_le_bytes());
                r.extend_from_slice(&d.subsec_nanos().to_le_bytes());
                r.extend_from_slice(&16u32.to_le_bytes());
                r.extend_from_slice(&16u32.to_le_bytes());
                r.extend_from_slice(&pkt);
                self.out.write_all(&r)?;
            }
            Format::Candump => {
                let line = format_record_line(t, &self.interface, record);
                self.out.write_all(line.as_bytes())?;
                self.out.write_all(b"\n")?;
            }
            Format::Asc => {
                let start = match self.asc_start {
                    Some(s) => s,
                    None => {
                        self.write_asc_header(t)?;
                        t
                    }
                };
                let rel = t.duration_since(start).unwrap_or_default();
                let line = asc_line(rel, record).ok_or_else(unsupported)?;
                self.out.write_all(line.as_bytes())?;
            }
        }
        self.out.flush()
    }

    fn write_asc_header(&mut self, start: SystemTime) -> io::Result<()> {
        let date = asc_date(start);
        write!(
            self.out,
            "date {date}\nbase hex  timestamps absolute\ninternal events logged\n\
             // version 9.0.0\nBegin Triggerblock {date}\n   0.000000 Start of measurement\n"
        )?;
        self.asc_start = Some(start);
        Ok(())
    }

    /// Ends the file (ASC: `End TriggerBlock`; a capture with no frames still gets its header)
    /// and returns the writer.
    pub fn finish(mut self) -> io::Result<W> {
        if self.format == Format::Asc {
            if self.asc_start.is_none() {
                self.write_asc_header(SystemTime::now())?;
            }
            self.out.write_all(b"End TriggerBlock\n")?;
        }
        self.out.flush()?;
        Ok(self.out)
    }
}

/// The ASC line of one record (`   1.234567 1  123             Rx   d 2 01 02`), relative to
/// the start of measurement; channel 1.
pub fn asc_line(rel: Duration, record: &Record) -> Option<String> {
    use std::fmt::Write as _;
    let mut s = format!("{:>11.6} ", rel.as_secs_f64());
    match record {
        Record::Frame(f) => {
            let mut id = format!("{:X}", f.id());
            if f.is_extended() {
                id.push('x');
            }
            let _ = write!(s, "1  {id:<15} Rx   ");
            if f.is_remote() {
                let _ = write!(s, "r {:X}", f.dlc());
            } else {
                let _ = write!(s, "d {:X}", f.dlc());
                for b in f.data() {
                    let _ = write!(s, " {b:02X}");
                }
            }
        }
        Record::Error(_) => s.push_str("1  ErrorFrame"),
        Record::Fd(_) => return None,
    }
    s.push('\n');
    Some(s)
}

const WEEKDAYS: [&str; 7] = ["Thu", "Fri", "Sat", "Sun", "Mon", "Tue", "Wed"];
const MONTHS: [&str; 12] = [
    "Jan", "Feb", "Mar", "Apr", "May", "Jun", "Jul", "Aug", "Sep", "Oct", "Nov", "Dec",
];

/// UTC civil date of a day count since 1970-01-01 (H. Hinnant's algorithm): (year, month, day).
pub fn civil_from_days(days: i64) -> (i64, u32, u32) {
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = (doy - (153 * mp + 2) / 5 + 1) as u32;
    let m = if mp < 10 { mp + 3 } else { mp - 9 } as u32;
    (yoe + era * 400 + (m <= 2) as i64, m, d)
}

/// UTC broken down: (year, month, day, hour, minute, second, millisecond, weekday 0=Thu).
fn utc(t: SystemTime) -> (i64, u32, u32, u32, u32, u32, u32, usize) {
    let d = since_epoch(t);
    let secs = d.as_secs() as i64;
    let days = secs.div_euclid(86_400);
    let sod = secs.rem_euclid(86_400) as u32;
    let (y, m, dd) = civil_from_days(days);
    (
        y,
        m,
        dd,
        sod / 3600,
        sod / 60 % 60,
        sod % 60,
        d.subsec_millis(),
        days.rem_euclid(7) as usize,
    )
}

/// The ASC header date, `Tue Dec 1 08:01:02.123 pm 2026` (UTC).
pub fn asc_date(t: SystemTime) -> String {
    let (y, m, d, h, mi, s, ms, wd) = utc(t);
    let (h12, ampm) = match h {
        0 => (12, "am"),
        1..=11 => (h, "am"),
        12 => (12, "pm"),
        _ => (h - 12, "pm"),
    };
    format!(
        "{} {} {d} {h12:02}:{mi:02}:{s:02}.{ms:03} {ampm} {y}",
        WEEKDAYS[wd],
        MONTHS[m as usize - 1]
    )
}

/// The date and time of `t` (UTC) as an EDS wants them: `MM-DD-YYYY` and `hh:mm(AM|PM)`.
pub fn eds_date_time(t: SystemTime) -> (String, String) {
    let (y, m, d, h, mi, ..) = utc(t);
    let (h12, ampm) = match h {
        0 => (12, "AM"),
        1..=11 => (h, "AM"),
        12 => (12, "PM"),
        _ => (h - 12, "PM"),
    };
    (
        format!("{m:02}-{d:02}-{y:04}"),
        format!("{h12:02}:{mi:02}{ampm}"),
    )
}

/// What an ASC line holds.
#[derive(Debug, Clone, PartialEq)]
pub enum AscLine {
    /// A header or event line without a frame (`date …`, `Start of measurement`, comments).
    NoFrame,
    /// A frame line: seconds since the start of measurement and the record.
    Record(f64, Record),
}

/// Parses one line of a Vector ASC file (hex base). `Err` holds why a line is malformed.
pub fn parse_asc_line(line: &str) -> Result<AscLine, String> {
    let l = line.trim();
    let lower = l.to_ascii_lowercase();
    if lower.starts_with("base dec") {
        return Err("decimal ASC files (`base dec`) are not read".into());
    }
    if l.is_empty()
        || l.starts_with("//")
        || [
            "date ",
            "base ",
            "internal events",
            "no internal events",
            "begin triggerblock",
            "end triggerblock",
        ]
        .iter()
        .any(|p| lower.starts_with(p))
    {
        return Ok(AscLine::NoFrame);
    }
    let mut tok = l.split_ascii_whitespace();
    let t: f64 = tok
        .next()
        .and_then(|s| s.parse().ok())
        .filter(|t: &f64| t.is_finite() && *t >= 0.0)
        .ok_or("expected a timestamp in seconds")?;
    let rest: Vec<&str> = tok.collect();
    match rest.as_slice() {
        [] => Err("nothing after the timestamp".into()),
        ["Start", "of", "measurement"] => Ok(AscLine::NoFrame),
        ["CANFD", ..] => {
            // CANFD ch dir id [symbolic name] brs esi dlc len data…: the frame is counted, not
            // decoded further.
            Ok(AscLine::Record(
                t,
                Record::Fd(FdFrame {
                    id: 0,
                    extended: false,
                    flags: 0,
                    len: 0,
                    data: [0; 64],
                }),
            ))
        }
        [_, "ErrorFrame", ..] | ["ErrorFrame", ..] => Ok(AscLine::Record(
            t,
            // ASC says only "an error frame"; SocketCAN's nearest class is a protocol error.
            Record::Error(ErrorFrame::new(0x8, [0; 8])),
        )),
        [ch, id, dir, kind, more @ ..] if ch.parse::<u8>().is_ok() => {
            if !matches!(*dir, "Rx" | "Tx" | "TxRq") {
                return Err(format!("expected Rx or Tx, found `{dir}`"));
            }
            let (id_s, ext) = match id.strip_suffix(['x', 'X']) {
                Some(s) => (s, true),
                None => (*id, false),
            };
            let raw = u32::from_str_radix(id_s, 16).map_err(|_| format!("bad id `{id}`"))?;
            let dlc_of = |s: Option<&&str>| -> Result<u8, String> {
                s.and_then(|d| u8::from_str_radix(d, 16).ok())
                    .filter(|&d| d <= 8)
                    .ok_or_else(|| "bad or missing DLC (0…8)".to_string())
            };
            let frame = match *kind {
                "r" | "R" => {
                    // Older writers put no DLC after `r`.
                    let dlc = if more.is_empty() {
                        0
                    } else {
                        dlc_of(more.first())?
                    };
                    Frame::remote(raw, ext, dlc)
                }
                "d" | "D" => {
                    let dlc = dlc_of(more.first())? as usize;
                    let bytes = more.get(1..=dlc).ok_or("fewer data bytes than the DLC")?;
                    let mut data = [0u8; 8];
                    for (i, b) in bytes.iter().enumerate() {
                        data[i] = u8::from_str_radix(b, 16)
                            .ok()
                            .filter(|_| b.len() <= 2)
                            .ok_or_else(|| format!("bad data byte `{b}`"))?;
                    }
                    Frame::with_id(raw, ext, &data[..dlc])
                }
                k => return Err(format!("expected d or r, found `{k}`")),
            }
            .map_err(|_| format!("id `{id}` out of range"))?;
            Ok(AscLine::Record(t, Record::Frame(frame)))
        }
        // Other events (statistics, status lines of a CAN channel): no frame to play.
        [ch, ..] if ch.parse::<u8>().is_ok() => Ok(AscLine::NoFrame),
        _ => Err("not an ASC frame line".into()),
    }
}

/// One line of a log as `canpos replay` takes it.
#[derive(Debug, Clone, PartialEq)]
pub enum LogItem {
    /// A record at `t` seconds from the log's start (candump: the first line's stamp; ASC: the
    /// start of measurement), from line `line`.
    Record {
        /// 1-based line number.
        line: usize,
        /// Seconds from the log's start.
        t: f64,
        /// What the line holds.
        record: Record,
    },
    /// A line that is neither a frame nor a line a log may hold besides frames.
    Malformed {
        /// 1-based line number.
        line: usize,
        /// Why.
        why: String,
    },
}

/// The lines of a candump `-L` log or an ASC file, one at a time: no line longer than
/// [`MAX_LINE`] is held (a longer one ends the log with [`LogError::TooLong`]), and nothing
/// is read ahead of the line asked for but the reader's buffer. Lines without a frame (blank
/// lines, ASC headers and events) are passed over.
pub struct LogItems {
    inner: Inner,
}

enum Inner {
    Candump {
        reader: LogReader<Box<dyn BufRead>>,
        first: Option<SystemTime>,
    },
    Asc {
        input: Box<dyn BufRead>,
        line_no: usize,
        line: Vec<u8>,
        done: bool,
    },
}

impl LogItems {
    /// The lines of `input` in `format`: candump or ASC (the others are not read back).
    pub fn new(input: Box<dyn BufRead>, format: Format) -> Option<LogItems> {
        let inner = match format {
            Format::Candump => Inner::Candump {
                reader: LogReader::new(input),
                first: None,
            },
            Format::Asc => Inner::Asc {
                input,
                line_no: 0,
                line: Vec::new(),
                done: false,
            },
            Format::Pcapng | Format::Pcap => return None,
        };
        Some(LogItems { inner })
    }
}

impl Iterator for LogItems {
    type Item = Result<LogItem, LogError>;

    fn next(&mut self) -> Option<Self::Item> {
        match &mut self.inner {
            Inner::Candump { reader, first } => {
                let item = match reader.next()? {
                    Ok(e) => {
                        let t0 = *first.get_or_insert(e.timestamp);
                        // A stamp before the first one plays at the start.
                        let rel = e.timestamp.duration_since(t0).unwrap_or_default();
                        LogItem::Record {
                            line: reader.line_number(),
                            t: rel.as_secs_f64(),
                            record: e.record,
                        }
                    }
                    Err(LogError::Parse { line, error }) => LogItem::Malformed {
                        line,
                        why: error.to_string(),
                    },
                    Err(e) => return Some(Err(e)),
                };
                Some(Ok(item))
            }
            Inner::Asc {
                input,
                line_no,
                line,
                done,
            } => loop {
                if *done {
                    return None;
                }
                let read = read_line_bounded(input, line, MAX_LINE);
                *line_no += 1;
                match read {
                    Ok(LineRead::Line) => {}
                    Ok(LineRead::End) => return None,
                    Ok(LineRead::TooLong) => {
                        *done = true;
                        return Some(Err(LogError::TooLong { line: *line_no }));
                    }
                    Err(e) => {
                        *done = true;
                        return Some(Err(LogError::Io(e)));
                    }
                }
                // Bytes per line: one that is not UTF-8 is malformed, not the end of the log.
                let Ok(text) = std::str::from_utf8(line) else {
                    return Some(Ok(LogItem::Malformed {
                        line: *line_no,
                        why: "not UTF-8 text".into(),
                    }));
                };
                match parse_asc_line(text) {
                    Ok(AscLine::NoFrame) => {}
                    Ok(AscLine::Record(t, record)) => {
                        return Some(Ok(LogItem::Record {
                            line: *line_no,
                            t,
                            record,
                        }))
                    }
                    Err(why) => {
                        return Some(Ok(LogItem::Malformed {
                            line: *line_no,
                            why,
                        }))
                    }
                }
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn t(s: u64, ns: u32) -> SystemTime {
        UNIX_EPOCH + Duration::new(s, ns)
    }

    #[test]
    fn socketcan_encoding() {
        let f = Frame::new(0x181, &[1, 2]).unwrap();
        let b = socketcan_bytes(&Record::Frame(f)).unwrap();
        assert_eq!(&b[..], &[0, 0, 1, 0x81, 2, 0, 0, 0, 1, 2, 0, 0, 0, 0, 0, 0]);
        let r = Frame::remote(0x705, false, 1).unwrap();
        let b = socketcan_bytes(&Record::Frame(r)).unwrap();
        assert_eq!(&b[..8], &[0x40, 0, 0x07, 0x05, 1, 0, 0, 0]);
        let x = Frame::with_id(0x1234_5678, true, &[9]).unwrap();
        let b = socketcan_bytes(&Record::Frame(x)).unwrap();
        assert_eq!(&b[..5], &[0x92, 0x34, 0x56, 0x78, 1]);
        // Bus-off (CAN_ERR_BUSOFF 0x40) and a protocol form error (CAN_ERR_PROT 0x8,
        // data[2] = CAN_ERR_PROT_FORM 0x02) as SocketCAN delivers them.
        let e = ErrorFrame::new(0x48, [0, 0, 0x02, 0, 0, 0, 0x7F, 0x10]);
        let b = socketcan_bytes(&Record::Error(e)).unwrap();
        assert_eq!(
            &b[..],
            &[0x20, 0, 0, 0x48, 8, 0, 0, 0, 0, 0, 2, 0, 0, 0, 0x7F, 0x10]
        );
        for rec in [
            Record::Frame(f),
            Record::Frame(r),
            Record::Frame(x),
            Record::Error(e),
        ] {
            assert_eq!(parse_socketcan(&socketcan_bytes(&rec).unwrap()), Some(rec));
        }
    }

    #[test]
    fn pcapng_layout() {
        let mut w = CaptureWriter::new(Vec::new(), Format::Pcapng, "can0").unwrap();
        let f = Frame::new(0x701, &[0]).unwrap();
        w.write(t(1, 5), &Record::Frame(f)).unwrap();
        let b = w.finish().unwrap();
        // SHB: type, length, byte-order magic.
        assert_eq!(&b[..4], &[0x0A, 0x0D, 0x0D, 0x0A]);
        assert_eq!(&b[8..12], &0x1A2B_3C4Du32.to_le_bytes());
        let shb_len = u32::from_le_bytes(b[4..8].try_into().unwrap()) as usize;
        let idb = &b[shb_len..];
        assert_eq!(u32::from_le_bytes(idb[..4].try_into().unwrap()), 1);
        assert_eq!(u16::from_le_bytes(idb[8..10].try_into().unwrap()), 227);
        let idb_len = u32::from_le_bytes(idb[4..8].try_into().unwrap()) as usize;
        let epb = &idb[idb_len..];
        assert_eq!(u32::from_le_bytes(epb[..4].try_into().unwrap()), 6);
        let ns = 1_000_000_005u64;
        assert_eq!(
            u32::from_le_bytes(epb[12..16].try_into().unwrap()),
            (ns >> 32) as u32
        );
        assert_eq!(
            u32::from_le_bytes(epb[16..20].try_into().unwrap()),
            ns as u32
        );
        assert_eq!(parse_socketcan(&epb[28..44]), Some(Record::Frame(f)));
        assert_eq!(epb.len(), 48);
    }

    #[test]
    fn pcap_layout() {
        let mut w = CaptureWriter::new(Vec::new(), Format::Pcap, "can0").unwrap();
        let e = ErrorFrame::new(0x4, [0, 0x10, 0, 0, 0, 0, 0, 0]);
        w.write(t(7, 123), &Record::Error(e)).unwrap();
        let b = w.finish().unwrap();
        assert_eq!(b.len(), 24 + 16 + 16);
        assert_eq!(&b[20..24], &227u32.to_le_bytes());
        assert_eq!(&b[24..28], &7u32.to_le_bytes());
        assert_eq!(&b[28..32], &123u32.to_le_bytes());
        assert_eq!(parse_socketcan(&b[40..]), Some(Record::Error(e)));
    }

    #[test]
    fn asc_roundtrip() {
        let recs = [
            Record::Frame(Frame::new(0x123, &[0xDE, 0xAD]).unwrap()),
            Record::Frame(Frame::with_id(0x1abc_def0, true, &[]).unwrap()),
            Record::Frame(Frame::remote(0x705, false, 1).unwrap()),
            Record::Error(ErrorFrame::new(0x8, [0; 8])),
        ];
        let mut w = CaptureWriter::new(Vec::new(), Format::Asc, "can0").unwrap();
        for (i, r) in recs.iter().enumerate() {
            w.write(
                t(1_764_619_262, 0) + Duration::from_millis(i as u64 * 1500),
                r,
            )
            .unwrap();
        }
        let text = String::from_utf8(w.finish().unwrap()).unwrap();
        assert!(
            text.starts_with("date Mon Dec 1 08:01:02.000 pm 2025\n"),
            "{text}"
        );
        assert!(
            text.contains("   1.500000 1  1ABCDEF0x       Rx   d 0\n"),
            "{text}"
        );
        assert!(text.ends_with("End TriggerBlock\n"));
        let got: Vec<(f64, Record)> = text
            .lines()
            .filter_map(|l| match parse_asc_line(l).unwrap() {
                AscLine::Record(t, r) => Some((t, r)),
                AscLine::NoFrame => None,
            })
            .collect();
        assert_eq!(got.len(), 4);
        for (i, ((ts, r), want)) in got.iter().zip(&recs).enumerate() {
            assert_eq!(r, want);
            assert!((ts - i as f64 * 1.5).abs() < 1e-9);
        }
    }

    #[test]
    fn asc_bad_lines() {
        for l in [
            "x 1 123 Rx d 1 00",
            "0.1 1 123 Up d 1 00",
            "0.1 1 ZZZ Rx d 1 00",
            "0.1 1 123 Rx d 2 00",
            "0.1 1 123 Rx d 9 00",
            "0.1 1 123 Rx q 1 00",
            "0.1 1 800 Rx d 0",
            "0.1 1 123 Rx d 1 100",
            "base dec  timestamps absolute",
            "-1 1 123 Rx d 0",
            "NaN 1 123 Rx d 0",
        ] {
            assert!(parse_asc_line(l).is_err(), "{l}");
        }
        assert_eq!(
            parse_asc_line("   0.000000 Start of measurement"),
            Ok(AscLine::NoFrame)
        );
        assert!(matches!(
            parse_asc_line("0.2 CANFD   1 Rx 123  1 0 8 8 11 22 33 44 55 66 77 88 0 0 0 0 0 0 0 0"),
            Ok(AscLine::Record(_, Record::Fd(_)))
        ));
    }

    /// Every prefix of real lines and every one-character change of them: an answer, never a
    /// panic (the fuzz-like sweep of a line parser, deterministic).
    #[test]
    fn asc_parser_takes_any_mutation() {
        let lines = [
            "   0.001000 1  701             Rx   d 8 01 02 03 04 05 06 07 08",
            "   0.004000 1  1ABCDEF0x       Rx   r 8",
            "0.2 CANFD   1 Rx 123  1 0 8 8 11 22 33 44 55 66 77 88 0 0 0 0 0 0 0 0",
            "   0.002000 1  ErrorFrame",
            "date Tue Dec 1 08:01:02.000 pm 2026",
        ];
        let subs = ['0', 'F', 'x', ' ', '-', '.', 'r', 'd', '9', '\u{e9}', '\t'];
        for l in lines {
            let chars: Vec<char> = l.chars().collect();
            for i in 0..=chars.len() {
                let _ = parse_asc_line(&chars[..i].iter().collect::<String>());
                if i < chars.len() {
                    for c in subs {
                        let mut m = chars.clone();
                        m[i] = c;
                        let _ = parse_asc_line(&m.iter().collect::<String>());
                    }
                }
            }
        }
        // Huge numbers: errors, not panics or wrap-arounds.
        assert!(parse_asc_line("1e400 1 123 Rx d 0").is_err());
        assert!(parse_asc_line("0.1 1 FFFFFFFFFFFFFFFFFFFF Rx d 0").is_err());
        assert!(parse_asc_line("0.1 1 123 Rx d FFFFFFFFFFFFFFFFFFFFFF").is_err());
    }

    /// Every writer, every kind of record: what each reader gets back is what was written.
    #[test]
    fn writers_roundtrip() {
        let recs = [
            Record::Frame(Frame::new(0x000, &[0x01, 0x05]).unwrap()),
            Record::Frame(Frame::new(0x7FF, &[0xFF; 8]).unwrap()),
            Record::Frame(Frame::with_id(0x1FFF_FFFF, true, &[1, 2, 3]).unwrap()),
            Record::Frame(Frame::remote(0x705, false, 0).unwrap()),
            Record::Frame(Frame::remote(0x1234_5678, true, 8).unwrap()),
            Record::Error(ErrorFrame::new(0x40, [0, 0, 0, 0, 0, 0, 0x80, 0x7F])),
        ];
        let stamps: Vec<SystemTime> = (0..recs.len())
            .map(|i| t(1_700_000_000 + i as u64, 1000 * i as u32))
            .collect();
        for format in [Format::Pcapng, Format::Pcap, Format::Candump, Format::Asc] {
            let mut w = CaptureWriter::new(Vec::new(), format, "vcan0").unwrap();
            for (r, ts) in recs.iter().zip(&stamps) {
                w.write(*ts, r).unwrap();
            }
            let b = w.finish().unwrap();
            let got: Vec<Record> = match format {
                Format::Pcapng => {
                    // Skip SHB and IDB, then 48-byte EPBs.
                    let shb = u32::from_le_bytes(b[4..8].try_into().unwrap()) as usize;
                    let idb = u32::from_le_bytes(b[shb + 4..shb + 8].try_into().unwrap()) as usize;
                    b[shb + idb..]
                        .chunks(48)
                        .map(|epb| parse_socketcan(&epb[28..44]).unwrap())
                        .collect()
                }
                Format::Pcap => b[24..]
                    .chunks(32)
                    .map(|r| parse_socketcan(&r[16..]).unwrap())
                    .collect(),
                Format::Candump => canpos_host::candump::LogReader::new(&b[..])
                    .map(|e| e.unwrap().record)
                    .collect(),
                Format::Asc => std::str::from_utf8(&b)
                    .unwrap()
                    .lines()
                    .filter_map(|l| match parse_asc_line(l).unwrap() {
                        AscLine::Record(_, r) => Some(r),
                        AscLine::NoFrame => None,
                    })
                    .collect(),
            };
            // ASC carries no error class: an error frame reads back as "an error frame".
            let want: Vec<Record> = recs
                .iter()
                .map(|r| match (format, r) {
                    (Format::Asc, Record::Error(_)) => Record::Error(ErrorFrame::new(0x8, [0; 8])),
                    _ => *r,
                })
                .collect();
            assert_eq!(got, want, "{format:?}");
        }
    }

    #[test]
    fn dates() {
        assert_eq!(civil_from_days(0), (1970, 1, 1));
        assert_eq!(civil_from_days(19_723), (2024, 1, 1));
        assert_eq!(civil_from_days(11_016), (2000, 2, 29));
        let (d, h) = eds_date_time(t(1_764_619_262, 0));
        assert_eq!((d.as_str(), h.as_str()), ("12-01-2025", "08:01PM"));
        let (_, h) = eds_date_time(t(0, 0));
        assert_eq!(h, "12:00AM");
        assert_eq!(asc_date(t(0, 0)), "Thu Jan 1 12:00:00.000 am 1970");
    }
}
