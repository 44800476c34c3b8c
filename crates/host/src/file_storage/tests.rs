use super::*;
use canpos_stack::storage::{parse_image, ImageWriter};
use std::os::unix::fs::symlink;

fn image(value: u32) -> Vec<u8> {
    let mut buf = [0u8; IMAGE_MAX];
    let mut w = ImageWriter::new(&mut buf, 1);
    w.push(0x0010_1700, value);
    let n = w.finish();
    buf[..n].to_vec()
}

fn load_value(s: &mut FileStorage) -> Result<u32, StorageError> {
    let mut buf = [0u8; IMAGE_MAX];
    let n = s.load(&mut buf)?;
    let mut it = parse_image(&buf[..n], 1)?;
    Ok(it.next().unwrap().1)
}

fn names(dir: &Path) -> Vec<String> {
    let mut names: Vec<_> = fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    names.sort();
    names
}

/// A file outside the state directory that links in the directory point at: whatever the
/// sensor does, its bytes stay.
struct Decoy {
    _dir: tempfile::TempDir,
    path: PathBuf,
}

const DECOY: &[u8] = b"precious bytes of someone else's file\n";

impl Decoy {
    fn new() -> Decoy {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("decoy");
        fs::write(&path, DECOY).unwrap();
        Decoy { _dir: dir, path }
    }
    fn assert_untouched(&self) {
        assert_eq!(
            fs::read(&self.path).unwrap(),
            DECOY,
            "the decoy was written"
        );
        assert!(fs::symlink_metadata(&self.path).unwrap().is_file());
    }
}

#[test]
fn round_trip_empty_and_erase() {
    let dir = tempfile::tempdir().unwrap();
    let mut s = FileStorage::new(dir.path().join("sub/th-1.bin"));
    assert_eq!(load_value(&mut s), Err(StorageError::Empty));
    s.save(&image(7)).unwrap();
    assert_eq!(load_value(&mut s), Ok(7));
    s.save(&image(8)).unwrap();
    assert_eq!(load_value(&mut s), Ok(8));
    assert_eq!(s.saves(), 2);
    // No temporary file left behind.
    assert_eq!(names(&dir.path().join("sub")), ["th-1.bin"]);
    s.erase().unwrap();
    assert_eq!(load_value(&mut s), Err(StorageError::Empty));
    s.erase().unwrap();
}

#[test]
fn crash_before_rename_keeps_old_image() {
    let dir = tempfile::tempdir().unwrap();
    let mut s = FileStorage::new(dir.path().join("th-1.bin"));
    s.save(&image(1)).unwrap();
    // Simulate a kill in the middle of a save: the temp file is (partly) written, the
    // rename never happened.
    let new = image(2);
    let stale = dir.path().join(random_temp_name(OsStr::new("th-1.bin")));
    fs::write(&stale, &new[..new.len() / 2]).unwrap();
    let mut after = FileStorage::new(dir.path().join("th-1.bin"));
    assert_eq!(load_value(&mut after), Ok(1));
    // The next save goes to a temp file of its own and succeeds.
    after.save(&image(3)).unwrap();
    assert_eq!(load_value(&mut after), Ok(3));
    // Opening with the lock removes the stale one.
    let _locked = FileStorage::open(dir.path().join("th-1.bin")).unwrap();
    assert!(!stale.exists());
}

#[test]
fn temporary_names_are_new_each_time_and_recognised_as_temporary() {
    let image = OsStr::new("th-1.bin");
    let a = random_temp_name(image);
    let b = random_temp_name(image);
    assert_ne!(a, b);
    for n in [&a, &b] {
        assert!(is_temp_name(image, n.as_encoded_bytes()), "{n:?}");
        assert_eq!(n.len(), "th-1.bin.tmp.".len() + 16, "{n:?}");
    }
    // The pid names of earlier versions too; not other names or other units' files.
    assert!(is_temp_name(image, b"th-1.bin.tmp.4194000"));
    for other in [
        &b"th-1.bin.tmp."[..],
        b"th-1.bin.tmp.notes",
        b"th-2.bin.tmp.12",
        b"th-1.bin.lock",
        b"th-1.bin.tmp.0123456789abcdef01234",
    ] {
        assert!(!is_temp_name(image, other), "{other:?}");
    }
}

