//! `canpos replay`: a candump -L log or Vector ASC file onto a bus.

use std::fs::File;
use std::io::{self, BufRead, BufReader};
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{anyhow, bail, Context, Result};
use canpos_host::transport::Transport;
use canpos_stack::Frame;
use clap::{Args, ValueEnum};

use crate::common::{open_bus, usage, BusArg, EXIT_OK};

/// What `canpos replay` does with a malformed line.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum OnMalformed {
    /// Report it with its line number and send nothing (the whole log is read first).
    Stop,
    /// Report it with its line number, skip it and play the rest.
    Skip,
}

/// `canpos replay`: send the frames of a candump `-L` log or Vector ASC file with their
/// original timing.
#[derive(Args, Debug, Clone)]
pub struct ReplayArgs {
    /// Log file (`-` = standard input): candump -L (can-utils, python-can), or ASC (.asc).
    pub file: PathBuf,
    #[command(flatten)]
    #[allow(missing_docs)]
    pub bus: BusArg,
    /// Input format (default: ASC for .asc, else candump).
    #[arg(long, value_enum)]
    pub format: Option<crate::capture::Format>,
    /// Time scale: 2 = twice as fast; 0 = as fast as possible (else 0.001 … 1e6).
    #[arg(long, default_value_t = 1.0, value_parser = crate::limits::parse_speed)]
    pub speed: f64,
    /// Start again at the end of the file (until killed).
    #[arg(long = "loop")]
    pub repeat: bool,
    /// A malformed line: stop (nothing is sent) or skip it and play the rest.
    #[arg(long, value_enum, default_value = "stop", value_name = "ACTION")]
    pub on_malformed: OnMalformed,
    /// Shorten every pause between frames longer than this to it (seconds of replay, after
    /// --speed), as python-can's `can.player --skip` does; default: the log's pauses.
    #[arg(long, value_name = "SECONDS", value_parser = crate::limits::parse_seconds)]
    pub max_gap: Option<f64>,
}

fn open_log(path: &PathBuf) -> Result<Box<dyn BufRead>> {
    if path.as_os_str() == "-" {
        return Ok(Box::new(BufReader::new(io::stdin())));
    }
    let f = File::open(path).with_context(|| format!("cannot open {}", path.display()))?;
    Ok(Box::new(BufReader::new(f)))
}

/// Most frames `canpos replay` holds from an input it cannot read twice (standard input, a
/// pipe, a device): it checks a whole log before the first frame goes out, so such an input is
/// held, and no more than this of it (about 80 MB). A regular file is read twice instead and
/// holds nothing.
pub const REPLAY_HELD_MAX: usize = 2_000_000;

/// A wait for the next frame longer than this (seconds) is announced on stderr first.
pub const REPLAY_LONG_WAIT: f64 = 10.0;

/// Malformed lines `--on-malformed stop` reports before it stops reading: the first one already
/// means nothing is sent, so an endless input of them (`yes | canpos replay -`) ends here.
pub const REPLAY_MALFORMED_MAX: u64 = 100;

/// What replay does with a record: a frame it sends, or a kind it counts.
#[derive(Clone, Copy)]
enum Play {
    Frame(Frame),
    Error,
    Fd,
}

impl From<canpos_host::candump::Record> for Play {
    fn from(r: canpos_host::candump::Record) -> Play {
        use canpos_host::candump::Record;
        match r {
            Record::Frame(f) => Play::Frame(f),
            Record::Error(_) => Play::Error,
            Record::Fd(_) => Play::Fd,
        }
    }
}

/// Each record's time of replay (seconds from the start): its log time divided by `--speed`,
/// less what `--max-gap` took off the pauses before it.
#[derive(Clone, Copy)]
pub(crate) struct Timeline {
    speed: f64,
    max_gap: Option<f64>,
    /// The latest log time seen (scaled), from the log's start.
    latest: f64,
    cut: f64,
}

impl Timeline {
    pub(crate) fn new(speed: f64, max_gap: Option<f64>) -> Timeline {
        Timeline {
            speed,
            max_gap,
            latest: 0.0,
            cut: 0.0,
        }
    }

    /// What [`offset`](Self::offset) would give for `t`, without taking `t` in.
    fn peek(&self, t: f64) -> f64 {
        let mut probe = *self;
        probe.offset(t)
    }

    pub(crate) fn offset(&mut self, t: f64) -> f64 {
        if self.speed <= 0.0 {
            return 0.0;
        }
        let t = t / self.speed;
        if t > self.latest {
            if let Some(m) = self.max_gap {
                self.cut += (t - self.latest - m).max(0.0);
            }
            self.latest = t;
        }
        t - self.cut
    }
}

