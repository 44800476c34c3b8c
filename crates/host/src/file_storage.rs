//! Non-volatile storage of a device as one file (SPEC §8).
//!
//! The core hands over a self-checking image (magic, version, model tag, CRC-32); this module
//! only keeps the bytes, and keeps them safely:
//!
//! - **save** writes a temporary file with an unpredictable name in the same directory
//!   (created with `O_CREAT | O_EXCL | O_NOFOLLOW`: never an existing file, never through a
//!   link), `fsync`s it, renames it over the image and `fsync`s the directory. `rename` is
//!   atomic within one file system, so after a crash at any point the path holds either the
//!   complete old image or the complete new one.
//! - **load** returns [`StorageError::Empty`] when there is no file, and
//!   [`StorageError::Corrupt`] with a log line naming the file and the reason when it cannot be
//!   read, is longer than any image, or fails the image's own check (length, magic, version,
//!   model tag, CRC). The device then starts on defaults and reports it (EMCY 0x6300).
//! - with the model known ([`FileStorage::for_model`]), load passes on only the records the
//!   model uses, the last of each key (a load applies them in order): records of objects the
//!   model does not store, unknown keys and repeats are dropped with one log line, so that
//!   they never fill the image and make every later save fail.
//! - nothing here ever deletes the good image on an error: a failed save removes only its own
//!   temporary file.
//! - **no link is followed in the state directory.** Every file is opened, created, renamed
//!   and removed relative to the directory's descriptor with `O_NOFOLLOW`: a symbolic link
//!   where the image or its lock file should be is refused with an error naming it, so nothing
//!   outside the state directory is ever written. (The directory itself may be reached through
//!   links: its path is the user's choice.)
//! - only a regular file is ever read: the image is opened non-blocking and checked with
//!   `fstat`, so a FIFO or device in its place is reported instead of hanging the boot.
//!
//! [`FileStorage::open`] (what the command line uses) also takes a lock: an exclusive `flock`
//! on `<image>.lock`, held as long as any clone of the storage lives, so that a second process
//! on the same state file gets a clear error instead of silently sharing it. Holding the lock, it
//! removes the `<image>.tmp.*` files that killed processes left behind (regular files only), and
//! it checks that the directory is writable before the sensor boots. It keeps the directory
//! open: a directory moved or replaced under the path later still gets no file of this unit.

use std::ffi::{OsStr, OsString};
use std::fs::{self, File, TryLockError};
use std::io::{self, Read, Seek, Write};
use std::os::fd::OwnedFd;
use std::os::unix::ffi::OsStrExt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use canpos_models::Model;
use canpos_stack::od::{Group, Hook};
use canpos_stack::storage::{
    app_record, check_image, is_object_key, parse_image, ImageFault, ImageWriter, Storage,
    StorageError, IMAGE_MAX, IMAGE_MIN, KEY_LSS_BITRATE, KEY_LSS_NODE_ID, KEY_SAVED_NODE_ID,
};
use canpos_stack::Table;
use rustix::fs::{self as rfs, AtFlags, FileType, Mode, OFlags};
use rustix::io::Errno;

/// A [`Storage`] kept in one file.
#[derive(Clone)]
pub struct FileStorage {
    path: PathBuf,
    saves: u64,
    /// The lock file, held open (and locked) while any clone lives; `None` for [`FileStorage::new`].
    lock: Option<Arc<File>>,
    /// The state directory, held open by [`FileStorage::open`]; `None`: opened by path at each
    /// use.
    dir: Option<Arc<OwnedFd>>,
    /// The model whose images these are ([`FileStorage::for_model`]).
    /// The table whose records a state file keeps (the widest unit's), and whether the
    /// application's own records are kept (CiA 406's internal preset offsets).
    model: Option<(&'static Table, bool)>,
    /// The last problem a load reported: the same one again is not logged again.
    reported: Option<String>,
}

impl std::fmt::Debug for FileStorage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FileStorage")
            .field("path", &self.path)
            .field("saves", &self.saves)
            .field("locked", &self.lock.is_some())
            .field("model", &self.model.map(|m| m.0.name))
            .finish()
    }
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
    /// Something other than a regular file is where the image or its lock file should be.
    #[error("{what} {} is not a regular file ({kind}); remove it or choose another --state-dir", path.display())]
    NotRegular {
        /// `state file` or `lock file`.
        what: &'static str,
        /// Its path.
        path: PathBuf,
        /// What it is (FIFO, directory, …).
        kind: &'static str,
    },
    /// A symbolic link is where the image or its lock file should be. It is not followed:
    /// whoever can write the state directory could otherwise make the sensor write any file
    /// its user may write.
    #[error("{what} {} is a symbolic link; canpos follows no link in a state directory and wrote nothing through it: remove it", path.display())]
    Link {
        /// `state file` or `lock file`.
        what: &'static str,
        /// The link's path.
        path: PathBuf,
    },
    /// The lock file has other names too (hard links): writing the pid into it would change a
    /// file elsewhere.
    #[error("lock file {} has {links} hard links; canpos writes only a lock file of its own: remove it", path.display())]
    HardLinked {
        /// The lock file's path.
        path: PathBuf,
        /// Its link count.
        links: u64,
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

fn kind_name(ft: FileType) -> &'static str {
    match ft {
        FileType::Directory => "a directory",
        FileType::Fifo => "a FIFO",
        FileType::Socket => "a socket",
        FileType::CharacterDevice => "a character device",
        FileType::BlockDevice => "a block device",
        FileType::Symlink => "a symbolic link",
        _ => "not a regular file",
    }
}

