//! `canpos bus netsim`: canpos's bus timeline as the CAN network simulator of a Vector SIL Kit
//! network (issue 32 item 3, docs/SILKIT.md "canpos as the network simulator").

use std::ffi::OsString;
use std::io::{BufRead as _, BufReader, Write as _};
use std::os::unix::process::{CommandExt as _, ExitStatusExt as _};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, Context as _, Result};
use canpos_host::silkit::netsim::{NetworkReport, NetworkSpec, Simulator, TimeMode};
use canpos_host::silkit::{check_name, sys, RegistryUri};
use clap::{Args, ValueEnum};

use crate::common::{parse_bitrate, stop_signal, Usage};

/// Time modes of `canpos bus netsim`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum NetsimTime {
    /// The simulator's own monotonic clock (participants not synchronised).
    Wall,
    /// SIL Kit's simulation time (a synchronised participant; deterministic).
    Sync,
}

/// Options of `canpos bus netsim`.
#[derive(Debug, Args)]
pub struct NetsimArgs {
    /// The SIL Kit registry, `silkit://HOST:PORT`.
    #[arg(long, value_name = "URI")]
    pub registry: String,
    /// A CAN network to simulate (SIL Kit network name); repeat for several networks in this
    /// one process.
    #[arg(long = "network", value_name = "NAME", required = true)]
    pub networks: Vec<String>,
    /// Bit rate of the networks in kbit/s (or bit/s; a CiA 301 rate).
    #[arg(long, value_name = "KBPS", value_parser = parse_bitrate)]
    pub bitrate: u32,
    /// Time mode: `wall` (the simulator's clock) or `sync` (SIL Kit's simulation time).
    #[arg(long, value_enum, default_value_t = NetsimTime::Wall)]
    pub time: NetsimTime,
    /// Simulation step in µs (`--time sync`; default 40 bit times: 320 µs at 125 kbit/s). Keep
    /// it shorter than the shortest frame (44 bit times to its end of frame): then every
    /// receiver has each frame before its step passes the frame's end (D40).
    #[arg(long, value_name = "US",
          value_parser = clap::value_parser!(u64).range(1..=1_000_000))]
    pub step_us: Option<u64>,
    /// Coordinated lifecycle (`--time sync`): a system controller starts and stops the
    /// simulation (default: autonomous, it joins a running simulation).
    #[arg(long)]
    pub coordinated: bool,
    /// SIL Kit participant name.
    #[arg(long, value_name = "NAME", default_value = "canpos-netsim")]
    pub participant: String,
    /// Log every network's counters every this many seconds (0: never).
    #[arg(long, value_name = "S", default_value_t = 10.0)]
    pub stats_interval: f64,
    /// Stop after this many seconds (default: at Ctrl-C / SIGTERM or SIL Kit's stop).
    #[arg(long, value_name = "S", value_parser = crate::limits::parse_positive_seconds)]
    pub duration: Option<f64>,
}

/// `silkit://HOST:PORT` (no path; an IPv6 host in brackets): the registry's address.
fn registry_uri(s: &str) -> Result<RegistryUri, String> {
    let bad = || format!("`{s}` is not silkit://HOST:PORT");
    let rest = s.strip_prefix("silkit://").ok_or_else(bad)?;
    let (host, port) = rest.rsplit_once(':').ok_or_else(bad)?;
    let host = match host.strip_prefix('[') {
        Some(h) => h.strip_suffix(']').ok_or_else(bad)?,
        None => host,
    };
    let port: u16 = port.parse().map_err(|_| bad())?;
    if host.is_empty() || host.contains(['/', '[', ']']) || port == 0 {
        return Err(bad());
    }
    Ok(RegistryUri {
        host: host.to_string(),
        port,
    })
}

/// The environment variable that makes a `canpos bus netsim` process the worker of a
/// supervising one (D57); its value is the supervisor's process id.
const WORKER_ENV: &str = "CANPOS_NETSIM_WORKER";

