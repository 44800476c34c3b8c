//! The storage image format of `storage.rs` (magic "CPOS", version, model tag, record count,
//! key / value records, CRC-32 of all before, all little-endian), the record keys, the scopes of
//! 0x1010 / 0x1011 sub-indices, and the contract of the reference media (`RamStorage`,
//! `NoStorage`).

use canpos_stack::od::{Access, DataType, DefaultValue, Entry, Group, Range};
use canpos_stack::storage::update_image;
use canpos_stack::storage::{
    app_key, app_record, crc32, is_object_key, load_image, parse_image, ImageWriter, APP_RECORDS,
    IMAGE_MAX, KEY_LSS_BITRATE, KEY_LSS_NODE_ID, KEY_SAVED_NODE_ID,
};
use canpos_stack::{NoStorage, RamStorage, Scope, Storage, StorageError};

/// The image of two records, byte by byte (CRC-32 as zlib computes it).
const IMAGE: [u8; 28] = [
    0x43, 0x50, 0x4F, 0x53, // "CPOS"
    0x01, // version
    0x03, // model tag
    0x02, 0x00, // two records
    0x00, 0x17, 0x10, 0x00, 0x64, 0x00, 0x70, 0x00, // 0x1017/0 = 0x00700064
    0x01, 0x00, 0x00, 0xFF, 0x05, 0x00, 0x00, 0x00, // LSS node-id = 5
    0x22, 0x7F, 0x4D, 0x9D, // CRC-32
];

#[test]
fn the_image_is_laid_out_as_documented() {
    let mut buf = [0u8; IMAGE_MAX];
    let mut w = ImageWriter::new(&mut buf, 3);
    assert!(w.push(0x0010_1700, 0x0070_0064));
    assert!(w.push(KEY_LSS_NODE_ID, 5));
    let n = w.finish();
    assert_eq!(&buf[..n], &IMAGE[..]);
    assert_eq!(crc32(&IMAGE[..24]), 0x9D4D_7F22);
    let recs: Vec<(u32, u32)> = parse_image(&IMAGE, 3).unwrap().collect();
    assert_eq!(recs, [(0x0010_1700, 0x0070_0064), (KEY_LSS_NODE_ID, 5)]);
    // An empty image is a header and a CRC.
    let mut buf = [0u8; IMAGE_MAX];
    let n = ImageWriter::new(&mut buf, 9).finish();
    assert_eq!(n, 12);
    assert_eq!(&buf[..8], b"CPOS\x01\x09\x00\x00");
    assert_eq!(parse_image(&buf[..n], 9).unwrap().count(), 0);
}

/// On a host an image holds up to 240 records ("any device an EDS may describe").
#[cfg(feature = "host-buffers")]
#[test]
fn a_host_image_holds_240_records() {
    assert_eq!(IMAGE_MAX, 8 + 8 * 240 + 4);
    let mut buf = [0u8; IMAGE_MAX];
    let mut w = ImageWriter::new(&mut buf, 1);
    for k in 0..240 {
        assert!(w.push(k, !k), "record {k}");
    }
    assert!(!w.push(240, 0));
    assert_eq!(w.finish(), IMAGE_MAX);
    let mut st = RamStorage::default();
    assert_eq!(st.save(&buf), Ok(()), "a full image fits the medium");
    let mut b = [0u8; IMAGE_MAX];
    let recs = load_image(&mut st, 1, &mut b).unwrap();
    assert_eq!(recs.clone().count(), 240);
    assert_eq!(recs.last(), Some((239, !239)));

    // Updating the stored image to exactly 240 records fits too; one more does not.
    let mut st = RamStorage::default();
    update_image(&mut st, 1, &|_| true, &mut (0..200).map(|k| (k, k))).unwrap();
    update_image(&mut st, 1, &|k| k >= 200, &mut (200..240).map(|k| (k, k))).unwrap();
    let mut b = [0u8; IMAGE_MAX];
    assert_eq!(st.load(&mut b), Ok(IMAGE_MAX));
    assert_eq!(
        update_image(&mut st, 1, &|k| k >= 200, &mut (200..241).map(|k| (k, k))),
        Err(StorageError::Io)
    );
    assert_eq!(load_image(&mut st, 1, &mut b).unwrap().count(), 240);
}

/// Object records are keyed `index << 8 | sub` (24 bits); the LSS and bookkeeping keys lie
/// above that space.
#[test]
fn record_keys_of_objects_and_of_lss_values_do_not_overlap() {
    for k in [0, 0x0010_1700, 0x00FF_FFFF] {
        assert!(is_object_key(k), "{k:#X}");
    }
    for k in [
        0x0100_0000,
        KEY_LSS_NODE_ID,
        KEY_LSS_BITRATE,
        KEY_SAVED_NODE_ID,
        u32::MAX,
    ] {
        assert!(!is_object_key(k), "{k:#X}");
    }
}

