//! `canpos bench`: the performance instruments of issue 6.
//!
//! - `core`: N operations of the device core in-process, no I/O, every answer checked; prints
//!   ns/op. Run it under `valgrind --tool=callgrind` with two values of N and divide the
//!   difference of the instruction counts by the difference of N: set-up and process start-up
//!   cancel out and what is left is the cost of one operation.
//! - `scale`: N TH sensors at a 1 ms event timer in one [`Runtime`]; one JSON line with the
//!   frame rate, wake-up lateness, missed periods, CPU and RSS.
//! - `sdo-rtt`: SDO round trips of canpos's own master ([`SdoClient`]) against a sensor on a bus.
//! - `boot`: time from starting `canpos run` to its boot-up frame on the bus.
//!
//! Targets live in `docs/BENCHMARKS.md`, never in tests: a loaded CI machine must not fail a
//! build for being slow.

use std::hint::black_box;
use std::time::{Duration, Instant as StdInstant};

use anyhow::{bail, ensure, Context as _, Result};
use canpos_host::mem::MemBus;
use canpos_host::runtime::Runtime;
use canpos_host::transport::Transport;
use canpos_models::SensorNode;
use canpos_models::{self as models, Model};
use canpos_stack::lss::{Inquire, LssRequest, LssResponse, MODE_CONFIGURATION};
use canpos_stack::nmt::{NmtCommand, NmtFrame, ALL_NODES};
use canpos_stack::sdo::wire::{Mux, Request, Response};
use canpos_stack::storage::NoStorage;
use canpos_stack::{cob, Frame, Instant, Node};
use clap::{Args, Subcommand, ValueEnum};
use serde_json::{json, Value};

use crate::client::SdoClient;
use crate::sensor::{build_setup, SensorOpts};

/// `canpos bench` options.
#[derive(Debug, Args)]
pub struct BenchArgs {
    #[command(subcommand)]
    cmd: BenchCmd,
}

#[derive(Debug, Subcommand)]
enum BenchCmd {
    /// N operations of the device core, in-process, no I/O; prints ns/op.
    Core(CoreArgs),
    /// N TH sensors at a 1 ms event timer in one process; prints one JSON line.
    Scale(ScaleArgs),
    /// SDO round trips (canpos's master against a sensor on the bus); median / p99.
    SdoRtt(RttArgs),
    /// Time from starting `canpos run` to its boot-up frame seen by a client.
    Boot(BootArgs),
    /// Bytes of per-node state of the core (`size_of` of the node and its parts).
    Size,
    /// Paced buses kept full in one process: CPU per bus and delivery lateness against the
    /// bus timeline; prints one JSON line.
    Buses(BusesArgs),
}

/// Runs `canpos bench …`.
pub fn bench(a: BenchArgs) -> Result<i32> {
    match a.cmd {
        BenchCmd::Core(a) => core(a),
        BenchCmd::Scale(a) => scale(a),
        BenchCmd::SdoRtt(a) => sdo_rtt(a),
        BenchCmd::Boot(a) => boot(a),
        BenchCmd::Size => size(),
        BenchCmd::Buses(a) => buses(a),
    }
}

// ------------------------------------------------------------------------------------ buses

#[derive(Debug, Args)]
struct BusesArgs {
    /// Number of buses (each its own timeline and driver thread).
    #[arg(long, default_value_t = 16, value_parser = clap::value_parser!(u16).range(1..=256))]
    buses: u16,
    /// Bit rate of every bus, kbit/s (a CiA 301 rate).
    #[arg(long, default_value_t = 1000, value_parser = crate::common::parse_bitrate)]
    bitrate: u32,
    /// Length of the measured window in seconds (after 1 s of warm-up).
    #[arg(long, default_value_t = 5.0, value_parser = crate::limits::parse_positive_seconds)]
    seconds: f64,
}

