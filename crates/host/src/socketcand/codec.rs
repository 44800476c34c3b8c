//! socketcand ASCII elements: incremental stream decoder, element parser and formatters.
//!
//! The wire format (see `docs/TRANSPORT.md`) is a stream of `< ... >` elements with no separators.
//! TCP may split an element over reads or put several in one, and a broken peer may send
//! anything, so the decoder is a byte-level state machine with a bounded buffer: bytes outside
//! elements are skipped, an over-long element is dropped, and a `<` inside an element restarts.

use std::io::Write as _;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use canpos_stack::Frame;

use crate::can::RxFrame;
pub use crate::can::{err_class, ErrorFrame};

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

    /// Feeds bytes; calls `on_element` with each complete element body, in order (over-long
    /// elements are skipped: see [`Decoder::next`] to hear of them).
    pub fn feed(&mut self, mut input: &[u8], mut on_element: impl FnMut(&[u8])) {
        while !input.is_empty() {
            let (n, piece) = self.next(input);
            input = &input[n..];
            if let Some(Piece::Body(body)) = piece {
                on_element(body);
            }
        }
    }

    /// Consumes bytes of `input` up to the end of the next element (or all of it): returns how
    /// many it took and the element, if one ended. Lets a caller stop between two elements (the
    /// hub does when a client's output is full) and hears of over-long elements, which are
    /// dropped (bounded: only [`MAX_ELEMENT`] bytes are kept) but reported, so that the client
    /// gets an answer.
    pub fn next<'a>(&'a mut self, input: &[u8]) -> (usize, Option<Piece<'a>>) {
        for (i, &b) in input.iter().enumerate() {
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
                    self.in_element = false;
                    if self.overflow {
                        self.skipped += 1;
                        return (i + 1, Some(Piece::TooLong));
                    }
                    return (i + 1, Some(Piece::Body(&self.buf)));
                }
                b'<' => {
                    // An unterminated element followed by a new one: drop the broken part.
                    self.skipped += self.buf.len() as u64 + 1;
                    self.buf.clear();
                    if std::mem::take(&mut self.overflow) {
                        return (i + 1, Some(Piece::TooLong));
                    }
                }
                _ if self.buf.len() < MAX_ELEMENT => self.buf.push(b),
                _ => {
                    self.overflow = true;
                    self.skipped += 1;
                }
            }
        }
        (input.len(), None)
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

