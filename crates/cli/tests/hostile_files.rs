//! Hostile files (issue 35): a state directory holding links where the sensor's files go,
//! state files that fail their checks or hold records no model uses, `canpos replay` on input
//! without end or without newlines, and DCF values that are no numbers.

mod common;

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use canpos_stack::storage::{parse_image, ImageWriter, IMAGE_MAX};
use common::{assert_fails, free_port, run_in, text, wait_port, Proc, BIN};

const SHORT: Duration = Duration::from_secs(10);

/// A file outside the state directory for links to point at; its bytes must stay.
const DECOY: &[u8] = b"someone else's file: must stay as it is\n";

fn decoy(dir: &Path) -> PathBuf {
    let p = dir.join("decoy");
    std::fs::write(&p, DECOY).unwrap();
    p
}

fn th_tag() -> u8 {
    canpos_models::by_name("th").unwrap().features.tag
}

/// `canpos run --model th --serial 4242` on an embedded hub at `port` (as the issue ran it),
/// with node-id 5.
fn run_th(dir: &Path, port: u16, state: &Path) -> Proc {
    Proc::start(
        dir,
        &[
            "run",
            "--model",
            "th",
            "--serial",
            "4242",
            "--node-id",
            "5",
            "--bus",
            &format!("socketcand://127.0.0.1:{port}/can0"),
            "--hub",
            "always",
            "--state-dir",
            state.to_str().unwrap(),
        ],
    )
}

/// `canpos sdo write 5 1010 1 save` (0x1010/1 "save") on the hub at `port`: its output.
fn save_over_sdo(dir: &Path, port: u16) -> std::process::Output {
    run_in(
        dir,
        &[
            "sdo",
            "write",
            "5",
            "1010",
            "1",
            "0x65766173",
            "--type",
            "u32",
            "--bus",
            &format!("socketcand://127.0.0.1:{port}/can0"),
        ],
        SHORT,
    )
}

// ------------------------------------------------------------------------ state directory

/// Issue 35 item 1: `ln -s $TARGET $STATE/th-4242.bin.lock; canpos run --model th --serial
/// 4242 --bus socketcand://… --hub always --state-dir $STATE` left only the pid in $TARGET.
#[test]
fn a_symlinked_lock_file_is_refused_and_its_target_stays() {
    let dir = tempfile::tempdir().unwrap();
    let target = decoy(dir.path());
    let state = dir.path().join("state");
    std::fs::create_dir(&state).unwrap();
    let lock = state.join("th-4242.bin.lock");
    std::os::unix::fs::symlink(&target, &lock).unwrap();
    let port = free_port();
    let mut p = run_th(dir.path(), port, &state);
    let code = p.wait_exit(SHORT);
    let out = p.output();
    assert_eq!(code, Some(1), "{out}");
    assert!(
        out.contains(&format!("lock file {} is a symbolic link", lock.display())),
        "{out}"
    );
    assert!(!out.contains("panicked"), "{out}");
    assert_eq!(std::fs::read(&target).unwrap(), DECOY);
    assert!(std::fs::symlink_metadata(&lock)
        .unwrap()
        .file_type()
        .is_symlink());
}

/// Issue 35 item 2: the pid in the lock file named the temporary file of the next save
/// (`<file>.tmp.<pid>`); a link planted there made the save write the image into its target
/// and turned the state file into a link to it.
#[test]
fn a_link_at_the_temporary_name_of_the_pid_gets_nothing_from_a_save() {
    let dir = tempfile::tempdir().unwrap();
    let target = decoy(dir.path());
    let state = dir.path().join("state");
    let port = free_port();
    let mut p = run_th(dir.path(), port, &state);
    p.wait_for("canpos: sensor 0:", SHORT);
    wait_port(port);
    let pid = std::fs::read_to_string(state.join("th-4242.bin.lock")).unwrap();
    let planted = state.join(format!("th-4242.bin.tmp.{}", pid.trim()));
    std::os::unix::fs::symlink(&target, &planted).unwrap();
    let o = save_over_sdo(dir.path(), port);
    assert!(o.status.success(), "{}", text(&o));
    let file = state.join("th-4242.bin");
    assert!(std::fs::symlink_metadata(&file).unwrap().is_file());
    assert!(parse_image(&std::fs::read(&file).unwrap(), th_tag()).is_ok());
    assert_eq!(std::fs::read(&target).unwrap(), DECOY);
    assert!(std::fs::symlink_metadata(&planted)
        .unwrap()
        .file_type()
        .is_symlink());
}