#[test]
fn torn_or_garbage_files_are_corrupt() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("th-1.bin");
    let mut s = FileStorage::new(&path);
    let img = image(5);
    fs::write(&path, &img[..img.len() - 3]).unwrap();
    assert_eq!(load_value(&mut s), Err(StorageError::Corrupt));
    fs::write(&path, vec![0xAA; IMAGE_MAX + 10]).unwrap();
    assert_eq!(load_value(&mut s), Err(StorageError::Corrupt));
    s.save(&img).unwrap();
    s.corrupt().unwrap();
    assert_eq!(load_value(&mut s), Err(StorageError::Corrupt));
}

/// Each check the core makes has its reason in words (the host logs it with the file: the
/// core's answer is only EMCY 0x6300), and a load refuses the image for it.
#[test]
fn an_image_failing_a_check_is_corrupt_with_its_reason() {
    let th = canpos_models::by_name("th").unwrap();
    let tag = th.features.tag;
    let mut buf = [0u8; IMAGE_MAX];
    let mut w = ImageWriter::new(&mut buf, tag);
    w.push(0x0010_1700, 100);
    let n = w.finish();
    let good = buf[..n].to_vec();
    let reseal = |at: usize, v: u8| {
        let mut b = good.clone();
        b[at] = v;
        let crc = canpos_stack::storage::crc32(&b[..n - 4]).to_le_bytes();
        b[n - 4..].copy_from_slice(&crc);
        b
    };
    let mut flipped = good.clone();
    flipped[9] ^= 1;
    let cases = [
        (good[..7].to_vec(), "7 bytes, shorter than any image (12)"),
        (reseal(0, b'X'), "not a canpos state image"),
        (
            reseal(4, 9),
            "format version 9, this canpos reads version 1",
        ),
        (
            reseal(5, 3),
            "an image of another model (tag 3, this model's is 1)",
        ),
        (reseal(6, 2), "20 bytes, but its header's 2 records make 28"),
        (flipped, "CRC mismatch"),
    ];
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("th-1.bin");
    for (bytes, why) in cases {
        let got = image_problem(&bytes, tag);
        assert!(got.starts_with(why), "{got} / {why}");
        fs::write(&path, &bytes).unwrap();
        let mut s = FileStorage::new(&path).for_model(th);
        assert_eq!(
            s.load(&mut [0u8; IMAGE_MAX]),
            Err(StorageError::Corrupt),
            "{why}"
        );
        // What was reported is that reason.
        assert!(
            s.reported.as_deref().is_some_and(|r| r.starts_with(why)),
            "{why}: {:?}",
            s.reported
        );
    }
    fs::write(&path, &good).unwrap();
    let mut s = FileStorage::new(&path).for_model(th);
    assert_eq!(s.load(&mut [0u8; IMAGE_MAX]), Ok(n));
    assert_eq!(s.reported, None);
}

#[test]
fn fifo_is_refused_not_waited_on() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("th-1.bin");
    let c = std::ffi::CString::new(path.as_os_str().as_encoded_bytes()).unwrap();
    // SAFETY: a valid NUL-terminated path.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
    // Without a lock: load returns at once (no writer would ever come).
    let mut s = FileStorage::new(&path);
    assert_eq!(load_value(&mut s), Err(StorageError::Corrupt));
    let e = FileStorage::open(&path).unwrap_err();
    assert!(e.to_string().contains("a FIFO"), "{e}");
    // Nor a FIFO as the lock file: refused before it is opened.
    fs::remove_file(&path).unwrap();
    let lock = dir.path().join("th-1.bin.lock");
    let c = std::ffi::CString::new(lock.as_os_str().as_encoded_bytes()).unwrap();
    // SAFETY: as above.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
    let e = FileStorage::open(&path).unwrap_err();
    assert!(
        matches!(&e, OpenError::NotRegular { what: "lock file", path, .. } if *path == lock),
        "{e}"
    );
}

#[test]
fn lock_refuses_a_second_user_until_released() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("th-1.bin");
    let a = FileStorage::open(&path).unwrap();
    assert!(a.is_locked());
    let clone = a.clone();
    drop(a);
    // flock conflicts between open file descriptions, also within one process.
    let e = FileStorage::open(&path).unwrap_err();
    assert!(
        matches!(e, OpenError::InUse { holder: Some(p), .. } if p == std::process::id()),
        "{e}"
    );
    assert!(e.to_string().contains("--serial"), "{e}");
    drop(clone);
    FileStorage::open(&path).unwrap();
}

