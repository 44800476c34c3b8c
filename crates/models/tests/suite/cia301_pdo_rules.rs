//! CiA 301 §7.5.2.35 / §7.5.2.37 TPDO communication and mapping parameter rules (TH, node-id
//! 0x7F: SDO 0x67F / 0x5FF, TPDO1 COB-ID 0x1FF, mapping 0x1A00).

use crate::common::{hex, Rig};
use canpos_models::th::TH;

fn abort_code(answer: &(u16, Vec<u8>)) -> Option<u32> {
    (answer.1[0] == 0x80).then(|| u32::from_le_bytes(answer.1[4..8].try_into().unwrap()))
}

fn write_u32(r: &mut Rig, index: u16, sub: u8, v: u32) -> Option<u32> {
    r.download(index, sub, v, 4).err()
}

fn write_u8(r: &mut Rig, index: u16, sub: u8, v: u8) -> Option<u32> {
    r.download(index, sub, v.into(), 1).err()
}

/// §7.5.2.35: the CAN-ID of a PDO that exists (bit 31 clear) cannot be changed: 0x06090030.
/// Bit 31 may be set, the CAN-ID changed while the PDO does not exist, and the PDO made valid
/// again under the new CAN-ID, where it is then sent.
#[test]
fn cia301_7_5_2_35_can_id_of_a_valid_tpdo_cannot_change() {
    let mut r = Rig::booted(&TH);
    assert_eq!(write_u32(&mut r, 0x1800, 1, 0x0000_01FE), Some(0x0609_0030));
    assert_eq!(
        r.req(0x67F, &hex("40 00 18 01 00 00 00 00")).1,
        hex("43 00 18 01 FF 01 00 00")
    );
    assert_eq!(
        write_u32(&mut r, 0x1800, 1, 0x8000_01FF),
        None,
        "bit 31 may be set"
    );
    assert_eq!(
        write_u32(&mut r, 0x1800, 1, 0x8000_01FE),
        None,
        "CAN-ID changes while invalid"
    );
    assert_eq!(
        write_u32(&mut r, 0x1800, 1, 0x0000_01FE),
        None,
        "valid again"
    );
    r.send(0x000, &[0x01, 0x7F]);
    let f = r.advance_ms(5);
    assert!(f.iter().any(|(_, f)| f.std_id() == Some(0x1FE)));
    assert!(f.iter().all(|(_, f)| f.std_id() != Some(0x1FF)));
}

/// §7.5.2.37: a mapping entry names an object and its length in bits; a length of 0, one that is
/// not a whole number of bytes, or one longer than the object is refused with 0x06040041, and the
/// entry keeps its value.
#[test]
fn cia301_7_5_2_37_mapping_entry_lengths_must_be_whole_bytes_of_the_object() {
    let mut r = Rig::booted(&TH);
    assert_eq!(
        write_u8(&mut r, 0x1A00, 0, 0),
        None,
        "sub 0 to zero before changing entries"
    );
    let before = r.req(0x67F, &hex("40 00 1A 01 00 00 00 00")).1;
    for bad in [0x6020_0100, 0x6020_0104, 0x6020_0111, 0x6020_0128] {
        assert_eq!(
            write_u32(&mut r, 0x1A00, 1, bad),
            Some(0x0604_0041),
            "{bad:08X}"
        );
    }
    assert_eq!(r.req(0x67F, &hex("40 00 1A 01 00 00 00 00")).1, before);
    for good in [0x6020_0108, 0x6020_0110, 0x6020_0120] {
        assert_eq!(write_u32(&mut r, 0x1A00, 1, good), None, "{good:08X}");
    }
}

/// One 1 ms measurement cycle at `nm` on channel 1; the TPDO1 frames it produced.
fn cycle_tpdo1(r: &mut Rig, nm: i64) -> usize {
    r.cycle(Some(nm))
        .iter()
        .filter(|f| f.std_id() == Some(0x1FF))
        .count()
}

/// CiA 301 §7.2.2.2 / CiA 406: an application event (here a cam switching) triggers the
/// asynchronous TPDOs that map the value that changed, and no other.
#[test]
fn cia301_7_2_2_an_event_triggers_only_the_tpdos_that_map_its_value() {
    for maps_cam in [true, false] {
        let mut r = Rig::booted(&TH);
        assert_eq!(write_u32(&mut r, 0x6310, 1, 20_100), None); // cam 1 at 20100 steps
        assert_eq!(write_u8(&mut r, 0x6301, 1, 1), None);
        // No event timer (UNSIGNED16): events only.
        assert_eq!(
            abort_code(&r.req(0x67F, &hex("2B 00 18 05 00 00 00 00"))),
            None
        );
        if !maps_cam {
            // TPDO1: position only.
            assert_eq!(write_u8(&mut r, 0x1A00, 0, 0), None);
            assert_eq!(write_u32(&mut r, 0x1A00, 1, 0x6020_0120), None);
            assert_eq!(write_u8(&mut r, 0x1A00, 0, 1), None);
        }
        r.send(0x000, &[0x01, 0x7F]);
        r.take();
        let sent: usize = (0..10i64)
            .map(|k| cycle_tpdo1(&mut r, 100_000_000 + k * 100_000))
            .sum();
        // The cam switches once, at 20100 steps.
        assert_eq!(
            sent,
            usize::from(maps_cam),
            "maps the cam state: {maps_cam}"
        );
    }
}