/// A link where the state file itself should be is refused by name; nothing is read or
/// written through it.
#[test]
fn a_symlinked_state_file_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let target = decoy(dir.path());
    let state = dir.path().join("state");
    std::fs::create_dir(&state).unwrap();
    let file = state.join("th-4242.bin");
    std::os::unix::fs::symlink(&target, &file).unwrap();
    let mut p = run_th(dir.path(), free_port(), &state);
    assert_eq!(p.wait_exit(SHORT), Some(1), "{}", p.output());
    assert!(
        p.output()
            .contains(&format!("state file {} is a symbolic link", file.display())),
        "{}",
        p.output()
    );
    assert_eq!(std::fs::read(&target).unwrap(), DECOY);
}

/// A valid TH image of `records`.
fn th_image(records: &[(u32, u32)]) -> Vec<u8> {
    let mut buf = [0u8; IMAGE_MAX];
    let mut w = ImageWriter::new(&mut buf, th_tag());
    for &(k, v) in records {
        assert!(w.push(k, v));
    }
    let n = w.finish();
    buf[..n].to_vec()
}

/// Issue 35 item 9: a state file that fails its CRC, version, tag or length check printed
/// nothing on stderr (only the EMCY 0x6300 told); now a WARN names the file and the reason.
#[test]
fn a_state_file_failing_its_check_is_named_on_stderr_with_the_reason() {
    let good = th_image(&[(0x0010_1700, 100)]);
    let n = good.len();
    let reseal = |at: usize, v: u8| {
        let mut b = good.clone();
        b[at] = v;
        let crc = canpos_stack::storage::crc32(&b[..n - 4]).to_le_bytes();
        b[n - 4..].copy_from_slice(&crc);
        b
    };
    let mut flipped = good.clone();
    flipped[10] ^= 0x10;
    for (bytes, why) in [
        (flipped, "CRC mismatch"),
        (reseal(4, 2), "format version 2"),
        (reseal(5, 3), "an image of another model"),
        (good[..n - 8].to_vec(), "but its header's 1 records make 20"),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let state = dir.path().join("state");
        std::fs::create_dir(&state).unwrap();
        let file = state.join("th-9.bin");
        std::fs::write(&file, &bytes).unwrap();
        let mut p = Proc::start(
            dir.path(),
            &[
                "run",
                "--bus",
                "mem://r",
                "--serial",
                "9",
                "--state-dir",
                state.to_str().unwrap(),
            ],
        );
        let out = p.wait_for("canpos: sensor 0:", SHORT);
        let warn = out
            .lines()
            .find(|l| l.contains("WARN") && l.contains(why))
            .unwrap_or_else(|| panic!("no WARN with `{why}`: {out}"));
        assert!(warn.contains(&file.display().to_string()), "{warn}");
        // Once, though the image is loaded more than once at a power-on.
        assert_eq!(out.matches(why).count(), 1, "{out}");
    }
}

