//! Rules of the stack whose test needs a product model's table: moved here with the split of the
//! core (issue 37 item 3), as the stack's own tests cannot name a product.

use canpos_stack::lss::cs;
use canpos_stack::pdo::Tpdos;
use canpos_stack::{Abort, Dictionary, Instant};

/// `check_value` of a mapping count looks up sub `raw`: the same answer as counting the
/// record's entries, as long as every model's mapping records have no gap in their subs.
#[test]
fn mapping_count_is_checked_against_the_entries_there_are() {
    use canpos_stack::od::Hook;
    let mut records = 0;
    for model in canpos_models::all() {
        let od = Dictionary::new(model);
        for e in od.entries() {
            if e.hook != Hook::TpdoMap || e.sub != 0 {
                continue;
            }
            records += 1;
            let n = od
                .entries()
                .iter()
                .filter(|x| x.index == e.index && x.sub > 0)
                .count() as u32;
            for raw in (0..0x300).chain([0x1_0000, u32::MAX]) {
                let want = if raw > n {
                    Err(Abort::MappingLength)
                } else {
                    Ok(())
                };
                let got = Tpdos::check_value(&od, e.index, 0, raw);
                assert_eq!(got, want, "{model:?} {:#X} {raw:#X}", e.index);
            }
        }
    }
    assert!(records >= 3, "no mapping record found");
}

/// Store configuration on the TMI: the pending node-id and bit rate go to the LSS records
/// and to their copies 0x2000 / 0x2001, in that order, and nothing else is stored.
#[test]
fn store_configuration_keeps_the_records_and_the_objects_copies() {
    use canpos_models::tmi::TMI;
    use canpos_stack::storage::{self, RamStorage, IMAGE_MAX, KEY_LSS_BITRATE, KEY_LSS_NODE_ID};
    let mut n = canpos_models::SensorNode::new(
        &TMI,
        TMI.configure(TMI.default_config),
        RamStorage::default(),
    );
    n.power_on(Instant::ZERO);
    for (i, d) in [
        [cs::SWITCH_GLOBAL, 1, 0, 0, 0, 0, 0, 0],
        [cs::CONFIGURE_NODE_ID, 9, 0, 0, 0, 0, 0, 0],
        [cs::CONFIGURE_BIT_TIMING, 0, 2, 0, 0, 0, 0, 0],
        [cs::STORE_CONFIGURATION, 0, 0, 0, 0, 0, 0, 0],
    ]
    .into_iter()
    .enumerate()
    {
        let now = Instant::from_micros(1_000 * (i as u64 + 1));
        n.handle_frame(&canpos_stack::Frame::new(0x7E5, &d).unwrap(), now);
        while n.poll(now).is_some() {}
    }
    let mut buf = [0; IMAGE_MAX];
    let tag = TMI.features.tag;
    let mut it = storage::load_image(n.storage_mut(), tag, &mut buf).unwrap();
    let recs: [Option<(u32, u32)>; 5] = core::array::from_fn(|_| it.next());
    assert_eq!(
        recs,
        [
            Some((KEY_LSS_NODE_ID, 9)),
            Some((KEY_LSS_BITRATE, 500)),
            Some((0x0020_0000, 9)),
            Some((0x0020_0100, 500)),
            None,
        ]
    );
}
