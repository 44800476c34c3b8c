//! Property tests of the measurement model and the parsers.

use canpos_sim::motion::{MotionSpec, Profile, Ramp};
use canpos_sim::{parse_order_code, Model, Sensor, SensorSpec, Variant};
use proptest::prelude::*;

fn any_spec() -> impl Strategy<Value = SensorSpec> {
    prop_oneof![
        (25.0f64..7620.0, 1usize..=4).prop_map(|(s, m)| SensorSpec::th(s, m).unwrap()),
        (50.0f64..2540.0, 1usize..=2, 0usize..3).prop_map(|(s, m, v)| {
            let v = [Variant::Ep, Variant::El, Variant::Eh][v];
            SensorSpec::e_series(v, s, m).unwrap()
        }),
        (50.0f64..4500.0, 1usize..=2).prop_map(|(s, m)| SensorSpec::tmi(s, m).unwrap()),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 200, ..ProptestConfig::default() })]

    /// Seeded noise is reproducible: same seed + same inputs → same samples.
    #[test]
    fn same_seed_same_samples(spec in any_spec(), seed in any::<u64>(), u in 0.0f64..1.0) {
        let x = u * spec.stroke_mm;
        let mut a = Sensor::new(spec.clone(), seed, false);
        let mut b = Sensor::new(spec.clone(), seed, false);
        for i in 0..50 {
            let t = f64::from(i) * spec.cycle_time_s();
            prop_assert_eq!(a.measure(t, &[Some(x)]), b.measure(t, &[Some(x)]));
        }
    }

    /// Every reported position stays within the datasheet error budget (the temperature term
    /// at the waveguide's temperature).
    #[test]
    fn error_within_budget(
        spec in any_spec(),
        seed in any::<u64>(),
        u in 0.0f64..=1.0,
        ambient in -40.0f64..75.0,
        moves in proptest::collection::vec(-5.0f64..5.0, 1..40),
    ) {
        let mut s = Sensor::new(spec.clone(), seed, false);
        s.set_ambient_temperature_c(ambient).unwrap();
        let mut x = u * spec.stroke_mm;
        // Let the waveguide settle at the ambient first, so the tempco term is in play.
        s.measure(0.0, &[Some(x)]);
        let t0 = 100.0 * spec.waveguide_time_constant_s;
        for (i, d) in moves.iter().enumerate() {
            x = (x + d).clamp(0.0, spec.stroke_mm);
            let out = s.measure(t0 + i as f64 * 1e-3, &[Some(x)]);
            let got_mm = out.positions_nm[0].unwrap() as f64 / 1e6;
            let err_um = (got_mm - x).abs() * 1000.0;
            let bound = spec.max_error_um(x, s.waveguide_temperature_c()) + 0.001;
            prop_assert!(err_um <= bound, "error {} µm > bound {} µm at {} mm", err_um, bound, x);
        }
    }

    /// The unit's linearity curve stays within ±bound over the whole stroke.
    #[test]
    fn linearity_within_bound(spec in any_spec(), seed in any::<u64>()) {
        let s = Sensor::new(spec.clone(), seed, false);
        let bound = spec.linearity_bound_um();
        for i in 0..=200 {
            let x = spec.stroke_mm * f64::from(i) / 200.0;
            prop_assert!(s.unit_errors().linearity_um(x, spec.stroke_mm).abs() < bound);
        }
        prop_assert!(s.unit_errors().tempco_ppm_per_k.abs() < spec.tempco_ppm_per_k);
        prop_assert!(s.unit_errors().hysteresis_um < spec.hysteresis_um);
    }

    /// Ideal mode reports the exact true positions (to the nm), ordered from the head.
    #[test]
    fn ideal_is_exact(spec in any_spec(), us in proptest::collection::vec(0.0f64..=1.0, 1..=4)) {
        let mut s = Sensor::new(spec.clone(), 0, true);
        let xs: Vec<Option<f64>> = us.iter().map(|u| Some(u * spec.stroke_mm)).collect();
        let out = s.measure(0.0, &xs);
        let mut sorted: Vec<f64> = xs.iter().flatten().copied().collect();
        sorted.sort_by(f64::total_cmp);
        for (ch, x) in sorted.iter().enumerate().take(spec.magnets) {
            let too_close = (ch > 0 && x - sorted[ch - 1] < spec.min_magnet_distance_mm)
                || (ch + 1 < sorted.len() && sorted[ch + 1] - x < spec.min_magnet_distance_mm);
            let expect = if too_close { None } else { Some((x * 1e6).round() as i64) };
            prop_assert_eq!(out.positions_nm[ch], expect);
        }
        for ch in spec.magnets.min(sorted.len())..4 {
            prop_assert_eq!(out.positions_nm[ch], None);
        }
    }

    /// Arbitrary (even hostile) inputs never panic.
    #[test]
    fn measure_never_panics(
        spec in any_spec(),
        xs in proptest::collection::vec(proptest::option::of(any::<f64>()), 0..8),
        t in any::<f64>(),
    ) {
        let mut s = Sensor::new(spec, 1, false);
        let _ = s.measure(t, &xs);
        let _ = s.measure(t, &xs);
    }

    /// Motion spec text never panics and valid specs round-trip through Display.
    #[test]
    fn motion_parser_never_panics(s in ".{0,60}") {
        if let Ok(spec) = s.parse::<MotionSpec>() {
            prop_assert_eq!(spec.to_string().parse::<MotionSpec>().unwrap(), spec);
        }
    }

    /// Profiles built from arbitrary finite values round-trip through their text form.
    #[test]
    fn motion_round_trip(
        a in -1e4f64..1e4, b in -1e4f64..1e4, p in 0.001f64..1e3, v in 0.001f64..1e4,
        acc in 0.001f64..1e5, dwell in 0.0f64..10.0, repeat in any::<bool>(),
    ) {
        let profiles = vec![
            Profile::Static { pos_mm: a },
            Profile::Sine { center_mm: a, amplitude_mm: b, period_s: p, phase_deg: b },
            Profile::Triangle { min_mm: a, max_mm: b, period_s: p },
            Profile::Ramp(Ramp { from_mm: a, to_mm: b, max_velocity_mm_s: v,
                acceleration_mm_s2: acc, dwell_s: dwell, repeat }),
            Profile::Steps(vec![(0.0, a), (p, b)]),
            Profile::Absent,
        ];
        let spec = MotionSpec::Profiles(profiles);
        prop_assert_eq!(spec.to_string().parse::<MotionSpec>().unwrap(), spec);
    }

    /// Order-code text never panics.
    #[test]
    fn order_code_parser_never_panics(s in "[A-Z0-9 .µ]{0,30}") {
        let _ = parse_order_code(&s);
    }

    /// Every TH code built from the boxes parses back to its fields (strokes in the 5 mm
    /// increments of 000 §3.1).
    #[test]
    fn th_order_codes(step in 5u32..=1524, baud in 1u32..=4, res in 1u32..=2, z in 1usize..=4) {
        let stroke = step * 5;
        let zs = if z == 1 { String::new() } else { format!("Z0{z}") };
        let code = format!("THM{stroke:04}MC011DNNC304{baud}{res}1{zs}");
        let c = parse_order_code(&code).unwrap();
        prop_assert_eq!(c.model, Model::Th);
        prop_assert_eq!(c.stroke_mm, f64::from(stroke));
        prop_assert_eq!(c.bit_rate_kbit, [1000, 500, 250, 125][baud as usize - 1]);
        prop_assert_eq!(c.resolution_um, if res == 1 { 5 } else { 2 });
        prop_assert_eq!(c.magnets, z);
        prop_assert!(c.sensor_spec().is_ok());
    }
}
