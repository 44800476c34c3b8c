//! TMI preset 0x6010 as CiA 406 defines it (issue 36 item 5): writing the preset makes the
//! current position read it, the device keeps the offset and stores it with 0x6010 (002
//! §1.16), cams and work areas are compared in the preset's coordinates ("limits regard the
//! preset", 002 §1.10 / §1.11.2), and work-area bit 0 is set at "Position <= Preset Value or
//! Position >= Sensor length" (002 §1.11.2). Everything through SDO, on both channels of a
//! two-channel unit (500 mm, 1 µm steps).

use crate::common::{expedited_download, model, Rig};
use canpos_models::DeviceConfig;

const SAVE: u32 = u32::from_le_bytes(*b"save");
const LOAD: u32 = u32::from_le_bytes(*b"load");
/// Channel 1's and channel 2's magnets (more than the 100 mm apart the manual asks, §4.3).
const AT: [i64; 2] = [300_000_000, 450_000_000];

fn two_channels() -> Rig {
    let m = model("tmi");
    let mut r = Rig::with_config(
        m,
        DeviceConfig {
            channels: 2,
            ..m.default_config
        },
    );
    r.take();
    r
}

/// Both magnets moved by `d_nm` from [`AT`], one measurement cycle.
fn measure(r: &mut Rig, d_nm: [i64; 2]) {
    r.cycle_channels(&[Some(AT[0] + d_nm[0]), Some(AT[1] + d_nm[1])]);
}

/// The SDO answer of node 0x7F to `req` (a write may send a cam or work-area EMCY beside it).
fn sdo(r: &mut Rig, req: [u8; 8]) -> Vec<u8> {
    let answers: Vec<_> = r
        .send(0x67F, &req)
        .into_iter()
        .filter(|f| f.std_id() == Some(0x5FF))
        .collect();
    assert_eq!(answers.len(), 1, "one answer to {req:02X?}");
    answers[0].data().to_vec()
}

/// SDO download (expedited) of the `n` low bytes of `v`, which must be confirmed.
fn write(r: &mut Rig, index: u16, sub: u8, v: u32, n: usize) {
    let a = sdo(r, expedited_download(index, sub, v, n));
    assert_eq!(a[0], 0x60, "write {index:04X}:{sub} = {v}: {a:02X?}");
}

/// SDO upload (expedited) from node 0x7F.
fn upload(r: &mut Rig, index: u16, sub: u8) -> i32 {
    let [i0, i1] = index.to_le_bytes();
    let a = sdo(r, [0x40, i0, i1, sub, 0, 0, 0, 0]);
    assert_eq!(a[0] & 0xF3, 0x43, "upload {index:04X}:{sub}: {a:02X?}");
    i32::from_le_bytes([a[4], a[5], a[6], a[7]])
}

/// 0x1010 (store) or 0x1011 (restore) sub `sub` with `signature`, confirmed after the store
/// time.
fn storage_command(r: &mut Rig, index: u16, sub: u8, signature: u32) {
    let answer = r
        .store_cmd(0x67F, &expedited_download(index, sub, signature, 4), 25)
        .into_iter()
        .find(|(_, f)| f.std_id() == Some(0x5FF))
        .map(|(_, f)| f.data().to_vec())
        .unwrap();
    assert_eq!(answer[0], 0x60, "{index:04X}:{sub}: {answer:02X?}");
}

fn position(r: &mut Rig, ch: u8) -> i32 {
    upload(r, 0x6020, ch)
}

/// 002 §1.11.2 / CiA 406: the written preset is what the current position reads at once (no
/// measurement cycle in between), 0x6010 reads the preset back, and the next positions follow
/// with the same offset. The other channel is untouched.
#[test]
fn writing_the_preset_makes_the_current_position_read_it_on_both_channels() {
    let mut r = two_channels();
    measure(&mut r, [0, 0]);
    assert_eq!(position(&mut r, 1), 300_000);
    assert_eq!(position(&mut r, 2), 450_000);

    write(&mut r, 0x6010, 1, 7777, 4);
    assert_eq!(
        position(&mut r, 1),
        7777,
        "channel 1 reads its preset at once"
    );
    assert_eq!(
        upload(&mut r, 0x6010, 1),
        7777,
        "0x6010:1 reads the preset back"
    );
    assert_eq!(position(&mut r, 2), 450_000, "channel 2 untouched");

    write(&mut r, 0x6010, 2, -5000i32 as u32, 4);
    assert_eq!(
        position(&mut r, 2),
        -5000,
        "channel 2 reads its preset at once"
    );
    assert_eq!(upload(&mut r, 0x6010, 2), -5000);
    assert_eq!(position(&mut r, 1), 7777);

    // The magnets move: the positions follow from the preset (1 µm steps).
    measure(&mut r, [10_000_000, -2_000_000]);
    assert_eq!(position(&mut r, 1), 17_777);
    assert_eq!(position(&mut r, 2), -7000);
    // A second preset at the new place replaces the first.
    write(&mut r, 0x6010, 1, 0, 4);
    assert_eq!(position(&mut r, 1), 0);
    assert_eq!(upload(&mut r, 0x6010, 1), 0);
}