/// Two transmit-only producers per bus offer about 1.25 times what the bus carries (8-byte
/// frames, queues kept full); one listener per bus drains it. Producers and listeners run on this thread;
/// every bus's driver on its own.
fn buses(a: BusesArgs) -> Result<i32> {
    use canpos_host::bus::Pacing;
    let n = usize::from(a.buses);
    let buses: Vec<MemBus> = (0..n)
        .map(|_| MemBus::with_pacing(Pacing::Paced(a.bitrate)))
        .collect();
    let mut producers: Vec<[canpos_host::MemPort; 2]> = buses
        .iter()
        .map(|b| [b.attach_transmitter(), b.attach_transmitter()])
        .collect();
    let mut listeners: Vec<canpos_host::MemPort> = buses.iter().map(|b| b.attach()).collect();
    // 8-byte frames of 111…135 bits: a bus carries about bitrate / 125 of them per ms.
    let per_ms = (a.bitrate as usize).div_ceil(125) * 5 / 4;
    let mut seq = 0u32;
    let mut received = 0u64;
    let mut run = |until: StdInstant, received: &mut u64| {
        let mut next = StdInstant::now();
        while next < until {
            next += Duration::from_millis(1);
            canpos_host::runtime::sleep_until(next);
            for (k, pair) in producers.iter_mut().enumerate() {
                for i in 0..per_ms {
                    seq = seq.wrapping_add(1);
                    let id = 0x181 + (k % 64) as u16 + (i % 2) as u16 * 0x100;
                    let f = Frame::new(id, &[seq as u8, (seq >> 8) as u8, 0x55, 0xAA, 1, 2, 3, 4])
                        .expect("valid frame");
                    let _ = pair[i % 2].send(&f);
                }
            }
            for l in &mut listeners {
                while let Ok(Some(_)) = l.try_recv() {
                    *received += 1;
                }
            }
        }
    };
    run(StdInstant::now() + Duration::from_secs(1), &mut received);
    let lat0: Vec<_> = buses.iter().filter_map(|b| b.lateness()).collect();
    let frames0: u64 = buses
        .iter()
        .filter_map(|b| b.stats())
        .map(|s| s.frames)
        .sum();
    let (c0, t0) = (cpu_time(), StdInstant::now());
    received = 0;
    run(t0 + Duration::from_secs_f64(a.seconds), &mut received);
    let (cpu, wall) = (cpu_time() - c0, t0.elapsed());
    let stats: Vec<_> = buses.iter().filter_map(|b| b.stats()).collect();
    let frames: u64 = stats.iter().map(|s| s.frames).sum::<u64>() - frames0;
    let loads: Vec<f64> = stats.iter().map(|s| s.load * 100.0).collect();
    // Lateness within the window: the histograms' difference.
    let mut late = canpos_host::mem::LatenessHistogram::default();
    for (b, before) in buses.iter().zip(&lat0) {
        if let Some(h) = b.lateness() {
            late.merge_difference(&h, before);
        }
    }
    let line = json!({
        "buses": n,
        "bitrate_kbps": a.bitrate,
        "seconds": wall.as_secs_f64(),
        "frames_per_s_per_bus": frames as f64 / wall.as_secs_f64() / n as f64,
        "load_pct_min": loads.iter().cloned().fold(f64::INFINITY, f64::min),
        "load_pct_mean": loads.iter().sum::<f64>() / n as f64,
        "cpu_pct_total": cpu.as_secs_f64() / wall.as_secs_f64() * 100.0,
        "cpu_pct_per_bus": cpu.as_secs_f64() / wall.as_secs_f64() * 100.0 / n as f64,
        "lateness_us_p50": late.quantile_us(0.5),
        "lateness_us_p99": late.quantile_us(0.99),
        "lateness_us_max": late.quantile_us(1.0),
        "delivered": received,
        "tx_lost": stats.iter().map(|s| s.tx_lost).sum::<u64>(),
        "rx_dropped": stats.iter().map(|s| s.rx_dropped).sum::<u64>(),
    });
    println!("{line}");
    Ok(0)
}

// ------------------------------------------------------------------------------------- core

/// What one core operation is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum CoreOp {
    /// SDO expedited upload of 0x1000 (request in, response out).
    SdoUpload,
    /// SDO expedited download of the object's current value (`--index`, default 0x1014 COB-ID
    /// EMCY, 4 bytes) back into it.
    SdoDownload,
    /// One event-timer TPDO1 with the default mapping (timer expiry in, TPDO out).
    Tpdo,
    /// LSS inquire node-id in LSS configuration state.
    LssInquire,
    /// SDO expedited uploads of 0x1000 and 0x1018/1 in turn (no two requests for the same
    /// object in a row).
    SdoUploadAlternating,
    /// SYNC in, synchronous TPDO1 (transmission type 1) out.
    SyncTpdo,
    /// A step with nothing to do (pre-operational, no timer due): the host loop's idle cost.
    Idle,
    /// Another node's PDO in (0x181 + 1), nothing out: what most of a busy bus is.
    ForeignPdo,
}