/// The application's values of its own (TMI preset offsets) have keys of their own, one per
/// value, none of them an object's or an LSS value's.
#[test]
fn application_record_keys_name_exactly_their_values() {
    for k in 0..APP_RECORDS {
        assert_eq!(app_record(app_key(k)), Some(k));
        assert!(!is_object_key(app_key(k)));
    }
    for key in [
        app_key(APP_RECORDS),
        app_key(0) - 1,
        KEY_LSS_NODE_ID,
        KEY_LSS_BITRATE,
        KEY_SAVED_NODE_ID,
        0x0060_1001,
        0,
        u32::MAX,
    ] {
        assert_eq!(app_record(key), None, "{key:#X}");
    }
}

fn entry(group: Group) -> Entry {
    Entry::build(
        0x2000,
        0,
        "x",
        DataType::Unsigned8,
        Access::Rw,
        false,
        DefaultValue::Const(0),
        &Range::Any,
        group,
    )
}

/// CiA 301 §7.5.2.13 / §7.5.2.14: sub 1 all parameters, sub 2 communication, sub 3
/// application (any other sub: all); what the device keeps by itself (Auto) and volatile
/// values are in none of them.
#[test]
fn cia301_7_5_2_13_store_scopes_by_sub_index() {
    assert_eq!(Scope::of_sub(1), Scope::All);
    assert_eq!(Scope::of_sub(2), Scope::Comm);
    assert_eq!(Scope::of_sub(3), Scope::App);
    assert_eq!(Scope::of_sub(4), Scope::All);
    let groups = [Group::Volatile, Group::Comm, Group::App, Group::Auto];
    let covers = |s: Scope| groups.map(|g| s.covers(&entry(g)));
    assert_eq!(covers(Scope::All), [false, true, true, false]);
    assert_eq!(covers(Scope::Comm), [false, true, false, false]);
    assert_eq!(covers(Scope::App), [false, false, true, false]);
    assert_eq!(covers(Scope::Auto), [false, false, false, true]);
}

/// The RAM medium keeps one image: empty until saved, the bytes saved come back, erase empties
/// it, a failing medium (fault injection) neither saves nor erases, an image larger than the
/// medium is an I/O error, a buffer too small to read into finds it corrupt.
#[test]
fn ram_storage_keeps_one_image() {
    let mut st = RamStorage::default();
    let mut b = [0u8; IMAGE_MAX];
    assert_eq!(st.load(&mut b), Err(StorageError::Empty));
    assert_eq!(st.saves, 0);
    assert_eq!(st.save(&IMAGE), Ok(()));
    assert_eq!(st.saves, 1);
    assert_eq!(st.load(&mut b), Ok(IMAGE.len()));
    assert_eq!(&b[..IMAGE.len()], &IMAGE[..]);
    let mut small = [0u8; 27];
    assert_eq!(st.load(&mut small), Err(StorageError::Corrupt));
    let mut exact = [0u8; 28];
    assert_eq!(st.load(&mut exact), Ok(28));

    st.fail = true;
    assert_eq!(st.save(&IMAGE[..12]), Err(StorageError::Io));
    assert_eq!(st.erase(), Err(StorageError::Io));
    assert_eq!(st.saves, 1);
    assert_eq!(st.load(&mut b), Ok(IMAGE.len()), "unchanged");
    st.fail = false;

    let big = vec![0u8; IMAGE_MAX + 1];
    assert_eq!(st.save(&big), Err(StorageError::Io));
    assert_eq!(st.save(&big[..IMAGE_MAX]), Ok(()));
    assert_eq!(st.load(&mut b), Ok(IMAGE_MAX));
    assert_eq!(st.saves, 2);

    assert_eq!(st.erase(), Ok(()));
    assert_eq!(st.load(&mut b), Err(StorageError::Empty));
}

/// Fault injection "stored-data corruption" flips exactly one bit of the stored image, which
/// the image's check then refuses; with nothing stored there is nothing to flip.
#[test]
fn ram_storage_corruption_flips_one_bit() {
    let mut st = RamStorage::default();
    st.corrupt();
    let mut b = [0u8; IMAGE_MAX];
    assert_eq!(st.load(&mut b), Err(StorageError::Empty));
    st.save(&IMAGE).unwrap();
    st.corrupt();
    let n = st.load(&mut b).unwrap();
    assert_eq!(n, IMAGE.len());
    let flipped: u32 = b[..n]
        .iter()
        .zip(IMAGE)
        .map(|(a, b)| (a ^ b).count_ones())
        .sum();
    assert_eq!(flipped, 1);
    assert_eq!(
        load_image(&mut st, 3, &mut [0u8; IMAGE_MAX]).err(),
        Some(StorageError::Corrupt)
    );
}

/// A unit without non-volatile memory has nothing stored, cannot save, and erasing is
/// trivially done.
#[test]
fn no_storage_keeps_nothing() {
    let mut st = NoStorage;
    let mut b = [0u8; IMAGE_MAX];
    assert_eq!(st.load(&mut b), Err(StorageError::Empty));
    assert_eq!(st.save(&IMAGE), Err(StorageError::Io));
    assert_eq!(st.erase(), Ok(()));
    assert_eq!(st.load(&mut b), Err(StorageError::Empty));
}
