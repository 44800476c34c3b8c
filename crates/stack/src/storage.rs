//! Non-volatile storage (CiA 301 0x1010 / 0x1011, CiA 305 "store configuration").
//!
//! The core serialises what must survive a power cycle into one self-checking image; a
//! [`Storage`] implementation (a file on the host, a flash page on a microcontroller) only keeps
//! the bytes. Image layout (all little-endian):
//!
//! ```text
//! magic "CPOS" · version u8 · model tag u8 · record count u16 · records · CRC-32 of all before
//! record = key u32 (index << 8 | sub, an LSS or bookkeeping key, or an application key) · value u32
//! ```
//!
//! A torn or corrupt image fails its CRC and is never loaded.

use crate::lss::UNCONFIGURED;
use crate::nmt::NmtState;
use crate::od::{Abort, Entry, Group};

/// Largest image any model produces (header + records + CRC).
pub const IMAGE_MAX: usize = 8 + 8 * RECORDS_MAX + 4;

/// Bytes of an image without records: the header (mark, version, model tag, count) and the CRC.
pub const IMAGE_MIN: usize = 8 + 4;

use crate::config::RECORDS_MAX;

const MAGIC: &[u8; 4] = b"CPOS";
const VERSION: u8 = 1;

/// Record key of the LSS-configured node-id (outside the index space).
pub const KEY_LSS_NODE_ID: u32 = 0xFF00_0001;
/// Record key of the LSS-configured bit rate (kbit/s).
pub const KEY_LSS_BITRATE: u32 = 0xFF00_0002;

/// Record key of the node-id that was active when the parameters were saved, so that a later
/// power-on under another node-id re-derives exactly the COB-IDs that were the pre-defined
/// ones for it (D15).
pub const KEY_SAVED_NODE_ID: u32 = 0xFF00_0003;

/// Record key of the application's first value of its own ([`app_key`]).
pub const KEY_APP: u32 = 0xFF00_0100;

pub use crate::config::APP_RECORDS;

/// Record key of the application's value `k` (< [`APP_RECORDS`]): stored with the application
/// parameters ([`crate::app::Application::stored_value`]).
pub const fn app_key(k: usize) -> u32 {
    KEY_APP + k as u32
}

/// The application value a record key names, if it names one.
pub const fn app_record(key: u32) -> Option<usize> {
    let k = key.wrapping_sub(KEY_APP) as usize;
    if k < APP_RECORDS {
        Some(k)
    } else {
        None
    }
}

/// Whether a record key names an object (`index << 8 | sub`) rather than an LSS or
/// bookkeeping value.
pub const fn is_object_key(key: u32) -> bool {
    key <= 0x00FF_FFFF
}

/// What a store or a restore covers: the CiA 301 0x1010 / 0x1011 sub-indices, or the values
/// the device keeps by itself. Membership comes from each entry's [`Group`] in the model's
/// table, so no index list decides it. Each scope's discriminant is the set of groups it
/// covers (bit `group as u32`), so that [`Scope::covers`] is one AND.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u32)]
pub enum Scope {
    /// Sub 1: every parameter.
    All = group_bit(Group::Comm) | group_bit(Group::App),
    /// Sub 2: the communication parameters.
    Comm = group_bit(Group::Comm),
    /// Sub 3: the application parameters.
    App = group_bit(Group::App),
    /// The values the device stores whenever they change ([`Group::Auto`]); "save" and
    /// "load" leave them alone, they are records of the unit, not parameters.
    Auto = group_bit(Group::Auto),
}

/// `g`'s bit in a [`Scope`]'s set of groups.
const fn group_bit(g: Group) -> u32 {
    1 << g as u32
}

impl Scope {
    /// The scope of 0x1010 / 0x1011 sub-index `sub` (sub 1 and any other: all).
    pub const fn of_sub(sub: u8) -> Scope {
        match sub {
            2 => Scope::Comm,
            3 => Scope::App,
            _ => Scope::All,
        }
    }

    /// Whether `e`'s value belongs to this scope.
    pub const fn covers(self, e: &Entry) -> bool {
        self as u32 & group_bit(e.group) != 0
    }