/// The `FILE:LINE: why` of an error that ends reading a log.
fn log_error(file: &str, e: canpos_host::candump::LogError) -> anyhow::Error {
    use canpos_host::candump::LogError;
    match e {
        LogError::TooLong { line } => anyhow!(
            "{file}:{line}: longer than {} bytes without a newline: not a candump -L log or ASC file; nothing more is read",
            canpos_host::candump::MAX_LINE
        ),
        LogError::Parse { line, error } => anyhow!("{file}:{line}: {error}"),
        LogError::Io(e) => anyhow::Error::new(e).context(format!("reading {file}")),
    }
}

/// Sends the records of a replay on their times.
struct Player {
    bus: Box<dyn Transport>,
    file: String,
    t0: Instant,
    timeline: Timeline,
    /// The latest replay time sent at, s from the start.
    last: f64,
    sent: u64,
    errors: u64,
    fd: u64,
    refused: u64,
}

impl Player {
    fn play(&mut self, line: usize, t: f64, p: Play) -> Result<()> {
        let f = match p {
            Play::Frame(f) => f,
            Play::Error => {
                self.errors += 1;
                return Ok(());
            }
            Play::Fd => {
                self.fd += 1;
                return Ok(());
            }
        };
        let off = self.timeline.offset(t);
        let pause = off - self.last;
        self.last = self.last.max(off);
        if off > 0.0 {
            if let Some(due) = crate::limits::deadline(self.t0, off) {
                let now = Instant::now();
                if due > now {
                    let wait = due - now;
                    if wait.as_secs_f64() > REPLAY_LONG_WAIT {
                        let hint = if self.timeline.max_gap.is_none() {
                            " (--max-gap shortens such pauses)"
                        } else {
                            ""
                        };
                        eprintln!(
                            "{}:{line}: this frame comes {} after the one before: waiting{hint}",
                            self.file,
                            show_wait(pause.max(wait.as_secs_f64()))
                        );
                    }
                    std::thread::sleep(wait);
                }
            }
        }
        match self.bus.send(&f) {
            Ok(()) => self.sent += 1,
            // The transport cannot carry this frame (socketcand: a remote frame with DLC).
            Err(e) if e.kind() == io::ErrorKind::InvalidInput => self.refused += 1,
            Err(e) => return Err(anyhow::Error::new(e).context("sending a frame")),
        }
        Ok(())
    }
}

/// A pause in words: seconds, and days or years when that long.
fn show_wait(s: f64) -> String {
    let days = s / 86_400.0;
    if days >= 365.25 {
        format!("{s:.1} s ({:.1} years)", days / 365.25)
    } else if days >= 1.0 {
        format!("{s:.1} s ({days:.1} days)")
    } else {
        format!("{s:.1} s")
    }
}