#[derive(Debug, Args)]
struct CoreArgs {
    /// The operation.
    #[arg(long, value_enum)]
    op: CoreOp,
    /// Number of operations.
    #[arg(long, default_value_t = 1_000_000)]
    iterations: u64,
    /// Product model: th, e-series or tmi.
    #[arg(long, default_value = "th")]
    model: String,
    /// Object of `sdo-download` (hex), e.g. 0x1014, 0x1005 (4 bytes), 0x1017 (2 bytes).
    #[arg(long, default_value = "0x1014", value_parser = parse_hex16)]
    index: u16,
    /// Sub-index of `sdo-download`.
    #[arg(long, default_value_t = 0)]
    sub: u8,
}

fn parse_hex16(s: &str) -> Result<u16, String> {
    let h = s.trim_start_matches("0x").trim_start_matches("0X");
    u16::from_str_radix(h, 16).map_err(|_| format!("`{s}` is not a 16-bit hex index"))
}

/// A node of `model` after power-on, boot-up frames taken, in pre-operational.
fn booted(model: &'static Model) -> SensorNode<NoStorage> {
    let mut n = Node::new(model, model.default_config, NoStorage);
    n.power_on(Instant::from_micros(0));
    while n.poll_transmit().is_some() {}
    n
}

/// The node's full processing step after an input: its timers if due, then one frame out
/// ([`Node::poll`], what the host runtime calls).
#[inline(always)]
fn step_out(n: &mut SensorNode<NoStorage>, now: Instant) -> Option<Frame> {
    n.poll(now)
}

fn core(a: CoreArgs) -> Result<i32> {
    let model = models::by_name(&a.model).with_context(|| format!("unknown model {}", a.model))?;
    let mut n = booted(model);
    let id = n.device().node_id();
    ensure!(
        id <= 127,
        "the model's default configuration has no node-id"
    );
    let id16 = u16::from(id);
    let iters = a.iterations;
    let mut now = Instant::from_micros(1000);
    let start;
    match a.op {
        CoreOp::SdoUpload => {
            let expect = n
                .read_object(0x1000, 0)
                .map_err(|e| anyhow::anyhow!("{e:?}"))?;
            let req = Frame::std8(cob::SDO_RX + id16, upload_request(0x1000, 0));
            let want = expedited_upload(0x1000, 0, expect);
            start = StdInstant::now();
            for _ in 0..iters {
                now = Instant::from_micros(now.micros() + 1);
                n.handle_frame(black_box(&req), now);
                let r = step_out(&mut n, now);
                check(r, cob::SDO_TX + id16, &want)?;
            }
        }
        CoreOp::SdoDownload => {
            let (index, sub) = (a.index, a.sub);
            let v = n
                .read_object(index, sub)
                .map_err(|e| anyhow::anyhow!("{index:04X}/{sub}: {e:?}"))?;
            let slot = n
                .device()
                .od()
                .find(index, sub)
                .map_err(|e| anyhow::anyhow!("{e:?}"))?;
            let len = match n.device().od().entry(slot).ty.size() {
                Some(len @ (1 | 2 | 4)) => len as u32,
                other => bail!("{index:04X}/{sub} has size {other:?}: not an expedited number"),
            };
            let req = Frame::std8(cob::SDO_RX + id16, download_request(index, sub, len, v));
            let mux = Mux { index, sub };
            let want = Response::DownloadInitiate { mux }.emit();
            start = StdInstant::now();
            for _ in 0..iters {
                now = Instant::from_micros(now.micros() + 1);
                n.handle_frame(black_box(&req), now);
                let r = step_out(&mut n, now);
                check(r, cob::SDO_TX + id16, &want)?;
            }
        }
        CoreOp::Tpdo => {
            // Event timer 1 ms (all models default to it, but say so), then NMT start.
            n.handle_frame(
                &Frame::std8(cob::SDO_RX + id16, download_request(0x1800, 5, 2, 1)),
                now,
            );
            n.handle_frame(&nmt_start_all(), now);
            while n.poll_transmit().is_some() {}
            let first = n
                .poll_timeout()
                .context("no TPDO deadline after NMT start")?;
            now = first;
            // The first TPDO gives the expected frame (default mapping, values unchanged).
            let want = step_out(&mut n, now).context("no TPDO at the first deadline")?;
            ensure!(
                want.std_id() == Some(0x180 + id16) && !want.is_remote(),
                "not TPDO1: {want:?}"
            );
            start = StdInstant::now();
            for _ in 0..iters {
                now = Instant::from_micros(now.micros() + 1000);
                // The whole frame (identifier, format, DLC, data) must be the expected one.
                match step_out(&mut n, now) {
                    Some(f) if f == want => {}
                    other => bail!("expected {want:?} at {now:?}, got {other:?}"),
                }
            }
        }
        CoreOp::LssInquire => {
            // Switch state global: configuration (no answer).
            let mode = MODE_CONFIGURATION;
            let switch = LssRequest::SwitchGlobal { mode }.emit();
            n.handle_frame(&Frame::std8(cob::LSS_RX, switch), now);
            while n.poll_transmit().is_some() {}
            let inquire = LssRequest::Inquire(Inquire::NodeId).emit();
            let req = Frame::std8(cob::LSS_RX, inquire);
            let want = LssResponse::NodeId(id).emit();
            start = StdInstant::now();
            for _ in 0..iters {
                now = Instant::from_micros(now.micros() + 1);
                n.handle_frame(black_box(&req), now);
                let r = step_out(&mut n, now);
                check(r, cob::LSS_TX, &want)?;
            }
        }
        _ => start = more_ops(a.op, &mut n, id, now, iters)?,
    }
    let el = start.elapsed();
    // Nothing else may be left over: one answer per request.
    ensure!(n.poll_transmit().is_none(), "extra frame after the run");
    let object = match a.op {
        CoreOp::SdoDownload => format!(" object={:04X}/{}", a.index, a.sub),
        _ => String::new(),
    };
    println!(
        "op={:?}{object} model={} iterations={} ns_per_op={:.1} total_ms={:.1}",
        a.op,
        model.name,
        iters,
        el.as_nanos() as f64 / iters.max(1) as f64,
        el.as_secs_f64() * 1e3
    );
    Ok(0)
}