    /// Whether this scope covers the application's values of its own ([`app_key`]), which
    /// belong to the application parameters.
    pub const fn covers_app_values(self) -> bool {
        self as u32 & group_bit(Group::App) != 0
    }
}

/// "save" signature (0x1010).
pub const SIG_SAVE: u32 = 0x6576_6173;
/// "load" signature (0x1011).
pub const SIG_LOAD: u32 = 0x6461_6F6C;
/// "kill" as ASCII bytes on the wire (D23).
pub const SIG_KILL_ASCII: u32 = 0x6C6C_696B;
/// "kill" as the TMI manual prints it (D23).
pub const SIG_KILL_MANUAL: u32 = 0x6B69_6C6C;

/// A change of the stored image: what a "save", "load" or "kill" ([`command`]), the automatic
/// store or LSS "store configuration" asks for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Change {
    /// "save" (0x1010) of a scope, or the automatic store ([`Scope::Auto`]).
    Save(Scope),
    /// "load" (0x1011) of a scope, or "kill": forgets what was stored for it (the LSS
    /// configuration and records of entries outside the scope stay, records this model has no
    /// entry for go); defaults apply at the next reset (D7).
    Forget(Scope),
    /// LSS "store configuration".
    Lss,
}

/// The change a write of `raw` to sub `sub` of 0x1010 (`save`) or 0x1011 asks for, or why it
/// is refused: "save" stores and "load" forgets (a wrong signature: 0x08000020); "kill", where
/// the model has it (`kill_signature`, D23), forgets through 0x1010; a model that stores in
/// pre-operational only (`store_preop_only`, the TMI) refuses "save" and "kill" in any other
/// state (0x08000022).
#[inline]
pub(crate) fn command(
    save: bool,
    sub: u8,
    raw: u32,
    kill_signature: bool,
    store_preop_only: bool,
    nmt: NmtState,
) -> Result<Change, Abort> {
    let scope = Scope::of_sub(sub);
    if !save {
        return if raw == SIG_LOAD {
            Ok(Change::Forget(scope))
        } else {
            Err(Abort::CannotStore)
        };
    }
    let kill = kill_signature && (raw == SIG_KILL_ASCII || raw == SIG_KILL_MANUAL);
    if raw != SIG_SAVE && !kill {
        return Err(Abort::CannotStore);
    }
    if store_preop_only && nmt != NmtState::PreOperational {
        return Err(Abort::WrongState);
    }
    Ok(if kill {
        Change::Forget(scope)
    } else {
        Change::Save(scope)
    })
}

/// A stored node-id if it is one a node may have (1…127, or [`UNCONFIGURED`]).
#[inline]
pub(crate) fn stored_node_id(v: u32) -> Option<u8> {
    ((1..=127).contains(&v) || v == u32::from(UNCONFIGURED)).then_some(v as u8)
}

/// A stored value of `e` as it applies under node-id `node` (D15): a COB-ID whose CAN-ID was the
/// pre-defined one (`base + node-id`) for the node-id it was saved under moves to this node's,
/// keeping its other bits; any other value stays as stored. Images without the saved node-id
/// ([`KEY_SAVED_NODE_ID`], written before it was recorded) keep the earlier rule: a CAN-ID in
/// the pre-defined range of another node-id follows.
#[inline]
pub(crate) fn follow_node_id(e: &Entry, v: u32, saved: Option<u8>, node: u8) -> u32 {
    let crate::od::DefaultValue::NodeId(base) = e.default else {
        return v;
    };
    // The default's flag bits (e.g. "not valid") are no part of the CAN-ID.
    let base = base & 0x7FF;
    let id = v & 0x7FF;
    let ours = base + node as u32;
    let follows = match saved {
        Some(old) => id == base + old as u32,
        None => id > base && id <= base + 0x7F,
    };
    if follows && node != UNCONFIGURED && id != ours {
        (v & !0x7FF) | ours
    } else {
        v
    }
}

