//! `canpos soak`: a long scale run that watches for slow failures.
//!
//! N TH sensors (node-ids 1…N) run in one [`Runtime`] on an in-process [`MemBus`], each
//! producing TPDO1 on an event timer (1 ms by default, TH's own default). An observer port on
//! the same bus counts every TPDO per node. Every `--report-s` seconds, and at the end, one JSON
//! line goes to stdout with:
//!
//! - **drift**: frames received vs the ideal count `nodes × elapsed / period`. The core schedules
//!   event timers on absolute deadlines and *skips* periods it was too late for (it does not
//!   burst), so a deficit here is exactly the number of periods lost to late wake-ups; a surplus
//!   would mean a timer running fast.
//! - **deadline misses**: the runtime's wake-up lateness (median, p99, max, wakes later than
//!   200 µs / 1 ms) and the observer's count of gaps longer than two periods.
//! - **RSS growth**: `VmRSS` now minus `VmRSS` after a warm-up, from `/proc/self/status`. A
//!   leak of even a few bytes per frame shows up as megabytes within minutes at 127 kframe/s.
//! - **dropped**: deliveries the bus dropped because the observer's queue was full (the
//!   observer would then under-count, so the drift check is only meaningful when this is 0).
//!
//! Exit code 0 when every check passed, 3 otherwise (as `bench scale`); the final line says
//! which failed.

use std::collections::HashMap;
use std::io::Write as _;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Result};
use canpos_host::mem::MemBus;
use canpos_host::runtime::Runtime;
use canpos_host::transport::Transport;
use canpos_stack::nmt::{NmtCommand, NmtFrame, ALL_NODES};
use canpos_stack::sdo::wire::{Mux, Request, Response};
use canpos_stack::{cob, Frame};
use clap::Args;
use serde_json::{json, Value};

use crate::sensor::{build_setup, SensorOpts};

/// `canpos soak` options.
#[derive(Debug, Args)]
pub struct SoakArgs {
    /// Number of TH sensors (node-ids 1…N, at most 127).
    #[arg(long, default_value_t = 127)]
    pub nodes: u8,
    /// Length of the run in minutes (fractions allowed, e.g. 0.5).
    #[arg(long, default_value_t = 1.0)]
    pub minutes: f64,
    /// TPDO1 event timer in ms (0x1800/5), written to every node by SDO before the start.
    #[arg(long, default_value_t = 1)]
    pub event_ms: u16,
    /// Seconds between progress lines.
    #[arg(long, default_value_t = 60.0)]
    pub report_s: f64,
    /// Seconds of warm-up before the RSS baseline is taken (allocator pools, queues fill up).
    #[arg(long, default_value_t = 10.0)]
    pub warmup_s: f64,
    /// Fail when RSS grew by more than this (KiB) after the warm-up.
    #[arg(long, default_value_t = 4096)]
    pub max_rss_growth_kib: u64,
    /// Fail when more than this fraction of the ideal frame count is missing or extra
    /// (after subtracting one period per node for the start-up edge).
    #[arg(long, default_value_t = 0.001)]
    pub max_drift: f64,
}

/// What the observer thread has counted.
struct Counts {
    /// TPDO1 frames per node-id (index = node-id).
    per_node: Vec<AtomicU64>,
    /// Gaps between consecutive TPDOs of one node longer than two periods.
    long_gaps: AtomicU64,
    /// Frames that were neither a TPDO1 of a soak node nor expected traffic.
    unexpected: AtomicU64,
    /// Largest gap between consecutive TPDOs of one node, µs.
    max_gap_us: AtomicU64,
}

