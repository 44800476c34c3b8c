//! Building a simulated sensor from the command line's or a scenario's options: the model or
//! order code, the unit's configuration, motion and faults, and its state file.

use std::path::Path;

use anyhow::{anyhow, bail, Context as _, Result};
use canpos_host::control::{self};
use canpos_host::runtime::{self, SensorSetup};
use canpos_host::FileStorage;
use canpos_models::{self as models, DeviceConfig};
use canpos_sim::motion::{MotionSpec, Profile, Profiles};
use canpos_sim::{parse_order_code, SensorSpec};
use serde::Deserialize;

use crate::common::usage;

/// Model names the command line accepts (some may not be built into the core yet).
const MODEL_NAMES: [&str; 3] = ["th", "e-series", "tmi"];

/// What selects and configures one simulated sensor (shared by `run` and scenario files).
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorOpts {
    /// `th`, `e-series` or `tmi`.
    pub model: Option<String>,
    /// With `model`: the position channels of the unit when it is not the model's default
    /// one (a two-channel TMI named by a DCF without `OrderCode`); not a scenario key.
    #[serde(skip)]
    pub unit_channels: Option<u8>,
    /// A product order code (selects model, stroke, resolution, bit rate, magnets).
    pub order_code: Option<String>,
    /// Node-id (1…127, 255 = unconfigured).
    pub node_id: Option<u8>,
    /// Serial number.
    pub serial: Option<u32>,
    /// Static magnet positions, mm.
    #[serde(default)]
    pub magnets: Vec<f64>,
    /// Motion spec.
    pub motion: Option<String>,
    /// No measurement errors.
    #[serde(default)]
    pub ideal: bool,
    /// Noise / unit error seed (default: the serial number).
    pub seed: Option<u64>,
    /// NMT state to put the node in right after its boot-up (`pre-operational`, the default
    /// as on a real unit, `operational` or `stopped`).
    pub nmt: Option<String>,
    /// Factor on the thermal time constants (electronics, waveguide); default 1.
    pub thermal_time_scale: Option<f64>,
    /// Delay before every SDO response, ms (default 0: the manuals state none).
    pub sdo_delay_ms: Option<f64>,
    /// Random extra delay of SDO responses, up to this many ms (default 0).
    pub sdo_jitter_ms: Option<f64>,
    /// Power-on to boot-up, ms (default 0).
    pub boot_delay_ms: Option<f64>,
    /// NMT reset (node or communication) to boot-up, ms (default 0).
    pub reset_boot_delay_ms: Option<f64>,
}

/// A problem with one option of a sensor: the option (its scenario key), and what is wrong.
#[derive(Debug)]
pub struct SetupError {
    /// The scenario key / option concerned, when one is.
    pub field: Option<&'static str>,
    /// What is wrong.
    pub error: anyhow::Error,
}

impl std::fmt::Display for SetupError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:#}", self.error)
    }
}

impl std::error::Error for SetupError {}

fn field_err(field: &'static str) -> impl FnOnce(anyhow::Error) -> SetupError {
    move |error| SetupError {
        field: Some(field),
        error,
    }
}

/// Something the sensor accepts, as a real unit would, but that is likely a mistake.
#[derive(Debug, Clone, PartialEq)]
pub struct SetupWarning {
    /// The scenario key / option concerned.
    pub field: &'static str,
    /// What to know.
    pub message: String,
}

/// A sensor ready to add to a runtime, and what its options gave reason to warn about.
pub struct Built {
    /// The runtime's description of the sensor.
    pub setup: SensorSetup,
    /// Warnings (the caller prints them with the right location).
    pub warnings: Vec<SetupWarning>,
    /// The NMT command to give the node after its boot-up, if any (`start`, `stop`).
    pub nmt: Option<&'static str>,
    /// The device's own timing (SDO response delay, boot delays).
    pub timing: canpos_host::timing::DeviceTiming,
}

/// The NMT state names `nmt` takes and the command that reaches each from pre-operational.
pub const NMT_STATES: [(&str, Option<&str>); 3] = [
    ("pre-operational", None),
    ("operational", Some("start")),
    ("stopped", Some("stop")),
];

/// Parses an `nmt` state name ([`NMT_STATES`]) into the command that reaches it.
pub fn parse_nmt_state(s: &str) -> Result<Option<&'static str>, String> {
    NMT_STATES
        .iter()
        .find(|(n, _)| n.eq_ignore_ascii_case(s.trim()))
        .map(|(_, c)| *c)
        .ok_or_else(|| {
            let names: Vec<_> = NMT_STATES.iter().map(|(n, _)| *n).collect();
            format!(
                "unknown NMT state `{s}`; expected one of: {}",
                names.join(", ")
            )
        })
}

fn sim_model(name: &str) -> Option<canpos_sim::Model> {
    canpos_sim::Model::ALL
        .into_iter()
        .find(|m| m.name() == name)
}

