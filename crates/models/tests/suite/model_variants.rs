//! The unit variants each manual lists (order code / technical data) and what a master reads
//! of them: TH 000 §8 "Measurement parameters" (resolution, cycle time by stroke and the
//! velocity step table), E-Series 001 §8, TMI 002 §1.6–§1.8 (channels, minimum step, product
//! code), D1 device type, D16 autobaud, D18 velocity step, D21 TPDO2.

use crate::common::{model, Rig};
use canpos_models::{DeviceConfig, Model};

fn unit(m: &'static Model, cfg: DeviceConfig) -> Rig {
    let mut r = Rig::with_config(m, m.configure(cfg));
    r.take();
    r
}

#[test]
fn th_velocity_step_table() {
    // (stroke mm, ordered resolution nm) → 0x6005/1 step, 0x6005/2 in 0.01 mm/s: the
    // manual's table (0.125 mm/s rounds to 13).
    let th = model("th");
    for (stroke, res, step, vstep) in [
        (1000, 5000, 5000, 50),
        (2400, 5000, 5000, 50),
        (2400, 2000, 2000, 20),
        (2401, 5000, 5000, 25),
        (4800, 2000, 2000, 10),
        (4801, 5000, 5000, 13),
        (7620, 2000, 2000, 5),
        (1000, 1000, 2000, 20),
        (1000, 2001, 5000, 50),
    ] {
        let cfg = th.default_config.with_stroke_mm(stroke).with_step_nm(res);
        let mut r = unit(th, cfg);
        assert_eq!(r.read(0x6005, 1), step, "{stroke} mm, {res} nm");
        assert_eq!(r.read(0x6005, 2), vstep, "{stroke} mm, {res} nm");
        assert_eq!(r.read(0x6501, 0), step, "{stroke} mm, {res} nm");
    }
}

#[test]
fn th_channels_and_device_type() {
    // 1 to 4 magnets; D1: 0x00080196 with one, 0x000A0196 multi-position.
    let th = model("th");
    for (n, want, dt) in [
        (0, 1, 0x0008_0196),
        (1, 1, 0x0008_0196),
        (2, 2, 0x000A_0196),
        (4, 4, 0x000A_0196),
        (9, 4, 0x000A_0196),
    ] {
        let cfg = th.configure(th.default_config.with_channels(n));
        assert_eq!(cfg.channels, want, "{n}");
        let mut r = unit(th, cfg);
        assert_eq!(r.read(0x1000, 0), dt, "{n}");
    }
}

#[test]
fn e_series_variants() {
    // 10 µm or 20 µm, 1 ms cycle, 1 or 2 magnets.
    let e = model("e-series");
    for (res, step, vstep) in [
        (5000, 10_000, 100),
        (10_000, 10_000, 100),
        (10_001, 20_000, 200),
        (20_000, 20_000, 200),
    ] {
        let mut r = unit(e, e.default_config.with_step_nm(res).with_stroke_mm(3000));
        assert_eq!(r.read(0x6005, 1), step, "{res}");
        assert_eq!(r.read(0x6005, 2), vstep, "{res}: 1 ms at any stroke");
    }
    assert_eq!(e.configure(e.default_config.with_channels(3)).channels, 2);
    assert_eq!(e.configure(e.default_config.with_channels(0)).channels, 1);
}

#[test]
fn tmi_variants_and_product_code() {
    // §1.8 product code: bit 31 two channels, bit 30 5 µm minimum step, bits 16…0 length.
    let t = model("tmi");
    for (ch, res, stroke, step, code) in [
        (1, 1000, 500, 1000, 500),
        (1, 4999, 500, 1000, 500),
        (1, 5000, 500, 5000, 0x4000_0000 | 500),
        (2, 1000, 1200, 1000, 0x8000_0000 | 1200),
        (3, 7000, 0x2_0000, 5000, 0xC001_FFFF),
    ] {
        let cfg = t.configure(
            t.default_config
                .with_channels(ch)
                .with_step_nm(res)
                .with_stroke_mm(stroke),
        );
        assert_eq!(cfg.cycle_us, 1000);
        let mut r = unit(t, cfg);
        assert_eq!(r.read(0x6005, 1), step, "{ch} ch {res} nm {stroke} mm");
        assert_eq!(r.read(0x1018, 2), code, "{ch} ch {res} nm {stroke} mm");
        assert_eq!(r.read(0x6005, 2), 250, "D18: 2.5 mm/s");
        // D21: TPDO2 (channel 2) only valid on a two-channel unit; "no RTR's" (bit 30).
        let tpdo2 = r.read(0x1801, 1);
        assert_eq!(tpdo2 & 0x7FFF_FFFF, 0x4000_02FF);
        assert_eq!(tpdo2 & 0x8000_0000 == 0, ch > 1, "{ch} channels");
    }
}

#[test]
fn tmi_autobaud_reads_0xffff() {
    // D16: 0x2001 = 0xFFFF is autobaud (0 in the configuration).
    let t = model("tmi");
    let mut r = unit(t, t.default_config.with_bitrate(0));
    assert_eq!(r.read(0x2001, 0), 0xFFFF);
    let mut r = unit(t, t.default_config.with_bitrate(250));
    assert_eq!(r.read(0x2001, 0), 250);
}

#[test]
fn max_position_is_the_range_in_steps_within_integer32() {
    // 0x650A/3 (and the work-area high limit default): stroke / step, at most INTEGER32 max.
    let th = model("th");
    let mut r = unit(th, th.default_config.with_stroke_mm(1000));
    assert_eq!(r.read(0x650A, 3), 200_000);
    assert_eq!(r.read(0x650A, 2), 0);
    assert_eq!(r.read(0x6402, 1), 200_000);
    let mut r = unit(
        th,
        th.default_config
            .with_stroke_mm(5_000_000)
            .with_step_nm(2000),
    );
    assert_eq!(r.read(0x650A, 3), i32::MAX as u32);
}
