//! Hostile files (issue 35): a state directory holding links where the sensor's files go,
//! state files that fail their checks or hold records no model uses, `canpos replay` on input
//! without end or without newlines, and DCF values that are no numbers.

mod common;

use std::path::{Path, PathBuf};
use std::time::Duration;

use canpos_core::storage::{parse_image, ImageWriter, IMAGE_MAX};
use common::{free_port, run_in, text, wait_port, Proc};

const SHORT: Duration = Duration::from_secs(10);

/// A file outside the state directory for links to point at; its bytes must stay.
const DECOY: &[u8] = b"someone else's file: must stay as it is\n";

fn decoy(dir: &Path) -> PathBuf {
    let p = dir.join("decoy");
    std::fs::write(&p, DECOY).unwrap();
    p
}

fn th_tag() -> u8 {
    canpos_core::models::by_name("th").unwrap().features.tag
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
        let crc = canpos_core::storage::crc32(&b[..n - 4]).to_le_bytes();
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