/// What [`Decoder::next`] found at the end of an element.
#[derive(Debug, PartialEq, Eq)]
pub enum Piece<'a> {
    /// A complete element body (without the angle brackets).
    Body(&'a [u8]),
    /// An element longer than [`MAX_ELEMENT`] ended (its bytes were dropped).
    TooLong,
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
    /// `< rawmode >`, `< bcmmode >`, `< controlmode >`, `< isotpmode >`: a mode switch.
    Mode(Mode),
    /// `< open CHANNEL >`
    Open(String),
    /// `< send ID DLC B0 .. >` from a client; a remote frame from the extension's
    /// `< send ID DLC R >` or `< sendrtr ID [DLC] >` (see docs/SOCKETCAND.md).
    Send(Frame),
    /// `< frame ID SEC.USEC DATA >` from a server (raw mode: `DATA` as one hex string; BCM mode:
    /// one token per byte), or the extension's `< rtr ID SEC.USEC DLC >`.
    Frame(RxFrame),
    /// BCM `< add SEC USEC ID DLC B0 .. >`: send `frame` every `interval`.
    Add {
        /// Cycle time (never zero after parsing).
        interval: Duration,
        /// The frame to send.
        frame: Frame,
    },
    /// BCM `< update ID DLC B0 .. >`: new content for the job of that identifier.
    Update(Frame),
    /// BCM `< delete ID >`.
    Delete(CanId),
    /// BCM `< subscribe SEC USEC ID >`: deliver frames of `id`, at most one per `interval`
    /// (zero: every one).
    Subscribe {
        /// Throttle interval.
        interval: Duration,
        /// The identifier.
        id: CanId,
    },
    /// BCM `< unsubscribe ID >`.
    Unsubscribe(CanId),
    /// BCM `< filter SEC USEC ID DLC M0 .. >`: deliver frames of the identifier whose data under
    /// the mask (or whose DLC) changed, at most one per `interval`.
    Filter {
        /// Throttle interval.
        interval: Duration,
        /// Identifier; the data bytes are the mask.
        mask: Frame,
    },
    /// Control mode `< statistics MS >` (0: off).
    Statistics(u32),
    /// The extension `< rtr on >` / `< rtr off >`: carry remote frames as such.
    RtrOption(bool),
    /// The extension `< errors on >` / `< errors off >`: receive `< error … >` bus error elements.
    ErrorsOption(bool),
    /// The extension `< txorder priority >` / `< txorder fifo >`: the order in which the
    /// client's transmit queue on the bus goes out (a device's CAN controller sends its most
    /// important frame first; a host's SocketCAN interface in submission order, the default).
    TxOrderOption(crate::bus::TxOrder),
    /// The extension `< clock on >` / `< clock off >`: the client becomes (or stops being) a
    /// timed participant of its channel bus's simulation clock (docs/CLOCK.md).
    ClockOption(bool),
    /// The extension `< at SEC.USEC >` of a timed client: its horizon, a wall-clock time (the
    /// time base of the `< frame … >` stamps); its following `send`s are stamped with it.
    At(SystemTime),
    /// `< error CLASS SEC.USEC [D0 .. D7] >`: a CAN error frame from a server.
    ErrorFrame(ErrorFrame),
    /// `< error TEXT >`: a server's answer to a failed command.
    Error(String),
    /// A known command whose arguments do not parse; its name.
    Malformed(&'static str),
    /// Anything else (kept for logs and for `< error unknown command >`).
    Other(String),
    /// An element longer than [`MAX_ELEMENT`] (never from [`Element::parse`]: the decoder
    /// reports it, [`Piece::TooLong`]).
    TooLong,
}

/// A CAN identifier and its format.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct CanId {
    /// 11 or 29 bits.
    pub id: u32,
    /// 29-bit identifier.
    pub extended: bool,
}

impl CanId {
    /// The identifier of a frame.
    pub fn of(frame: &Frame) -> CanId {
        CanId {
            id: frame.id(),
            extended: frame.is_extended(),
        }
    }
}

/// The socketcand modes (states after `open`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mode {
    /// Broadcast manager: `send`, cyclic `add` / `update` / `delete`, `subscribe`, `filter`.
    Bcm,
    /// Every frame of the bus, `send`.
    Raw,
    /// Statistics.
    Control,
    /// ISO-TP (not supported by the canpos hub; answered with an error).
    Isotp,
}

impl Mode {
    /// The command that switches to this mode, without brackets.
    pub fn command(self) -> &'static str {
        match self {
            Mode::Bcm => "bcmmode",
            Mode::Raw => "rawmode",
            Mode::Control => "controlmode",
            Mode::Isotp => "isotpmode",
        }
    }
}