/// Review of issue 35: the holder's pid was read with no bound, so a held lock file of
/// 1 GiB (sparse: no disk needed) cost the second process 1 GiB of memory. Only the pid's
/// few bytes are read now.
#[test]
fn a_huge_held_lock_file_is_read_no_further_than_its_pid() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("th-1.bin");
    let a = FileStorage::open(&path).unwrap();
    let lock = dir.path().join("th-1.bin.lock");
    std::fs::OpenOptions::new()
        .write(true)
        .open(&lock)
        .unwrap()
        .set_len(256 << 20)
        .unwrap();
    let e = FileStorage::open(&path).unwrap_err();
    assert!(
        matches!(e, OpenError::InUse { holder: Some(p), .. } if p == std::process::id()),
        "{e}"
    );
    drop(a);
}

/// Issue 35 item 1: a link at `<file>.lock` to a file outside the state directory used to
/// be truncated and given the pid. Now the link is refused by name and its target (an
/// existing file, or a name nothing has yet) stays as it was.
#[test]
fn a_symlinked_lock_file_is_refused_and_its_target_untouched() {
    let decoy = Decoy::new();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("th-4242.bin");
    let lock = dir.path().join("th-4242.bin.lock");
    symlink(&decoy.path, &lock).unwrap();
    let e = FileStorage::open(&path).unwrap_err();
    assert!(
        matches!(&e, OpenError::Link { what: "lock file", path } if *path == lock),
        "{e}"
    );
    let msg = e.to_string();
    assert!(
        msg.contains(&lock.display().to_string()) && msg.contains("symbolic link"),
        "{msg}"
    );
    decoy.assert_untouched();
    // A link to a name that does not exist yet: nothing is created there.
    fs::remove_file(&lock).unwrap();
    let absent = decoy.path.with_file_name("absent");
    symlink(&absent, &lock).unwrap();
    assert!(matches!(
        FileStorage::open(&path),
        Err(OpenError::Link { .. })
    ));
    assert!(!absent.exists());
    // Nothing else was made in the state directory either.
    assert_eq!(names(dir.path()), ["th-4242.bin.lock"]);
}

/// A hard link to another file as the lock file: its pid would land in that file.
#[test]
fn a_hard_linked_lock_file_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    // On the same file system as the state directory, as a hard link must be.
    let outside = dir.path().join("outside");
    fs::write(&outside, DECOY).unwrap();
    let state = dir.path().join("state");
    fs::create_dir(&state).unwrap();
    fs::hard_link(&outside, state.join("th-1.bin.lock")).unwrap();
    let e = FileStorage::open(state.join("th-1.bin")).unwrap_err();
    assert!(matches!(e, OpenError::HardLinked { links: 2, .. }), "{e}");
    assert!(e.to_string().contains("th-1.bin.lock"), "{e}");
    assert_eq!(fs::read(&outside).unwrap(), DECOY);
}

/// A link where the state file should be: refused at open by name; a load does not read
/// through it (even to a valid image), and a save replaces the link itself.
#[test]
fn a_symlinked_state_file_is_refused_and_never_read_or_written_through() {
    let decoy = Decoy::new();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("th-1.bin");
    symlink(&decoy.path, &path).unwrap();
    let e = FileStorage::open(&path).unwrap_err();
    assert!(
        matches!(&e, OpenError::Link { what: "state file", path: p } if *p == path),
        "{e}"
    );
    assert!(e.to_string().contains(&path.display().to_string()), "{e}");
    // Not even the lock was made.
    assert_eq!(names(dir.path()), ["th-1.bin"]);
    let mut s = FileStorage::new(&path);
    assert_eq!(load_value(&mut s), Err(StorageError::Corrupt));
    assert!(s
        .reported
        .as_deref()
        .is_some_and(|r| r.contains("symbolic link")));
    s.save(&image(4)).unwrap();
    assert!(fs::symlink_metadata(&path).unwrap().is_file());
    assert_eq!(load_value(&mut s), Ok(4));
    decoy.assert_untouched();
    // A valid image behind a link is not read either.
    fs::write(&decoy.path, image(9)).unwrap();
    fs::remove_file(&path).unwrap();
    symlink(&decoy.path, &path).unwrap();
    assert_eq!(load_value(&mut s), Err(StorageError::Corrupt));
    // Erasing removes the link, not its target.
    s.erase().unwrap();
    assert_eq!(fs::read(&decoy.path).unwrap(), image(9));
}