/// Runs the soak; returns the exit code (0 = every check passed).
pub fn soak(a: SoakArgs) -> Result<i32> {
    if !(1..=127).contains(&a.nodes) {
        bail!("--nodes must be 1…127");
    }
    if a.event_ms == 0 {
        bail!("--event-ms must be ≥ 1");
    }
    if !(a.minutes.is_finite() && a.minutes > 0.0) {
        bail!("--minutes must be > 0");
    }
    crate::limits::check_seconds(a.minutes * 60.0, true).map_err(|e| anyhow!("--minutes: {e}"))?;
    for (name, v) in [("--report-s", a.report_s), ("--warmup-s", a.warmup_s)] {
        crate::limits::check_seconds(v, false).map_err(|e| anyhow!("{name}: {e}"))?;
    }
    let n = usize::from(a.nodes);
    let period = Duration::from_millis(u64::from(a.event_ms));
    let run_for = Duration::from_secs_f64(a.minutes * 60.0);

    // State files go to a private directory: the soak must not touch the user's units.
    let state = crate::common::private_state_dir("soak")?;
    let state_dir = state.path().to_path_buf();

    // The soak measures the runtime's timing, not the bus: the instant bus (127 × 1 ms is more
    // than any CAN bit rate carries).
    let bus = MemBus::instant();
    // The runtime's queue only sees the observer's few frames; the observer's must absorb
    // bursts of `nodes` frames per period while it is descheduled for a few ms.
    let node_port = bus.clone().with_queue_len(4096).attach();
    let mut observer = bus.clone().with_queue_len(1 << 17).attach();
    let mut rt = Runtime::new(Box::new(node_port), None);
    for id in 1..=a.nodes {
        let setup = build_setup(
            &SensorOpts {
                model: Some("th".into()),
                node_id: Some(id),
                serial: Some(90_000_000 + u32::from(id)),
                ideal: true,
                ..Default::default()
            },
            &state_dir,
        )?;
        rt.add(setup.setup);
    }
    // Power on here rather than at the start of the runtime thread: building 127 setups takes
    // ~100 ms, and powering on resets each node's measurement schedule to now, so the build
    // time is not counted as a stall (which the runtime would log and the lateness would show).
    rt.power_on_all();
    let handle = rt.spawn()?;

    // Boot-ups, then the event timer by SDO (a real master would do the same).
    wait_bootups(&mut observer, n)?;
    for id in 1..=a.nodes {
        // 0x1800/5, TPDO1's event timer (2 bytes).
        let req = Request::DownloadInitiate {
            mux: Mux {
                index: 0x1800,
                sub: 5,
            },
            expedited: true,
            size: Some(2),
            data: u32::from(a.event_ms).to_le_bytes(),
        };
        let req = Frame::std8(cob::SDO_RX + u16::from(id), req.emit());
        observer.send(&req)?;
        expect_sdo_ok(&mut observer, id)?;
    }

    let counts = Arc::new(Counts {
        per_node: (0..=127).map(|_| AtomicU64::new(0)).collect(),
        long_gaps: AtomicU64::new(0),
        unexpected: AtomicU64::new(0),
        max_gap_us: AtomicU64::new(0),
    });
    let stop = Arc::new(AtomicBool::new(false));
    // NMT start all: every node enters Operational and its event timer starts now.
    let [c, all] = NmtFrame {
        command: NmtCommand::Start,
        node: ALL_NODES,
    }
    .emit();
    observer.send(&Frame::std_len(cob::NMT, [c, all, 0, 0, 0, 0, 0, 0], 2))?;
    let t0 = Instant::now();
    let obs_thread = {
        let counts = Arc::clone(&counts);
        let stop = Arc::clone(&stop);
        std::thread::Builder::new()
            .name("soak-observer".into())
            .spawn(move || observe(observer, counts, stop, period))?
    };

    let start_cpu = cpu_time();
    let mut baseline_rss: Option<u64> = None;
    let mut max_rss = 0u64;
    let mut next_report = Duration::from_secs_f64(a.report_s.max(1.0));
    let warmup = Duration::from_secs_f64(a.warmup_s.max(0.0));
    let report_every = Duration::from_secs_f64(a.report_s.max(1.0));
    let control = handle.control();
    let stdout = std::io::stdout();
    let mut last = Value::Null;
    loop {
        let elapsed = t0.elapsed();
        let done = elapsed >= run_for || handle.is_finished();
        if baseline_rss.is_none() && elapsed >= warmup {
            baseline_rss = rss_kib();
        }
        max_rss = max_rss.max(rss_kib().unwrap_or(0));
        if done || elapsed >= next_report {
            let state = control.request(canpos_host::control::Request::State { sensor: Some(0) });
            last = summary(
                &a,
                &counts,
                &bus,
                elapsed,
                period,
                baseline_rss,
                max_rss,
                start_cpu,
                &state,
                done,
            );
            if !done {
                let mut o = stdout.lock();
                writeln!(o, "{last}")?;
                o.flush()?;
                next_report += report_every;
            }
        }
        if done {
            break;
        }
        std::thread::sleep(Duration::from_millis(200).min(run_for.saturating_sub(elapsed)));
    }
    let finished_early = handle.is_finished();
    let lateness = handle.stop();
    stop.store(true, Ordering::SeqCst);
    let _ = obs_thread.join();
    drop(state);

    // Final line: the runtime's own lateness histogram is only available after it stopped.
    let mut failures: Vec<String> = Vec::new();
    if let Value::Object(m) = &mut last {
        match &lateness {
            Ok(l) => {
                m.insert("wakes".into(), json!(l.count));
                m.insert("wake_over_200us".into(), json!(l.over_200us));
                m.insert("wake_max_us".into(), json!(l.max_us));
                m.insert("wake_p50_us".into(), json!(l.quantile_us(0.5)));
                m.insert("wake_p99_us".into(), json!(l.quantile_us(0.99)));
            }
            Err(e) => failures.push(format!("runtime error: {e}")),
        }
        if finished_early {
            failures.push("the runtime stopped before the end".into());
        }
        let get = |k: &str| m.get(k).and_then(Value::as_f64).unwrap_or(0.0);
        if get("drift_ratio").abs() > a.max_drift {
            failures.push(format!(
                "drift {:.6} beyond ±{}",
                get("drift_ratio"),
                a.max_drift
            ));
        }
        if get("rss_growth_kib") > a.max_rss_growth_kib as f64 {
            failures.push(format!(
                "RSS grew by {} KiB (limit {})",
                get("rss_growth_kib"),
                a.max_rss_growth_kib
            ));
        }
        if get("dropped") > 0.0 {
            failures.push("the bus dropped frames (observer too slow)".into());
        }
        if get("unexpected_frames") > 0.0 {
            failures.push("frames on unexpected COB-IDs".into());
        }
        if get("silent_nodes") > 0.0 {
            failures.push("some nodes sent no TPDO".into());
        }
        m.insert("pass".into(), json!(failures.is_empty()));
        m.insert("failures".into(), json!(failures));
    }
    println!("{last}");
    // A missed expectation is the bench's "refused" (3), distinct from a runtime error (1).
    Ok(if failures.is_empty() {
        0
    } else {
        crate::common::EXIT_REFUSED
    })
}