/// §1.16: 0x6010 is stored with the application parameters, and so is the offset its write
/// produced: after "save" and a power cycle the same magnet positions read the same (not a new
/// preset at the new power-up), and a moved magnet reads the preset plus the move. Restore
/// defaults (0x1011) and a power cycle bring back 0x6010 = 0 and the measured positions.
#[test]
fn the_offset_is_stored_with_the_preset_and_restore_defaults_clears_it() {
    let mut r = two_channels();
    measure(&mut r, [0, 0]);
    write(&mut r, 0x6010, 1, 1000, 4);
    write(&mut r, 0x6010, 2, 2000, 4);
    storage_command(&mut r, 0x1010, 1, SAVE);

    r.power_cycle();
    measure(&mut r, [0, 0]);
    assert_eq!(upload(&mut r, 0x6010, 1), 1000);
    assert_eq!(upload(&mut r, 0x6010, 2), 2000);
    assert_eq!(position(&mut r, 1), 1000, "same magnet, same reading");
    assert_eq!(position(&mut r, 2), 2000, "same magnet, same reading");

    // Powered up with the magnets elsewhere: the stored offset applies, no re-preset.
    r.power_cycle();
    measure(&mut r, [5_000_000, -3_000_000]);
    assert_eq!(position(&mut r, 1), 6000);
    assert_eq!(position(&mut r, 2), -1000);

    // Restore defaults: 0x6010 and the offsets go at the next power-up.
    storage_command(&mut r, 0x1011, 1, LOAD);
    r.power_cycle();
    measure(&mut r, [0, 0]);
    assert_eq!(upload(&mut r, 0x6010, 1), 0);
    assert_eq!(upload(&mut r, 0x6010, 2), 0);
    assert_eq!(position(&mut r, 1), 300_000);
    assert_eq!(position(&mut r, 2), 450_000);
}

/// The offset belongs to the application parameters: "save" of sub 3 keeps it, "save" of the
/// communication parameters (sub 2) does not, reset node forgets an unsaved one, reset
/// communication keeps it; restore of the application parameters (0x1011 sub 3) clears it.
#[test]
fn the_offset_follows_the_application_parameters_scopes() {
    let mut r = two_channels();
    measure(&mut r, [0, 0]);
    write(&mut r, 0x6010, 1, 1000, 4);
    storage_command(&mut r, 0x1010, 2, SAVE);
    r.power_cycle();
    measure(&mut r, [0, 0]);
    assert_eq!(position(&mut r, 1), 300_000, "not stored by sub 2");

    write(&mut r, 0x6010, 2, 1000, 4);
    r.send(0x000, &[0x82, 0x7F]);
    measure(&mut r, [0, 0]);
    assert_eq!(position(&mut r, 2), 1000, "reset communication keeps it");
    r.send(0x000, &[0x81, 0x7F]);
    measure(&mut r, [0, 0]);
    assert_eq!(
        position(&mut r, 2),
        450_000,
        "reset node forgets an unsaved preset"
    );
    assert_eq!(upload(&mut r, 0x6010, 2), 0);

    write(&mut r, 0x6010, 2, 1000, 4);
    storage_command(&mut r, 0x1010, 3, SAVE);
    r.send(0x000, &[0x81, 0x7F]);
    r.take();
    measure(&mut r, [0, 0]);
    assert_eq!(
        position(&mut r, 2),
        1000,
        "stored by sub 3, back at reset node"
    );
    storage_command(&mut r, 0x1011, 3, LOAD);
    r.power_cycle();
    measure(&mut r, [0, 0]);
    assert_eq!(position(&mut r, 2), 450_000, "restored by sub 3");
    assert_eq!(upload(&mut r, 0x6010, 2), 0);
}