/// The ops added after the first four, out of line so that their code does not change the
/// codegen of the first four's loops (their instruction counts stay comparable across stops).
#[inline(never)]
fn more_ops(
    op: CoreOp,
    n: &mut SensorNode<NoStorage>,
    id: u8,
    mut now: Instant,
    iters: u64,
) -> Result<StdInstant> {
    let id16 = u16::from(id);
    let start;
    match op {
        CoreOp::SdoUploadAlternating => {
            let objects = [(0x1000u16, 0u8), (0x1018, 1)];
            let mut reqs = Vec::new();
            for (index, sub) in objects {
                let v = n
                    .read_object(index, sub)
                    .map_err(|e| anyhow::anyhow!("{e:?}"))?;
                reqs.push((
                    Frame::std8(cob::SDO_RX + id16, upload_request(index, sub)),
                    expedited_upload(index, sub, v),
                ));
            }
            start = StdInstant::now();
            for k in 0..iters {
                now = Instant::from_micros(now.micros() + 1);
                let (req, want) = &reqs[(k & 1) as usize];
                n.handle_frame(black_box(req), now);
                let r = step_out(n, now);
                check(r, cob::SDO_TX + id16, want)?;
            }
        }
        CoreOp::SyncTpdo => {
            // TPDO1 synchronous on every SYNC, then NMT start.
            n.handle_frame(
                &Frame::std8(cob::SDO_RX + id16, download_request(0x1800, 2, 1, 1)),
                now,
            );
            n.handle_frame(&nmt_start_all(), now);
            while n.poll_transmit().is_some() {}
            let sync = Frame::new(0x080, &[]).map_err(|e| anyhow::anyhow!("SYNC frame: {e:?}"))?;
            n.handle_frame(&sync, now);
            let want = step_out(n, now).context("no TPDO after the first SYNC")?;
            ensure!(want.std_id() == Some(0x180 + id16), "not TPDO1: {want:?}");
            start = StdInstant::now();
            for _ in 0..iters {
                now = Instant::from_micros(now.micros() + 1000);
                n.handle_frame(black_box(&sync), now);
                match step_out(n, now) {
                    Some(f) if f == want => {}
                    other => bail!("expected {want:?} after SYNC at {now:?}, got {other:?}"),
                }
            }
        }
        CoreOp::Idle => {
            ensure!(
                n.poll_timeout().is_none(),
                "a timer is armed in the default pre-operational state"
            );
            start = StdInstant::now();
            for _ in 0..iters {
                now = Instant::from_micros(now.micros() + 1);
                if let Some(f) = step_out(n, black_box(now)) {
                    bail!("idle node sent {f:?}");
                }
            }
        }
        CoreOp::ForeignPdo => {
            let other = if id == 1 { 2 } else { 1 };
            let pdo = Frame::std8(0x180 + other, [1, 2, 3, 4, 5, 6, 7, 8]);
            start = StdInstant::now();
            for _ in 0..iters {
                now = Instant::from_micros(now.micros() + 1);
                n.handle_frame(black_box(&pdo), now);
                if let Some(f) = step_out(n, now) {
                    bail!("a foreign PDO made the node send {f:?}");
                }
            }
        }
        CoreOp::SdoUpload | CoreOp::SdoDownload | CoreOp::Tpdo | CoreOp::LssInquire => {
            bail!("{op:?} is measured by core()")
        }
    }
    Ok(start)
}

