//! The state-file loader: arbitrary stored bytes through `FileStorage` (a real file) and
//! `storage::parse_image` into `Node::power_on` of every model.
//!
//! Half the inputs are sealed into a well-formed image (magic, version, model tag, count, CRC)
//! so the fuzzer also reaches the interpretation of the records, not only the checksum.
//! Invariants: no panic; a rejected image boots the factory defaults and is reported as
//! corrupt; `FileStorage::for_model` passes on a subsequence of the file's records, no key
//! twice; whatever is stored, the node comes up with a node-id in 1…127 or unconfigured and
//! sends its boot-up only on its own COB-ID; a parsed image re-written with `ImageWriter` is
//! byte-identical.
#![no_main]

use std::path::PathBuf;
use std::sync::OnceLock;

use canpos_host::FileStorage;
use canpos_models as models;
use canpos_models::SensorNode;
use canpos_stack::storage::{self, ImageWriter, RamStorage, Storage, IMAGE_MAX};
use canpos_stack::Instant;

fn path() -> &'static PathBuf {
    static P: OnceLock<PathBuf> = OnceLock::new();
    // A scratch file inside the fuzz crate's own target directory, not the shared /tmp:
    // the target must not depend on (or litter) the machine it runs on.
    P.get_or_init(|| {
        let d = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/target/scratch"));
        std::fs::create_dir_all(&d)
            .unwrap_or_else(|e| panic!("environment: cannot create {}: {e}", d.display()));
        d.join(format!("state-{}.bin", std::process::id()))
    })
}

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let Some((&mode, body)) = data.split_first() else {
        return;
    };
    for model in models::all() {
        let tag = model.features.tag;
        let mut image = [0u8; IMAGE_MAX];
        let bytes: &[u8] = if mode & 1 == 1 {
            // Seal the body as records of a valid image.
            let mut w = ImageWriter::new(&mut image, tag);
            for r in body.chunks_exact(8) {
                let k = u32::from_le_bytes([r[0], r[1], r[2], r[3]]);
                let v = u32::from_le_bytes([r[4], r[5], r[6], r[7]]);
                if !w.push(k, v) {
                    break;
                }
            }
            let n = w.finish();
            &image[..n]
        } else {
            body
        };

        // parse_image: accepted images round-trip through ImageWriter exactly.
        if let Ok(recs) = storage::parse_image(bytes, tag) {
            let mut again = [0u8; IMAGE_MAX];
            let mut w = ImageWriter::new(&mut again, tag);
            for (k, v) in recs {
                assert!(w.push(k, v), "a parsed image does not fit again");
            }
            let n = w.finish();
            assert_eq!(&again[..n], bytes, "image round trip");
        }

        // The file path: FileStorage must hand the core exactly the file's bytes (or refuse).
        std::fs::write(path(), bytes)
            .unwrap_or_else(|e| panic!("environment: cannot write {}: {e}", path().display()));
        let mut fs = FileStorage::new(path());
        let mut buf = [0u8; IMAGE_MAX];
        if let Ok(n) = fs.load(&mut buf) {
            assert_eq!(&buf[..n], bytes, "FileStorage changed the bytes");
        }
        // With the model known, it passes on the records the model uses, the last of each
        // key, in the file's order: never a record the file does not hold.
        let mut fs = FileStorage::new(path()).for_model(model);
        if let Ok(n) = fs.load(&mut buf) {
            let kept: Vec<_> = storage::parse_image(&buf[..n], tag)
                .expect("FileStorage passed on an image the core refuses")
                .collect();
            let all: Vec<_> = storage::parse_image(bytes, tag)
                .expect("FileStorage passed on records of a refused image")
                .collect();
            let mut rest = all.iter();
            for r in &kept {
                assert!(rest.any(|a| a == r), "{r:08X?}: not in the file, or moved");
            }
            for (i, r) in kept.iter().enumerate() {
                assert!(
                    !kept[i + 1..].iter().any(|x| x.0 == r.0),
                    "key {:08X} passed on twice",
                    r.0
                );
            }
        }

        let mut ram = RamStorage::default();
        let stored = ram.save(bytes).is_ok();
        let mut node = SensorNode::new(model, model.default_config, ram);
        node.power_on(Instant::ZERO);
        let valid = stored && storage::parse_image(bytes, tag).is_ok();
        let dev = node.device();
        let id = dev.node_id();
        assert!(
            (1..=127).contains(&id) || id == 0xFF,
            "{}: stored bytes gave node-id {id}",
            model.name
        );
        if !valid {
            assert_eq!(
                id, model.default_config.node_id,
                "{}: defaults after a bad image",
                model.name
            );
            // Stored but rejected: reported; not stored at all (too long for the medium): empty.
            assert_eq!(
                dev.stats().storage_corrupt,
                stored,
                "{}: corrupt flag",
                model.name
            );
        }
        let id = u16::from(id);
        // The EMCY COB-ID in force: its default 0x080 + node-id, or any CAN-ID a master may
        // configure (CiA 301: not a restricted one), and a stored one is loaded as such. An
        // unconfigured node has none (it sends nothing until LSS gives it a node-id). Valid:
        // bit 31 clear; 11-bit: bit 29 clear (the other bits do not select the CAN-ID).
        let emcy = node
            .read_object(0x1014, 0)
            .ok()
            .filter(|v| v & 0xA000_0000 == 0 && id != 0xFF)
            .map(|v| (v & 0x7FF) as u16);
        if let Some(e) = emcy {
            assert!(
                !canpos_stack::pdo::restricted_id(u32::from(e)),
                "{}: EMCY on the restricted CAN-ID {e:03X}",
                model.name
            );
        }
        while let Some(f) = node.poll_transmit() {
            let cob = f.std_id().expect("extended frame at boot");
            assert!(f.dlc() <= 8);
            assert!(
                cob == 0x700 + id || Some(cob) == emcy,
                "{}: boot frame on {cob:03X} for node-id {id} (EMCY COB-ID {emcy:03X?})",
                model.name
            );
        }
    }
});
