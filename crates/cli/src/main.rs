//! `canpos`: run simulated CANopen position sensors, serve a virtual bus, and act as the
//! commissioning master. `canpos` without arguments runs the demo.
//!
//! Exit codes (README "Exit codes"): 0 success, 1 runtime error (the message says why), 2 bad
//! command line, 3 the device refused (SDO abort, LSS error status) or nothing was found, 4 no
//! answer within the timeout.

use std::process::ExitCode;

use canpos_cli::cmd::{
    bench, bus, ctl, dashboard, dcf, demo, eds, fmu, guard, lss, monitor, netsim, nmt, record,
    replay, run, scan, scenario, sdo, soak,
};
use canpos_cli::common;
use clap::{CommandFactory, FromArgMatches, Parser, Subcommand};

/// A software twin of CANopen magnetostrictive position sensors (Temposonics TH, E-Series,
/// Novotechnik TMI).
///
/// Without a command, runs the demo: a virtual bus, a TH sensor moving on a sine, its web
/// dashboard and its control interface (the demo's options below apply).
#[derive(Debug, Parser)]
#[command(name = "canpos", version, propagate_version = true)]
struct Cli {
    /// More log output on stderr (-v debug, -vv trace); RUST_LOG overrides.
    #[arg(short, long, global = true, help_heading = "Global options", action = clap::ArgAction::Count)]
    verbose: u8,
    /// Less log output (warnings and errors only).
    #[arg(short, long, global = true, help_heading = "Global options")]
    quiet: bool,
    /// Run under SCHED_FIFO at this priority (2-99; helper threads one lower) with all memory
    /// locked, so that other load on the machine cannot make the sensors miss periods (needs
    /// root or CAP_SYS_NICE).
    #[arg(long, global = true, help_heading = "Global options", value_name = "N", value_parser = clap::value_parser!(u8).range(2..=99))]
    rt_priority: Option<u8>,
    #[command(subcommand)]
    cmd: Option<Cmd>,
    /// Without a command: the demo's options (`canpos --web ADDR` = `canpos demo --web ADDR`).
    #[command(flatten)]
    demo: demo::DemoArgs,
}

#[derive(Debug, Subcommand)]
enum Cmd {
    /// Virtual CAN buses.
    #[command(subcommand)]
    Bus(bus::BusCmd),
    /// Run one simulated sensor on a bus.
    Run(Box<run::RunArgs>),
    /// Run several sensors on one bus with motion profiles and timed faults (TOML file).
    Scenario(scenario::ScenarioArgs),
    /// Drive a running sensor through its control interface.
    Ctl(ctl::CtlArgs),
    /// The demo (also what `canpos` without arguments runs).
    Demo(demo::DemoArgs),
    /// Send an NMT command (start, stop, preop, reset, reset-comm).
    Nmt(nmt::NmtArgs),
    /// Node guarding: remote frames on 0x700 + id, the answers' NMT state and toggle bit.
    Guard(guard::GuardArgs),
    /// Read or write an object by SDO.
    Sdo(sdo::SdoArgs),
    /// Layer setting services: switch, set node-id / bit rate, store, inquire, fastscan.
    Lss(lss::LssArgs),
    /// Find the nodes on a bus.
    Scan(scan::ScanArgs),
    /// Serve the web dashboard of a bus: nodes, live plots, errors, sensor control, SDO.
    Dashboard(dashboard::DashboardArgs),
    /// Show the bus traffic decoded (positions in mm, velocities in mm/s, EMCYs, heartbeats).
    Monitor(monitor::MonitorArgs),
    /// Write a model's EDS (CiA 306) file.
    Eds(eds::EdsArgs),
    /// Write an FMI 3.0 co-simulation FMU of a unit on the FMI-LS-BUS CAN layer.
    Fmu(fmu::FmuArgs),
    /// Write a configured unit's DCF, read from the running node over SDO.
    Dcf(dcf::DcfArgs),
    /// Record the bus to pcapng, pcap, a candump -L log or Vector ASC.
    Record(record::RecordArgs),
    /// Replay a candump -L log or Vector ASC file onto a bus.
    Replay(replay::ReplayArgs),
    /// Performance instruments: core ops/s, scale, SDO round trip, boot time.
    Bench(bench::BenchArgs),
    /// Scale soak: N TH sensors at a 1 ms event timer; checks drift, RSS growth, deadline misses.
    Soak(soak::SoakArgs),
}

fn init_logging(verbose: u8, quiet: bool) {
    use tracing_subscriber::EnvFilter;
    let default = match (quiet, verbose) {
        (true, _) => "warn",
        (false, 0) => "info",
        (false, 1) => "debug",
        _ => "trace",
    };
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new(default));
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_target(false)
        .init();
}