/// Signals of a worker that crashed (SIL Kit 5.0.3's SIGSEGV, D57), after which it is restarted;
/// any other end of the worker ends the command with it.
const CRASH_SIGNALS: [i32; 5] = [
    libc::SIGSEGV,
    libc::SIGBUS,
    libc::SIGABRT,
    libc::SIGILL,
    libc::SIGFPE,
];

/// Workers in a row that die before they simulate (a crash at start-up, not a controller
/// leaving) after which the supervisor gives up.
const MAX_EARLY_DEATHS: u32 = 5;

/// The first line a worker prints once it simulates its networks.
const BANNER: &str = "canpos bus netsim: simulating ";

/// Runs `canpos bus netsim`: a supervisor that runs the simulator in a worker process and
/// restarts it when SIL Kit crashes it (D57); in the worker, the simulator.
pub fn bus_netsim(args: NetsimArgs) -> Result<i32> {
    let (uri, specs, mode) = prepare(&args)?;
    match std::env::var_os(WORKER_ENV) {
        Some(parent) => {
            // The supervisor starts its worker with the stop signals blocked: one that comes
            // while the worker starts (Ctrl-C reaches the whole process group) waits for this
            // handler instead of killing the worker before it can leave SIL Kit.
            let stop = stop_signal()?;
            stop_signals_mask(libc::SIG_UNBLOCK).context("cannot unblock the stop signals")?;
            follow_parent(&parent)?;
            simulate(&args, &uri, &specs, mode, stop)
        }
        None => supervise(&args, mode),
    }
}

/// Signals that stop `canpos bus netsim` gracefully: those `stop_signal` handles.
const STOP_SIGNALS: [i32; 3] = [libc::SIGINT, libc::SIGTERM, libc::SIGHUP];

/// Blocks (`SIG_BLOCK`) or unblocks (`SIG_UNBLOCK`) [`STOP_SIGNALS`] for the calling thread.
/// Only async-signal-safe calls: it also runs in the forked worker before its `exec`.
fn stop_signals_mask(how: libc::c_int) -> std::io::Result<()> {
    // SAFETY: a sigset_t on the stack, initialised by sigemptyset before use.
    unsafe {
        let mut set = std::mem::zeroed::<libc::sigset_t>();
        libc::sigemptyset(&mut set);
        for s in STOP_SIGNALS {
            libc::sigaddset(&mut set, s);
        }
        match libc::pthread_sigmask(how, &set, std::ptr::null_mut()) {
            0 => Ok(()),
            e => Err(std::io::Error::from_raw_os_error(e)),
        }
    }
}

/// The worker ends with its supervisor (SIGTERM, a graceful leave), whatever ends that; a
/// process whose parent is not the supervisor `CANPOS_NETSIM_WORKER` names is refused.
fn follow_parent(parent: &std::ffi::OsStr) -> Result<()> {
    // SAFETY: prctl with an integer signal number; getppid has no arguments.
    let ppid = unsafe {
        libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM);
        libc::getppid()
    };
    // Checked after prctl: the supervisor may have ended before it took effect.
    if parent.to_str().and_then(|p| p.parse().ok()) != Some(ppid) {
        return Err(anyhow!(
            "{WORKER_ENV}={} marks this process as the simulator's worker of the `canpos bus \
             netsim` with that process id, but its parent is process {ppid}: that supervisor \
             has ended, or the variable was set by hand or inherited; unset it to run `canpos \
             bus netsim`",
            parent.to_string_lossy()
        ));
    }
    Ok(())
}

/// The worker's arguments: this command's, `--duration` given as what is left of it.
fn worker_args(args: impl Iterator<Item = OsString>, left: Option<Duration>) -> Vec<OsString> {
    let mut out = Vec::new();
    let mut skip_value = false;
    for a in args {
        if std::mem::take(&mut skip_value) {
            continue;
        }
        if a == "--duration" {
            skip_value = true;
            continue;
        }
        if a.to_str().is_some_and(|s| s.starts_with("--duration=")) {
            continue;
        }
        out.push(a);
    }
    if let Some(left) = left {
        out.push("--duration".into());
        out.push(format!("{:.3}", left.as_secs_f64().max(0.001)).into());
    }
    out
}