/// An SDO upload request of `index`/`sub`.
fn upload_request(index: u16, sub: u8) -> [u8; 8] {
    let mux = Mux { index, sub };
    Request::UploadInitiate { mux }.emit()
}

/// The expedited 4-byte upload answer carrying `v`.
fn expedited_upload(index: u16, sub: u8, v: u32) -> [u8; 8] {
    Response::UploadInitiate {
        mux: Mux { index, sub },
        expedited: true,
        size: Some(4),
        data: v.to_le_bytes(),
    }
    .emit()
}

/// An expedited SDO download of the low `len` (1…4) bytes of `v`.
fn download_request(index: u16, sub: u8, len: u32, v: u32) -> [u8; 8] {
    Request::DownloadInitiate {
        mux: Mux { index, sub },
        expedited: true,
        size: Some(len),
        data: v.to_le_bytes(),
    }
    .emit()
}

/// NMT start for all nodes.
fn nmt_start_all() -> Frame {
    let [c, n] = NmtFrame {
        command: NmtCommand::Start,
        node: ALL_NODES,
    }
    .emit();
    Frame::std_len(cob::NMT, [c, n, 0, 0, 0, 0, 0, 0], 2)
}

#[inline(always)]
fn check(r: Option<Frame>, id: u16, want: &[u8; 8]) -> Result<()> {
    match r {
        Some(f) if f.std_id() == Some(id) && f.dlc() == 8 && f.raw() == want => Ok(()),
        other => bail!("expected {id:03X} {want:02X?}, got {other:?}"),
    }
}

// ------------------------------------------------------------------------------------ scale

/// Which bus the scale run uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum ScaleBus {
    /// The in-process bus.
    Mem,
    /// An embedded socketcand hub on loopback (an ephemeral port); the sensors reach it over TCP.
    Socketcand,
}

#[derive(Debug, Args)]
struct ScaleArgs {
    /// Number of TH sensors (node-ids 1…N).
    #[arg(long, default_value_t = 127, value_parser = clap::value_parser!(u8).range(1..=127))]
    nodes: u8,
    /// TPDO1 event timer in ms (0x1800/5), written to every node before NMT start.
    #[arg(long, default_value_t = 1)]
    event_ms: u16,
    /// Length of the measured window in seconds (after the warm-up).
    #[arg(long, default_value_t = 10.0, value_parser = crate::limits::parse_positive_seconds)]
    seconds: f64,
    /// Seconds of production before the window starts.
    #[arg(long, default_value_t = 1.0, value_parser = crate::limits::parse_seconds)]
    warmup: f64,
    /// The bus.
    #[arg(long, value_enum, default_value = "mem")]
    bus: ScaleBus,
    /// Also run an observer thread that receives every frame (costs CPU of its own; the bus's
    /// frame counter is used either way).
    #[arg(long)]
    observe: bool,
    /// The bus delivers every frame at once, without bit time or limit: what measures the
    /// runtime's own scale (127 × 1 ms is 16 times what a 1 Mbit/s bus carries). Without it
    /// the bus is paced at 1000 kbit/s (docs/BUS.md).
    #[arg(long)]
    instant_bus: bool,
}