/// Issue 35 item 9: a CRC-valid image of 240 records the TH has no use for loaded, then every
/// save aborted 0x08000020 with nothing logged. Now one WARN names the file and the count, and
/// the save stores the unit's configuration without them.
#[test]
fn a_state_file_of_unused_records_is_reported_and_saves_still_work() {
    let dir = tempfile::tempdir().unwrap();
    let state = dir.path().join("state");
    std::fs::create_dir(&state).unwrap();
    let file = state.join("th-4242.bin");
    let unused: Vec<(u32, u32)> = (0..240).map(|i| (0x0050_0000 + (i << 8), i)).collect();
    std::fs::write(&file, th_image(&unused)).unwrap();
    let port = free_port();
    let mut p = run_th(dir.path(), port, &state);
    p.wait_for("canpos: sensor 0:", SHORT);
    wait_port(port);
    let o = save_over_sdo(dir.path(), port);
    assert!(o.status.success(), "{}", text(&o));
    let out = p.output();
    assert!(
        out.lines().any(|l| l.contains("WARN")
            && l.contains("240 of its 240 records")
            && l.contains(&file.display().to_string())),
        "{out}"
    );
    let recs: Vec<_> = parse_image(&std::fs::read(&file).unwrap(), th_tag())
        .unwrap()
        .collect();
    assert!(recs.iter().all(|r| !unused.contains(r)), "{recs:?}");
    assert!(recs.iter().any(|r| r.0 == 0x0010_1700), "{recs:?}");
}

/// `canpos dcf --state` of a file it cannot use (a link, a FIFO, a failed check) exported the
/// unit's defaults and exited 0; now it is an error naming the file and the reason, and the
/// real file through no link still exports its stored values.
#[test]
fn dcf_of_a_state_file_it_cannot_use_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let real = dir.path().join("th-11.bin");
    std::fs::write(&real, th_image(&[(0x0010_1700, 250)])).unwrap();
    let links = dir.path().join("links");
    std::fs::create_dir(&links).unwrap();
    std::os::unix::fs::symlink(&real, links.join("th-11.bin")).unwrap();
    let fifos = dir.path().join("fifos");
    std::fs::create_dir(&fifos).unwrap();
    let fifo = fifos.join("th-11.bin");
    let c = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
    // SAFETY: a valid NUL-terminated path.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
    let bad = dir.path().join("bad");
    std::fs::create_dir(&bad).unwrap();
    let mut flipped = th_image(&[(0x0010_1700, 250)]);
    flipped[10] ^= 0x10;
    std::fs::write(bad.join("th-11.bin"), &flipped).unwrap();
    for (file, why) in [
        ("links/th-11.bin", "symbolic link"),
        ("fifos/th-11.bin", "FIFO"),
        ("bad/th-11.bin", "CRC mismatch"),
    ] {
        let o = run_in(
            dir.path(),
            &["dcf", "--state", file, "--output", "out.dcf"],
            SHORT,
        );
        assert_fails(&o, 1, &format!("{file}: not a usable state file"));
        assert!(text(&o).contains(why), "{file}: {}", text(&o));
        assert!(!dir.path().join("out.dcf").exists(), "{file}");
    }
    let o = run_in(
        dir.path(),
        &["dcf", "--state", "th-11.bin", "--output", "out.dcf"],
        SHORT,
    );
    assert!(o.status.success(), "{}", text(&o));
    let dcf = std::fs::read_to_string(dir.path().join("out.dcf")).unwrap();
    assert!(dcf.contains("ParameterValue=0x00FA"), "{dcf}");
}

/// The demo kept its sensor's state in `$TMPDIR/canpos-demo-<pid>`, a name anyone could
/// plant a link (or a directory of their own) at ahead: the state and lock files went into the
/// link's target. Now the directory has a random name, created exclusively.
#[test]
fn the_demo_writes_nothing_through_a_link_at_its_old_predictable_name() {
    let dir = tempfile::tempdir().unwrap();
    let victim = dir.path().join("victim");
    std::fs::create_dir(&victim).unwrap();
    let tmp = dir.path().join("tmp");
    std::fs::create_dir(&tmp).unwrap();
    let out = Command::new("sh")
        .arg("-c")
        .arg(format!(
            "ln -s {} \"$TMPDIR/canpos-demo-$$\" && exec {BIN} demo --listen 127.0.0.1:0 --duration 1",
            victim.display()
        ))
        .env("TMPDIR", &tmp)
        .current_dir(dir.path())
        .stdin(Stdio::null())
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", text(&out));
    assert_eq!(
        std::fs::read_dir(&victim).unwrap().count(),
        0,
        "the demo wrote through the planted link"
    );
    // Its own directory is gone again; only the planted link is left.
    let left: Vec<_> = std::fs::read_dir(&tmp)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(left.len(), 1, "{left:?}");
}