/// Runs the simulator in a worker process (this program, these arguments) and starts a new one
/// when the worker crashes: SIL Kit 5.0.3 can crash the simulator when a controller leaves (a
/// send it queued for the controller reaches the controller's freed record, D57), and no order
/// of canpos's calls prevents it. The new worker joins the registry again, takes its networks
/// over again (the controllers go on as they were, D39) and tells wall-clock times again (D41);
/// counters and bus time start anew. Ctrl-C / SIGTERM stop the worker gracefully.
fn supervise(args: &NetsimArgs, mode: TimeMode) -> Result<i32> {
    let stop = stop_signal()?;
    let exe = std::env::current_exe().context("cannot find this program to run the simulator")?;
    let started = Instant::now();
    let end = args.duration.map(|d| started + Duration::from_secs_f64(d));
    let networks = args.networks.join(", ");
    let (mut restarts, mut early) = (0u32, 0u32);
    loop {
        let left = end.map(|t| t.saturating_duration_since(Instant::now()));
        if left.is_some_and(|l| l.is_zero()) {
            return Ok(0);
        }
        let mut cmd = Command::new(&exe);
        cmd.args(worker_args(std::env::args_os().skip(1), left))
            .env(WORKER_ENV, std::process::id().to_string())
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit());
        // Blocked until the worker handles them (see `bus_netsim`).
        // SAFETY: the closure only calls async-signal-safe functions.
        unsafe { cmd.pre_exec(|| stop_signals_mask(libc::SIG_BLOCK)) };
        let mut child = cmd
            .spawn()
            .context("cannot start the simulator's worker process")?;
        // Its output is this command's; the banner says it simulates.
        let up = Arc::new(AtomicBool::new(false));
        let out = child.stdout.take().map(|o| {
            let up = up.clone();
            std::thread::spawn(move || {
                for line in BufReader::new(o).lines() {
                    let Ok(line) = line else { break };
                    if line.starts_with(BANNER) {
                        up.store(true, Ordering::Relaxed);
                    }
                    let mut so = std::io::stdout().lock();
                    let _ = writeln!(so, "{line}");
                    let _ = so.flush();
                }
            })
        });
        let status = loop {
            if let Some(st) = child.try_wait()? {
                break st;
            }
            // Often: the networks go untimed from a crash until a new worker is up.
            if stop.recv_timeout(Duration::from_millis(20)).is_ok() {
                let st = terminate(&mut child)?;
                if let Some(t) = out {
                    let _ = t.join();
                }
                return Ok(after_stop(&st));
            }
        };
        if let Some(t) = out {
            let _ = t.join();
        }
        let up = up.load(Ordering::Relaxed);
        match after_worker(&status, mode, up, restarts > 0, &mut early) {
            AfterWorker::End(code) => return Ok(code),
            AfterWorker::Fail(e) => return Err(anyhow!("canpos bus netsim: {e}")),
            AfterWorker::Restart(sig) => {
                restarts += 1;
                tracing::error!(
                    signal = sig,
                    restarts,
                    "the simulator's SIL Kit part crashed (SIL Kit 5.0.3 frees a controller that \
                     left while a send to it is queued, D57): restarting it as simulator of \
                     {networks}; until it is back the frames go over SIL Kit's own bus, and its \
                     counters start anew"
                );
            }
            AfterWorker::Retry(code) => tracing::warn!(
                exit = code,
                attempt = early,
                "the restarted simulator could not take over {networks} (the registry may not \
                 have seen the crashed one leave yet): trying again"
            ),
        }
        // A pause, longer after each worker in a row that did not come up (at most ~1.5 s in
        // all before the supervisor gives up).
        let pause = Duration::from_millis(50) * (1 << early.min(MAX_EARLY_DEATHS));
        if stop.recv_timeout(pause).is_ok() {
            return Ok(0);
        }
    }
}