/// One JSON summary line.
#[allow(clippy::too_many_arguments)]
fn summary(
    a: &SoakArgs,
    c: &Counts,
    bus: &MemBus,
    elapsed: Duration,
    period: Duration,
    baseline_rss: Option<u64>,
    max_rss: u64,
    start_cpu: Duration,
    state: &Value,
    last: bool,
) -> Value {
    let n = usize::from(a.nodes);
    let per: Vec<u64> = (1..=n)
        .map(|id| c.per_node[id].load(Ordering::Relaxed))
        .collect();
    let frames: u64 = per.iter().sum();
    let ideal = n as f64 * elapsed.as_secs_f64() / period.as_secs_f64();
    // The first TPDO of a node comes one period after its NMT start, and the last period may be
    // half done: up to one frame per node either way is the measurement's own edge, not drift.
    let raw = frames as f64 - ideal;
    let edge = n as f64;
    let drift = if raw.abs() <= edge {
        0.0
    } else {
        raw - raw.signum() * edge
    };
    let rss = rss_kib().unwrap_or(0);
    let cpu = cpu_time().saturating_sub(start_cpu).as_secs_f64();
    let lat = &state["wake_lateness_us"];
    json!({
        "final": last,
        "nodes": n,
        "event_ms": a.event_ms,
        "elapsed_s": (elapsed.as_secs_f64() * 1000.0).round() / 1000.0,
        "frames": frames,
        "ideal_frames": ideal.round() as u64,
        "frames_per_s": (frames as f64 / elapsed.as_secs_f64().max(1e-9)).round(),
        "drift_frames": raw.round() as i64,
        "drift_ratio": drift / ideal.max(1.0),
        "min_node_frames": per.iter().min().copied().unwrap_or(0),
        "max_node_frames": per.iter().max().copied().unwrap_or(0),
        "silent_nodes": per.iter().filter(|&&f| f == 0).count(),
        "long_gaps": c.long_gaps.load(Ordering::Relaxed),
        "max_gap_us": c.max_gap_us.load(Ordering::Relaxed),
        "unexpected_frames": c.unexpected.load(Ordering::Relaxed),
        "dropped": bus.dropped(),
        "wake_p50_us": lat["median"],
        "wake_p99_us": lat["p99"],
        "wake_max_us": lat["max"],
        "rss_kib": rss,
        "rss_baseline_kib": baseline_rss,
        "rss_max_kib": max_rss,
        "rss_growth_kib": baseline_rss.map_or(0, |b| rss.saturating_sub(b)),
        "cpu_percent": (cpu / elapsed.as_secs_f64().max(1e-9) * 1000.0).round() / 10.0,
    })
}