// ------------------------------------------------------------------------ replay input

/// Peak resident memory a replay may reach before the watch below kills it.
const RSS_LIMIT_KB: u64 = 256 * 1024;

/// What [`run_watched`] saw.
struct Watched {
    code: Option<i32>,
    out: String,
    /// Peak RSS in KiB (`getrusage` of the child, from `wait4`).
    max_rss_kb: u64,
    /// Killed for memory past [`RSS_LIMIT_KB`] or time past 20 s.
    killed: Option<String>,
}

/// Runs `canpos ARGS` in `dir`, its standard input copied from `input` (by a thread, until the
/// child stops reading); kills it when its RSS passes [`RSS_LIMIT_KB`] (read from /proc while
/// it runs, so that an unbounded reader cannot take the machine's memory) or after 20 s.
fn run_watched(dir: &Path, args: &[&str], input: Option<Box<dyn Read + Send>>) -> Watched {
    // Reaped by `wait4` below, which also gives its peak RSS (std's `wait` does not).
    #[allow(clippy::zombie_processes)]
    let mut child = Command::new(BIN)
        .args(args)
        .current_dir(dir)
        .stdin(if input.is_some() {
            Stdio::piped()
        } else {
            Stdio::null()
        })
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let pid = child.id() as libc::pid_t;
    if let Some(mut src) = input {
        let mut w = child.stdin.take().unwrap();
        // Ends with the child's end (EPIPE: the test harness ignores SIGPIPE, as Rust does).
        std::thread::spawn(move || {
            let _ = std::io::copy(&mut src, &mut w);
        });
    }
    let out = Arc::new(Mutex::new(String::new()));
    let readers: Vec<_> = [
        Box::new(child.stdout.take().unwrap()) as Box<dyn Read + Send>,
        Box::new(child.stderr.take().unwrap()),
    ]
    .into_iter()
    .map(|mut s| {
        let out = Arc::clone(&out);
        std::thread::spawn(move || {
            let mut t = String::new();
            let _ = s.read_to_string(&mut t);
            out.lock().unwrap().push_str(&t);
        })
    })
    .collect();
    let end = Instant::now() + Duration::from_secs(20);
    let mut killed = None;
    let (code, max_rss_kb) = loop {
        let mut status = 0;
        // SAFETY: a zeroed rusage is a valid value for wait4 to fill.
        let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
        // SAFETY: waits for our own child, with valid pointers.
        let r = unsafe { libc::wait4(pid, &mut status, libc::WNOHANG, &mut ru) };
        if r == pid {
            let code = libc::WIFEXITED(status).then(|| libc::WEXITSTATUS(status));
            break (code, ru.ru_maxrss as u64);
        }
        assert_eq!(r, 0, "wait4: {}", std::io::Error::last_os_error());
        if killed.is_none() {
            let hwm = std::fs::read_to_string(format!("/proc/{pid}/status"))
                .ok()
                .and_then(|s| {
                    s.lines()
                        .find_map(|l| l.strip_prefix("VmHWM:"))
                        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
                })
                .unwrap_or(0);
            let why = if hwm > RSS_LIMIT_KB {
                Some(format!("RSS {hwm} kB"))
            } else if Instant::now() > end {
                Some("still running after 20 s".to_string())
            } else {
                None
            };
            if let Some(why) = why {
                // SAFETY: our child, not yet reaped.
                unsafe { libc::kill(pid, libc::SIGKILL) };
                killed = Some(why);
            }
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    for r in readers {
        let _ = r.join();
    }
    let out = out.lock().unwrap().clone();
    Watched {
        code,
        out,
        max_rss_kb,
        killed,
    }
}

fn assert_refused_at_line_one(w: &Watched, file: &str, rss_kb: u64) {
    assert_eq!(w.killed, None, "killed: {}", w.out);
    assert_eq!(w.code, Some(1), "{}", w.out);
    assert!(
        w.out.contains(&format!(
            "error: {file}:1: longer than 4096 bytes without a newline"
        )),
        "{}",
        w.out
    );
    assert!(!w.out.contains("panicked"), "{}", w.out);
    assert!(w.max_rss_kb < rss_kb, "peak RSS {} kB", w.max_rss_kb);
}

/// A regular file is read twice, checked and then played, and only the first read was
/// checked: lines added to a log still being written, between the check and the play (a
/// malformed one, a frame 63 years on), were played or waited for without a word. Now the play
/// takes the file as far as it was checked.
#[test]
fn replay_plays_a_growing_file_only_as_far_as_it_was_checked() {
    use canpos_host::transport::Transport;
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("grow.log");
    std::fs::write(&log, "(1.0) can0 123#11\n(5.0) can0 124#22\n").unwrap();
    let hub = canpos_host::Hub::bind("127.0.0.1:0")
        .unwrap()
        .spawn()
        .unwrap();
    let mut port = hub.attach("can0");
    let mut p = Proc::start(
        dir.path(),
        &[
            "replay",
            "grow.log",
            "--bus",
            &format!("socketcand://{}/can0", hub.local_addr()),
        ],
    );
    // The first frame on the bus: the check is over and the play waits 4 s for the second.
    let first = port
        .recv_deadline(Instant::now() + SHORT)
        .unwrap()
        .expect("the first frame");
    assert_eq!(first.frame.data(), [0x11]);
    let mut f = std::fs::OpenOptions::new().append(true).open(&log).unwrap();
    std::io::Write::write_all(
        &mut f,
        b"garbage line here\n(6.0) can0 125#33\n(2000000000.0) can0 126#44\n",
    )
    .unwrap();
    drop(f);
    assert_eq!(p.wait_exit(SHORT + SHORT), Some(0), "{}", p.output());
    let out = p.output();
    assert!(out.contains("replayed 2 frames"), "{out}");
    assert!(!out.contains("years"), "{out}");
    let mut seen = vec![first.frame.data().to_vec()];
    while let Ok(Some(rx)) = port.recv_deadline(Instant::now() + Duration::from_millis(200)) {
        seen.push(rx.frame.data().to_vec());
    }
    assert_eq!(seen, [vec![0x11], vec![0x22]]);
}

/// `--on-malformed stop` (the default) reported every malformed line of an endless input
/// (`yes | canpos replay -`) and never ended; it stops after the first 100.
#[test]
fn replay_stops_reading_an_endless_input_of_malformed_lines() {
    let dir = tempfile::tempdir().unwrap();
    let w = run_watched(
        dir.path(),
        &["replay", "-", "--bus", "mem://r"],
        Some(Box::new(YesLines)),
    );
    assert_eq!(w.killed, None, "killed: {}", w.out);
    assert_eq!(w.code, Some(1), "{}", w.out);
    assert!(
        w.out
            .contains("-: 100 malformed lines, and the rest not read; nothing sent"),
        "{}",
        w.out
    );
}

/// `yes`: endless `y` lines.
struct YesLines;

impl Read for YesLines {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        for pair in buf.chunks_exact_mut(2) {
            pair.copy_from_slice(b"y\n");
        }
        Ok(buf.len() & !1)
    }
}

/// Issue 35 item 7: `canpos replay /dev/zero` reached 4.2 GB in 15 s. Now it ends at the line
/// limit with the file and line, well under 256 MB.
#[test]
fn replay_of_dev_zero_ends_with_an_error_in_bounded_memory() {
    let dir = tempfile::tempdir().unwrap();
    let w = run_watched(
        dir.path(),
        &["replay", "/dev/zero", "--bus", "mem://r"],
        None,
    );
    assert_refused_at_line_one(&w, "/dev/zero", RSS_LIMIT_KB);
}

/// … an endless standard input without a newline likewise (it reached 2.6 GB in 10 s) …
#[test]
fn replay_of_an_endless_stdin_without_newline_ends_with_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let endless = Box::new(std::io::repeat(b'7').take(8 << 30));
    let w = run_watched(
        dir.path(),
        &["replay", "-", "--bus", "mem://r"],
        Some(endless),
    );
    assert_refused_at_line_one(&w, "-", RSS_LIMIT_KB);
}