fn core_model(name: &str) -> Result<&'static models::Model> {
    if !MODEL_NAMES.contains(&name) {
        bail!(
            "unknown model `{name}`; expected one of: {}",
            MODEL_NAMES.join(", ")
        );
    }
    models::by_name(name).ok_or_else(|| {
        let have: Vec<_> = models::all().iter().map(|m| m.name).collect();
        anyhow!(
            "model `{name}` is not available in this build yet (available: {})",
            have.join(", ")
        )
    })
}

/// The unit an order code names: its model, the model's configuration with the code's stroke,
/// resolution, channels and bit rate, its measurement spec and the decoded code.
pub fn order_code_unit(
    code: &str,
) -> Result<(
    &'static models::Model,
    DeviceConfig,
    SensorSpec,
    canpos_sim::OrderCode,
)> {
    let oc = parse_order_code(code).with_context(|| format!("bad order code `{code}`"))?;
    let model = core_model(oc.model_name())?;
    let spec = oc.sensor_spec()?;
    let mut cfg = model.default_config;
    cfg.stroke_mm = oc.stroke_mm.round() as u32;
    cfg.position_step_nm = oc.resolution_nm();
    cfg.channels = oc.magnets as u8;
    cfg.bitrate_kbps = oc.bit_rate_kbit as u16;
    cfg.cycle_us = spec.cycle_time_us;
    Ok((model, cfg, spec, oc))
}