/// Issue 35 item 2: a link at the temporary name a save used to write (`<file>.tmp.<pid>`,
/// the pid readable in the lock file) made the save write the image into its target. Now
/// a save writes only a new file of its own, the links are left alone, and a taken name
/// costs one more try.
#[test]
fn symlinks_at_temporary_names_are_never_written_through() {
    let decoy = Decoy::new();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("th-1.bin");
    let pid_name = dir
        .path()
        .join(format!("th-1.bin.tmp.{}", std::process::id()));
    let hex_name = dir.path().join("th-1.bin.tmp.0123456789abcdef");
    for l in [&pid_name, &hex_name] {
        symlink(&decoy.path, l).unwrap();
    }
    let mut s = FileStorage::open(&path).unwrap();
    for v in 0..5 {
        s.save(&image(v)).unwrap();
        assert_eq!(load_value(&mut s), Ok(v));
    }
    assert!(fs::symlink_metadata(&path).unwrap().is_file());
    // The links are still there, neither followed nor removed.
    for l in [&pid_name, &hex_name] {
        assert!(fs::symlink_metadata(l).unwrap().file_type().is_symlink());
    }
    decoy.assert_untouched();
    // A save whose first temporary name is taken by a link takes the next one.
    let names = [
        hex_name.file_name().unwrap().to_os_string(),
        OsString::from("th-1.bin.tmp.ff"),
    ];
    s.write_atomic_via(&image(7), &mut names.into_iter())
        .unwrap();
    assert_eq!(load_value(&mut s), Ok(7));
    decoy.assert_untouched();
    // Only taken names: the save fails naming the last one, and the image stays.
    let taken = std::iter::repeat(hex_name.file_name().unwrap().to_os_string());
    let e = s
        .write_atomic_via(&image(8), &mut taken.take(3))
        .unwrap_err();
    assert!(
        e.to_string().contains("th-1.bin.tmp.0123456789abcdef"),
        "{e}"
    );
    assert_eq!(load_value(&mut s), Ok(7));
    decoy.assert_untouched();
    // Creating a temporary file at a link's name is refused by the kernel (O_EXCL).
    let d = s.dir(false).unwrap();
    let e = create_new(&d, hex_name.file_name().unwrap()).unwrap_err();
    assert_eq!(e.kind(), io::ErrorKind::AlreadyExists);
    decoy.assert_untouched();
}

#[test]
fn stale_temporary_files_are_removed_at_open() {
    let decoy = Decoy::new();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("th-1.bin");
    fs::write(dir.path().join("th-1.bin.tmp.99999"), b"half").unwrap();
    fs::write(dir.path().join("th-1.bin.tmp.12"), b"half").unwrap();
    fs::write(dir.path().join("th-1.bin.tmp.00c0ffee00c0ffee"), b"half").unwrap();
    // Not ours: another unit's temp file, and a name that only looks similar.
    fs::write(dir.path().join("th-2.bin.tmp.99999"), b"other").unwrap();
    fs::write(dir.path().join("th-1.bin.tmp.notes"), b"keep").unwrap();
    // A link at a temporary name: left alone, its target too.
    symlink(&decoy.path, dir.path().join("th-1.bin.tmp.77")).unwrap();
    let _s = FileStorage::open(&path).unwrap();
    assert_eq!(
        names(dir.path()),
        [
            "th-1.bin.lock",
            "th-1.bin.tmp.77",
            "th-1.bin.tmp.notes",
            "th-2.bin.tmp.99999"
        ]
    );
    decoy.assert_untouched();
}

#[test]
fn unwritable_directory_is_reported_at_open() {
    let dir = tempfile::tempdir().unwrap();
    // A file where the directory should be: nothing can be created below it, whatever
    // the user's privileges (root ignores permission bits).
    let blocker = dir.path().join("not-a-dir");
    fs::write(&blocker, b"").unwrap();
    let e = FileStorage::open(blocker.join("th-1.bin")).unwrap_err();
    assert!(matches!(e, OpenError::Unwritable { .. }), "{e}");
    assert!(e.to_string().contains("not writable"), "{e}");
}