/// CPU time (user + system) of this process, from getrusage.
fn cpu_time() -> Duration {
    // SAFETY: getrusage fills the struct we own; RUSAGE_SELF is always valid.
    let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut ru) };
    let tv = |t: libc::timeval| Duration::new(t.tv_sec as u64, t.tv_usec as u32 * 1000);
    tv(ru.ru_utime) + tv(ru.ru_stime)
}

/// Resident set size of this process in KiB (`VmRSS`).
fn rss_kib() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmRSS:"))
                .and_then(|l| l.split_whitespace().nth(1).map(str::to_string))
        })
        .and_then(|v| v.parse().ok())
        .unwrap_or(0)
}

/// A fresh private directory for the sensors' state files, removed when dropped.
struct TempDir(tempfile::TempDir);

impl TempDir {
    fn new(tag: &str) -> Result<TempDir> {
        crate::common::private_state_dir(&format!("bench-{tag}")).map(TempDir)
    }
}

/// Waits until `n` distinct boot-up frames (0x701…) were seen on `port`.
fn wait_boot(port: &mut dyn Transport, n: usize, within: Duration) -> Result<()> {
    let end = StdInstant::now() + within;
    let mut seen = std::collections::HashSet::new();
    while seen.len() < n {
        match port.recv_deadline(end)? {
            Some(rx) => {
                if let Some(id @ 0x701..=0x77F) = rx.frame.std_id() {
                    if rx.frame.data() == [0] {
                        seen.insert(id);
                    }
                }
            }
            None => bail!("only {} of {n} boot-ups within {within:?}", seen.len()),
        }
    }
    Ok(())
}

