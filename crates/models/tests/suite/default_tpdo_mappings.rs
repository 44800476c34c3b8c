//! The default TPDO mappings of each manual (TH / E-Series Table 16, TMI D21): TPDO n maps
//! the objects of channel n, sub-index n, with their sizes, whether or not it counts them by
//! default (the entries are there to be switched on with sub 0). A one-channel TMI has no
//! channel 2: its TPDO2 maps nothing (002 §1.12).

use crate::common::{booted, model, Rig};

#[test]
fn tpdo_n_maps_channel_n() {
    for (name, tpdos, objects) in [
        ("th", 4u16, &[0x6020_0020u32, 0x6030_0010, 0x6300_0008][..]),
        ("e-series", 3, &[0x6020_0020, 0x6030_0010, 0x6400_0008][..]),
        (
            "tmi",
            2,
            &[0x6020_0020, 0x6030_0010, 0x6300_0008, 0x6400_0008][..],
        ),
    ] {
        // The TMI with both channels (order-code interface 62x).
        let m = model(name);
        let mut r = Rig::booted_with(m, m.default_config.with_channels(2));
        for n in 1..=tpdos {
            for (k, &o) in objects.iter().enumerate() {
                let want = o | u32::from(n) << 8;
                assert_eq!(
                    r.node.read_object(0x19FF + n, k as u8 + 1),
                    Ok(want),
                    "{name} TPDO{n} entry {}",
                    k + 1
                );
            }
        }
    }
}

#[test]
fn a_one_channel_tmis_tpdo2_maps_nothing() {
    let mut r = booted("tmi");
    assert_eq!(r.node.read_object(0x1A00, 1), Ok(0x6020_0120));
    for sub in 0..=5 {
        assert_eq!(r.node.read_object(0x1A01, sub), Ok(0), "1A01:{sub}");
    }
    // Invalid by default (D21).
    assert_eq!(r.node.read_object(0x1801, 1).map(|c| c >> 31), Ok(1));
}