/// Why the storage medium could not do what was asked.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StorageError {
    /// Nothing has been stored yet.
    Empty,
    /// The stored bytes are torn or corrupt (bad magic, version, length or checksum).
    Corrupt,
    /// The medium failed (I/O error, flash write error).
    Io,
}

/// A place to keep one image across power cycles. Implementations write atomically: after a
/// crash during `save`, `load` returns either the old or the new image.
pub trait Storage {
    /// Reads the stored image into `buf`, returning its length.
    fn load(&mut self, buf: &mut [u8]) -> Result<usize, StorageError>;
    /// Replaces the stored image.
    fn save(&mut self, image: &[u8]) -> Result<(), StorageError>;
    /// Deletes the stored image.
    fn erase(&mut self) -> Result<(), StorageError>;
}

/// Storage that keeps nothing (a unit with no non-volatile memory, or tests).
#[derive(Debug, Default, Clone, Copy)]
pub struct NoStorage;

impl Storage for NoStorage {
    fn load(&mut self, _buf: &mut [u8]) -> Result<usize, StorageError> {
        Err(StorageError::Empty)
    }
    fn save(&mut self, _image: &[u8]) -> Result<(), StorageError> {
        Err(StorageError::Io)
    }
    fn erase(&mut self) -> Result<(), StorageError> {
        Ok(())
    }
}

/// Storage in RAM: survives resets and simulated power cycles of the node that owns it. Used by
/// tests and as the MCU-independent reference.
#[derive(Clone)]
pub struct RamStorage {
    buf: [u8; IMAGE_MAX],
    len: Option<usize>,
    /// Number of completed saves (tests look at it).
    pub saves: u32,
    /// When set, every save fails (fault injection).
    pub fail: bool,
}

impl core::default::Default for RamStorage {
    fn default() -> Self {
        RamStorage {
            buf: [0; IMAGE_MAX],
            len: None,
            saves: 0,
            fail: false,
        }
    }
}

impl RamStorage {
    /// Flips one bit of the stored image (fault injection: stored-data corruption).
    pub fn corrupt(&mut self) {
        if let Some(n) = self.len {
            if n > 0 {
                self.buf[n / 2] ^= 0x10;
            }
        }
    }
}

impl Storage for RamStorage {
    fn load(&mut self, buf: &mut [u8]) -> Result<usize, StorageError> {
        let n = self.len.ok_or(StorageError::Empty)?;
        if buf.len() < n {
            return Err(StorageError::Corrupt);
        }
        buf[..n].copy_from_slice(&self.buf[..n]);
        Ok(n)
    }
    fn save(&mut self, image: &[u8]) -> Result<(), StorageError> {
        if self.fail || image.len() > self.buf.len() {
            return Err(StorageError::Io);
        }
        self.buf[..image.len()].copy_from_slice(image);
        self.len = Some(image.len());
        self.saves += 1;
        Ok(())
    }
    fn erase(&mut self) -> Result<(), StorageError> {
        if self.fail {
            return Err(StorageError::Io);
        }
        self.len = None;
        Ok(())
    }
}

/// Builds an image in a caller-provided buffer.
pub struct ImageWriter<'a> {
    buf: &'a mut [u8],
    len: usize,
    count: u16,
}

impl<'a> ImageWriter<'a> {
    /// Starts an image for the model with `model_tag`. `buf` must hold [`IMAGE_MAX`] bytes.
    pub fn new(buf: &'a mut [u8], model_tag: u8) -> Self {
        buf[..4].copy_from_slice(MAGIC);
        buf[4] = VERSION;
        buf[5] = model_tag;
        buf[6] = 0;
        buf[7] = 0;
        ImageWriter {
            buf,
            len: 8,
            count: 0,
        }
    }

    /// Appends one record; returns false when the buffer is full.
    // One window for the record and the CRC that must still fit after it: one bounds check.
    pub fn push(&mut self, key: u32, value: u32) -> bool {
        let Some(window) = self
            .buf
            .get_mut(self.len..)
            .and_then(<[u8]>::first_chunk_mut::<12>)
        else {
            return false;
        };
        let (rec, _crc) = window.split_at_mut(8);
        rec[..4].copy_from_slice(&key.to_le_bytes());
        rec[4..].copy_from_slice(&value.to_le_bytes());
        self.len += 8;
        self.count += 1;
        true
    }

