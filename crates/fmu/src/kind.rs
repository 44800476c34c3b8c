//! The kind of an FMU instance, read from the FMU's `resources/canpos-fmu.txt`: one shared
//! library serves every kind, and the file the packager wrote says which one this FMU is.
//!
//! The file is `key = value` lines (`#` starts a comment): `kind = sensor` with `model = th`
//! or `order_code = CODE`. Another kind adds a [`Kind`] variant and its arms in this file;
//! the FMI glue ([`crate::ffi`]) does not change.

use crate::bus_fmu::BusUnit;
use crate::model::{Description, FmuModel};
use crate::sensor::SensorUnit;

pub use crate::resource::{Entries, RESOURCE_FILE};

/// Changes whenever the variables' layout changes: part of every instantiation token.
const LAYOUT_VERSION: &str = "canpos-fmu-layout-1";

/// What one FMU is.
// One per instance, made once: the sensor variant's size costs nothing worth a box.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone)]
pub enum Kind {
    /// A canpos sensor (one unit: a model's default or an order code's).
    Sensor(SensorUnit),
    /// canpos's bus as an LS-BUS bus simulation (`kind = bus-simulation`, `nodes`, `bitrate`).
    BusSimulation(BusUnit),
}

impl Kind {
    /// The kind a resource file names.
    pub fn from_resource(text: &str) -> Result<Kind, String> {
        let e = Entries::parse(text)?;
        match e.get("kind") {
            Some("sensor") => Ok(Kind::Sensor(SensorUnit::from_entries(&e)?)),
            Some("bus-simulation") => Ok(Kind::BusSimulation(BusUnit::from_entries(&e)?)),
            Some(k) => Err(format!(
                "{RESOURCE_FILE}: unknown kind `{k}` (this library knows: sensor, bus-simulation)"
            )),
            None => Err(format!("{RESOURCE_FILE}: no `kind`")),
        }
    }

    /// The resource file that names this kind (what the packager writes).
    pub fn resource_text(&self) -> String {
        let body = match self {
            Kind::Sensor(u) => u.resource_entries(),
            Kind::BusSimulation(b) => b.resource_entries(),
        };
        let mut s = String::from("# canpos FMU: what this FMU is (read by the shared library)\n");
        for (k, v) in body {
            s.push_str(&format!("{k} = {v}\n"));
        }
        s
    }

    /// The FMU's description (variables, terminals, token).
    pub fn description(&self) -> Result<Description, String> {
        let token = token(&self.resource_text());
        let mut d = match self {
            Kind::Sensor(u) => u.description(token)?,
            Kind::BusSimulation(b) => b.description(token)?,
        };
        // Looked up by value reference (binary search) in every call of the glue.
        d.variables.sort_by_key(|v| v.vr);
        if let Some(w) = d.variables.windows(2).find(|w| w[0].vr == w[1].vr) {
            return Err(format!(
                "value reference {} used twice ({}, {})",
                w[0].vr, w[0].name, w[1].name
            ));
        }
        Ok(d)
    }

    /// A new instance of this kind.
    pub fn instantiate(&self) -> Result<Box<dyn FmuModel>, String> {
        let d = self.description()?;
        match self {
            Kind::Sensor(u) => Ok(Box::new(crate::sensor::SensorFmu::new(u.clone(), d)?)),
            Kind::BusSimulation(b) => Ok(Box::new(crate::bus_fmu::BusFmu::new(*b, d)?)),
        }
    }
}

/// The instantiation token: stable for one build of this library and one unit, different
/// when either changes (an FMU whose modelDescription and library disagree is refused).
pub fn token(resource_text: &str) -> String {
    let text = format!(
        "{LAYOUT_VERSION}\n{}\n{resource_text}",
        env!("CARGO_PKG_VERSION")
    );
    let fnv = |basis: u64| {
        text.bytes().fold(basis, |h, b| {
            (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01B3)
        })
    };
    let (a, b) = (fnv(0xcbf2_9ce4_8422_2325), fnv(0x6c62_272e_07bb_0142));
    format!(
        "{{{:08x}-{:04x}-{:04x}-{:04x}-{:012x}}}",
        a >> 32,
        (a >> 16) & 0xFFFF,
        a & 0xFFFF,
        b >> 48,
        b & 0xFFFF_FFFF_FFFF
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resource_files_are_checked_line_by_line() {
        assert!(Kind::from_resource("kind = sensor\nmodel = th\n").is_ok());
        for (bad, why) in [
            ("model = th", "no `kind`"),
            ("kind = toaster", "unknown kind `toaster`"),
            ("kind = sensor\nmodel th", ":2: expected `key = value`"),
            ("kind = sensor\nkind = sensor", "given twice"),
            (
                "kind = sensor\nmodel = th\ncolour = red",
                "unknown key `colour`",
            ),
            ("kind = sensor\nmodel = xyz", "unknown model `xyz`"),
        ] {
            let e = Kind::from_resource(bad).unwrap_err();
            assert!(e.contains(why), "{bad}: {e}");
        }
    }

    #[test]
    fn tokens_are_stable_per_unit_and_differ_between_units() {
        let th = Kind::from_resource("kind = sensor\nmodel = th").unwrap();
        let tmi = Kind::from_resource("kind = sensor\nmodel = tmi").unwrap();
        let t1 = th.description().unwrap().token;
        assert_eq!(t1, th.description().unwrap().token);
        assert_ne!(t1, tmi.description().unwrap().token);
        assert_eq!(t1.len(), 38, "{t1}");
    }
}