/// The storage keeps the directory it opened: a directory moved away and a link put at
/// its path (to somewhere else) get none of this unit's files.
#[test]
fn saves_go_to_the_directory_opened_even_when_its_path_changes() {
    let decoy_dir = tempfile::tempdir().unwrap();
    let root = tempfile::tempdir().unwrap();
    let state = root.path().join("state");
    let mut s = FileStorage::open(state.join("th-1.bin")).unwrap();
    s.save(&image(1)).unwrap();
    fs::rename(&state, root.path().join("moved")).unwrap();
    symlink(decoy_dir.path(), &state).unwrap();
    s.save(&image(2)).unwrap();
    assert_eq!(load_value(&mut s), Ok(2));
    assert!(names(decoy_dir.path()).is_empty());
    assert_eq!(
        names(&root.path().join("moved")),
        ["th-1.bin", "th-1.bin.lock"]
    );
}

#[test]
fn unreadable_path_is_corrupt_not_empty() {
    let dir = tempfile::tempdir().unwrap();
    // A directory where the file should be: open succeeds on Linux, read fails.
    let path = dir.path().join("th-1.bin");
    fs::create_dir(&path).unwrap();
    let mut s = FileStorage::new(&path);
    assert_eq!(load_value(&mut s), Err(StorageError::Corrupt));
    // And a failing save leaves the directory (the "old image") alone.
    assert_eq!(s.save(&image(1)), Err(StorageError::Io));
    assert!(path.is_dir());
    assert_eq!(names(dir.path()), ["th-1.bin"]);
}

/// Issue 35 item 9: a CRC-valid image full of records the model has no use for (240 of
/// them) loaded, and every later save then aborted 0x08000020 (the kept records left no
/// room), with nothing logged. The records are now dropped at load (one log line), and
/// the save stores the unit's own configuration.
#[test]
fn an_image_of_unused_records_does_not_block_later_saves() {
    use canpos_stack::{Duration, Frame, Instant, Node};
    let th = canpos_models::by_name("th").unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("th-1.bin");
    let fit = (IMAGE_MAX - 12) / 8;
    let mut buf = [0u8; IMAGE_MAX];
    let mut w = ImageWriter::new(&mut buf, th.features.tag);
    // Objects a TH does not have, one it has but never stores (0x6004 position value),
    // keys of no kind, and the heartbeat repeated: 240 records in all.
    let mut unused = Vec::new();
    for i in 0..(fit as u32 - 2) {
        unused.push(match i % 3 {
            0 => (0x0050_0000 + (i << 8), i),
            1 => (0x0060_0400, i),
            _ => (0xFE00_0000 + i, i),
        });
    }
    unused.push((0x0010_1700, 100));
    unused.push((0x0010_1700, 300));
    for &(k, v) in &unused {
        assert!(w.push(k, v));
    }
    let n = w.finish();
    assert_eq!(n, IMAGE_MAX);
    fs::write(&path, &buf[..n]).unwrap();

    let mut node = canpos_models::SensorNode::new(
        th,
        th.default_config.with_node_id(5),
        FileStorage::new(&path).for_model(th),
    );
    let mut now = Instant::ZERO;
    node.power_on(now);
    while node.poll(now).is_some() {}
    // The heartbeat's last record is the one in force.
    assert_eq!(node.read_object(0x1017, 0), Ok(300));
    assert!(
        node.storage_mut()
            .reported
            .as_deref()
            .is_some_and(|r| r.starts_with("239 of its 240 records")),
        "{:?}",
        node.storage_mut().reported
    );
    let mut sdo = |node: &mut Node<_, FileStorage>, req: [u8; 8]| {
        now += Duration::from_millis(1);
        node.handle_frame(&Frame::std8(0x605, req), now);
        for _ in 0..1000 {
            while let Some(f) = node.poll(now) {
                if f.std_id() == Some(0x585) {
                    return *f.raw();
                }
            }
            now += Duration::from_millis(10);
        }
        panic!("no SDO answer");
    };
    // Heartbeat 250 ms, then 0x1010/1 "save".
    assert_eq!(sdo(&mut node, [0x2B, 0x17, 0x10, 0, 250, 0, 0, 0])[0], 0x60);
    let save = u32::from_le_bytes(*b"save").to_le_bytes();
    let a = sdo(
        &mut node,
        [0x23, 0x10, 0x10, 1, save[0], save[1], save[2], save[3]],
    );
    assert_eq!(a[0], 0x60, "save answered {a:02X?}");
    // The file holds the unit's records only, the new heartbeat among them.
    let bytes = fs::read(&path).unwrap();
    let recs: Vec<_> = parse_image(&bytes, th.features.tag).unwrap().collect();
    assert!(recs.contains(&(0x0010_1700, 250)), "{recs:?}");
    assert!(
        recs.iter()
            .all(|&(k, _)| record_used(FileStorage::new(&path).for_model(th).model.unwrap(), k)),
        "{recs:?}"
    );
    assert_eq!(recs.iter().filter(|r| r.0 == 0x0010_1700).count(), 1);
    // And a later save works too.
    let a = sdo(
        &mut node,
        [0x23, 0x10, 0x10, 1, save[0], save[1], save[2], save[3]],
    );
    assert_eq!(a[0], 0x60, "second save answered {a:02X?}");
}

