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

use std::fs::{self, File, OpenOptions};
use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};

use canpos_core::storage::{Storage, StorageError, IMAGE_MAX};

/// A [`Storage`] kept in one file.
#[derive(Clone, Debug)]
pub struct FileStorage {
    path: PathBuf,
    saves: u64,
}

impl FileStorage {
    /// Storage at `path`. The file need not exist; its directory is created at the first save.
    pub fn new(path: impl Into<PathBuf>) -> Self {
        FileStorage {
            path: path.into(),
            saves: 0,
        }
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
        let mut name = self
            .path
            .file_name()
            .map(|n| n.to_os_string())
            .unwrap_or_default();
        name.push(format!(".tmp.{}", std::process::id()));
        self.path.with_file_name(name)
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
        let mut f = match File::open(&self.path) {
            Ok(f) => f,
            Err(e) if e.kind() == io::ErrorKind::NotFound => return Err(StorageError::Empty),
            Err(e) => {
                tracing::warn!(path = %self.path.display(), error = %e,
                    "cannot open the stored image; starting on defaults");
                return Err(StorageError::Corrupt);
            }
        };
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