/// … and a 200 MB file without a newline errors at the line limit instead of after holding
/// all of it (206 MB): its memory stays far below the file's size.
#[test]
fn replay_of_a_200_mb_file_without_newline_errors_at_the_limit() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("one-line.log");
    // Sparse: 200 MB of zeros that take no disk.
    std::fs::File::create(&file)
        .unwrap()
        .set_len(200_000_000)
        .unwrap();
    let name = file.to_str().unwrap();
    let w = run_watched(dir.path(), &["replay", name, "--bus", "mem://r"], None);
    assert_refused_at_line_one(&w, name, 64 * 1024);
}

/// Issue 35 item 10: a log with a 1e9 s pause waited 31 years without a word. Now the wait is
/// announced with its line first, and `--max-gap` shortens it.
#[test]
fn replay_announces_a_long_pause_and_max_gap_shortens_it() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("gap.log");
    std::fs::write(
        &log,
        "(0.000000) can0 181#01\n(0.500000) can0 181#02\n(1000000000.000000) can0 181#03\n",
    )
    .unwrap();
    let log = log.to_str().unwrap();
    let mut p = Proc::start(dir.path(), &["replay", log, "--bus", "mem://r"]);
    let out = p.wait_for("waiting", SHORT);
    assert!(
        out.contains(&format!(
            "{log}:3: this frame comes 999999999.5 s (31.7 years) after the one before: waiting"
        )),
        "{out}"
    );
    assert!(out.contains("--max-gap"), "{out}");
    p.stop();
    let o = run_in(
        dir.path(),
        &["replay", log, "--bus", "mem://r", "--max-gap", "0.2"],
        SHORT,
    );
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("replayed 3 frames"), "{}", text(&o));
    assert!(!text(&o).contains("waiting"), "{}", text(&o));
    assert_fails(
        &run_in(
            dir.path(),
            &["replay", log, "--bus", "mem://r", "--max-gap=-1"],
            SHORT,
        ),
        2,
        "--max-gap",
    );
}