/// Builds the runtime's description of a sensor from the options, checking every value
/// against the model. The state file is not opened yet (see [`open_storage`]).
pub fn build_setup(o: &SensorOpts, state_dir: &Path) -> Result<Built, SetupError> {
    let mut warnings = Vec::new();
    let (model, mut cfg, spec): (&'static models::Model, DeviceConfig, SensorSpec) =
        match (&o.model, &o.order_code) {
            (Some(_), Some(_)) => {
                return Err(field_err("order_code")(anyhow!(
                    "give either a model or an order code, not both"
                )))
            }
            (_, Some(code)) => order_code_unit(code)
                .map(|(model, cfg, spec, _)| (model, cfg, spec))
                .map_err(field_err("order_code"))?,
            (m, None) => (|| {
                let name = m.as_deref().unwrap_or("th");
                let model = core_model(name)?;
                let mut cfg = model.default_config;
                if let Some(n) = o.unit_channels {
                    // Only a unit the model has (the widest one's channels at most).
                    cfg.channels = n.min(models::widest(model).default_config.channels);
                }
                let sm =
                    sim_model(name).ok_or_else(|| anyhow!("no measurement model for `{name}`"))?;
                let spec =
                    SensorSpec::for_model(sm, f64::from(cfg.stroke_mm), cfg.channels as usize)?;
                Ok((model, cfg, spec))
            })()
            .map_err(field_err("model"))?,
        };
    cfg.cycle_us = spec.cycle_time_us;
    let mut spec = spec;
    let mut timing = canpos_host::timing::DeviceTiming::default();
    for (field, v, slot) in [
        ("sdo_delay_ms", o.sdo_delay_ms, &mut timing.sdo_delay),
        ("sdo_jitter_ms", o.sdo_jitter_ms, &mut timing.sdo_jitter),
        ("boot_delay_ms", o.boot_delay_ms, &mut timing.boot_delay),
        (
            "reset_boot_delay_ms",
            o.reset_boot_delay_ms,
            &mut timing.reset_boot_delay,
        ),
    ] {
        if let Some(v) = v {
            *slot =
                canpos_host::timing::millis(field, v).map_err(|e| field_err(field)(anyhow!(e)))?;
        }
    }
    if let Some(k) = o.thermal_time_scale {
        // Bounded too: a huge factor would make the thermal model's arithmetic overflow.
        if !(k.is_finite() && k > 0.0 && k <= 1e6) {
            return Err(field_err("thermal_time_scale")(anyhow!(
                "thermal time scale {} must be a positive number, at most 1e6",
                control::show_num(k)
            )));
        }
        spec.thermal_time_constant_s *= k;
        spec.waveguide_time_constant_s *= k;
    }
    if let Some(id) = o.node_id {
        if !(1..=127).contains(&id) && id != 255 {
            return Err(field_err("node_id")(anyhow!(
                "node-id {id} is out of range (1…127, or 255 = unconfigured)"
            )));
        }
        cfg.node_id = id;
    }
    if let Some(s) = o.serial {
        cfg.serial = s;
    }
    let nmt = match &o.nmt {
        Some(n) => parse_nmt_state(n).map_err(|e| field_err("nmt")(anyhow!(e)))?,
        None => None,
    };
    let channels = usize::from(cfg.channels.max(1));
    let too_many = |n: usize| {
        anyhow!(
            "{n} magnets for a {} with {channels} position channel(s); give at most {channels} \
             (more channels come with the order code's magnet option; an additional magnet on \
             the rod is the extra-magnet fault)",
            model.name
        )
    };
    let motion: Box<dyn canpos_sim::motion::Motion> = match (&o.motion, o.magnets.is_empty()) {
        (Some(_), false) => {
            return Err(field_err("motion")(anyhow!(
                "give either magnet positions or a motion, not both"
            )))
        }
        (Some(m), true) => {
            let motion = MotionSpec::parse(m)
                .with_context(|| format!("bad motion spec `{m}`"))
                .and_then(|s| Ok(s.build()?))
                .map_err(field_err("motion"))?;
            if motion.magnets() > channels {
                return Err(field_err("motion")(too_many(motion.magnets())));
            }
            motion
        }
        (None, false) => {
            if o.magnets.len() > channels {
                return Err(field_err("magnets")(too_many(o.magnets.len())));
            }
            for &mm in &o.magnets {
                if !canpos_sim::motion::in_range(mm) {
                    return Err(field_err("magnets")(anyhow!(
                        "magnet position {} mm is not a finite number within ±{:e} mm",
                        control::show_num(mm),
                        canpos_sim::motion::MAX_MAGNITUDE
                    )));
                }
                if !(0.0..=spec.stroke_mm).contains(&mm) {
                    warnings.push(SetupWarning {
                        field: "magnets",
                        message: format!(
                            "magnet at {mm} mm is outside the stroke (0…{} mm); the sensor reports it as a real one would (out of range)",
                            spec.stroke_mm
                        ),
                    });
                }
            }
            if o.magnets.len() < channels {
                warnings.push(SetupWarning {
                    field: "magnets",
                    message: format!(
                        "{} magnet(s) for {channels} channels: the channels without a magnet report a missing magnet (EMCY 0x5000), as a real unit does",
                        o.magnets.len()
                    ),
                });
            }
            Box::new(Profiles(
                o.magnets
                    .iter()
                    .map(|&pos_mm| Profile::Static { pos_mm })
                    .collect(),
            ))
        }
        // Default: one magnet per channel, evenly spread over the stroke.
        (None, true) => {
            let n = f64::from(cfg.channels.max(1));
            Box::new(Profiles(
                (0..cfg.channels.max(1))
                    .map(|k| Profile::Static {
                        pos_mm: spec.stroke_mm * (f64::from(k) + 1.0) / (n + 1.0),
                    })
                    .collect(),
            ))
        }
    };
    let path = runtime::state_file(state_dir, model.name, cfg.serial);
    Ok(Built {
        setup: SensorSetup {
            name: format!("{}-{}", model.name, cfg.serial),
            model,
            cfg,
            spec,
            seed: o.seed.unwrap_or(u64::from(cfg.serial)),
            ideal: o.ideal,
            motion,
            storage: FileStorage::new(path).for_model(model),
        },
        warnings,
        nmt,
        timing,
    })
}

/// Opens the sensor's state file for use: locked against other processes, regular files only,
/// stale temporaries removed, the directory checked for writing (see [`FileStorage::open`]).
pub fn open_storage(setup: &mut SensorSetup) -> Result<()> {
    setup.storage = FileStorage::open(setup.storage.path())?.for_model(setup.model);
    Ok(())
}

/// The model (and unit configuration, and order code) an export is for.
pub(crate) fn export_unit(
    model: Option<&str>,
    order_code: Option<&str>,
) -> Result<(
    &'static canpos_models::Model,
    canpos_models::DeviceConfig,
    String,
)> {
    if let Some(code) = order_code {
        let (m, cfg, _, oc) = order_code_unit(code).map_err(|e| usage!("{e:#}"))?;
        return Ok((m, cfg, oc.normalized));
    }
    let name = model.unwrap_or("th");
    let names: Vec<&str> = canpos_models::all().iter().map(|m| m.name).collect();
    let Some(m) = canpos_models::by_name(name) else {
        bail!("unknown model `{name}` (known: {})", names.join(", "));
    };
    Ok((m, m.default_config, String::new()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn thermal_time_scale_scales_both_time_constants() {
        let dir = tempfile::tempdir().unwrap();
        let plain = build_setup(&SensorOpts::default(), dir.path())
            .unwrap()
            .setup
            .spec;
        let o = SensorOpts {
            thermal_time_scale: Some(0.01),
            ..SensorOpts::default()
        };
        let fast = build_setup(&o, dir.path()).unwrap().setup.spec;
        assert!((fast.thermal_time_constant_s - plain.thermal_time_constant_s * 0.01).abs() < 1e-9);
        assert!(
            (fast.waveguide_time_constant_s - plain.waveguide_time_constant_s * 0.01).abs() < 1e-9
        );
        for bad in [0.0, -1.0, f64::NAN, 1e300] {
            let o = SensorOpts {
                thermal_time_scale: Some(bad),
                ..SensorOpts::default()
            };
            assert!(build_setup(&o, dir.path()).is_err(), "{bad}");
        }
    }
}
