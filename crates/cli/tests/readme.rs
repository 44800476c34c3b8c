//! The README as a newcomer follows it: the examples of its command table in order, then the
//! LSS walkthrough, on a fresh directory and state directory and on free ports (the README's
//! ports replaced by free ones). A broken or colliding example fails here.
//!
//! Rows left out, each for a reason: the LSS row (its walkthrough runs instead), the benches and
//! the soak (measurements of minutes, with their own expectations; docs/BENCHMARKS.md) and
//! `--rt-priority` (needs root or CAP_SYS_NICE).

mod common;

use std::path::Path;
use std::time::Duration;

use common::{free_port, run_in, text, Ctl, Proc};

const README: &str = include_str!("../../../README.md");
const SCENARIO: &str = include_str!("../../../examples/scenario.toml");
const IO_DEVICE: &str = include_str!("../../../examples/io-device.eds");

/// Rows whose description starts so are not run (see the module docs).
const SKIPPED_ROWS: [&str; 4] = [
    "LSS",
    "performance instruments",
    "long-running soak",
    "keep 1 ms timing",
];

/// Commands that take `--bus`; those without one get the test's hub.
const BUS_COMMANDS: [&str; 10] = [
    "run", "scenario", "nmt", "sdo", "scan", "monitor", "record", "replay", "lss", "dcf",
];

/// The `canpos …` examples of the command table, in order.
fn table_commands() -> Vec<String> {
    let start = README
        .find("| command | example |")
        .expect("the README's command table");
    let mut out = Vec::new();
    for row in README[start..].lines().skip(2) {
        if !row.starts_with('|') {
            break;
        }
        let cells: Vec<&str> = row.trim_matches('|').split(" | ").collect();
        let (what, example) = (cells[0].trim(), cells.get(1).copied().unwrap_or(""));
        if SKIPPED_ROWS.iter().any(|s| what.starts_with(s)) {
            continue;
        }
        for (k, span) in example.split('`').enumerate() {
            if k % 2 == 1 && span.starts_with("canpos ") && !span.contains('…') {
                out.push(span.to_string());
            }
        }
    }
    out
}

/// The commands of the LSS walkthrough's code block.
fn lss_walkthrough() -> Vec<String> {
    let start = README
        .find("### LSS walkthrough")
        .expect("the LSS walkthrough");
    README[start..]
        .lines()
        .skip_while(|l| !l.starts_with("    canpos "))
        .take_while(|l| l.starts_with("    canpos "))
        .map(|l| l.trim().to_string())
        .collect()
}

/// Splits a command line as a shell would for these examples (double quotes only).
fn words(line: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut cur = String::new();
    let mut quoted = false;
    for ch in line.chars() {
        match ch {
            '"' => quoted = !quoted,
            ' ' if !quoted => {
                if !cur.is_empty() {
                    out.push(std::mem::take(&mut cur));
                }
            }
            c => cur.push(c),
        }
    }
    if !cur.is_empty() {
        out.push(cur);
    }
    out
}

/// The README's ports, replaced by free ones.
struct Ports {
    map: Vec<(String, String)>,
    hub: u16,
}

impl Ports {
    fn new() -> Ports {
        let hub = free_port();
        let map = [(29536, hub), (29600, free_port()), (29601, free_port())]
            .into_iter()
            .map(|(from, to)| (format!("127.0.0.1:{from}"), format!("127.0.0.1:{to}")))
            .collect();
        Ports { map, hub }
    }

    fn apply(&self, s: &str) -> String {
        self.map
            .iter()
            .fold(s.to_string(), |acc, (from, to)| acc.replace(from, to))
    }

    /// The arguments after `canpos` of an example, pointed at this test's ports.
    fn args(&self, line: &str) -> Vec<String> {
        let mut w: Vec<String> = words(line)
            .into_iter()
            .skip(1)
            .map(|t| self.apply(&t))
            .collect();
        if BUS_COMMANDS.contains(&w[0].as_str()) && !w.iter().any(|t| t == "--bus") {
            w.push("--bus".into());
            w.push(format!("socketcand://127.0.0.1:{}/can0", self.hub));
        }
        w
    }
}