/// Counts TPDO1s per node until `stop`.
fn observe(mut port: impl Transport, c: Arc<Counts>, stop: Arc<AtomicBool>, period: Duration) {
    // Per-node time of the last TPDO, to count long gaps (a gap is only measured between two
    // frames this thread saw, so its own scheduling delays count too: an upper bound).
    let mut last: HashMap<u32, Instant> = HashMap::new();
    let long = period * 2;
    let mut max_gap = 0u64;
    while !stop.load(Ordering::Relaxed) {
        let rx = match port.recv_timeout(Some(Duration::from_millis(100))) {
            Ok(Some(rx)) => rx,
            Ok(None) => continue,
            Err(_) => break,
        };
        let id = rx.frame.id();
        let now = Instant::now();
        if (0x181..=0x1FF).contains(&id) && !rx.frame.is_extended() {
            c.per_node[(id - 0x180) as usize].fetch_add(1, Ordering::Relaxed);
            if let Some(prev) = last.insert(id, now) {
                let gap = now - prev;
                if gap > long {
                    c.long_gaps.fetch_add(1, Ordering::Relaxed);
                }
                let us = gap.as_micros() as u64;
                if us > max_gap {
                    max_gap = us;
                    c.max_gap_us.store(us, Ordering::Relaxed);
                }
            }
        } else {
            c.unexpected.fetch_add(1, Ordering::Relaxed);
        }
    }
}

/// How long the setup waits for an answer (boot-ups, each SDO download).
const SETUP_WAIT: Duration = Duration::from_secs(10);

fn wait_bootups(port: &mut impl Transport, n: usize) -> Result<()> {
    let deadline = Instant::now() + SETUP_WAIT;
    let mut seen = 0;
    while seen < n {
        match port.recv_deadline(deadline)? {
            Some(rx) if (0x701..=0x77F).contains(&rx.frame.id()) && rx.frame.data() == [0] => {
                seen += 1
            }
            Some(_) => {}
            None => bail!(
                "only {seen} of {n} boot-ups within {} s",
                SETUP_WAIT.as_secs()
            ),
        }
    }
    Ok(())
}

fn expect_sdo_ok(port: &mut impl Transport, id: u8) -> Result<()> {
    // A host too slow for 127 nodes runs the twin late, up to the simulation clock's stall
    // bound (2 s, docs/CLOCK.md), and answers that late: the soak measures it, it is no error.
    let deadline = Instant::now() + SETUP_WAIT;
    loop {
        match port.recv_deadline(deadline)? {
            Some(rx) if rx.frame.id() == u32::from(cob::SDO_TX + u16::from(id)) => {
                let d = rx.frame.data();
                // Read as if padded with zeros (a confirmation's bytes after the command byte are
                // reserved, so a short one still confirms); an empty answer is none.
                let mut f = [0u8; 8];
                f[..d.len().min(8)].copy_from_slice(&d[..d.len().min(8)]);
                if !d.is_empty() && matches!(Response::parse(&f), Response::DownloadInitiate { .. })
                {
                    return Ok(());
                }
                bail!("node {id} refused the event timer: {d:02X?}");
            }
            Some(_) => {}
            None => bail!(
                "node {id} did not answer the SDO download within {} s",
                SETUP_WAIT.as_secs()
            ),
        }
    }
}

/// `VmRSS` of this process in KiB.
fn rss_kib() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    s.lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
}

/// CPU time (user + system) of this process.
fn cpu_time() -> Duration {
    // SAFETY: getrusage writes one rusage struct we own.
    let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: RUSAGE_SELF with a valid pointer.
    if unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut ru) } != 0 {
        return Duration::ZERO;
    }
    let tv = |t: libc::timeval| Duration::new(t.tv_sec as u64, t.tv_usec as u32 * 1000);
    tv(ru.ru_utime) + tv(ru.ru_stime)
}
