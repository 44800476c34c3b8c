//! The sensor FMU's inputs: a fault the unit cannot have is not offered, and an input the
//! runtime refuses changes nothing (the next inputs still apply) (issue 31 items 1, 4).

use canpos_fmu::kind::Kind;
use canpos_fmu::model::{FmuModel, Value};
use canpos_fmu::sensor::SensorUnit;

fn running(unit: SensorUnit) -> Box<dyn FmuModel> {
    let mut m = Kind::Sensor(unit).instantiate().unwrap();
    m.enter_initialization(0.0).unwrap();
    m.exit_initialization().unwrap();
    m.enter_step_mode().unwrap();
    m
}

fn vr(m: &dyn FmuModel, name: &str) -> u32 {
    m.description()
        .variables
        .iter()
        .find(|v| v.name == name)
        .unwrap_or_else(|| panic!("no {name}"))
        .vr
}

fn units() -> Vec<SensorUnit> {
    vec![
        SensorUnit::for_model("th").unwrap(),
        SensorUnit::for_model("e-series").unwrap(),
        SensorUnit::for_model("tmi").unwrap(),
        // Two magnets.
        SensorUnit::for_order_code("EP00600MD341C304241Z02").unwrap(),
    ]
}

#[test]
fn every_offered_fault_applies_and_the_magnet_follows_after_it() {
    for (k, unit) in units().into_iter().enumerate() {
        let what = format!("{} {}", unit.model.name, unit.order_code);
        let two = unit.cfg.channels >= 2;
        let faults: Vec<(String, u32)> = Kind::Sensor(unit)
            .description()
            .unwrap()
            .variables
            .iter()
            .filter(|v| v.name.starts_with("fault_"))
            .map(|v| (v.name.clone(), v.vr))
            .collect();
        assert_eq!(
            faults.iter().any(|f| f.0 == "fault_magnets_too_close"),
            two,
            "{what}: magnets-too-close needs two channels"
        );
        for (name, f) in faults {
            let mut m = running(units().swap_remove(k));
            let mag = vr(m.as_ref(), "magnet_position[1]");
            m.set(f, Value::Boolean(true))
                .unwrap_or_else(|e| panic!("{what}: {name}: {e}"));
            m.set(mag, Value::Float64(123.0))
                .unwrap_or_else(|e| panic!("{what}: magnet after {name}: {e}"));
            m.do_step(0.0, 1e-3, false).unwrap();
        }
    }
}
