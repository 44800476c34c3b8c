//! The default TPDO mappings of each manual (TH / E-Series Table 16, TMI D21): TPDO n maps
//! the objects of channel n, sub-index n, with their sizes, whether or not it counts them by
//! default (the entries are there to be switched on with sub 0).

use crate::common::booted;

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
        let mut r = booted(name);
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
