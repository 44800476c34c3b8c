//! `canpos bus netsim` in the loop (issue 32 item 3, docs/SILKIT.md "canpos as the network
//! simulator"): a `sil-kit-registry` on 127.0.0.1, a TH and a TMI in their own `canpos run`
//! processes, `canpos bus netsim` for their network at 250 kbit/s and a recorder, all
//! synchronised under SIL Kit's system controller. The recorded end-of-frame times show
//! docs/BUS.md's bit time and arbitration, and two runs give the same frames at the same
//! simulated times. Needs `scripts/silkit.sh`; without it the test says so and passes, unless
//! `CANPOS_SILKIT_REQUIRED=1` (the test command sets it).

mod common;

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use canpos_host::bus::bits::frame_length;
use canpos_host::silkit::{self, LocalRegistry};
use canpos_stack::Frame;
use common::{run_in, text, Proc};

const LIMIT: Duration = Duration::from_secs(120);

fn have_silkit() -> bool {
    match silkit::api() {
        Ok(_) => true,
        Err(e) if std::env::var_os("CANPOS_SILKIT_REQUIRED").is_some_and(|v| v == "1") => {
            panic!("CANPOS_SILKIT_REQUIRED=1 but {e}")
        }
        Err(e) => {
            eprintln!("NOTE: SIL Kit test skipped: {e}");
            false
        }
    }
}

/// `sil-kit-system-controller` waiting for `names`; killed on drop.
struct SystemController(Child);

impl Drop for SystemController {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn system_controller(reg: &LocalRegistry, names: &[&str]) -> SystemController {
    let exe = silkit::sys::registry_executable()
        .expect("registry")
        .with_file_name("sil-kit-system-controller");
    SystemController(
        Command::new(exe)
            .arg("--connect-uri")
            .arg(reg.uri().to_string())
            .args(["--log", "off"])
            .args(names)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("system controller"),
    )
}

/// One run: the recorder's first `count` frames (candump, simulated end-of-frame times).
fn run(d: &Path, count: usize) -> Vec<(u64, u32, String)> {
    let reg = LocalRegistry::start(LIMIT).expect("registry");
    let _sc = system_controller(&reg, &["netsim", "th-11", "tmi-12", "rec"]);
    let uri = reg.uri().to_string();
    let bus = format!("{uri}/can0");
    let state = d.to_str().unwrap();
    let _netsim = Proc::start(
        d,
        &[
            "bus",
            "netsim",
            "--registry",
            &uri,
            "--network",
            "can0",
            "--bitrate",
            "250",
            "--time",
            "sync",
            "--coordinated",
            "--participant",
            "netsim",
        ],
    );
    let sensor = |model: &str, serial: &str, node: &str| {
        Proc::start(
            d,
            &[
                "run",
                "--model",
                model,
                "--serial",
                serial,
                "--node-id",
                node,
                "--nmt",
                "operational",
                "--bus",
                &bus,
                "--time",
                "sync",
                "--state-dir",
                state,
            ],
        )
    };
    let _th = sensor("th", "11", "5");
    let _tmi = sensor("tmi", "12", "6");
    let rec = d.join("sync.log");
    let url = format!("{bus}?participant=rec&time=sync");
    let args = [
        "record",
        "--bus",
        &url,
        "--format",
        "candump",
        "--count",
        &count.to_string(),
        rec.to_str().unwrap(),
    ];
    let o = run_in(d, &args, LIMIT);
    assert!(o.status.success(), "canpos {args:?}: {}", text(&o));
    std::fs::read_to_string(&rec)
        .unwrap()
        .lines()
        .map(|l| {
            // (S.UUUUUU) can0 ID#DATA
            let (t, rest) = l.trim_start_matches('(').split_once(") can0 ").expect(l);
            let (s, us) = t.split_once('.').expect(l);
            let ns = (s.parse::<u64>().unwrap() * 1_000_000 + us.parse::<u64>().unwrap()) * 1000;
            let (id, data) = rest.split_once('#').expect(l);
            (ns, u32::from_str_radix(id, 16).unwrap(), data.to_string())
        })
        .collect()
}

fn bits(id: u32, data: &str) -> u64 {
    let bytes: Vec<u8> = (0..data.len() / 2)
        .map(|i| u8::from_str_radix(&data[2 * i..2 * i + 2], 16).unwrap())
        .collect();
    u64::from(frame_length(&Frame::with_id(id, false, &bytes).unwrap()).total)
}

#[test]
fn the_simulator_times_the_frames_as_docs_bus_md_and_synchronised_runs_repeat() {
    if !have_silkit() {
        return;
    }
    let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    // From 10 ms of simulated time on: a participant's frames before it has discovered the
    // simulator go over SIL Kit's own bus and are lost (docs/SILKIT.md, known limit), which
    // can hit the boot-ups at 0. 250 kbit/s, not 125: the TH's 1 ms TPDO and the TMI's take
    // 101 % of a 125 kbit/s bus, whose backlog then keeps the phase of such a start-up loss
    // for good; at 250 kbit/s the bus is idle between the steps.
    let settled = |v: Vec<(u64, u32, String)>| -> Vec<(u64, u32, String)> {
        v.into_iter()
            .filter(|f| f.0 >= 10_000_000)
            .take(300)
            .collect()
    };
    let first = settled(run(a.path(), 340));
    assert_eq!(first.len(), 300);
    let bit = 4_000; // ns at 250 kbit/s
                     // Both sensors' TPDOs are there, arbitrated: the TH's 0x185 and the TMI's 0x186.
    assert!(first.iter().any(|f| f.1 == 0x185) && first.iter().any(|f| f.1 == 0x186));
    // Each frame either started on an idle bus at its sender's step (the sensors step by
    // 1 ms, and its end of frame is its length less the 3-bit intermission later), or waited
    // for the frame before it and went out right after it (its length after that one's end):
    // docs/BUS.md's bit time, one frame at a time. Both kinds occur.
    let (mut idle, mut waited) = (0, 0);
    for w in first.windows(2) {
        let ((ta, _, _), (tb, id, data)) = (&w[0], &w[1]);
        let len = bits(*id, data) * bit;
        assert!(tb - ta >= len, "{w:?}: less than a frame time apart");
        if (tb - (len - 3 * bit)).is_multiple_of(1_000_000) {
            idle += 1;
        } else {
            assert_eq!(
                tb - ta,
                len,
                "{w:?}: neither at a step nor right after the frame before"
            );
            waited += 1;
        }
    }
    assert!(idle > 0 && waited > 0, "idle {idle}, waited {waited}");
    let second = settled(run(b.path(), 340));
    if let Some(i) = (0..300).find(|&i| first[i] != second[i]) {
        panic!(
            "two synchronised runs through the simulator differ at frame {i}: {:?} / {:?}",
            &first[i.saturating_sub(2)..(i + 3).min(300)],
            &second[i.saturating_sub(2)..(i + 3).min(300)]
        );
    }
}
