//! The measurement model driving the CANopen core: a magnet at constant speed reads back through
//! the dictionary within the model's resolution and error budget (exactly with `ideal`).

use canpos_models::SensorNode;
use canpos_models::{by_name, Model};
use canpos_sim::{Sensor, SensorSpec};
use canpos_stack::storage::RamStorage;
use canpos_stack::{Instant, Node};

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
    let mut node = SensorNode::new(model, cfg, RamStorage::default());
    node.power_on(Instant::ZERO);
    let step_nm = node.read_object(0x6005, 1).unwrap();
    let vstep = node.read_object(0x6005, 2).unwrap();
    for k in 1..=1000u64 {
        let t_us = k * cycle_us;
        let t = t_us as f64 / 1e6;
        let true_mm = START_MM + SPEED_MM_S * t;
        let s = sensor.measure(t, &[Some(true_mm)]);
        node.update_sample(&s, Instant::from_micros(t_us));
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
            // Quantised to the nearest step.
            let want = (true_mm * 1e6 / step_nm as f64).round() as i32;
            assert_eq!(pos, want, "{}", model.name);
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

/// A TH node (5 µm steps by default) fed by an ideal sensor through [`Sensor::cycle`], one
/// cycle per call.
struct Chain {
    sensor: Sensor,
    node: SensorNode<RamStorage>,
    k: u64,
    cycle_us: u64,
}

impl Chain {
    fn new(name: &str, spec: SensorSpec) -> Chain {
        let model = by_name(name).unwrap();
        let mut cfg = model.default_config;
        cfg.stroke_mm = spec.stroke_mm as u32;
        cfg.channels = 1;
        cfg.cycle_us = spec.cycle_time_us;
        let mut node = Node::new(model, cfg, RamStorage::default());
        node.power_on(Instant::ZERO);
        Chain {
            cycle_us: u64::from(spec.cycle_time_us),
            sensor: Sensor::new(spec, 3, true),
            node,
            k: 0,
        }
    }

    /// Runs `n` cycles with the magnet at `mm`.
    fn run(&mut self, mm: f64, n: u32) {
        for _ in 0..n {
            self.k += 1;
            let t_us = self.k * self.cycle_us;
            if let Some(s) = self.sensor.cycle(t_us as f64 / 1e6, &[Some(mm)]) {
                self.node.update_sample(&s, Instant::from_micros(t_us));
            }
        }
    }

    fn read(&mut self, index: u16, sub: u8) -> u32 {
        self.node.read_object(index, sub).unwrap()
    }
}

#[test]
fn quantisation_rounds_to_nearest() {
    let mut c = Chain::new("th", SensorSpec::th(1000.0, 1).unwrap());
    assert_eq!(c.read(0x6005, 1), 5000);
    for (mm, steps) in [
        (55.0032, 11001), // truncation would give 11000 (55.000 mm)
        (55.0024, 11000),
        (55.0025, 11001), // halves up
        (55.0074, 11001),
        (0.0024, 0),
    ] {
        c.run(mm, 3);
        assert_eq!(c.read(0x6020, 1) as i32, steps, "{mm} mm");
    }
    // No mean bias over a sweep through one step in 0.1 µm increments.
    let mut sum = 0.0;
    for i in 0..50 {
        let mm = 100.0 + f64::from(i) * 1e-4;
        c.run(mm, 2);
        sum += f64::from(c.read(0x6020, 1) as i32) * 0.005 - mm;
    }
    let bias_um = sum / 50.0 * 1000.0;
    assert!(bias_um.abs() < 0.2, "bias {bias_um} µm");
}

#[test]
fn soft_edge_is_measured_with_work_area_bit_0() {
    for (name, spec) in [
        ("th", SensorSpec::th(1000.0, 1).unwrap()),
        (
            "e-series",
            SensorSpec::e_series(canpos_sim::Variant::Ep, 1000.0, 1).unwrap(),
        ),
        ("tmi", SensorSpec::tmi(1000.0, 1).unwrap()),
    ] {
        let (start, end) = (spec.soft_edge_start_mm, spec.soft_edge_end_mm);
        let mut c = Chain::new(name, spec);
        let step_mm = f64::from(c.read(0x6005, 1)) / 1e6;
        c.run(500.0, 3);
        assert_eq!(c.read(0x6400, 1) & 1, 0, "{name}");
        // Inside the soft edge at either end: measured, outside the measuring range.
        for mm in [1000.0 + end * 0.8, -start * 0.8] {
            c.run(mm, 3);
            let pos = f64::from(c.read(0x6020, 1) as i32) * step_mm;
            assert!((pos - mm).abs() <= step_mm, "{name}: {pos} vs {mm}");
            assert_eq!(c.read(0x6400, 1) & 1, 1, "{name} at {mm} mm");
            assert_eq!(c.read(0x6503, 0) & 1, 0, "{name}: no alarm at {mm} mm");
        }
        // Past the soft edge: missing magnet (alarm), the position holds.
        c.run(1000.0 + end + 1.0, 3);
        assert_eq!(c.read(0x6503, 0) & 1, 1, "{name}");
    }
}

#[test]
fn position_change_reaches_the_dictionary_one_cycle_later() {
    // 7620 mm TH: 4 ms cycle, time of flight from 7600 mm ≈ 2.7 ms.
    let mut c = Chain::new("th", SensorSpec::th(7620.0, 1).unwrap());
    c.run(7500.0, 5);
    assert_eq!(c.read(0x6020, 1), 1_500_000);
    // The boundary that measures 7600 mm still shows 7500 mm; the next one shows 7600 mm.
    c.run(7600.0, 1);
    assert_eq!(c.read(0x6020, 1), 1_500_000);
    c.run(7600.0, 1);
    assert_eq!(c.read(0x6020, 1), 1_520_000);
    let (timing, _) = *c.sensor.last_published().unwrap();
    assert_eq!(timing.output_delay_us, 4000);
    assert!(timing.ready_after_us > 2700.0 && timing.ready_after_us < 4000.0);
}