// ------------------------------------------------------------------------ DCF

/// Issue 35 item 10: a non-numeric `LSS_SerialNumber` was ignored while a bad `NodeID` is an
/// error; now both are errors with the file and line.
#[test]
fn a_dcf_serial_number_that_is_none_is_an_error_at_its_line() {
    let dir = tempfile::tempdir().unwrap();
    let o = Command::new(BIN)
        .args(["eds", "--model", "th"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{o:?}");
    let eds = String::from_utf8(o.stdout).unwrap();
    // The EDS on stdout, then the DCF's commissioning: the line of the bad key is the last.
    let eds: String = eds.lines().map(|l| format!("{l}\n")).collect();
    for (key, value) in [("LSS_SerialNumber", "twelve"), ("NodeID", "200")] {
        let mut dcf = eds.clone();
        dcf.push_str("\n[DeviceComissioning]\nNodeID=5\nBaudrate=125\n");
        if key == "NodeID" {
            dcf = dcf.replace("NodeID=5", &format!("NodeID={value}"));
        } else {
            dcf.push_str(&format!("{key}={value}\n"));
        }
        let line = 1 + dcf
            .lines()
            .position(|l| l == format!("{key}={value}"))
            .unwrap();
        let file = dir.path().join("unit.dcf");
        std::fs::write(&file, &dcf).unwrap();
        let o = run_in(
            dir.path(),
            &[
                "run",
                "--dcf",
                "unit.dcf",
                "--bus",
                "mem://r",
                "--state-dir",
                "state",
            ],
            SHORT,
        );
        assert_fails(
            &o,
            1,
            &format!("unit.dcf:{line}: [DeviceComissioning] {key}: not a"),
        );
    }
}