/// A TMI's preset, saved to its state file, gives the same magnet position the same
/// reading in the next process (the offset is kept with 0x6010, issue 36 item 5).
#[test]
fn a_tmi_preset_survives_a_restart_through_the_state_file() {
    use canpos_encoder::Sample;
    use canpos_stack::{Duration, Frame, Instant, Node};
    let tmi = canpos_models::by_name("tmi").unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("tmi-1.bin");
    let mut s = Sample::default();
    s.positions_nm[0] = Some(300_000_000);
    let mut now = Instant::ZERO;
    let mut sdo = |node: &mut Node<_, FileStorage>, req: [u8; 8]| {
        now += Duration::from_millis(1);
        node.update_sample(&s, now);
        node.handle_frame(&Frame::std8(0x67F, req), now);
        for _ in 0..100 {
            while let Some(f) = node.poll(now) {
                if f.std_id() == Some(0x5FF) {
                    return *f.raw();
                }
            }
            now += Duration::from_millis(10);
        }
        panic!("no SDO answer");
    };
    let read = |a: [u8; 8]| i32::from_le_bytes([a[4], a[5], a[6], a[7]]);
    let save = u32::from_le_bytes(*b"save").to_le_bytes();
    let position = [0x40, 0x20, 0x60, 1, 0, 0, 0, 0];
    {
        let storage = FileStorage::new(&path).for_model(tmi);
        let mut node = canpos_models::SensorNode::new(tmi, tmi.default_config, storage);
        node.power_on(Instant::ZERO);
        assert_eq!(read(sdo(&mut node, position)), 300_000);
        // Preset 1000 (0x3E8), then "save".
        assert_eq!(
            sdo(&mut node, [0x23, 0x10, 0x60, 1, 0xE8, 0x03, 0, 0])[0],
            0x60
        );
        assert_eq!(read(sdo(&mut node, position)), 1000);
        let a = sdo(
            &mut node,
            [0x23, 0x10, 0x10, 1, save[0], save[1], save[2], save[3]],
        );
        assert_eq!(a[0], 0x60, "save answered {a:02X?}");
    }
    let storage = FileStorage::new(&path).for_model(tmi);
    let mut node = canpos_models::SensorNode::new(tmi, tmi.default_config, storage);
    // A new process: its own clock.
    node.power_on(Instant::ZERO);
    assert_eq!(
        read(sdo(&mut node, position)),
        1000,
        "same magnet, same reading"
    );
    assert_eq!(
        read(sdo(&mut node, [0x40, 0x10, 0x60, 1, 0, 0, 0, 0])),
        1000
    );
    assert_eq!(node.storage_mut().reported, None);
}

