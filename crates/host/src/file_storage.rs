//! Non-volatile storage of a device as one file (SPEC §8).
//!
//! The core hands over a self-checking image (magic, version, model tag, CRC-32); this module
//! only keeps the bytes, and keeps them safely:
//!
//! - **save** writes a temporary file in the same directory, `fsync`s it, renames it over the
//!   image and `fsync`s the directory. `rename` is atomic within one file system, so after a
//!   crash at any point the path holds either the complete old image or the complete new one.
//! - **load** returns [`StorageError::Empty`] when there is no file, and
//!   [`StorageError::Corrupt`] (with a log line) when it cannot be read or is longer than any
//!   image; a short or bit-flipped file is caught by the core's CRC check. The device then
//!   starts on defaults and reports it.
//! - nothing here ever deletes the good image on an error: a failed save removes only its own
//!   temporary file.
//! - only a regular file is ever read: the image is opened non-blocking and checked with
//!   `fstat`, so a FIFO or device in its place is reported instead of hanging the boot.
//!
//! [`FileStorage::open`] (what the command line uses) also takes a lock: an exclusive `flock`
//! on `<image>.lock`, held as long as any clone of the storage lives, so that a second process
//! on the same state file gets a clear error instead of silently sharing it. Holding the lock, it
//! removes the `<image>.tmp.<pid>` files that killed processes left behind, and it checks that
//! the directory is writable before the sensor boots.

use std::fs::{self, File, OpenOptions, TryLockError};
use std::io::{self, Read, Write};
use std::os::unix::fs::{FileTypeExt, OpenOptionsExt};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use canpos_core::storage::{Storage, StorageError, IMAGE_MAX};

/// A [`Storage`] kept in one file.
#[derive(Clone, Debug)]
pub struct FileStorage {
    path: PathBuf,
    saves: u64,
    /// The lock file, held open (and locked) while any clone lives; `None` for [`FileStorage::new`].
    lock: Option<Arc<File>>,
}

/// Why [`FileStorage::open`] refused a state file.
#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    /// Another process holds the state file's lock.
    #[error("state file {} is in use by another process{}; give each sensor its own --serial (or --state-dir)", path.display(), holder.map(|p| format!(" (pid {p})")).unwrap_or_default())]
    InUse {
        /// The image path.
        path: PathBuf,
        /// The pid written in the lock file by its holder, when readable.
        holder: Option<u32>,
    },
    /// Something other than a regular file is at the image path.
    #[error("state file {} is not a regular file ({kind}); remove it or choose another --state-dir", path.display())]
    NotRegular {
        /// The image path.
        path: PathBuf,
        /// What it is (FIFO, directory, …).
        kind: &'static str,
    },
    /// The state directory cannot be created or written.
    #[error("state directory {} is not writable: {source}", dir.display())]
    Unwritable {
        /// The directory.
        dir: PathBuf,
        /// The operating system's error.
        source: io::Error,
    },
}

fn kind_name(ft: fs::FileType) -> &'static str {
    if ft.is_dir() {
        "a directory"
    } else if ft.is_fifo() {
        "a FIFO"
    } else if ft.is_socket() {
        "a socket"
    } else if ft.is_char_device() {
        "a character device"
    } else if ft.is_block_device() {
        "a block device"
    } else {
        "not a regular file"
    }
}

impl FileStorage {
    /// Storage at `path`, without a lock (tests, benchmarks, throw-away directories). The file
    /// need not exist; its directory is created at the first save.
    pub fn new(path: impl Into<PathBuf>) -> Self {
        FileStorage {
            path: path.into(),
            saves: 0,
            lock: None,
        }
    }