/// Raises the soft limit of open files to the hard one: a hub serves up to `--max-clients`
/// connections, more than the usual soft limit of 1024 descriptors (Go and systemd services
/// do the same). Failing to raise it only leaves the old limit.
fn raise_open_file_limit() {
    let mut lim = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit / setrlimit read and write the struct we own.
    unsafe {
        if libc::getrlimit(libc::RLIMIT_NOFILE, &mut lim) == 0 && lim.rlim_cur < lim.rlim_max {
            lim.rlim_cur = lim.rlim_max;
            let _ = libc::setrlimit(libc::RLIMIT_NOFILE, &lim);
        }
    }
}

/// Parses the command line. The demo's options are the top level's (`canpos --web ADDR`), so a
/// command given beside one of them is refused: `canpos --web A run` would drop it silently.
fn parse() -> Cli {
    let matches = Cli::command().get_matches();
    let cli = Cli::from_arg_matches(&matches).unwrap_or_else(|e| e.exit());
    if let Some((name, _)) = matches.subcommand() {
        let demo = <demo::DemoArgs as clap::Args>::augment_args(clap::Command::new("demo"));
        let given = demo.get_arguments().find(|a| {
            matches.value_source(a.get_id().as_str())
                == Some(clap::parser::ValueSource::CommandLine)
        });
        if let Some(a) = given {
            let flag = a.get_long().unwrap_or_default();
            Cli::command()
                .error(
                    clap::error::ErrorKind::ArgumentConflict,
                    format!(
                        "--{flag} before a command is an option of the demo (`canpos --{flag} …` \
                         or `canpos demo --{flag} …`); an option of `{name}` goes after its name"
                    ),
                )
                .exit();
        }
    }
    cli
}

fn main() -> ExitCode {
    let cli = parse();
    init_logging(cli.verbose, cli.quiet);
    raise_open_file_limit();
    if let Some(p) = cli.rt_priority {
        // Before any thread starts: they inherit the policy.
        if let Err(e) = canpos_host::realtime::enter(p) {
            eprintln!("error: --rt-priority: {e}");
            return ExitCode::from(1);
        }
        tracing::info!(priority = p, "running under SCHED_FIFO, memory locked");
    }
    let result = match cli.cmd {
        None => demo::demo(cli.demo),
        Some(Cmd::Bus(bus::BusCmd::Serve(a))) => bus::bus_serve(a),
        Some(Cmd::Bus(bus::BusCmd::Bridge(a))) => bus::bus_bridge(a),
        Some(Cmd::Bus(bus::BusCmd::Netsim(a))) => netsim::bus_netsim(a),
        Some(Cmd::Run(a)) => run::run(*a),
        Some(Cmd::Scenario(a)) => scenario::scenario(a),
        Some(Cmd::Ctl(a)) => ctl::ctl(a),
        Some(Cmd::Demo(a)) => demo::demo(a),
        Some(Cmd::Nmt(a)) => nmt::nmt(a),
        Some(Cmd::Sdo(a)) => sdo::sdo(a),
        Some(Cmd::Guard(a)) => guard::guard(a),
        Some(Cmd::Lss(a)) => lss::lss(a),
        Some(Cmd::Scan(a)) => scan::scan(a),
        Some(Cmd::Dashboard(a)) => dashboard::dashboard(a),
        Some(Cmd::Monitor(a)) => monitor::monitor(a),
        Some(Cmd::Eds(a)) => eds::eds(a),
        Some(Cmd::Fmu(a)) => fmu::fmu(a),
        Some(Cmd::Dcf(a)) => dcf::dcf(a),
        Some(Cmd::Record(a)) => record::record(a),
        Some(Cmd::Replay(a)) => replay::replay(a),
        Some(Cmd::Bench(a)) => bench::bench(a),
        Some(Cmd::Soak(a)) => soak::soak(a),
    };
    match result {
        Ok(code) => ExitCode::from(code.clamp(0, 255) as u8),
        // `canpos monitor | head`: the reader left; that ends the output, it is no failure.
        Err(e)
            if e.chain().any(|c| {
                c.downcast_ref::<std::io::Error>()
                    .is_some_and(|io| io.kind() == std::io::ErrorKind::BrokenPipe)
            }) =>
        {
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {}", render(&e));
            let usage = e.chain().any(|c| c.is::<common::Usage>());
            ExitCode::from(if usage {
                common::EXIT_USAGE
            } else {
                common::EXIT_ERROR
            } as u8)
        }
    }
}

/// The error and its causes on one line, each said once: a cause whose text a message above
/// it already contains (`cannot connect to X: refused` over `refused`) is left out.
fn render(e: &anyhow::Error) -> String {
    let mut out = String::new();
    for cause in e.chain() {
        let text = cause.to_string();
        if text.is_empty() || out.contains(&text) {
            continue;
        }
        if !out.is_empty() {
            out.push_str(": ");
        }
        out.push_str(&text);
    }
    out
}