/// The command's exit code when its worker ended after the command was asked to stop.
fn after_stop(st: &std::process::ExitStatus) -> i32 {
    match st.signal() {
        None => st.code().unwrap_or(1),
        // Stopped before it could take the signal gracefully (the worker blocks them from
        // its start, so only one started by hand).
        Some(sig) if STOP_SIGNALS.contains(&sig) => 0,
        Some(sig) if CRASH_SIGNALS.contains(&sig) => {
            tracing::error!(
                signal = sig,
                "the simulator's SIL Kit part crashed as it stopped: no report"
            );
            1
        }
        Some(sig) => {
            tracing::error!(
                signal = sig,
                "the simulator's worker was killed as it stopped: no report"
            );
            1
        }
    }
}

/// What the supervisor does when its worker ended by itself.
#[derive(Debug, PartialEq, Eq)]
enum AfterWorker {
    /// End the command with this exit code (the worker's own end).
    End(i32),
    /// End the command with this error.
    Fail(String),
    /// Start a new worker: this one crashed with this signal.
    Restart(i32),
    /// Start a new worker: this one, started after a crash, failed with this exit code before
    /// it simulated (the registry may still list the crashed one under the same name).
    Retry(i32),
}

/// The supervisor's decision on a worker's end: `up` says whether it had simulated,
/// `restarted` whether it was started after a crash; `early` counts the workers in a row that
/// ended before they simulated.
fn after_worker(
    status: &std::process::ExitStatus,
    mode: TimeMode,
    up: bool,
    restarted: bool,
    early: &mut u32,
) -> AfterWorker {
    if let Some(sig) = status.signal().filter(|s| !CRASH_SIGNALS.contains(s)) {
        // Not SIL Kit's crash: someone (the OOM killer, a user) killed it.
        return AfterWorker::Fail(format!(
            "the simulator's worker was killed by signal {sig}: no report"
        ));
    }
    let Some(sig) = status.signal() else {
        let code = status.code().unwrap_or(1);
        if restarted && !up && code != 0 && status.code().is_some() {
            *early += 1;
            if *early < MAX_EARLY_DEATHS {
                return AfterWorker::Retry(code);
            }
            return AfterWorker::Fail(format!(
                "the restarted simulator failed (exit {code}) before it simulated, {early} \
                 times in a row: given up"
            ));
        }
        return AfterWorker::End(code);
    };
    if let TimeMode::Sync {
        coordinated: true, ..
    } = mode
    {
        return AfterWorker::Fail(format!(
            "the simulator's SIL Kit part died of signal {sig} (SIL Kit 5.0.3, D57); a \
             coordinated simulation cannot take a simulator back: restart the run"
        ));
    }
    if up {
        *early = 0;
    } else {
        *early += 1;
        if *early >= MAX_EARLY_DEATHS {
            return AfterWorker::Fail(format!(
                "the simulator died of signal {sig} before it simulated, {early} times in a \
                 row: given up"
            ));
        }
    }
    AfterWorker::Restart(sig)
}

