//! The measurement model driving the CANopen core: a magnet at constant speed reads back through
//! the dictionary within the model's resolution and error budget (exactly with `ideal`).

use canpos_core::models::{by_name, Model};
use canpos_core::storage::RamStorage;
use canpos_core::{Instant, Node};
use canpos_sim::{Sensor, SensorSpec};

const SPEED_MM_S: f64 = 100.0;
const START_MM: f64 = 200.0;

fn run(
    model: &'static Model,
    spec: SensorSpec,
    ideal: bool,
    mut check: impl FnMut(f64, i32, i16, u32, u32, f64),
) {
    let mut cfg = model.default_config;
    cfg.stroke_mm = spec.stroke_mm as u32;
    cfg.channels = 1;
    let cycle_us = spec.cycle_time_us as u64;
    cfg.cycle_us = cycle_us as u32;
    let max_err_um = spec.max_error_um(START_MM + SPEED_MM_S, 20.0);
    let mut sensor = Sensor::new(spec, 7, ideal);
    let mut node = Node::new(model, cfg, RamStorage::default());
    node.power_on(Instant::ZERO);
    let step_nm = node.read_object(0x6005, 1).unwrap();
    let vstep = node.read_object(0x6005, 2).unwrap();
    for k in 1..=1000u64 {
        let t_us = k * cycle_us;
        let t = t_us as f64 / 1e6;
        let true_mm = START_MM + SPEED_MM_S * t;
        let s = sensor.measure(t, &[Some(true_mm)]);
        node.update_sample(&s, Instant(t_us));
        if k < 3 {
            continue;
        }
        let pos = node.read_object(0x6020, 1).unwrap() as i32;
        let vel = node.read_object(0x6030, 1).unwrap() as u16 as i16;
        check(true_mm, pos, vel, step_nm, vstep, max_err_um);
    }
}

fn models() -> Vec<(&'static Model, SensorSpec)> {
    vec![
        (by_name("th").unwrap(), SensorSpec::th(1000.0, 1).unwrap()),
        (
            by_name("e-series").unwrap(),
            SensorSpec::e_series(canpos_sim::Variant::Ep, 1000.0, 1).unwrap(),
        ),
        (by_name("tmi").unwrap(), SensorSpec::tmi(1000.0, 1).unwrap()),
    ]
}

#[test]
fn ideal_constant_speed_gives_exact_counts() {
    for (model, spec) in models() {
        let cycle_s = spec.cycle_time_us as f64 / 1e6;
        run(model, spec, true, |true_mm, pos, vel, step_nm, vstep, _| {
            let want = (true_mm * 1e6 / step_nm as f64).floor() as i32;
            assert!(
                (pos - want).abs() <= 1,
                "{}: pos {pos} want {want}",
                model.name
            );
            // Velocity in steps of 0.01 mm/s × vstep, from the cycle difference.
            let dx_nm = (SPEED_MM_S * cycle_s * 1e6).round();
            let want_v = (dx_nm / 10.0 / cycle_s / 1000.0 / vstep as f64).round() as i16;
            assert!(
                (vel - want_v).abs() <= 1,
                "{}: vel {vel} want {want_v}",
                model.name
            );
        });
    }
}

#[test]
fn constant_speed_within_error_budget() {
    for (model, spec) in models() {
        let cycle_s = spec.cycle_time_us as f64 / 1e6;
        let rep_um = spec.repeatability_bound_um();
        run(
            model,
            spec,
            false,
            |true_mm, pos, vel, step_nm, vstep, max_err_um| {
                let read_mm = pos as f64 * step_nm as f64 / 1e6;
                let err_um = (read_mm - true_mm).abs() * 1000.0;
                let bound = max_err_um + step_nm as f64 / 1000.0;
                assert!(
                    err_um <= bound,
                    "{}: error {err_um:.2} µm > {bound:.2} µm",
                    model.name
                );
                // Velocity noise: two repeatability errors (and one step of each) over one cycle.
                let v_mm_s = vel as f64 * vstep as f64 / 100.0;
                let v_bound = 2.0 * (rep_um + step_nm as f64 / 1000.0) / 1000.0 / cycle_s
                    + vstep as f64 / 100.0
                    + 1.0;
                assert!(
                    (v_mm_s - SPEED_MM_S).abs() <= v_bound,
                    "{}: v {v_mm_s} bound ±{v_bound}",
                    model.name
                );
            },
        );
    }
}
