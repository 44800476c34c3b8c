//! Physical model of the magnetostrictive measurement behind canpos (SPEC §2, §11).
//!
//! * [`SensorSpec`]: technical data of each product and variant (stroke, zones, minimum magnet
//!   distance, cycle time, error budget), with the manual section each number comes from.
//! * [`parse_order_code`]: the products' order codes → model, stroke, resolution, bit rate,
//!   magnets.
//! * [`motion`]: where the magnets truly are — static, sine, triangle, trapezoid ramp, steps,
//!   CSV trajectories, live set-points — and the textual spec parser used by the CLI.
//! * [`Sensor`]: one unit; per measurement cycle it turns true positions into a
//!   [`canpos_encoder::Sample`] (channels ordered from the head, missing magnets, soft
//!   stroke edges, seeded error budget, electronics temperature), with [`Faults`] injection;
//!   [`Sensor::cycle`] publishes each measurement after the strain pulse's time of flight
//!   (the next cycle boundary), and electronics and waveguide follow the ambient temperature
//!   with first-order lags. Every term, its source and how to turn it off:
//!   `docs/MEASUREMENT.md`.
//!
//! Everything is deterministic: randomness comes from a per-sensor seed (ChaCha8), there is no
//! global state.
//!
//! ```
//! use canpos_sim::{motion::{Motion, MotionSpec}, Sensor, SensorSpec};
//!
//! let spec = SensorSpec::th(1000.0, 2)?;
//! let mut motion = "sine:center=300,amp=100,period=2;static:800".parse::<MotionSpec>()?.build()?;
//! let mut sensor = Sensor::new(spec.clone(), 42, false);
//! let t = 0.5;
//! let sample = sensor.measure(t, &motion.positions_mm(t));
//! let ch1_mm = sample.positions_nm[0].unwrap() as f64 / 1e6;
//! assert!((ch1_mm - 400.0).abs() < spec.max_error_um(400.0, 20.0) / 1000.0);
//! # Ok::<(), canpos_sim::Error>(())
//! ```

#![warn(missing_docs)]

mod error;
pub mod motion;
mod order_code;
mod sensor;
mod spec;

pub use error::{Error, Result};
pub use order_code::{parse_order_code, OrderCode};
pub use sensor::{CycleTiming, Faults, Sensor, UnitErrors, DEFAULT_AMBIENT_C};
pub use spec::{
    ErrorBound, Model, NoiseSpec, SensorSpec, SupplyRange, Variant, REFERENCE_TEMPERATURE_C,
    WAVEGUIDE_SPEED_MM_PER_US,
};