/// Starts a long-running example and waits until it is ready.
fn start(dir: &Path, args: &[String]) -> Proc {
    let a: Vec<&str> = args.iter().map(String::as_str).collect();
    let mut p = Proc::start(dir, &a);
    let ready = Duration::from_secs(20);
    match a[0] {
        "bus" => {
            p.wait_for("listening on", ready);
        }
        "scenario" => {
            p.wait_for("canpos: sensor 1:", ready);
        }
        _ => {
            p.wait_for("canpos: sensor 0:", ready);
        }
    }
    if a.contains(&"--control") || a[0] == "scenario" {
        p.wait_for("control interface on", ready);
    }
    p
}

fn is_long_running(args: &[String]) -> bool {
    matches!(args[0].as_str(), "bus" | "run" | "scenario")
}

fn one_shot(dir: &Path, args: &[String]) -> String {
    let a: Vec<&str> = args.iter().map(String::as_str).collect();
    let o = run_in(dir, &a, Duration::from_secs(60));
    assert_eq!(
        o.status.code(),
        Some(0),
        "README example `canpos {}` failed: {}",
        a.join(" "),
        text(&o)
    );
    text(&o)
}

#[test]
fn readme_examples_run_in_order_without_colliding() {
    let dir = tempfile::tempdir().unwrap();
    let ports = Ports::new();
    // The scenario example, at the path the README gives, on this test's ports.
    std::fs::create_dir(dir.path().join("examples")).unwrap();
    std::fs::write(
        dir.path().join("examples/scenario.toml"),
        ports.apply(SCENARIO),
    )
    .unwrap();
    std::fs::write(dir.path().join("examples/io-device.eds"), IO_DEVICE).unwrap();
    let commands = table_commands();
    assert!(commands.len() >= 15, "too few examples found: {commands:?}");
    let mut running = Vec::new();
    for line in &commands {
        let args = ports.args(line);
        if is_long_running(&args) {
            running.push(start(dir.path(), &args));
            if args.iter().any(|a| a == "--order-code") {
                // The order-code example boots clean: a magnet on each of its two channels,
                // error register 0 (no missing-magnet EMCY).
                let addr = &args[args.iter().position(|a| a == "--control").unwrap() + 1];
                let port = addr.rsplit(':').next().unwrap().parse().unwrap();
                let st = Ctl::connect(port).state_when(|st| {
                    st["reported_mm"]
                        .as_array()
                        .is_some_and(|r| r.len() == 2 && r.iter().all(|v| v.is_number()))
                });
                assert_eq!(st["error_register"], 0, "{st}");
                assert!(
                    st["reported_mm"]
                        .as_array()
                        .is_some_and(|r| r.len() == 2 && r.iter().all(|v| v.is_number())),
                    "{st}"
                );
            }
            continue;
        }
        let out = one_shot(dir.path(), &args);
        if args[0] == "scan" {
            // Every sensor of the examples answers, each on its own row.
            for node in [127, 10, 1, 2] {
                let rows = out
                    .lines()
                    .filter(|l| l.split_whitespace().next() == Some(&node.to_string()))
                    .count();
                assert_eq!(rows, 1, "node {node} in the scan: {out}");
            }
        }
    }
    drop(running);
}

#[test]
fn readme_lss_walkthrough_ends_on_the_new_node_id() {
    let dir = tempfile::tempdir().unwrap();
    let ports = Ports::new();
    let steps = lss_walkthrough();
    assert!(steps.len() >= 6, "{steps:?}");
    assert!(
        steps.iter().any(|s| s.contains("reset-comm")),
        "the walkthrough must say reset-comm: {steps:?}"
    );
    let mut sensor = None;
    for line in &steps {
        let args = ports.args(line);
        if is_long_running(&args) {
            sensor = Some((start(dir.path(), &args), args));
            continue;
        }
        one_shot(dir.path(), &args);
    }
    // Restarted, the sensor comes up on its stored node-id, and the banner says so.
    let (mut p, args) = sensor.expect("the walkthrough starts a sensor");
    p.stop();
    let mut again = start(dir.path(), &args);
    let out = again.wait_for("canpos: sensor 0:", Duration::from_secs(20));
    assert!(out.contains("(node-id 5,"), "{out}");
}