/// Bytes read of a held lock file for its holder's pid (a `u32` in decimal and a newline fit).
const PID_TEXT_MAX: u64 = 16;

/// Temporary names a save tries before it gives up: each is created only if no file of that
/// name exists, so a taken name (a planted link, say) costs one more try.
const TEMP_TRIES: usize = 16;

/// `<image>.tmp.<16 hex digits>`: a name nobody can guess ahead (keyed SipHash of a counter,
/// with the process's random keys), so no one can plant a file where the next save will go.
fn random_temp_name(image: &OsStr) -> OsString {
    use std::hash::{BuildHasher, Hasher};
    static COUNT: AtomicU64 = AtomicU64::new(0);
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u64(COUNT.fetch_add(1, Ordering::Relaxed));
    h.write_u32(std::process::id());
    let mut name = image.to_os_string();
    name.push(format!(".tmp.{:016x}", h.finish()));
    name
}

/// Whether `name` is a temporary file of `image` (`<image>.tmp.` and hex digits: this
/// version's random names and the `.tmp.<pid>` of earlier ones).
fn is_temp_name(image: &OsStr, name: &[u8]) -> bool {
    let mut prefix = image.as_encoded_bytes().to_vec();
    prefix.extend_from_slice(b".tmp.");
    name.strip_prefix(&prefix[..])
        .is_some_and(|s| !s.is_empty() && s.len() <= 20 && s.iter().all(u8::is_ascii_hexdigit))
}

/// Creates `name` in `dir`, only as a new file and never through a link.
fn create_new(dir: &OwnedFd, name: &OsStr) -> io::Result<File> {
    let fd = rfs::openat(
        dir,
        name,
        OFlags::WRONLY | OFlags::CREATE | OFlags::EXCL | OFlags::NOFOLLOW | OFlags::CLOEXEC,
        Mode::from_raw_mode(0o666),
    )?;
    Ok(File::from(fd))
}

/// A new temporary file in `dir`, under the first of `names` that no file has yet.
fn create_temp(
    dir: &OwnedFd,
    names: &mut dyn Iterator<Item = OsString>,
) -> io::Result<(OsString, File)> {
    let mut last = None;
    for name in names.take(TEMP_TRIES) {
        match create_new(dir, &name) {
            Ok(f) => return Ok((name, f)),
            Err(e) if e.kind() == io::ErrorKind::AlreadyExists => last = Some(name),
            Err(e) => return Err(e),
        }
    }
    Err(io::Error::new(
        io::ErrorKind::AlreadyExists,
        format!(
            "every temporary name tried exists (the last: {}); something keeps creating files in the state directory",
            last.as_deref().unwrap_or(OsStr::new("none")).to_string_lossy()
        ),
    ))
}

/// Opens the directory at `dir` (following links in its path: the user chose it).
fn open_dir(dir: &Path) -> io::Result<OwnedFd> {
    Ok(rfs::open(
        dir,
        OFlags::RDONLY | OFlags::DIRECTORY | OFlags::CLOEXEC,
        Mode::empty(),
    )?)
}

/// The file type of `name` in `dir`, the name itself (a link is a link), or `None` when there
/// is none.
fn type_at(dir: &OwnedFd, name: &OsStr) -> io::Result<Option<(FileType, u64)>> {
    match rfs::statat(dir, name, AtFlags::SYMLINK_NOFOLLOW) {
        Ok(st) => Ok(Some((FileType::from_raw_mode(st.st_mode), st.st_nlink))),
        Err(Errno::NOENT) => Ok(None),
        Err(e) => Err(e.into()),
    }
}