fn scale(a: ScaleArgs) -> Result<i32> {
    let dir = TempDir::new("scale")?;
    let nodes = a.nodes;
    // The bus: the runtime's port, a master port for the set-up, and a frame counter.
    let pacing = crate::common::pacing(None, a.instant_bus);
    let mem = MemBus::with_pacing(pacing).with_queue_len(65536);
    let mut hub = None;
    let (runtime_port, mut master): (Box<dyn Transport>, Box<dyn Transport>) = match a.bus {
        ScaleBus::Mem => (Box::new(mem.attach()), Box::new(mem.attach())),
        ScaleBus::Socketcand => {
            let config = canpos_host::socketcand::HubConfig {
                pacing,
                ..Default::default()
            };
            let h = canpos_host::Hub::bind_with("127.0.0.1:0", config)?.spawn()?;
            let url = format!("socketcand://{}/can0", h.local_addr());
            let rt = canpos_host::transport::open(&url)?;
            let m = canpos_host::transport::open(&url)?;
            hub = Some(h);
            (rt, m)
        }
    };
    let frames_now = |hub: &Option<canpos_host::HubHandle>| match hub {
        Some(h) => h.stats().frames_in,
        None => mem.frames(),
    };
    let mut rt = Runtime::new(runtime_port, None);
    for id in 1..=nodes {
        let opts = SensorOpts {
            model: Some("th".into()),
            node_id: Some(id),
            serial: Some(u32::from(id)),
            magnets: vec![250.0],
            ..Default::default()
        };
        rt.add(build_setup(&opts, dir.0.path())?.setup);
    }
    let handle = rt.spawn()?;
    wait_boot(&mut *master, nodes as usize, Duration::from_secs(10))?;
    // Event timer, then NMT start for all.
    for id in 1..=nodes {
        let mut c = SdoClient::new(&mut *master, id, Duration::from_secs(2));
        c.download(0x1800, 5, &a.event_ms.to_le_bytes())
            .with_context(|| format!("writing 0x1800/5 of node {id}"))?;
    }
    master.send(&nmt_start_all())?;
    // The master port would only fill up: leave the bus (the socketcand client stays connected
    // but is drained by the observer or not at all; the hub drops for it without blocking).
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let observed = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
    let observer = if a.observe {
        let stop = stop.clone();
        let observed = observed.clone();
        Some(std::thread::spawn(move || {
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                if let Ok(Some(rx)) = master.recv_timeout(Some(Duration::from_millis(100))) {
                    if rx
                        .frame
                        .std_id()
                        .is_some_and(|id| (0x181..=0x1FF).contains(&id))
                    {
                        observed.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    }
                }
            }
        }))
    } else {
        drop(master);
        None
    };
    std::thread::sleep(Duration::from_secs_f64(a.warmup));
    let control = handle.control();
    let missed = |control: &canpos_host::ControlHandle| -> Result<(u64, Value)> {
        let mut total = 0u64;
        let mut last = Value::Null;
        for i in 0..nodes as usize {
            let st = control.request(canpos_host::control::Request::State { sensor: Some(i) });
            ensure!(st["ok"] == true, "state of sensor {i}: {st}");
            total += st["tpdo_missed"].as_u64().unwrap_or(0);
            last = st;
        }
        Ok((total, last))
    };
    let (missed0, _) = missed(&control)?;
    let r = control.request(canpos_host::control::Request::ResetLateness { sensor: None });
    ensure!(r["ok"] == true, "reset-lateness: {r}");
    let f0 = frames_now(&hub);
    let o0 = observed.load(std::sync::atomic::Ordering::Relaxed);
    let c0 = cpu_time();
    let t0 = StdInstant::now();
    std::thread::sleep(Duration::from_secs_f64(a.seconds));
    let wall = t0.elapsed().as_secs_f64();
    let cpu = (cpu_time() - c0).as_secs_f64();
    let f1 = frames_now(&hub);
    let o1 = observed.load(std::sync::atomic::Ordering::Relaxed);
    let (missed1, st) = missed(&control)?;
    let rss = rss_kib();
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    handle.stop()?;
    if let Some(o) = observer {
        let _ = o.join();
    }
    if let Some(h) = hub {
        h.shutdown()?;
    }
    let late = &st["wake_lateness_us"];
    let expected = f64::from(nodes) * 1000.0 / f64::from(a.event_ms.max(1));
    let line = json!({
        "bench": "scale",
        "bus": format!("{:?}", a.bus).to_lowercase(),
        "nodes": nodes,
        "event_ms": a.event_ms,
        "seconds": wall,
        "expected_frames_per_s": expected,
        "frames_per_s": (f1 - f0) as f64 / wall,
        "observed_tpdo_per_s": a.observe.then(|| (o1 - o0) as f64 / wall),
        "lateness_us_p50": late["median"],
        "lateness_us_p99": late["p99"],
        "lateness_us_max": late["max"],
        "lateness_wakes": late["count"],
        "missed_periods": missed1 - missed0,
        "cpu_percent": 100.0 * cpu / wall,
        "rss_kib": rss,
    });
    // The bench's own expectation: every period produced, none skipped.
    let frames_per_s = (f1 - f0) as f64 / wall;
    let missed = missed1 - missed0;
    let mut failures = Vec::new();
    if missed > 0 {
        failures.push(format!("{missed} event-timer periods missed"));
    }
    if frames_per_s < 0.99 * expected {
        failures.push(format!(
            "{frames_per_s:.0} frames/s, under 99 % of the expected {expected:.0}"
        ));
    }
    let mut line = line;
    line["verdict"] = json!(if failures.is_empty() { "pass" } else { "fail" });
    line["failures"] = json!(failures);
    println!("{line}");
    if failures.is_empty() {
        Ok(0)
    } else {
        eprintln!(
            "error: bench scale missed its expectation: {}",
            failures.join("; ")
        );
        Ok(crate::common::EXIT_REFUSED)
    }
}

// ---------------------------------------------------------------------------------- sdo-rtt

#[derive(Debug, Args)]
struct RttArgs {
    /// Bus URL of the hub the sensor is on, e.g. socketcand://127.0.0.1:29536/can0.
    #[arg(long, default_value = canpos_host::DEFAULT_URL)]
    bus: String,
    /// Number of round trips measured (after 100 unmeasured ones).
    #[arg(long, default_value_t = 10_000)]
    count: usize,
    /// Node-id of the sensor.
    #[arg(long, default_value_t = 127)]
    node: u8,
}

/// The `q` quantile (0…1) of sorted samples, nearest rank.
fn quantile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let k = ((sorted.len() as f64 * q).ceil() as usize).clamp(1, sorted.len());
    sorted[k - 1]
}