    /// Storage at `path` for a running sensor: creates the directory (reporting it when not
    /// writable), refuses anything but a regular file at `path`, locks `<path>.lock` against
    /// other processes and removes stale temporary files of earlier, killed processes.
    pub fn open(path: impl Into<PathBuf>) -> Result<Self, OpenError> {
        let mut s = FileStorage::new(path);
        let dir = s.dir();
        let unwritable = |source| OpenError::Unwritable {
            dir: dir.clone(),
            source,
        };
        fs::create_dir_all(&dir).map_err(unwritable)?;
        if let Ok(m) = fs::metadata(&s.path) {
            if !m.file_type().is_file() {
                return Err(OpenError::NotRegular {
                    path: s.path.clone(),
                    kind: kind_name(m.file_type()),
                });
            }
        }
        let lock_path = s.sibling(".lock");
        let mut lock = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .custom_flags(libc::O_NONBLOCK)
            .open(&lock_path)
            .map_err(unwritable)?;
        match lock.try_lock() {
            Ok(()) => {}
            Err(TryLockError::WouldBlock) => {
                let holder = fs::read_to_string(&lock_path)
                    .ok()
                    .and_then(|t| t.trim().parse().ok());
                return Err(OpenError::InUse {
                    path: s.path.clone(),
                    holder,
                });
            }
            Err(TryLockError::Error(e)) => return Err(unwritable(e)),
        }
        // For the "in use" message of a second process; the lock is what counts.
        let _ = lock.set_len(0);
        let _ = writeln!(lock, "{}", std::process::id());
        // Probe that the directory takes new files (a read-only directory would only show at
        // the first store, long after the boot).
        let probe = s.temp_path();
        File::create(&probe).map_err(unwritable)?;
        let _ = fs::remove_file(&probe);
        s.remove_stale_temps();
        s.lock = Some(Arc::new(lock));
        Ok(s)
    }

    /// `<image><suffix>` in the image's directory.
    fn sibling(&self, suffix: &str) -> PathBuf {
        let mut name = self
            .path
            .file_name()
            .map(|n| n.to_os_string())
            .unwrap_or_default();
        name.push(suffix);
        self.path.with_file_name(name)
    }

    /// Removes `<image>.tmp.*` left by killed processes. Only called with the lock held: no
    /// other process is writing this image, so every such file is stale.
    fn remove_stale_temps(&self) {
        let Some(prefix) = self.sibling(".tmp.").file_name().map(|n| n.to_os_string()) else {
            return;
        };
        let Ok(entries) = fs::read_dir(self.dir()) else {
            return;
        };
        for e in entries.flatten() {
            let name = e.file_name();
            let is_temp = name
                .as_encoded_bytes()
                .strip_prefix(prefix.as_encoded_bytes())
                .is_some_and(|pid| !pid.is_empty() && pid.iter().all(u8::is_ascii_digit));
            if is_temp && e.file_type().is_ok_and(|t| t.is_file()) {
                match fs::remove_file(e.path()) {
                    Ok(()) => {
                        tracing::info!(file = %e.path().display(), "removed a stale temporary state file")
                    }
                    Err(err) => {
                        tracing::warn!(file = %e.path().display(), error = %err, "cannot remove a stale temporary state file")
                    }
                }
            }
        }
    }

    /// Whether this storage holds its state file's lock ([`FileStorage::open`]).
    pub fn is_locked(&self) -> bool {
        self.lock.is_some()
    }

    /// The image file's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Completed saves since this value was created.
    pub fn saves(&self) -> u64 {
        self.saves
    }

    /// The temporary file a save writes before renaming. Per process, so two processes
    /// pointed at the same state directory by mistake never write into each other's temp file.
    fn temp_path(&self) -> PathBuf {
        self.sibling(&format!(".tmp.{}", std::process::id()))
    }

    fn dir(&self) -> PathBuf {
        match self.path.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        }
    }

    /// Writes `image` atomically (see the module docs).
    pub fn write_atomic(&self, image: &[u8]) -> io::Result<()> {
        let dir = self.dir();
        fs::create_dir_all(&dir)?;
        let tmp = self.temp_path();
        let result = (|| {
            let mut f = OpenOptions::new()
                .write(true)
                .create(true)
                .truncate(true)
                .open(&tmp)?;
            f.write_all(image)?;
            // The data must be on disk before the rename makes it the image; otherwise a power
            // loss could leave a renamed but empty file.
            f.sync_all()?;
            drop(f);
            fs::rename(&tmp, &self.path)?;
            // Make the rename itself durable.
            sync_dir(&dir)
        })();
        if result.is_err() {
            // Only our own temporary file; the previous image stays untouched.
            let _ = fs::remove_file(&tmp);
        }
        result
    }

    /// Fault injection (stored-data corruption): flips one bit in the middle of the stored
    /// image, or writes a short garbage file when nothing is stored, so the next load fails the
    /// core's check. Written atomically like a save.
    pub fn corrupt(&mut self) -> io::Result<()> {
        let mut bytes = match fs::read(&self.path) {
            Ok(b) => b,
            Err(e) if e.kind() == io::ErrorKind::NotFound => b"not a canpos image".to_vec(),
            Err(e) => return Err(e),
        };
        if !bytes.is_empty() {
            let i = bytes.len() / 2;
            bytes[i] ^= 0x10;
        }
        self.write_atomic(&bytes)
    }
}