    /// Seals the image with its count and CRC; returns its length.
    pub fn finish(self) -> usize {
        let (body, crc) = self.buf.split_at_mut(self.len);
        body[6..8].copy_from_slice(&self.count.to_le_bytes());
        crc[..4].copy_from_slice(&crc32(body).to_le_bytes());
        self.len + 4
    }
}

/// Checks an image and iterates over its records.
pub fn parse_image(
    image: &[u8],
    model_tag: u8,
) -> Result<impl Iterator<Item = (u32, u32)> + Clone + '_, StorageError> {
    parse_records(image, model_tag)
}

/// Why an image fails its check ([`check_image`]), in the order the checks are made.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ImageFault {
    /// Shorter than an image without records (this many bytes).
    TooShort(usize),
    /// No `CPOS` mark: not a state image.
    NotAnImage,
    /// An image format this build does not read (its version).
    Version(u8),
    /// An image of another model (its tag).
    OtherModel(u8),
    /// Its length does not match the record count in its header.
    Length {
        /// The image's length.
        len: usize,
        /// The header's record count.
        count: usize,
    },
    /// The CRC does not match: torn or altered.
    Crc {
        /// The CRC stored in the image.
        stored: u32,
        /// The CRC of its bytes.
        computed: u32,
    },
}

impl ImageFault {
    /// The image format version this build reads and writes.
    pub const VERSION: u8 = VERSION;
}

/// Checks an image for a model with `model_tag`: its length, mark, version, tag, record count
/// and CRC. `Ok` holds the length of the header and records (the CRC follows them).
///
/// Inlined so that a firmware's `parse_image`, which drops the fault, keeps only the tests
/// (out of line the fault's values would cost a firmware flash: docs/FIRMWARE.md).
#[inline]
pub fn check_image(image: &[u8], model_tag: u8) -> Result<usize, ImageFault> {
    if image.len() < IMAGE_MIN {
        return Err(ImageFault::TooShort(image.len()));
    }
    if &image[..4] != MAGIC {
        return Err(ImageFault::NotAnImage);
    }
    if image[4] != VERSION {
        return Err(ImageFault::Version(image[4]));
    }
    if image[5] != model_tag {
        return Err(ImageFault::OtherModel(image[5]));
    }
    let count = u16::from_le_bytes([image[6], image[7]]) as usize;
    let body = 8 + count * 8;
    if image.len() != body + 4 {
        return Err(ImageFault::Length {
            len: image.len(),
            count,
        });
    }
    let stored = u32::from_le_bytes([
        image[body],
        image[body + 1],
        image[body + 2],
        image[body + 3],
    ]);
    let computed = crc32(&image[..body]);
    if stored != computed {
        return Err(ImageFault::Crc { stored, computed });
    }
    Ok(body)
}

/// [`parse_image`], its records as they lie in the image.
fn parse_records(image: &[u8], model_tag: u8) -> Result<Records<'_>, StorageError> {
    let body = check_image(image, model_tag).map_err(|_| StorageError::Corrupt)?;
    Ok(Records(&image[8..body]))
}

/// The records of a checked image, walked record by record: each step splits one 8-byte
/// record off the front, so no index is computed or bounds-checked per record.
#[derive(Clone)]
struct Records<'a>(&'a [u8]);

impl Iterator for Records<'_> {
    type Item = (u32, u32);

    fn next(&mut self) -> Option<(u32, u32)> {
        let (rec, rest) = self.0.split_first_chunk::<8>()?;
        self.0 = rest;
        let [k0, k1, k2, k3, v0, v1, v2, v3] = *rec;
        Some((
            u32::from_le_bytes([k0, k1, k2, k3]),
            u32::from_le_bytes([v0, v1, v2, v3]),
        ))
    }
}

/// Loads the stored image into `buf` and checks it: its records, or why there are none.
#[inline(always)] // only names `load_records`' answer for the public interface
pub fn load_image<'a, S: Storage>(
    st: &mut S,
    model_tag: u8,
    buf: &'a mut [u8; IMAGE_MAX],
) -> Result<impl Iterator<Item = (u32, u32)> + Clone + 'a, StorageError> {
    load_records(st, model_tag, buf)
}