/// Whether the core reads or keeps a record of `key` for `model` (node.rs: `stored_entry`,
/// `load_values`, `stored_lss_config`, `change_stored`): the LSS and node-id records, and
/// the preset offsets a TMI keeps with 0x6010, and objects of the model that are stored (or
/// hold the pending node-id or bit rate).
fn record_used((widest, app_records): (&'static Table, bool), key: u32) -> bool {
    match key {
        KEY_LSS_NODE_ID | KEY_LSS_BITRATE | KEY_SAVED_NODE_ID => true,
        // The preset offsets a TMI keeps with 0x6010 (no object holds them).
        k if app_record(k).is_some() => app_records,
        // Objects of any unit of the model: a two-channel TMI's state file keeps its channel-2
        // records when the storage is opened for the model (whose default unit has one
        // channel), and a one-channel unit loading it leaves them for the other.
        k if is_object_key(k) => widest
            .search(k)
            .ok()
            .and_then(|slot| widest.entries.get(slot))
            .is_some_and(|e| {
                e.group != Group::Volatile
                    || matches!(e.hook, Hook::PendingNodeId | Hook::PendingBitRate)
            }),
        _ => false,
    }
}

/// Why an image does not pass the core's check for a model with `tag`, in words.
fn image_problem(image: &[u8], tag: u8) -> String {
    match check_image(image, tag) {
        Err(ImageFault::TooShort(len)) => {
            format!("{len} bytes, shorter than any image ({IMAGE_MIN})")
        }
        Err(ImageFault::NotAnImage) => "not a canpos state image (no CPOS mark)".into(),
        Err(ImageFault::Version(v)) => format!(
            "format version {v}, this canpos reads version {}",
            ImageFault::VERSION
        ),
        Err(ImageFault::OtherModel(t)) => {
            format!("an image of another model (tag {t}, this model's is {tag})")
        }
        Err(ImageFault::Length { len, count }) => format!(
            "{len} bytes, but its header's {count} records make {}",
            IMAGE_MIN + 8 * count
        ),
        Err(ImageFault::Crc { stored, computed }) => {
            format!("CRC mismatch (stored {stored:08X}, computed {computed:08X}): torn or altered")
        }
        Ok(_) => "refused by the image check".into(),
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
            dir: None,
            model: None,
            reported: None,
        }
    }

    /// The same storage, for images of `model`: a load then also names an image of another
    /// model as such, and passes on only the records `model` uses (see the module docs).
    pub fn for_model(mut self, model: &'static Model) -> Self {
        let widest = canpos_models::widest(model);
        self.model = Some((&widest.table, model.profile.preset_offset_internal));
        self
    }

    /// Storage for a device of `table` with no records of the application's own (an EDS device).
    pub fn for_table(mut self, table: &'static Table) -> Self {
        self.model = Some((table, false));
        self
    }

    /// Storage at `path` for a running sensor: creates the directory (reporting it when not
    /// writable), refuses anything but a regular file at `path` and at its lock file (a
    /// symbolic link included), locks `<path>.lock` against other processes and removes stale
    /// temporary files of earlier, killed processes.
    pub fn open(path: impl Into<PathBuf>) -> Result<Self, OpenError> {
        let mut s = FileStorage::new(path);
        let dir_path = s.dir_path();
        let unwritable = |source| OpenError::Unwritable {
            dir: dir_path.clone(),
            source,
        };
        fs::create_dir_all(&dir_path).map_err(unwritable)?;
        let dir = open_dir(&dir_path).map_err(unwritable)?;
        if let Ok(st) = rfs::fstat(&dir) {
            // Sticky (as /tmp): others cannot remove or rename this unit's files.
            if st.st_mode & 0o1002 == 0o002 {
                tracing::warn!(dir = %dir_path.display(), mode = format!("{:o}", st.st_mode & 0o7777),
                    "the state directory is writable by every user: any of them can replace its state files");
            }
        }
        let name = s.name().map_err(unwritable)?.to_os_string();
        match type_at(&dir, &name).map_err(unwritable)? {
            Some((FileType::RegularFile, _)) | None => {}
            Some((FileType::Symlink, _)) => {
                return Err(OpenError::Link {
                    what: "state file",
                    path: s.path.clone(),
                })
            }
            Some((ft, _)) => {
                return Err(OpenError::NotRegular {
                    what: "state file",
                    path: s.path.clone(),
                    kind: kind_name(ft),
                })
            }
        }
        let mut lock = s.open_lock(&dir).map_err(|e| match e {
            LockOpen::Refused(e) => e,
            LockOpen::Io(e) => unwritable(e),
        })?;
        match lock.try_lock() {
            Ok(()) => {}
            Err(TryLockError::WouldBlock) => {
                // A pid and its newline: a few bytes. The file is someone else's while they
                // hold it, so no more than that is read, whatever its length.
                let mut text = String::new();
                let _ = (&mut lock).take(PID_TEXT_MAX).read_to_string(&mut text);
                return Err(OpenError::InUse {
                    path: s.path.clone(),
                    holder: text
                        .split(|c: char| !c.is_ascii_digit())
                        .next()
                        .and_then(|pid| pid.parse().ok()),
                });
            }
            Err(TryLockError::Error(e)) => return Err(unwritable(e)),
        }
        // For the "in use" message of a second process; the lock is what counts. The file is
        // our own regular file with one name (checked on its descriptor).
        let _ = lock.set_len(0);
        let _ = lock.rewind();
        let _ = writeln!(lock, "{}", std::process::id());
        // Probe that the directory takes new files (a read-only directory would only show at
        // the first store, long after the boot).
        let (probe, f) = create_temp(
            &dir,
            &mut std::iter::repeat_with(|| random_temp_name(&name)),
        )
        .map_err(unwritable)?;
        drop(f);
        let _ = rfs::unlinkat(&dir, &probe, AtFlags::empty());
        let dir = Arc::new(dir);
        s.dir = Some(Arc::clone(&dir));
        s.remove_stale_temps(&dir);
        s.lock = Some(Arc::new(lock));
        Ok(s)
    }

    /// Opens (creating it if need be) `<image>.lock` in `dir`: never through a link, only a
    /// regular file with no other name.
    fn open_lock(&self, dir: &OwnedFd) -> Result<File, LockOpen> {
        let mut name = self.name().map_err(LockOpen::Io)?.to_os_string();
        name.push(".lock");
        let path = self.path.with_file_name(&name);
        let refuse = |ft: FileType, links: u64| match ft {
            FileType::RegularFile if links <= 1 => Ok(()),
            FileType::RegularFile => Err(LockOpen::Refused(OpenError::HardLinked {
                path: path.clone(),
                links,
            })),
            FileType::Symlink => Err(LockOpen::Refused(OpenError::Link {
                what: "lock file",
                path: path.clone(),
            })),
            ft => Err(LockOpen::Refused(OpenError::NotRegular {
                what: "lock file",
                path: path.clone(),
                kind: kind_name(ft),
            })),
        };
        // Looked at before it is opened: a device or FIFO is not even opened.
        if let Some((ft, links)) = type_at(dir, &name).map_err(LockOpen::Io)? {
            refuse(ft, links)?;
        }
        let fd = match rfs::openat(
            dir,
            &name,
            OFlags::RDWR
                | OFlags::CREATE
                | OFlags::NOFOLLOW
                | OFlags::NONBLOCK
                | OFlags::NOCTTY
                | OFlags::CLOEXEC,
            Mode::from_raw_mode(0o666),
        ) {
            Ok(fd) => fd,
            // Made a link since the look above.
            Err(Errno::LOOP) => return Err(refuse(FileType::Symlink, 1).unwrap_err()),
            Err(e) => return Err(LockOpen::Io(e.into())),
        };
        // And what was opened is checked again, on its descriptor.
        let st = rfs::fstat(&fd).map_err(|e| LockOpen::Io(e.into()))?;
        refuse(FileType::from_raw_mode(st.st_mode), st.st_nlink)?;
        Ok(File::from(fd))
    }

    /// The image's file name.
    fn name(&self) -> io::Result<&OsStr> {
        self.path.file_name().ok_or_else(|| {
            io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("{} names no file", self.path.display()),
            )
        })
    }

    /// Removes `<image>.tmp.*` left by killed processes: regular files only, looked at
    /// without following links. Only called with the lock held: no other process is writing
    /// this image, so every such file is stale.
    fn remove_stale_temps(&self, dir: &OwnedFd) {
        let Ok(name) = self.name() else { return };
        let Ok(entries) = rfs::Dir::read_from(dir) else {
            return;
        };
        for e in entries.flatten() {
            let entry = OsStr::from_bytes(e.file_name().to_bytes());
            if !is_temp_name(name, entry.as_encoded_bytes()) {
                continue;
            }
            let file = self.path.with_file_name(entry);
            match type_at(dir, entry) {
                Ok(Some((FileType::RegularFile, _))) => {
                    match rfs::unlinkat(dir, entry, AtFlags::empty()) {
                        Ok(()) => {
                            tracing::info!(file = %file.display(), "removed a stale temporary state file")
                        }
                        Err(err) => {
                            tracing::warn!(file = %file.display(), error = %err, "cannot remove a stale temporary state file")
                        }
                    }
                }
                Ok(Some((ft, _))) => {
                    tracing::warn!(file = %file.display(), kind = kind_name(ft),
                        "not a regular file where a temporary state file would be: left alone, never followed or written")
                }
                Ok(None) | Err(_) => {}
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

    fn dir_path(&self) -> PathBuf {
        match self.path.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        }
    }

    /// The state directory's descriptor: the one held since [`FileStorage::open`], else the
    /// directory opened now (created first when `create`).
    fn dir(&self, create: bool) -> io::Result<Arc<OwnedFd>> {
        if let Some(d) = &self.dir {
            return Ok(Arc::clone(d));
        }
        let path = self.dir_path();
        if create {
            fs::create_dir_all(&path)?;
        }
        open_dir(&path).map(Arc::new)
    }

    /// Writes `image` atomically (see the module docs).
    pub fn write_atomic(&self, image: &[u8]) -> io::Result<()> {
        let name = self.name()?.to_os_string();
        self.write_atomic_via(
            image,
            &mut std::iter::repeat_with(|| random_temp_name(&name)),
        )
    }

    /// [`FileStorage::write_atomic`] through the first free one of `temp_names`.
    fn write_atomic_via(
        &self,
        image: &[u8],
        temp_names: &mut dyn Iterator<Item = OsString>,
    ) -> io::Result<()> {
        let name = self.name()?;
        let dir = self.dir(true)?;
        let (tmp, mut f) = create_temp(&dir, temp_names)?;
        let result = (|| {
            f.write_all(image)?;
            // The data must be on disk before the rename makes it the image; otherwise a power
            // loss could leave a renamed but empty file.
            f.sync_all()?;
            // rename replaces the name itself, whatever it is (a link included): it writes into
            // no other file.
            rfs::renameat(&*dir, &tmp, &*dir, name)?;
            // Make the rename itself durable.
            Ok(rfs::fsync(&*dir)?)
        })();
        if result.is_err() {
            // Only our own temporary file; the previous image stays untouched.
            let _ = rfs::unlinkat(&*dir, &tmp, AtFlags::empty());
        }
        result
    }

    /// The stored bytes (at most `IMAGE_MAX + 1`: enough to tell "too long"); `Ok(None)` when
    /// there is no file. Never through a link, never blocking on a FIFO.
    fn read_bytes(&self) -> Result<Option<Vec<u8>>, String> {
        let dir = match self.dir(false) {
            Ok(d) => d,
            Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(format!("cannot open its directory: {e}")),
        };
        let name = self.name().map_err(|e| e.to_string())?;
        // Non-blocking: opening a FIFO for reading would otherwise wait for a writer for ever.
        let fd = match rfs::openat(
            &*dir,
            name,
            OFlags::RDONLY | OFlags::NONBLOCK | OFlags::NOFOLLOW | OFlags::NOCTTY | OFlags::CLOEXEC,
            Mode::empty(),
        ) {
            Ok(fd) => fd,
            Err(Errno::NOENT) => return Ok(None),
            Err(Errno::LOOP) => return Err("it is a symbolic link; not followed".into()),
            Err(e) => return Err(format!("cannot open it: {}", io::Error::from(e))),
        };
        match rfs::fstat(&fd) {
            Ok(st) => match FileType::from_raw_mode(st.st_mode) {
                FileType::RegularFile => {}
                ft => return Err(format!("it is not a regular file ({})", kind_name(ft))),
            },
            Err(e) => return Err(format!("cannot stat it: {}", io::Error::from(e))),
        }
        // Read one byte more than any image can be, to tell "too long" from "fits".
        let mut bytes = Vec::with_capacity(IMAGE_MAX + 1);
        File::from(fd)
            .take((IMAGE_MAX + 1) as u64)
            .read_to_end(&mut bytes)
            .map_err(|e| format!("cannot read it: {e}"))?;
        Ok(Some(bytes))
    }

    /// Logs a load's problem once (the same one at the next load stays quiet).
    fn report(&mut self, why: String) {
        if self.reported.as_ref() != Some(&why) {
            tracing::warn!(path = %self.path.display(), reason = %why,
                "the stored image cannot be used; starting on defaults");
            self.reported = Some(why);
        }
    }

    /// What the last load found wrong with the file (a link, not a regular file, unreadable, a
    /// failed check, records dropped), in words; `None` after a clean load or none yet.
    pub fn problem(&self) -> Option<&str> {
        self.reported.as_deref()
    }

    /// Fault injection (stored-data corruption): flips one bit in the middle of the stored
    /// image, or writes a short garbage file when nothing is stored, so the next load fails the
    /// core's check. Written atomically like a save.
    pub fn corrupt(&mut self) -> io::Result<()> {
        let mut bytes = self
            .read_bytes()
            .map_err(io::Error::other)?
            .unwrap_or_else(|| b"not a canpos image".to_vec());
        if !bytes.is_empty() {
            let i = bytes.len() / 2;
            bytes[i] ^= 0x10;
        }
        self.write_atomic(&bytes)
    }
}

/// Why the lock file could not be opened: refused for what it is, or an I/O error.
enum LockOpen {
    Refused(OpenError),
    Io(io::Error),
}

impl Storage for FileStorage {
    fn load(&mut self, buf: &mut [u8]) -> Result<usize, StorageError> {
        let bytes = match self.read_bytes() {
            Ok(Some(b)) => b,
            Ok(None) => {
                self.reported = None;
                return Err(StorageError::Empty);
            }
            Err(why) => {
                self.report(why);
                return Err(StorageError::Corrupt);
            }
        };
        if bytes.len() > IMAGE_MAX || bytes.len() > buf.len() {
            self.report(format!(
                "longer than any valid image ({} bytes at most)",
                IMAGE_MAX.min(buf.len())
            ));
            return Err(StorageError::Corrupt);
        }
        // The core checks the image again; checked here too, to say why it failed (the core's
        // answer is only EMCY 0x6300). Without a model, the image's own tag is taken.
        let tag = match (self.model, bytes.get(5)) {
            (Some(m), _) => m.0.features.tag,
            (None, Some(&t)) => t,
            (None, None) => 0,
        };
        let records = match parse_image(&bytes, tag) {
            Ok(r) => r,
            Err(_) => {
                self.report(image_problem(&bytes, tag));
                return Err(StorageError::Corrupt);
            }
        };
        let Some(model) = self.model else {
            self.reported = None;
            buf[..bytes.len()].copy_from_slice(&bytes);
            return Ok(bytes.len());
        };
        // The records the model uses, the last of each key (what a load of the core applies).
        let all: Vec<(u32, u32)> = records.collect();
        let kept: Vec<(u32, u32)> = all
            .iter()
            .enumerate()
            .filter(|&(i, &(k, _))| record_used(model, k) && !all[i + 1..].iter().any(|r| r.0 == k))
            .map(|(_, &r)| r)
            .collect();
        if kept.len() == all.len() {
            self.reported = None;
            buf[..bytes.len()].copy_from_slice(&bytes);
            return Ok(bytes.len());
        }
        let why = format!(
            "{} of its {} records name nothing the {} stores or repeat a key; ignored, and the next save leaves them out",
            all.len() - kept.len(),
            all.len(),
            model.0.name
        );
        if self.reported.as_ref() != Some(&why) {
            tracing::warn!(path = %self.path.display(), "{why}");
            self.reported = Some(why);
        }
        let mut w = ImageWriter::new(buf, tag);
        for (k, v) in kept {
            // Fewer records than the image held: they fit.
            w.push(k, v);
        }
        Ok(w.finish())
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
        let result = (|| {
            let dir = match self.dir(false) {
                Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(()),
                d => d?,
            };
            match rfs::unlinkat(&*dir, self.name()?, AtFlags::empty()) {
                // unlink removes the name (a link's too), never what a link points at.
                Ok(()) => Ok(rfs::fsync(&*dir)?),
                Err(Errno::NOENT) => Ok(()),
                Err(e) => Err(io::Error::from(e)),
            }
        })();
        result.map_err(|e| {
            tracing::error!(path = %self.path.display(), error = %e, "erase failed");
            StorageError::Io
        })
    }
}

#[cfg(test)]
mod tests;