/// Replays a log; the frames keep their relative spacing, divided by `--speed`. Lines that
/// cannot go on this bus (error frames, CAN FD frames, remote frames with a DLC on a
/// transport without them) are skipped and counted; the counts are reported at the end.
///
/// The whole log is read and checked before the first frame goes out; memory stays bounded
/// whatever the input: lines of at most `MAX_LINE` bytes, a regular file read twice (checked,
/// then played) and any other input held up to [`REPLAY_HELD_MAX`] frames.
pub fn replay(a: ReplayArgs) -> Result<i32> {
    use crate::capture::{LogItem, LogItems};
    // Checked again for callers that build the arguments in code.
    crate::limits::parse_speed(&a.speed.to_string()).map_err(|e| anyhow!("--speed {e}"))?;
    if let Some(g) = a.max_gap {
        crate::limits::check_seconds(g, false).map_err(|e| anyhow!("--max-gap {e}"))?;
    }
    if a.repeat && a.file.as_os_str() == "-" {
        bail!("--loop needs a file, not standard input");
    }
    let format = match a.format {
        Some(f) => f,
        None => match crate::capture::Format::from_path(&a.file) {
            Some(crate::capture::Format::Asc) => crate::capture::Format::Asc,
            _ => crate::capture::Format::Candump,
        },
    };
    let name = a.file.display().to_string();
    let items = |input| {
        LogItems::new(input, format)
            .ok_or_else(|| usage!("replay reads candump -L logs and ASC files, not pcap / pcapng"))
    };
    // A regular file is read again to play it; anything else (standard input, a pipe, a
    // device) only once, so its frames are held.
    let again = a.file.as_os_str() != "-" && std::fs::metadata(&a.file).is_ok_and(|m| m.is_file());
    let mut held: Option<Vec<(usize, f64, Play)>> = (!again).then(Vec::new);
    // Read everything first so a malformed log (with --on-malformed stop) fails before
    // anything goes on the bus, and a log too long for this speed sends nothing.
    let (mut malformed, mut records) = (0u64, 0u64);
    let mut timeline = Timeline::new(a.speed, a.max_gap);
    let mut span = 0.0f64;
    // The last line checked: a file that grows after the check (a log still being recorded)
    // is played as far as it was checked, never further.
    let mut checked = 0usize;
    for item in items(open_log(&a.file)?)? {
        match item.map_err(|e| log_error(&name, e))? {
            LogItem::Malformed { line, why } => {
                eprintln!("{name}:{line}: {why}");
                malformed += 1;
                checked = line;
                if a.on_malformed == OnMalformed::Stop && malformed >= REPLAY_MALFORMED_MAX {
                    bail!(
                        "{name}: {malformed} malformed lines, and the rest not read; nothing sent (--on-malformed skip plays the rest)"
                    );
                }
            }
            LogItem::Record { line, t, record } => {
                records += 1;
                checked = line;
                let play = Play::from(record);
                if matches!(play, Play::Frame(_)) {
                    span = span.max(timeline.offset(t));
                }
                if let Some(h) = &mut held {
                    if h.len() >= REPLAY_HELD_MAX {
                        bail!(
                            "{name}:{line}: more than {REPLAY_HELD_MAX} frames from an input that cannot be read twice; replay checks a whole log before sending, so it holds them: write the log to a file and replay that; nothing sent"
                        );
                    }
                    h.push((line, t, play));
                }
            }
        }
    }
    if malformed > 0 && a.on_malformed == OnMalformed::Stop {
        bail!(
            "{name}: {malformed} malformed line(s), nothing sent (--on-malformed skip plays the rest)"
        );
    }
    if records == 0 {
        eprintln!("{name}: no frames");
        return Ok(EXIT_OK);
    }
    crate::limits::check_seconds(span, false)
        .map_err(|e| anyhow!("{name}: at --speed {} the replay would take {e}", a.speed))?;
    let mut p = Player {
        bus: open_bus(&a.bus.bus)?,
        file: name.clone(),
        t0: Instant::now(),
        timeline: Timeline::new(a.speed, a.max_gap),
        last: 0.0,
        sent: 0,
        errors: 0,
        fd: 0,
        refused: 0,
    };
    loop {
        p.t0 = Instant::now();
        p.timeline = Timeline::new(a.speed, a.max_gap);
        p.last = 0.0;
        let sent_before = p.sent;
        match &held {
            Some(h) => {
                for &(line, t, play) in h {
                    p.play(line, t, play)?;
                }
            }
            None => {
                // The file is read again: what the check found must still hold, or it changed
                // in between and is not played on.
                let changed = |line: usize, what: &str| {
                    anyhow!("{name}:{line}: {what} since replay checked the file; stopping")
                };
                for item in items(open_log(&a.file)?)? {
                    match item.map_err(|e| log_error(&name, e))? {
                        LogItem::Malformed { line, .. } if line > checked => break,
                        LogItem::Record { line, .. } if line > checked => break,
                        // Reported when the log was checked (and skipped by the user's choice).
                        LogItem::Malformed { line, why } => {
                            if a.on_malformed == OnMalformed::Stop {
                                return Err(changed(line, &format!("malformed ({why})")));
                            }
                        }
                        LogItem::Record { line, t, record } => {
                            let play = Play::from(record);
                            if matches!(play, Play::Frame(_)) && p.timeline.peek(t) > span {
                                return Err(changed(line, "a frame later than any checked"));
                            }
                            p.play(line, t, play)?;
                        }
                    }
                }
            }
        }
        if !a.repeat {
            break;
        }
        if p.sent == sent_before {
            // Nothing in the log could go on this bus: repeating would spin without end.
            eprintln!("--repeat: no frame of the log can be sent on this bus; stopping");
            break;
        }
    }
    eprintln!("replayed {} frames", p.sent);
    let skipped = p.errors + p.fd + p.refused + malformed;
    if skipped > 0 {
        eprintln!(
            "skipped {skipped} lines: {} error frames, {} CAN FD frames, {} frames this bus cannot carry (remote frames with a DLC), {malformed} malformed",
            p.errors, p.fd, p.refused
        );
    }
    Ok(EXIT_OK)
}