fn sync_dir(dir: &Path) -> io::Result<()> {
    File::open(dir)?.sync_all()
}

impl Storage for FileStorage {
    fn load(&mut self, buf: &mut [u8]) -> Result<usize, StorageError> {
        // Non-blocking: opening a FIFO for reading would otherwise wait for a writer for ever.
        let mut f = match OpenOptions::new()
            .read(true)
            .custom_flags(libc::O_NONBLOCK)
            .open(&self.path)
        {
            Ok(f) => f,
            Err(e) if e.kind() == io::ErrorKind::NotFound => return Err(StorageError::Empty),
            Err(e) => {
                tracing::warn!(path = %self.path.display(), error = %e,
                    "cannot open the stored image; starting on defaults");
                return Err(StorageError::Corrupt);
            }
        };
        match f.metadata() {
            Ok(m) if m.file_type().is_file() => {}
            Ok(m) => {
                tracing::warn!(path = %self.path.display(), kind = kind_name(m.file_type()),
                    "the stored image is not a regular file; starting on defaults");
                return Err(StorageError::Corrupt);
            }
            Err(e) => {
                tracing::warn!(path = %self.path.display(), error = %e,
                    "cannot stat the stored image; starting on defaults");
                return Err(StorageError::Corrupt);
            }
        }
        // Read one byte more than any image can be, to tell "too long" from "fits".
        let mut bytes = Vec::with_capacity(IMAGE_MAX + 1);
        if let Err(e) = Read::by_ref(&mut f)
            .take((IMAGE_MAX + 1) as u64)
            .read_to_end(&mut bytes)
        {
            tracing::warn!(path = %self.path.display(), error = %e,
                "cannot read the stored image; starting on defaults");
            return Err(StorageError::Corrupt);
        }
        if bytes.len() > IMAGE_MAX || bytes.len() > buf.len() {
            tracing::warn!(path = %self.path.display(), len = bytes.len(),
                "stored image is longer than any valid image; starting on defaults");
            return Err(StorageError::Corrupt);
        }
        buf[..bytes.len()].copy_from_slice(&bytes);
        Ok(bytes.len())
    }

    fn save(&mut self, image: &[u8]) -> Result<(), StorageError> {
        match self.write_atomic(image) {
            Ok(()) => {
                self.saves += 1;
                Ok(())
            }
            Err(e) => {
                tracing::error!(path = %self.path.display(), error = %e, "store failed");
                Err(StorageError::Io)
            }
        }
    }

    fn erase(&mut self) -> Result<(), StorageError> {
        match fs::remove_file(&self.path) {
            Ok(()) => sync_dir(&self.dir()).map_err(|_| StorageError::Io),
            Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(()),
            Err(e) => {
                tracing::error!(path = %self.path.display(), error = %e, "erase failed");
                Err(StorageError::Io)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use canpos_core::storage::{parse_image, ImageWriter};

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
        let names: Vec<_> = fs::read_dir(dir.path().join("sub")).unwrap().collect();
        assert_eq!(names.len(), 1);
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
        fs::write(s.temp_path(), &new[..new.len() / 2]).unwrap();
        let mut after = FileStorage::new(dir.path().join("th-1.bin"));
        assert_eq!(load_value(&mut after), Ok(1));
        // The next save overwrites the stale temp file and succeeds.
        after.save(&image(3)).unwrap();
        assert_eq!(load_value(&mut after), Ok(3));
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

    #[test]
    fn stale_temporary_files_are_removed_at_open() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("th-1.bin");
        fs::write(dir.path().join("th-1.bin.tmp.99999"), b"half").unwrap();
        fs::write(dir.path().join("th-1.bin.tmp.12"), b"half").unwrap();
        // Not ours: another unit's temp file, and a name that only looks similar.
        fs::write(dir.path().join("th-2.bin.tmp.99999"), b"other").unwrap();
        fs::write(dir.path().join("th-1.bin.tmp.notes"), b"keep").unwrap();
        let _s = FileStorage::open(&path).unwrap();
        let mut names: Vec<_> = fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        names.sort();
        assert_eq!(
            names,
            ["th-1.bin.lock", "th-1.bin.tmp.notes", "th-2.bin.tmp.99999"]
        );
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
    }
}