/// Stops a worker gracefully (SIGTERM: it leaves SIL Kit), killing it if it has not ended
/// within 15 s (its graceful leave waits at most 5 s for SIL Kit).
fn terminate(child: &mut Child) -> Result<std::process::ExitStatus> {
    // SAFETY: kill with our own child's pid (not yet waited for, so not reused).
    unsafe { libc::kill(child.id() as libc::pid_t, libc::SIGTERM) };
    let deadline = Instant::now() + Duration::from_secs(15);
    while Instant::now() < deadline {
        if let Some(st) = child.try_wait()? {
            return Ok(st);
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    tracing::warn!("the simulator's worker did not end within 15 s of SIGTERM: killed");
    let _ = child.kill();
    Ok(child.wait()?)
}

/// The registry, the networks and the time mode of the arguments, or a usage error.
fn prepare(args: &NetsimArgs) -> Result<(RegistryUri, Vec<NetworkSpec>, TimeMode)> {
    let usage = |m: String| anyhow::Error::new(Usage(m));
    let uri = registry_uri(&args.registry).map_err(usage)?;
    let mut specs = Vec::new();
    for n in &args.networks {
        check_name("network name", n).map_err(usage)?;
        if specs.iter().any(|s: &NetworkSpec| &s.name == n) {
            return Err(usage(format!("network `{n}` given twice")));
        }
        specs.push(NetworkSpec {
            name: n.clone(),
            kbps: args.bitrate,
        });
    }
    // Here, so that a missing SIL Kit fails once, before a worker is started.
    sys::api().map_err(|e| anyhow!(e))?;
    let mode = match args.time {
        NetsimTime::Wall => TimeMode::Wall,
        NetsimTime::Sync => {
            let bit = 1_000_000 / u64::from(args.bitrate); // ns
            let step = args.step_us.map_or(40 * bit, |us| us * 1000);
            TimeMode::Sync {
                step,
                coordinated: args.coordinated,
            }
        }
    };
    check_name("participant name", &args.participant).map_err(usage)?;
    Ok((uri, specs, mode))
}

/// The simulator itself (the worker).
fn simulate(
    args: &NetsimArgs,
    uri: &RegistryUri,
    specs: &[NetworkSpec],
    mode: TimeMode,
    stop: crossbeam_channel::Receiver<()>,
) -> Result<i32> {
    let api = sys::api().map_err(|e| anyhow!(e))?;
    if let TimeMode::Sync { step, .. } = mode {
        if step >= 44 * (1_000_000 / u64::from(args.bitrate)) {
            tracing::warn!(
                step_us = step / 1000,
                "a step as long as the shortest frame: a receiver may get a frame only after \
                 its step passed the frame's end, and synchronised runs may differ (D40)"
            );
        }
    }
    let sim = Simulator::start(api, uri, &args.participant, specs, mode)
        .map_err(|e| anyhow!("canpos bus netsim: {e}"))?;
    // Written, not printed: a worker whose supervisor was killed finds its stdout closed, and
    // must still leave SIL Kit gracefully.
    let mut so = std::io::stdout();
    let _ = writeln!(
        so,
        "{BANNER}{} at {} kbit/s as participant {} at {uri} ({})",
        args.networks.join(", "),
        args.bitrate,
        args.participant,
        match mode {
            TimeMode::Wall => "wall clock".to_string(),
            TimeMode::Sync { step, .. } => format!("synchronised, {} µs steps", step / 1000),
        }
    );
    let _ = so.flush();
    let every = (args.stats_interval.is_finite() && args.stats_interval > 0.0)
        .then(|| Duration::from_secs_f64(args.stats_interval.min(86_400.0)));
    let started = Instant::now();
    let end = args.duration.map(|d| started + Duration::from_secs_f64(d));
    let mut next_log = every.map(|e| started + e);
    let reason = loop {
        if stop.recv_timeout(Duration::from_millis(200)).is_ok() {
            break "signal";
        }
        if sim.is_stopped() {
            break "SIL Kit stopped the simulation";
        }
        if end.is_some_and(|t| Instant::now() >= t) {
            break "duration";
        }
        if let (Some(t), Some(e)) = (next_log, every) {
            if Instant::now() >= t {
                for r in sim.report() {
                    log_report(&r);
                }
                next_log = Some(t + e);
            }
        }
    };
    let reports = sim.report();
    drop(sim);
    for r in &reports {
        let _ = writeln!(so, "{}", summary(r));
    }
    tracing::info!(reason, "canpos bus netsim stopped");
    Ok(0)
}

fn log_report(r: &NetworkReport) {
    tracing::info!(
        network = %r.name,
        bus_time_s = format!("{:.3}", r.reached as f64 / 1e9),
        load_pct = format!("{:.1}", r.load.0 * 100.0),
        frames = r.counters.frames,
        deliveries = r.counters.deliveries,
        queue_full = r.counters.queue_full,
        canceled = r.counters.canceled,
        controllers = r.controllers.len(),
        "network"
    );
}

/// One JSON line per network at exit: what the scale benchmark reads.
fn summary(r: &NetworkReport) -> String {
    let ctrls: Vec<serde_json::Value> = r
        .controllers
        .iter()
        .map(|c| (c, false))
        .chain(r.departed.iter().map(|c| (c, true)))
        .map(|((d, mode, st), left)| {
            serde_json::json!({
                "descriptor": d,
                "left": left,
                "mode": format!("{mode:?}"),
                "state": st.map(|s| format!("{:?}", s.state)),
                "tec": st.map(|s| s.tec),
                "rec": st.map(|s| s.rec),
                "sent": st.map(|s| s.sent),
                "lost_overflow": st.map(|s| s.lost_overflow),
                "lost_bus_off": st.map(|s| s.lost_bus_off),
            })
        })
        .collect();
    serde_json::json!({
        "network": r.name,
        "bus_time_ns": r.reached,
        "frames": r.counters.frames,
        "deliveries": r.counters.deliveries,
        "queue_full": r.counters.queue_full,
        "canceled": r.counters.canceled,
        "bad_frames": r.counters.bad_frames,
        "controllers": ctrls,
    })
    .to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_worker_gets_the_commands_arguments_with_what_is_left_of_the_duration() {
        let args = |v: &[&str]| v.iter().map(OsString::from).collect::<Vec<_>>();
        let given = args(&[
            "-q",
            "bus",
            "netsim",
            "--registry",
            "silkit://127.0.0.1:8500",
            "--duration",
            "60",
            "--network",
            "can0",
            "--duration=30",
            "--bitrate",
            "125",
        ]);
        let bare = args(&[
            "-q",
            "bus",
            "netsim",
            "--registry",
            "silkit://127.0.0.1:8500",
            "--network",
            "can0",
            "--bitrate",
            "125",
        ]);
        assert_eq!(worker_args(given.clone().into_iter(), None), bare);
        let mut left = bare.clone();
        left.extend(args(&["--duration", "12.500"]));
        assert_eq!(
            worker_args(given.into_iter(), Some(Duration::from_millis(12_500))),
            left
        );
        // Never 0 (clap refuses it): the worker then ends at once.
        let mut least = bare.clone();
        least.extend(args(&["--duration", "0.001"]));
        assert_eq!(worker_args(bare.into_iter(), Some(Duration::ZERO)), least);
    }

    #[test]
    fn a_crashed_worker_is_restarted_and_any_other_end_ends_the_command() {
        use std::process::ExitStatus;
        // Raw wait statuses: a signal in the low 7 bits, or an exit code in the next byte.
        let killed = |sig: i32| ExitStatus::from_raw(sig);
        let exited = |code: i32| ExitStatus::from_raw(code << 8);
        let sync = |coordinated| TimeMode::Sync {
            step: 320_000,
            coordinated,
        };
        let mut early = 0;
        for mode in [TimeMode::Wall, sync(false)] {
            for sig in CRASH_SIGNALS {
                assert_eq!(
                    after_worker(&killed(sig), mode, true, false, &mut early),
                    AfterWorker::Restart(sig)
                );
            }
            assert_eq!(
                after_worker(&exited(0), mode, true, false, &mut early),
                AfterWorker::End(0)
            );
            assert_eq!(
                after_worker(&exited(1), mode, false, false, &mut early),
                AfterWorker::End(1)
            );
            // Killed by someone (not a crash): the command ends too, with exit 1 and saying so.
            for sig in [libc::SIGKILL, libc::SIGTERM, libc::SIGINT] {
                assert!(matches!(
                    after_worker(&killed(sig), mode, true, false, &mut early),
                    AfterWorker::Fail(e) if e.contains(&format!("killed by signal {sig}"))
                ));
            }
        }
        // A coordinated run cannot take a simulator back.
        assert!(matches!(
            after_worker(&killed(libc::SIGSEGV), sync(true), true, true, &mut early),
            AfterWorker::Fail(e) if e.contains("coordinated")
        ));
        // Crashes before it simulated: given up at the fifth in a row; one that had simulated
        // starts the count again.
        let mut early = 0;
        let segv = killed(libc::SIGSEGV);
        for _ in 1..MAX_EARLY_DEATHS {
            assert_eq!(
                after_worker(&segv, TimeMode::Wall, false, true, &mut early),
                AfterWorker::Restart(libc::SIGSEGV)
            );
        }
        assert_eq!(
            after_worker(&segv, TimeMode::Wall, true, true, &mut early),
            AfterWorker::Restart(libc::SIGSEGV)
        );
        for _ in 1..MAX_EARLY_DEATHS {
            assert_eq!(
                after_worker(&segv, TimeMode::Wall, false, true, &mut early),
                AfterWorker::Restart(libc::SIGSEGV)
            );
        }
        assert!(matches!(
            after_worker(&segv, TimeMode::Wall, false, true, &mut early),
            AfterWorker::Fail(e) if e.contains("5 times in a row")
        ));
        // A restarted worker that cannot join yet (the registry still lists the crashed one)
        // is tried again, up to the same bound; a first worker's failure is the command's, and
        // so is a restarted one's clean end or a failure after it simulated.
        let mut early = 0;
        for attempt in 1..MAX_EARLY_DEATHS {
            assert_eq!(
                after_worker(&exited(1), TimeMode::Wall, false, true, &mut early),
                AfterWorker::Retry(1)
            );
            assert_eq!(early, attempt);
        }
        assert!(matches!(
            after_worker(&exited(1), TimeMode::Wall, false, true, &mut early),
            AfterWorker::Fail(e) if e.contains("exit 1")
        ));
        let mut early = 0;
        for (status, up) in [(exited(0), false), (exited(1), true)] {
            assert_eq!(
                after_worker(&status, TimeMode::Wall, up, true, &mut early),
                AfterWorker::End(status.code().unwrap())
            );
        }
        assert_eq!(
            after_worker(&exited(1), TimeMode::Wall, false, false, &mut early),
            AfterWorker::End(1)
        );
    }

    #[test]
    fn a_stopped_worker_ends_the_command_with_its_code_and_a_crash_or_kill_with_1() {
        use std::process::ExitStatus;
        let killed = |sig: i32| ExitStatus::from_raw(sig);
        let exited = |code: i32| ExitStatus::from_raw(code << 8);
        for code in [0, 1, 2] {
            assert_eq!(after_stop(&exited(code)), code);
        }
        // Ended by the stop itself before it handled it: a stop, not a failure.
        for sig in STOP_SIGNALS {
            assert_eq!(after_stop(&killed(sig)), 0);
        }
        for sig in CRASH_SIGNALS.into_iter().chain([libc::SIGKILL]) {
            assert_eq!(after_stop(&killed(sig)), 1);
        }
    }

    #[test]
    fn registry_uris() {
        assert_eq!(
            registry_uri("silkit://127.0.0.1:8500").unwrap().to_string(),
            "silkit://127.0.0.1:8500"
        );
        assert!(registry_uri("silkit://localhost:8500").is_ok());
        assert_eq!(registry_uri("silkit://[::1]:8500").unwrap().host, "::1");
        for bad in [
            "127.0.0.1:8500",
            "silkit://127.0.0.1",
            "silkit://:8500",
            "silkit://127.0.0.1:0",
            "silkit://127.0.0.1:99999",
            "silkit://127.0.0.1:8500/can0",
            "socketcand://127.0.0.1:8500",
            "silkit://[::1:8500",
        ] {
            assert!(registry_uri(bad).is_err(), "{bad}");
        }
    }
}