impl Element {
    /// Parses an element body (without the angle brackets). Never panics.
    pub fn parse(body: &[u8]) -> Element {
        let Ok(text) = std::str::from_utf8(body) else {
            return Element::Other(String::from_utf8_lossy(body).into_owned());
        };
        let mut tok = text.split_ascii_whitespace();
        let other = || Element::Other(text.trim().to_string());
        let Some(cmd) = tok.next() else {
            return other();
        };
        let tok: Vec<&str> = tok.collect();
        let malformed = |name: &'static str| Element::Malformed(name);
        match cmd {
            "hi" if tok.is_empty() => Element::Hi,
            "ok" if tok.is_empty() => Element::Ok,
            "echo" if tok.is_empty() => Element::Echo,
            "rawmode" if tok.is_empty() => Element::Mode(Mode::Raw),
            "bcmmode" if tok.is_empty() => Element::Mode(Mode::Bcm),
            "controlmode" if tok.is_empty() => Element::Mode(Mode::Control),
            "isotpmode" if tok.is_empty() => Element::Mode(Mode::Isotp),
            "open" => match tok[..] {
                [ch] => Element::Open(ch.to_string()),
                _ => malformed("open"),
            },
            "send" => parse_send(&tok)
                .map(Element::Send)
                .unwrap_or(malformed("send")),
            "sendrtr" => parse_sendrtr(&tok)
                .map(Element::Send)
                .unwrap_or(malformed("sendrtr")),
            "frame" => parse_frame(&tok)
                .map(Element::Frame)
                .unwrap_or(malformed("frame")),
            "rtr" => match tok[..] {
                ["on"] => Element::RtrOption(true),
                ["off"] => Element::RtrOption(false),
                _ => parse_rtr(&tok)
                    .map(Element::Frame)
                    .unwrap_or(malformed("rtr")),
            },
            "errors" => match tok[..] {
                ["on"] => Element::ErrorsOption(true),
                ["off"] => Element::ErrorsOption(false),
                _ => malformed("errors"),
            },
            "txorder" => match tok[..] {
                ["priority"] => Element::TxOrderOption(crate::bus::TxOrder::Priority),
                ["fifo"] => Element::TxOrderOption(crate::bus::TxOrder::Fifo),
                _ => malformed("txorder"),
            },
            "clock" => match tok[..] {
                ["on"] => Element::ClockOption(true),
                ["off"] => Element::ClockOption(false),
                _ => malformed("clock"),
            },
            "at" => match tok[..] {
                [t] => parse_timestamp(t)
                    .map(Element::At)
                    .unwrap_or(malformed("at")),
                _ => malformed("at"),
            },
            "add" => parse_interval(&tok)
                .and_then(|iv| Some((iv, parse_send(&tok[2..])?)))
                .filter(|(iv, f)| !iv.is_zero() && !f.is_remote())
                .map(|(interval, frame)| Element::Add { interval, frame })
                .unwrap_or(malformed("add")),
            "update" => parse_send(&tok)
                .filter(|f| !f.is_remote())
                .map(Element::Update)
                .unwrap_or(malformed("update")),
            "delete" => match tok[..] {
                [id] => parse_id(id, false)
                    .map(|(id, extended)| Element::Delete(CanId { id, extended }))
                    .unwrap_or(malformed("delete")),
                _ => malformed("delete"),
            },
            "subscribe" => match (parse_interval(&tok), &tok[..]) {
                (Some(interval), [_, _, id]) => parse_id(id, false)
                    .map(|(id, extended)| Element::Subscribe {
                        interval,
                        id: CanId { id, extended },
                    })
                    .unwrap_or(malformed("subscribe")),
                _ => malformed("subscribe"),
            },
            "unsubscribe" => match tok[..] {
                [id] => parse_id(id, false)
                    .map(|(id, extended)| Element::Unsubscribe(CanId { id, extended }))
                    .unwrap_or(malformed("unsubscribe")),
                _ => malformed("unsubscribe"),
            },
            "filter" => parse_interval(&tok)
                .and_then(|iv| Some((iv, parse_send(&tok[2..])?)))
                .filter(|(_, f)| !f.is_remote())
                .map(|(interval, mask)| Element::Filter { interval, mask })
                .unwrap_or(malformed("filter")),
            "statistics" => match tok[..] {
                [ms] if ms.len() <= 10 && ms.bytes().all(|b| b.is_ascii_digit()) => ms
                    .parse()
                    .map(Element::Statistics)
                    .unwrap_or(malformed("statistics")),
                _ => malformed("statistics"),
            },
            "error" => match parse_error_frame(&tok) {
                Some(e) => Element::ErrorFrame(e),
                None => Element::Error(text.trim().to_string()),
            },
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
    if v > 0x1FFF_FFFF {
        return None;
    }
    Some((v, ext))
}

/// `SEC USEC` of `add`, `subscribe` and `filter` (decimal, as socketcand's `%llu`).
fn parse_interval(tok: &[&str]) -> Option<Duration> {
    let dec = |s: &str| {
        (!s.is_empty() && s.len() <= 10 && s.bytes().all(|b| b.is_ascii_digit()))
            .then(|| s.parse::<u64>().ok())
            .flatten()
    };
    let (sec, usec) = (dec(tok.first()?)?, dec(tok.get(1)?)?);
    Duration::from_secs(sec).checked_add(Duration::from_micros(usec))
}

fn parse_dlc(s: &str) -> Option<u8> {
    if s.len() > 2 {
        return None;
    }
    let dlc = hex_u32(s)?;
    (dlc <= 8).then_some(dlc as u8)
}

/// `ID DLC B0 ..`, or the extension `ID DLC R` (a remote frame requesting DLC bytes).
fn parse_send(tok: &[&str]) -> Option<Frame> {
    let (id, ext) = parse_id(tok.first()?, false)?;
    let dlc = parse_dlc(tok.get(1)?)?;
    let rest = &tok[2..];
    if let ["R"] = rest {
        return Frame::remote(id, ext, dlc).ok();
    }
    if rest.len() != dlc as usize {
        return None;
    }
    let mut data = [0u8; 8];
    for (d, t) in data.iter_mut().zip(rest) {
        if t.len() > 2 {
            return None;
        }
        *d = hex_u32(t)? as u8;
    }
    Frame::with_id(id, ext, &data[..rest.len()]).ok()
}

/// The extension `sendrtr ID [DLC]`.
fn parse_sendrtr(tok: &[&str]) -> Option<Frame> {
    let (id, ext) = parse_id(tok.first()?, false)?;
    let dlc = match tok[1..] {
        [] => 0,
        [d] => parse_dlc(d)?,
        _ => return None,
    };
    Frame::remote(id, ext, dlc).ok()
}

/// The extension `rtr ID SEC.USEC [DLC]` (server → client).
fn parse_rtr(tok: &[&str]) -> Option<RxFrame> {
    let (id, ext) = parse_id(tok.first()?, true)?;
    let timestamp = parse_timestamp(tok.get(1)?)?;
    let dlc = match tok[2..] {
        [] => 0,
        [d] => parse_dlc(d)?,
        _ => return None,
    };
    Some(RxFrame {
        frame: Frame::remote(id, ext, dlc).ok()?,
        timestamp,
    })
}

/// `ID SEC.USEC DATA` (raw mode: one hex string) or `ID SEC.USEC D0 D1 ..` (BCM mode).
fn parse_frame(tok: &[&str]) -> Option<RxFrame> {
    let (id, ext) = parse_id(tok.first()?, true)?;
    let timestamp = parse_timestamp(tok.get(1)?)?;
    let hex: String = match &tok[2..] {
        [] => String::new(),
        [one] => (*one).to_string(),
        bytes if bytes.len() <= 8 && bytes.iter().all(|b| b.len() == 2) => bytes.concat(),
        _ => return None,
    };
    if !hex.len().is_multiple_of(2) || hex.len() > 16 {
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

/// `CLASS SEC.USEC [D0 .. D7]`; `None` when it is not an error frame (a text error).
fn parse_error_frame(tok: &[&str]) -> Option<ErrorFrame> {
    let class = hex_u32(tok.first()?)?;
    let timestamp = parse_timestamp(tok.get(1)?)?;
    let data = match &tok[2..] {
        [] => None,
        bytes if bytes.len() == 8 => {
            let mut d = [0u8; 8];
            for (o, b) in d.iter_mut().zip(bytes.iter()) {
                if b.len() > 2 {
                    return None;
                }
                *o = hex_u32(b)? as u8;
            }
            Some(d)
        }
        _ => return None,
    };
    Some(ErrorFrame {
        class: class & 0x1FFF_FFFF,
        data,
        timestamp,
        id: None,
    })
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

const HEX: &[u8; 16] = b"0123456789ABCDEF";

/// Appends the low `digits` hex digits of `v`, upper case (the hub formats every frame for
/// every client: no `fmt` machinery on that path).
fn put_hex(out: &mut Vec<u8>, v: u32, digits: u32) {
    for i in (0..digits).rev() {
        out.push(HEX[((v >> (4 * i)) & 0xF) as usize]);
    }
}

/// Appends `v` in decimal, at least `width` digits (zero-padded).
fn put_dec(out: &mut Vec<u8>, mut v: u64, width: usize) {
    let mut buf = [0u8; 20];
    let mut i = buf.len();
    loop {
        i -= 1;
        buf[i] = b'0' + (v % 10) as u8;
        v /= 10;
        if v == 0 && buf.len() - i >= width {
            break;
        }
    }
    out.extend_from_slice(&buf[i..]);
}

fn write_id(out: &mut Vec<u8>, frame_id: u32, extended: bool) {
    put_hex(out, frame_id, if extended { 8 } else { 3 });
    out.push(b' ');
}

fn write_ts(out: &mut Vec<u8>, timestamp: SystemTime) {
    let t = since_epoch(timestamp);
    put_dec(out, t.as_secs(), 1);
    out.push(b'.');
    put_dec(out, u64::from(t.subsec_micros()), 6);
    out.push(b' ');
}

/// Appends `< at SEC.USEC >` (a timed client's horizon, canpos extension; the time truncated to
/// the microsecond like a frame's stamp).
pub fn write_at(out: &mut Vec<u8>, t: SystemTime) {
    out.extend_from_slice(b"< at ");
    write_ts(out, t);
    out.push(b'>');
}

/// Appends `< frame ID SEC.USEC DATA >` (server → client, raw mode).
///
/// A remote frame with DLC 0 becomes a zero-length data frame (the protocol has no RTR);
/// returns `false` and writes nothing for a remote frame with DLC > 0, which cannot be carried.
pub fn write_frame(out: &mut Vec<u8>, frame: &Frame, timestamp: SystemTime) -> bool {
    if frame.is_remote() && frame.dlc() > 0 {
        return false;
    }
    out.extend_from_slice(b"< frame ");
    write_id(out, frame.id(), frame.is_extended());
    write_ts(out, timestamp);
    for &b in frame.data() {
        put_hex(out, b.into(), 2);
    }
    // Always a space before `>`: an empty frame gets the two spaces python-can requires.
    out.extend_from_slice(b" >");
    true
}

/// Appends a raw-mode frame for a client that opted into remote frames (`< rtr on >`): a
/// remote frame as `< rtr ID SEC.USEC DLC >`, anything else as [`write_frame`].
pub fn write_frame_rtr(out: &mut Vec<u8>, frame: &Frame, timestamp: SystemTime) {
    if frame.is_remote() {
        out.extend_from_slice(b"< rtr ");
        write_id(out, frame.id(), frame.is_extended());
        write_ts(out, timestamp);
        let _ = write!(out, "{} >", frame.dlc());
    } else {
        write_frame(out, frame, timestamp);
    }
}

/// Appends `< frame ID SEC.USEC D0 D1 .. >`, the BCM mode's form (one token per byte, as
/// socketcand writes it, with the space before `>`). Remote frames as in [`write_frame`].
pub fn write_bcm_frame(out: &mut Vec<u8>, frame: &Frame, timestamp: SystemTime) -> bool {
    if frame.is_remote() && frame.dlc() > 0 {
        return false;
    }
    out.extend_from_slice(b"< frame ");
    write_id(out, frame.id(), frame.is_extended());
    write_ts(out, timestamp);
    for &b in frame.data() {
        put_hex(out, b.into(), 2);
        out.push(b' ');
    }
    out.extend_from_slice(b" >");
    true
}

/// Appends `< error CLASS SEC.USEC D0 .. D7 >` (the data as socketcand's BCM mode writes it;
/// its raw mode writes the class and time only, which python-can reads the same way).
pub fn write_error_frame(out: &mut Vec<u8>, e: &ErrorFrame) {
    let _ = write!(out, "< error {:03X} ", e.class & 0x1FFF_FFFF);
    write_ts(out, e.timestamp);
    if let Some(d) = e.data {
        for b in d {
            let _ = write!(out, "{b:02X} ");
        }
    }
    out.push(b'>');
}

/// Appends `< error TEXT >`, the answer to a command that failed.
pub fn write_error_text(out: &mut Vec<u8>, text: &str) {
    let _ = write!(out, "< error {text} >");
}

/// Appends control mode's `< stat RBYTES RPACKETS TBYTES TPACKETS >`.
pub fn write_stat(out: &mut Vec<u8>, rbytes: u64, rpackets: u64, tbytes: u64, tpackets: u64) {
    // socketcand prints the kernel's 32-bit counters; they wrap the same way here.
    let _ = write!(
        out,
        "< stat {} {} {} {} >",
        rbytes as u32, rpackets as u32, tbytes as u32, tpackets as u32
    );
}

/// Appends `< send ID DLC B0 .. >` (client → server); same RTR rule as [`write_frame`].
pub fn write_send(out: &mut Vec<u8>, frame: &Frame) -> bool {
    if frame.is_remote() && frame.dlc() > 0 {
        return false;
    }
    out.extend_from_slice(b"< send ");
    write_id(out, frame.id(), frame.is_extended());
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

/// Appends a send for a server that accepted `< rtr on >`: a remote frame as
/// `< send ID DLC R >`, anything else as [`write_send`].
pub fn write_send_rtr(out: &mut Vec<u8>, frame: &Frame) {
    if frame.is_remote() {
        out.extend_from_slice(b"< send ");
        write_id(out, frame.id(), frame.is_extended());
        let _ = write!(out, "{:x} R >", frame.dlc());
    } else {
        write_send(out, frame);
    }
}

/// Appends `< open CHANNEL >`.
pub fn write_open(out: &mut Vec<u8>, channel: &str) {
    let _ = write!(out, "< open {channel} >");
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::can::BusState;
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
                Element::Mode(Mode::Raw),
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
                matches!(
                    Element::parse(body),
                    Element::Other(_) | Element::Malformed(_)
                ),
                "{body:?}"
            );
        }
        assert_eq!(Element::parse(b" send 1 "), Element::Malformed("send"));
        assert_eq!(
            Element::parse(b" error unknown command "),
            Element::Error("error unknown command".into())
        );
    }

    #[test]
    fn parses_bcm_and_control_commands() {
        let sync = Frame::new(0x80, &[]).unwrap();
        assert_eq!(
            Element::parse(b" add 0 1000 080 0 "),
            Element::Add {
                interval: Duration::from_millis(1),
                frame: sync
            }
        );
        assert_eq!(
            Element::parse(b" add 1 5 00000123 1 ff "),
            Element::Add {
                interval: Duration::new(1, 5000),
                frame: Frame::with_id(0x123, true, &[0xff]).unwrap()
            }
        );
        assert_eq!(
            Element::parse(b" update 080 1 5 "),
            Element::Update(Frame::new(0x80, &[5]).unwrap())
        );
        let id = CanId {
            id: 0x80,
            extended: false,
        };
        assert_eq!(Element::parse(b" delete 080 "), Element::Delete(id));
        assert_eq!(
            Element::parse(b" unsubscribe 080 "),
            Element::Unsubscribe(id)
        );
        assert_eq!(
            Element::parse(b" subscribe 0 0 080 "),
            Element::Subscribe {
                interval: Duration::ZERO,
                id
            }
        );
        assert_eq!(
            Element::parse(b" filter 0 0 080 2 FF 0 "),
            Element::Filter {
                interval: Duration::ZERO,
                mask: Frame::new(0x80, &[0xff, 0]).unwrap()
            }
        );
        assert_eq!(
            Element::parse(b" statistics 1000 "),
            Element::Statistics(1000)
        );
        assert_eq!(Element::parse(b" bcmmode "), Element::Mode(Mode::Bcm));
        assert_eq!(
            Element::parse(b" controlmode "),
            Element::Mode(Mode::Control)
        );
        for (body, name) in [
            (&b" add 0 0 080 0 "[..], "add"),
            (b" add 0 1000 080 1 ", "add"),
            (b" add x 1000 080 0 ", "add"),
            (b" add 0 1000 080 0 R ", "add"),
            (b" update 080 ", "update"),
            (b" delete ", "delete"),
            (b" delete 080 1 ", "delete"),
            (b" subscribe 0 080 ", "subscribe"),
            (b" filter 0 0 080 1 ", "filter"),
            (b" statistics -1 ", "statistics"),
            (b" statistics 99999999999 ", "statistics"),
            (b" rtr maybe ", "rtr"),
            (b" errors ", "errors"),
            (b" sendrtr 705 9 ", "sendrtr"),
        ] {
            assert_eq!(Element::parse(body), Element::Malformed(name), "{body:?}");
        }
    }

    #[test]
    fn rtr_extension_round_trips() {
        let t = ts(7, 1);
        for dlc in [0u8, 1, 8] {
            for ext in [false, true] {
                let f = Frame::remote(0x705, ext, dlc).unwrap();
                let mut v = Vec::new();
                write_frame_rtr(&mut v, &f, t);
                write_send_rtr(&mut v, &f);
                assert_eq!(
                    Decoder::new().feed_parse(&v),
                    vec![
                        Element::Frame(RxFrame {
                            frame: f,
                            timestamp: t
                        }),
                        Element::Send(f)
                    ]
                );
            }
        }
        let mut v = Vec::new();
        write_frame_rtr(&mut v, &Frame::remote(0x705, false, 1).unwrap(), t);
        write_send_rtr(&mut v, &Frame::remote(0x705, false, 0).unwrap());
        assert_eq!(v, b"< rtr 705 7.000001 1 >< send 705 0 R >");
        // Data frames are written as without the extension.
        let mut v = Vec::new();
        write_frame_rtr(&mut v, &Frame::new(0x181, &[1]).unwrap(), t);
        assert_eq!(v, b"< frame 181 7.000001 01 >");
        assert_eq!(
            Element::parse(b" sendrtr 00000705 "),
            Element::Send(Frame::remote(0x705, true, 0).unwrap())
        );
        assert_eq!(Element::parse(b" rtr on "), Element::RtrOption(true));
        assert_eq!(
            Element::parse(b" errors off "),
            Element::ErrorsOption(false)
        );
        assert_eq!(
            Element::parse(b" txorder priority "),
            Element::TxOrderOption(crate::bus::TxOrder::Priority)
        );
        assert_eq!(
            Element::parse(b" txorder fifo "),
            Element::TxOrderOption(crate::bus::TxOrder::Fifo)
        );
        for bad in [&b" txorder "[..], b" txorder lifo ", b" txorder fifo fifo "] {
            assert_eq!(Element::parse(bad), Element::Malformed("txorder"));
        }
        assert_eq!(Element::parse(b" clock on "), Element::ClockOption(true));
        assert_eq!(Element::parse(b"clock off"), Element::ClockOption(false));
        for bad in [&b" clock "[..], b" clock maybe ", b" clock on on "] {
            assert_eq!(Element::parse(bad), Element::Malformed("clock"));
        }
        let t = UNIX_EPOCH + Duration::new(1_765_000_000, 123_456_000);
        let mut v = Vec::new();
        write_at(&mut v, t);
        assert_eq!(v, b"< at 1765000000.123456 >");
        assert_eq!(Element::parse(&v[1..v.len() - 1]), Element::At(t));
        for bad in [
            &b" at "[..],
            b" at 1.5 2 ",
            b" at -1.0 ",
            b" at 1.x ",
            b" at 1.0000000001 ",
            b" at 9999999999999.0 ",
            b" at now ",
        ] {
            assert_eq!(Element::parse(bad), Element::Malformed("at"), "{bad:?}");
        }
    }

    /// A transmit-queue overflow goes as a controller problem with `CAN_ERR_CRTL_TX_OVERFLOW`
    /// and comes back as one; it is no change of the controller's state.
    #[test]
    fn a_tx_overflow_error_frame_round_trips() {
        let e = ErrorFrame::tx_overflow(ts(3, 4));
        let mut v = Vec::new();
        write_error_frame(&mut v, &e);
        assert_eq!(v, b"< error 004 3.000004 00 02 00 00 00 00 00 00 >");
        let back = match Decoder::new().feed_parse(&v)[..] {
            [Element::ErrorFrame(back)] => back,
            ref other => panic!("{other:?}"),
        };
        assert_eq!(back, e);
        assert!(back.is_tx_overflow());
        assert_eq!(back.bus_state(), None);
        // Error passive (data byte 1 = 0x30) and a class-only report are not overflows.
        assert!(!ErrorFrame::for_state(BusState::ErrorPassive, ts(0, 0)).is_tx_overflow());
        assert!(!ErrorFrame {
            class: err_class::CRTL,
            data: None,
            timestamp: ts(0, 0),
            id: None,
        }
        .is_tx_overflow());
    }

    #[test]
    fn bcm_frames_error_frames_and_stats_are_written_as_socketcand_does() {
        let t = ts(5, 10);
        let mut v = Vec::new();
        write_bcm_frame(&mut v, &Frame::new(0x123, &[0xA, 0xFF]).unwrap(), t);
        assert_eq!(v, b"< frame 123 5.000010 0A FF  >");
        match Decoder::new().feed_parse(&v)[..] {
            [Element::Frame(r)] => assert_eq!(r.frame.data(), &[0xA, 0xFF]),
            ref e => panic!("{e:?}"),
        }
        let mut v = Vec::new();
        write_stat(&mut v, 1, 2, 3, 1 << 32);
        assert_eq!(v, b"< stat 1 2 3 0 >");
        let e = ErrorFrame::for_state(BusState::ErrorPassive, t);
        let mut v = Vec::new();
        write_error_frame(&mut v, &e);
        assert_eq!(v, b"< error 004 5.000010 00 30 00 00 00 00 00 00 >");
        assert_eq!(Decoder::new().feed_parse(&v), vec![Element::ErrorFrame(e)]);
    }

    #[test]
    fn error_frames_map_to_bus_states() {
        let t = ts(1, 0);
        let parse = |b: &[u8]| match Element::parse(b) {
            Element::ErrorFrame(e) => e.bus_state(),
            e => panic!("{e:?}"),
        };
        // socketcand's raw mode: the class only.
        assert_eq!(parse(b" error 040 1.000000 "), Some(BusState::BusOff));
        assert_eq!(parse(b" error 004 1.000000 "), Some(BusState::ErrorPassive));
        assert_eq!(parse(b" error 100 1.000000 "), Some(BusState::ErrorActive));
        assert_eq!(parse(b" error 020 1.000000 "), None);
        // Its BCM mode and canpos: with the data; byte 1 says which controller state.
        assert_eq!(
            parse(b" error 004 1.000000 00 04 00 00 00 00 00 00 "),
            None,
            "a warning level is not a state change"
        );
        assert_eq!(
            parse(b" error 004 1.000000 00 10 00 00 00 00 00 00 "),
            Some(BusState::ErrorPassive)
        );
        for s in [
            BusState::ErrorActive,
            BusState::ErrorPassive,
            BusState::BusOff,
        ] {
            assert_eq!(ErrorFrame::for_state(s, t).bus_state(), Some(s));
        }
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

    #[test]
    fn decoder_reports_overlong_elements_once_each() {
        // 1 MB in one element, closed by `>`, then one broken by a `<`: two reports, the
        // elements after them intact, the buffer bounded.
        let mut d = Decoder::new();
        let mut input = vec![b'<'];
        input.extend(std::iter::repeat_n(b'x', 1 << 20));
        input.extend_from_slice(b"><echo><");
        input.extend(std::iter::repeat_n(b'y', 2 * MAX_ELEMENT));
        input.extend_from_slice(b"<ok>");
        let mut got = Vec::new();
        let mut rest = &input[..];
        while !rest.is_empty() {
            let (n, p) = d.next(rest);
            rest = &rest[n..];
            match p {
                Some(Piece::Body(b)) => got.push(Element::parse(b)),
                Some(Piece::TooLong) => got.push(Element::TooLong),
                None => {}
            }
            assert!(d.buf.len() <= MAX_ELEMENT);
        }
        assert_eq!(
            got,
            vec![
                Element::TooLong,
                Element::Echo,
                Element::TooLong,
                Element::Ok
            ]
        );
        // A body of exactly the bound is an element, not an over-long one.
        let mut exact = vec![b'<'];
        exact.extend(std::iter::repeat_n(b'z', MAX_ELEMENT));
        exact.push(b'>');
        assert!(
            matches!(Decoder::new().next(&exact).1, Some(Piece::Body(b)) if b.len() == MAX_ELEMENT)
        );
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

        /// The hand-written formatting is `format!`'s, byte for byte.
        #[test]
        fn frame_text_is_formats(id in 0u32..0x2000_0000, ext in any::<bool>(), data in proptest::collection::vec(any::<u8>(), 0..=8), s in 0u64..u64::MAX / 2, us in 0u32..1_000_000) {
            let id = if ext { id } else { id & 0x7FF };
            let f = Frame::with_id(id, ext, &data).unwrap();
            let ts = UNIX_EPOCH + Duration::new(s, us * 1000);
            let idt = if ext { format!("{id:08X}") } else { format!("{id:03X}") };
            let hex: String = data.iter().map(|b| format!("{b:02X}")).collect();
            let bcm: String = data.iter().map(|b| format!("{b:02X} ")).collect();
            let mut out = Vec::new();
            write_frame(&mut out, &f, ts);
            prop_assert_eq!(String::from_utf8(out).unwrap(), format!("< frame {idt} {s}.{us:06} {hex} >"));
            let mut out = Vec::new();
            write_bcm_frame(&mut out, &f, ts);
            prop_assert_eq!(String::from_utf8(out).unwrap(), format!("< frame {idt} {s}.{us:06} {bcm} >"));
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