fn sdo_rtt(a: RttArgs) -> Result<i32> {
    let mut bus = crate::common::open_bus(&a.bus)?;
    let mut c = SdoClient::new(&mut *bus, a.node, Duration::from_secs(1));
    // Expected answer: whatever 0x1000 holds, the same every time.
    let want = c.upload(0x1000, 0).context("first SDO upload of 0x1000")?;
    for _ in 0..100 {
        c.upload(0x1000, 0)?;
    }
    let mut us = Vec::with_capacity(a.count);
    for _ in 0..a.count {
        let t = StdInstant::now();
        let v = c.upload(0x1000, 0)?;
        us.push(t.elapsed().as_secs_f64() * 1e6);
        ensure!(v == want, "0x1000 changed: {v:02X?}");
    }
    us.sort_by(f64::total_cmp);
    let mean = us.iter().sum::<f64>() / us.len().max(1) as f64;
    let line = json!({
        "bench": "sdo-rtt",
        "client": "canpos SdoClient",
        "bus": a.bus,
        "node": a.node,
        "count": us.len(),
        "median_us": quantile(&us, 0.5),
        "p99_us": quantile(&us, 0.99),
        "mean_us": mean,
        "min_us": us.first(),
        "max_us": us.last(),
    });
    println!("{line}");
    Ok(0)
}

// ------------------------------------------------------------------------------------- boot

#[derive(Debug, Args)]
struct BootArgs {
    /// Number of starts measured.
    #[arg(long, default_value_t = 10)]
    runs: usize,
}

/// Starts `canpos run` (this binary) against a hub on an ephemeral loopback port and times
/// process start → boot-up frame received by a socketcand client of that hub.
fn boot(a: BootArgs) -> Result<i32> {
    let dir = TempDir::new("boot")?;
    let hub = canpos_host::Hub::bind("127.0.0.1:0")?.spawn()?;
    let url = format!("socketcand://{}/can0", hub.local_addr());
    let mut client = canpos_host::transport::open(&url)?;
    let exe = std::env::current_exe()?;
    let mut ms = Vec::new();
    for run in 0..a.runs {
        let state = dir.0.path().join(format!("run{run}"));
        let t0 = StdInstant::now();
        let mut child = std::process::Command::new(&exe)
            .args([
                "-q",
                "run",
                "--model",
                "th",
                "--node-id",
                "5",
                "--magnet",
                "100",
            ])
            .arg("--bus")
            .arg(&url)
            .arg("--state-dir")
            .arg(&state)
            .stdin(std::process::Stdio::null())
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .context("cannot start canpos run")?;
        let end = t0 + Duration::from_secs(5);
        let mut seen = None;
        while let Some(rx) = client.recv_deadline(end)? {
            if rx.frame.std_id() == Some(0x705) && rx.frame.data() == [0] {
                seen = Some(t0.elapsed());
                break;
            }
        }
        // Only the child we started, by its own handle.
        let _ = child.kill();
        let _ = child.wait();
        let el = seen.context("no boot-up frame within 5 s")?;
        ms.push(el.as_secs_f64() * 1e3);
        // Let the hub forget the old connection before the next start.
        std::thread::sleep(Duration::from_millis(50));
        while client.try_recv()?.is_some() {}
    }
    hub.shutdown()?;
    let mut sorted = ms.clone();
    sorted.sort_by(f64::total_cmp);
    let line = json!({
        "bench": "boot",
        "runs": ms.len(),
        "boot_ms_median": quantile(&sorted, 0.5),
        "boot_ms_max": sorted.last(),
        "boot_ms": ms,
    });
    println!("{line}");
    Ok(0)
}

// ------------------------------------------------------------------------------------- size

/// `size_of` of the node: one type for every model (the model's table is `&'static` data, the
/// values array is sized for the largest table), so the figure holds for th, e-series and tmi.
fn size() -> Result<i32> {
    use canpos_stack::storage::RamStorage;
    use std::mem::size_of;
    let line = json!({
        "bench": "size",
        "models": models::all().map(|m| m.name),
        "node_no_storage": size_of::<SensorNode<NoStorage>>(),
        "node_ram_storage": size_of::<SensorNode<RamStorage>>(),
        "node_file_storage": size_of::<SensorNode<canpos_host::FileStorage>>(),
        "dictionary": size_of::<canpos_stack::od::Dictionary>(),
        "sdo_server": size_of::<canpos_stack::sdo::SdoServer>(),
        "tpdos": size_of::<canpos_stack::pdo::Tpdos>(),
        "emcy": size_of::<canpos_stack::emcy::Emcy>(),
        "encoder": size_of::<canpos_encoder::Encoder>(),
        "ram_storage": size_of::<RamStorage>(),
        "table_entries": models::all().map(|m| m.entries.len()),
    });
    println!("{line}");
    Ok(0)
}