/// §1.10 / §1.11.2: "The values for Low Limit and High Limit regard the values for preset
/// (0x6010)": a cam window and a work area set around the preset switch as the magnet moves
/// around the place where the preset was written.
#[test]
fn cam_and_work_area_limits_are_compared_in_the_preset_coordinates() {
    let mut r = two_channels();
    measure(&mut r, [0, 0]);
    for ch in 1..=2u8 {
        write(&mut r, 0x6010, ch, 1000, 4);
        // Cam 1: window 900…1100, enabled.
        write(&mut r, 0x6310, ch, 900, 4);
        write(&mut r, 0x6320, ch, 1100, 4);
        write(&mut r, 0x6301, ch, 0x01, 1);
        // Work area 500…1500.
        write(&mut r, 0x6401, ch, 500, 4);
        write(&mut r, 0x6402, ch, 1500, 4);
    }
    measure(&mut r, [0, 0]);
    for ch in 1..=2u8 {
        assert_eq!(upload(&mut r, 0x6300, ch) & 0xFF, 0x01, "ch {ch}: cam 1 on");
        assert_eq!(
            upload(&mut r, 0x6400, ch) & 0x06,
            0,
            "ch {ch}: inside the area"
        );
    }
    // 50 µm on: still inside the cam window.
    measure(&mut r, [50_000, 50_000]);
    for ch in 1..=2u8 {
        assert_eq!(position(&mut r, ch), 1050);
        assert_eq!(upload(&mut r, 0x6300, ch) & 0xFF, 0x01, "ch {ch}: cam 1 on");
    }
    // 200 µm on: past the cam's high limit, still in the work area.
    measure(&mut r, [200_000, 200_000]);
    for ch in 1..=2u8 {
        assert_eq!(upload(&mut r, 0x6300, ch) & 0xFF, 0, "ch {ch}: cam 1 off");
        assert_eq!(upload(&mut r, 0x6400, ch) & 0x06, 0, "ch {ch}");
    }
    // 1 mm on: 2000 > 1500, above the work area (bit 1).
    measure(&mut r, [1_000_000, 1_000_000]);
    for ch in 1..=2u8 {
        assert_eq!(upload(&mut r, 0x6400, ch) & 0x06, 0x02, "ch {ch}: above");
    }
    // 0.6 mm back from the preset: 400 < 500, below (bit 2).
    measure(&mut r, [-600_000, -600_000]);
    for ch in 1..=2u8 {
        assert_eq!(upload(&mut r, 0x6400, ch) & 0x06, 0x04, "ch {ch}: below");
    }
}

/// §1.11.2: work-area bit 0 is set while "Position <= Preset Value or Position >= Sensor
/// length"; the sensor length is the end of the 500 mm range, in the preset's coordinates.
#[test]
fn work_area_bit_0_is_set_at_or_below_the_preset_and_at_the_sensor_length() {
    let mut r = two_channels();
    measure(&mut r, [0, 0]);
    write(&mut r, 0x6010, 1, 1000, 4);
    write(&mut r, 0x6010, 2, -20_000i32 as u32, 4);
    let bit0 = |r: &mut Rig, ch: u8| upload(r, 0x6400, ch) & 0x01;
    measure(&mut r, [0, 0]);
    assert_eq!((bit0(&mut r, 1), bit0(&mut r, 2)), (1, 1), "at the preset");
    measure(&mut r, [1000, 1000]);
    assert_eq!((bit0(&mut r, 1), bit0(&mut r, 2)), (0, 0), "1 µm beyond it");
    measure(&mut r, [-5000, -5000]);
    assert_eq!((bit0(&mut r, 1), bit0(&mut r, 2)), (1, 1), "below it");
    // The range ends at 500 mm: channel 1 reads 201000 there, channel 2 30000.
    measure(&mut r, [199_999_000, 49_999_000]);
    assert_eq!(
        (position(&mut r, 1), position(&mut r, 2)),
        (200_999, 29_999)
    );
    assert_eq!(
        (bit0(&mut r, 1), bit0(&mut r, 2)),
        (0, 0),
        "inside the range"
    );
    measure(&mut r, [200_000_000, 50_000_000]);
    assert_eq!(
        (bit0(&mut r, 1), bit0(&mut r, 2)),
        (1, 1),
        "at the sensor length"
    );
}