/// [`load_image`], its records as they lie in `buf`. Out of line: every loader and every
/// change of the image share it.
#[inline(never)]
fn load_records<'a, S: Storage>(
    st: &mut S,
    model_tag: u8,
    buf: &'a mut [u8; IMAGE_MAX],
) -> Result<Records<'a>, StorageError> {
    let n = st.load(buf)?;
    parse_records(&buf[..n], model_tag)
}

/// The one way the stored image changes: `put` writes the new records, the stored records for
/// which `replaced` holds are dropped, and every other stored record stays. `replaced` must
/// hold for every key `put` writes, so that no key is stored twice; `put` answers false when
/// a record did not fit (see [`ImageWriter::push`]). A stored image that fails its check counts
/// as empty (it could not be loaded anyway).
///
/// The new image is built in the buffer the old one was loaded into (one [`IMAGE_MAX`] buffer
/// of stack, which matters on a microcontroller): the kept records are compacted to the front,
/// in their stored order, and the new ones follow them. Nothing is saved when they do not all
/// fit. The rule and the writing come as trait objects, so that every kind of store can share
/// one copy of the code. Its callers are kept out of line instead of it (the node's one
/// caller has it and the closures inlined), so that the buffer is on the stack only while a
/// change runs.
#[inline]
pub fn change_image<S: Storage>(
    st: &mut S,
    model_tag: u8,
    replaced: &dyn Fn(u32) -> bool,
    put: &mut dyn FnMut(&mut ImageWriter<'_>) -> bool,
) -> Result<(), StorageError> {
    let mut buf = [0u8; IMAGE_MAX];
    // The stored records, if the image passes its check, are the `old` bytes after the header.
    let old = load_records(st, model_tag, &mut buf).map_or(0, |recs| recs.0.len());
    let mut kept = 0;
    // Records only move towards the front here, so copying in place is safe.
    let (recs, _) = buf[8..8 + old].as_chunks_mut::<8>();
    for at in 0..recs.len() {
        let [k0, k1, k2, k3, ..] = recs[at];
        if !replaced(u32::from_le_bytes([k0, k1, k2, k3])) {
            recs[kept] = recs[at];
            kept += 1;
        }
    }
    let mut w = ImageWriter::new(&mut buf, model_tag);
    w.len += 8 * kept;
    w.count += kept as u16;
    if !put(&mut w) {
        return Err(StorageError::Io);
    }
    debug_assert!(
        Records(&w.buf[8 + 8 * kept..w.len]).all(|(k, _)| replaced(k)),
        "a record would be stored twice"
    );
    let n = w.finish();
    st.save(&buf[..n])
}

/// [`change_image`] with the new records from an iterator (out of line, for the buffer's sake).
#[inline(never)]
pub fn update_image<S: Storage>(
    st: &mut S,
    model_tag: u8,
    replaced: &dyn Fn(u32) -> bool,
    put: &mut dyn Iterator<Item = (u32, u32)>,
) -> Result<(), StorageError> {
    change_image(st, model_tag, replaced, &mut |w| {
        for (k, v) in &mut *put {
            if !w.push(k, v) {
                return false;
            }
        }
        true
    })
}

/// CRC-32 (IEEE 802.3, reflected, as zlib). Bitwise: images are small and stores are rare.
#[inline(never)] // stores and loads share one copy
pub fn crc32(data: &[u8]) -> u32 {
    let mut crc = 0xFFFF_FFFFu32;
    for &b in data {
        crc ^= b as u32;
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 0x1010 / 0x1011 by signature and state: "save" stores, "load" forgets, "kill" forgets
    /// where the model has it, and a store-in-pre-operational model refuses "save" and "kill"
    /// elsewhere (but not "load").
    #[test]
    fn store_and_restore_commands_by_signature_and_state() {
        use NmtState::{Operational as Op, PreOperational as PreOp};
        let wrong = Err(Abort::CannotStore);
        // (save, sub, raw, kill_signature, store_preop_only, state) → answer
        let cases = [
            (
                (true, 1, SIG_SAVE, false, false, Op),
                Ok(Change::Save(Scope::All)),
            ),
            (
                (true, 2, SIG_SAVE, false, false, Op),
                Ok(Change::Save(Scope::Comm)),
            ),
            ((true, 3, SIG_LOAD, false, false, PreOp), wrong),
            ((true, 1, SIG_KILL_ASCII, false, false, PreOp), wrong),
            (
                (true, 3, SIG_KILL_ASCII, true, false, Op),
                Ok(Change::Forget(Scope::App)),
            ),
            (
                (true, 1, SIG_KILL_MANUAL, true, true, PreOp),
                Ok(Change::Forget(Scope::All)),
            ),
            ((true, 1, SIG_SAVE, true, true, Op), Err(Abort::WrongState)),
            (
                (true, 1, SIG_KILL_MANUAL, true, true, Op),
                Err(Abort::WrongState),
            ),
            ((true, 1, 0, true, true, Op), wrong),
            (
                (false, 2, SIG_LOAD, true, true, Op),
                Ok(Change::Forget(Scope::Comm)),
            ),
            ((false, 1, SIG_SAVE, false, false, PreOp), wrong),
            ((false, 1, SIG_KILL_ASCII, true, false, PreOp), wrong),
        ];
        for ((save, sub, raw, kill, preop, nmt), want) in cases {
            let got = command(save, sub, raw, kill, preop, nmt);
            assert_eq!(got, want, "{save} {sub} {raw:#X} {kill} {preop} {nmt:?}");
        }
    }

    /// The group bitsets answer as the table they replace: each scope covers exactly its
    /// groups, the volatile one is in none.
    #[test]
    fn each_scope_covers_exactly_its_groups() {
        use crate::od::{Access, DataType, DefaultValue, Range};
        let groups = [Group::Volatile, Group::Comm, Group::App, Group::Auto];
        for scope in [Scope::All, Scope::Comm, Scope::App, Scope::Auto] {
            for g in groups {
                let e = Entry::build(
                    0x2000,
                    0,
                    "x",
                    DataType::Unsigned8,
                    Access::Rw,
                    false,
                    DefaultValue::Const(0),
                    &Range::Any,
                    g,
                );
                let expected = matches!(
                    (scope, g),
                    (Scope::All, Group::Comm | Group::App)
                        | (Scope::Comm, Group::Comm)
                        | (Scope::App, Group::App)
                        | (Scope::Auto, Group::Auto)
                );
                assert_eq!(scope.covers(&e), expected, "{scope:?} / {g:?}");
            }
        }
    }

    #[test]
    fn crc32_check_value() {
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
    }

    #[test]
    fn image_round_trip_and_corruption() {
        let mut buf = [0u8; IMAGE_MAX];
        let mut w = ImageWriter::new(&mut buf, 3);
        assert!(w.push(0x0010_1700, 100));
        assert!(w.push(KEY_LSS_NODE_ID, 5));
        let n = w.finish();
        let recs: [(u32, u32); 2] = {
            let mut it = parse_image(&buf[..n], 3).unwrap();
            [it.next().unwrap(), it.next().unwrap()]
        };
        assert_eq!(recs, [(0x0010_1700, 100), (KEY_LSS_NODE_ID, 5)]);
        assert!(parse_image(&buf[..n], 2).is_err(), "other model");
        for i in 0..n {
            let mut b = buf;
            b[i] ^= 1;
            assert!(parse_image(&b[..n], 3).is_err(), "flip at {i} not detected");
        }
        assert!(parse_image(&buf[..n - 1], 3).is_err(), "torn");
    }

    /// `check_image` names each fault, in the order of its checks, with the values found.
    #[test]
    fn check_image_names_each_fault() {
        let mut buf = [0u8; IMAGE_MAX];
        let mut w = ImageWriter::new(&mut buf, 3);
        assert!(w.push(0x0010_1700, 100));
        let n = w.finish();
        assert_eq!(n, IMAGE_MIN + 8);
        assert_eq!(check_image(&buf[..n], 3), Ok(n - 4));
        let empty = {
            let mut b = [0u8; IMAGE_MAX];
            let m = ImageWriter::new(&mut b, 3).finish();
            (b, m)
        };
        assert_eq!(empty.1, IMAGE_MIN);
        assert_eq!(check_image(&empty.0[..IMAGE_MIN], 3), Ok(8));
        assert_eq!(
            check_image(&empty.0[..IMAGE_MIN - 1], 3),
            Err(ImageFault::TooShort(IMAGE_MIN - 1))
        );
        // Each header field changed (the CRC resealed, so the header is what fails).
        let reseal = |at: usize, v: u8| {
            let mut b = buf;
            b[at] = v;
            let crc = crc32(&b[..n - 4]).to_le_bytes();
            b[n - 4..n].copy_from_slice(&crc);
            b
        };
        assert_eq!(
            check_image(&reseal(0, b'X')[..n], 3),
            Err(ImageFault::NotAnImage)
        );
        assert_eq!(
            check_image(&reseal(3, b'X')[..n], 3),
            Err(ImageFault::NotAnImage)
        );
        assert_eq!(
            check_image(&reseal(4, 2)[..n], 3),
            Err(ImageFault::Version(2))
        );
        assert_eq!(ImageFault::VERSION, 1);
        assert_eq!(check_image(&buf[..n], 4), Err(ImageFault::OtherModel(3)));
        assert_eq!(
            check_image(&reseal(6, 2)[..n], 3),
            Err(ImageFault::Length { len: n, count: 2 })
        );
        assert_eq!(
            check_image(&buf[..n + 1], 3),
            Err(ImageFault::Length {
                len: n + 1,
                count: 1
            })
        );
        let mut flipped = buf;
        flipped[10] ^= 0x10;
        let stored = u32::from_le_bytes([buf[n - 4], buf[n - 3], buf[n - 2], buf[n - 1]]);
        assert_eq!(
            check_image(&flipped[..n], 3),
            Err(ImageFault::Crc {
                stored,
                computed: crc32(&flipped[..n - 4])
            })
        );
    }

    /// An image whose CRC is right but whose header names another format (magic), another
    /// layout (version) or another model (tag) is not this unit's image.
    #[test]
    fn a_sealed_image_of_another_format_version_or_model_is_refused() {
        let mut buf = [0u8; IMAGE_MAX];
        let mut w = ImageWriter::new(&mut buf, 3);
        assert!(w.push(0x0010_1700, 100));
        let n = w.finish();
        let reseal = |at: usize, v: u8| {
            let mut b = buf;
            b[at] = v;
            let crc = crc32(&b[..n - 4]).to_le_bytes();
            b[n - 4..n].copy_from_slice(&crc);
            b
        };
        assert!(parse_image(&reseal(0, b'X')[..n], 3).is_err(), "magic");
        assert!(
            parse_image(&reseal(4, VERSION + 1)[..n], 3).is_err(),
            "version"
        );
        assert!(parse_image(&reseal(5, 2)[..n], 3).is_err(), "model tag");
        assert!(
            parse_image(&reseal(5, 3)[..n], 3).is_ok(),
            "resealing alone changes nothing"
        );
        // A count that claims more records than the image holds.
        assert!(parse_image(&reseal(6, 2)[..n], 3).is_err(), "count");
        assert!(
            parse_image(&buf[..11], 3).is_err(),
            "shorter than a header and a CRC"
        );
    }

    /// The writer takes records while the image, with its CRC, still fits the buffer: exactly
    /// (IMAGE_MAX − 12) / 8 of them, and the sealed image is then exactly IMAGE_MAX long.
    #[test]
    fn the_image_writer_fills_the_buffer_exactly() {
        let mut buf = [0u8; IMAGE_MAX];
        let mut w = ImageWriter::new(&mut buf, 1);
        let fit = (IMAGE_MAX - 12) / 8;
        // The buffer is sized for the most records a dictionary stores, neither fewer nor more.
        assert_eq!(fit, RECORDS_MAX);
        for k in 0..fit as u32 {
            assert!(w.push(k, k), "record {k} fits");
        }
        assert!(!w.push(0xFFFF, 0), "one more does not");
        assert_eq!(w.finish(), IMAGE_MAX);
        assert_eq!(parse_image(&buf, 1).unwrap().count(), fit);
    }

    /// `update_image` keeps the stored records it is not told to replace, and refuses (storing
    /// nothing) when the result would not fit.
    #[test]
    fn update_image_keeps_unreplaced_records_and_refuses_an_overflow() {
        let mut st = RamStorage::default();
        update_image(&mut st, 1, &|_| true, &mut [(1, 10), (2, 20)].into_iter()).unwrap();
        update_image(&mut st, 1, &|k| k == 2, &mut [(2, 21)].into_iter()).unwrap();
        let mut b = [0u8; IMAGE_MAX];
        let recs = load_image(&mut st, 1, &mut b).unwrap();
        assert_eq!(recs.clone().count(), 2);
        assert!(recs.clone().any(|r| r == (1, 10)) && recs.clone().any(|r| r == (2, 21)));
        let fit = (IMAGE_MAX - 12) / 8;
        let mut many = (100..100 + fit as u32).map(|k| (k, k));
        assert_eq!(
            update_image(&mut st, 1, &|k| k >= 100, &mut many),
            Err(StorageError::Io),
            "two kept + all that fit is too many"
        );
        let mut b = [0u8; IMAGE_MAX];
        assert_eq!(
            load_image(&mut st, 1, &mut b).unwrap().count(),
            2,
            "unchanged"
        );
    }

    #[test]
    fn update_in_place_keeps_the_stored_order_and_appends_the_new_records() {
        let mut st = RamStorage::default();
        let old = [(1, 10), (2, 20), (3, 30), (4, 40), (5, 50)];
        update_image(&mut st, 7, &|_| true, &mut old.into_iter()).unwrap();
        // Replace 2 and 4, add 9 and 8: 1, 3, 5 move to the front, the new ones follow.
        let put = [(9, 90), (2, 21), (8, 80), (4, 41)];
        update_image(
            &mut st,
            7,
            &|k| matches!(k, 2 | 4 | 8 | 9),
            &mut put.into_iter(),
        )
        .unwrap();
        let mut buf = [0u8; IMAGE_MAX];
        let got: [(u32, u32); 7] = {
            let mut it = load_image(&mut st, 7, &mut buf).unwrap();
            core::array::from_fn(|_| it.next().unwrap())
        };
        assert_eq!(
            got,
            [
                (1, 10),
                (3, 30),
                (5, 50),
                (9, 90),
                (2, 21),
                (8, 80),
                (4, 41)
            ]
        );
        // Dropping records only (the kept ones close the gaps, in order).
        update_image(&mut st, 7, &|k| k == 9 || k == 1, &mut core::iter::empty()).unwrap();
        let mut it = load_image(&mut st, 7, &mut buf).unwrap();
        let keys: [u32; 5] = core::array::from_fn(|_| it.next().unwrap().0);
        assert_eq!(keys, [3, 5, 2, 8, 4]);
        assert!(it.next().is_none());
        // Replacing the first record moves every other one down by one, over itself.
        update_image(&mut st, 7, &|k| k == 3, &mut [(3, 31)].into_iter()).unwrap();
        let mut buf5 = [0u8; IMAGE_MAX];
        let got: [(u32, u32); 5] = {
            let mut it = load_image(&mut st, 7, &mut buf5).unwrap();
            core::array::from_fn(|_| it.next().unwrap())
        };
        assert_eq!(got, [(5, 50), (2, 21), (8, 80), (4, 41), (3, 31)]);
        // An update that does not fit is refused and leaves the stored image as it was.
        let before = st.saves;
        let mut many = (0..RECORDS_MAX as u32).map(|k| (0x100 + k, k));
        assert_eq!(
            update_image(&mut st, 7, &|k| k >= 0x100, &mut many),
            Err(StorageError::Io)
        );
        assert_eq!(st.saves, before);
    }
}