/// A two-channel TMI (order code `62x`) keeps its channel-2 configuration in its state
/// file, although the storage is opened for the model `tmi` (whose default unit has one
/// channel), as `canpos run --order-code` opens it; a one-channel unit that loads and saves
/// the same file (both are `tmi-<serial>.bin`) loses none of it either (issue 36 item 2
/// review).
#[test]
fn a_two_channel_tmi_keeps_its_channel_2_configuration_in_the_state_file() {
    use canpos_stack::{Duration, Frame, Instant, Node};
    let tmi = canpos_models::by_name("tmi").unwrap();
    let one = tmi.default_config.with_channels(1);
    let two = tmi.default_config.with_channels(2);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("tmi-1.bin");
    let mut now = Instant::ZERO;
    let mut sdo = |node: &mut Node<_, FileStorage>, req: [u8; 8]| {
        now += Duration::from_millis(1);
        node.handle_frame(&Frame::std8(0x67F, req), now);
        for _ in 0..100 {
            while let Some(f) = node.poll(now) {
                if f.std_id() == Some(0x5FF) {
                    return *f.raw();
                }
            }
            now += Duration::from_millis(10);
        }
        panic!("no SDO answer");
    };
    let s = u32::from_le_bytes(*b"save").to_le_bytes();
    let save = [0x23, 0x10, 0x10, 1, s[0], s[1], s[2], s[3]];
    // Cam 1 low limit of channel 2 (0x6310:2, stored with the application parameters).
    let read_cam2 = [0x40, 0x10, 0x63, 2, 0, 0, 0, 0];
    let value = |a: [u8; 8]| i32::from_le_bytes([a[4], a[5], a[6], a[7]]);
    {
        let mut node =
            canpos_models::SensorNode::new(tmi, two, FileStorage::new(&path).for_model(tmi));
        node.power_on(Instant::ZERO);
        let a = sdo(&mut node, [0x23, 0x10, 0x63, 2, 0xD2, 0x04, 0, 0]);
        assert_eq!(a[0], 0x60, "write answered {a:02X?}");
        assert_eq!(sdo(&mut node, save)[0], 0x60);
    }
    {
        let mut node =
            canpos_models::SensorNode::new(tmi, two, FileStorage::new(&path).for_model(tmi));
        node.power_on(Instant::ZERO);
        assert_eq!(
            value(sdo(&mut node, read_cam2)),
            1234,
            "after a power cycle"
        );
    }
    {
        // The same file in a one-channel unit: it has no 0x6310:2, and a save of its own
        // leaves the other unit's record alone.
        let mut node =
            canpos_models::SensorNode::new(tmi, one, FileStorage::new(&path).for_model(tmi));
        node.power_on(Instant::ZERO);
        let a = sdo(&mut node, read_cam2);
        assert_eq!((a[0], value(a)), (0x80, 0x0609_0011), "{a:02X?}");
        assert_eq!(sdo(&mut node, save)[0], 0x60);
    }
    let mut node = canpos_models::SensorNode::new(tmi, two, FileStorage::new(&path).for_model(tmi));
    node.power_on(Instant::ZERO);
    assert_eq!(
        value(sdo(&mut node, read_cam2)),
        1234,
        "after the one-channel unit"
    );
    assert_eq!(node.storage_mut().reported, None);
}

/// The records the core uses are kept, every one (the LSS ones included), and in order.
#[test]
fn an_image_of_used_records_loads_unchanged() {
    let tmi = canpos_models::by_name("tmi").unwrap();
    let tag = tmi.features.tag;
    let mut buf = [0u8; IMAGE_MAX];
    let mut w = ImageWriter::new(&mut buf, tag);
    for (k, v) in [
        (KEY_LSS_NODE_ID, 5),
        (KEY_LSS_BITRATE, 125),
        (KEY_SAVED_NODE_ID, 5),
        (0x0020_0000, 5),
        (0x0010_1700, 100),
        // The TMI's preset offsets, kept with 0x6010 (issue 36 item 5).
        (canpos_stack::storage::app_key(0), -299_000i32 as u32),
        (canpos_stack::storage::app_key(1), 7),
    ] {
        w.push(k, v);
    }
    let n = w.finish();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("tmi-1.bin");
    fs::write(&path, &buf[..n]).unwrap();
    let mut s = FileStorage::new(&path).for_model(tmi);
    let mut got = [0u8; IMAGE_MAX];
    assert_eq!(s.load(&mut got), Ok(n));
    assert_eq!(got[..n], buf[..n]);
    assert_eq!(s.reported, None);
}
