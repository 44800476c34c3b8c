//! Per-product sensor specifications (technical data of the three manuals).
//!
//! Sources (the manuals: 000 TH, 001 E-Series, 002 TMI; docs/OD.md §0 names them):
//!
//! | value | TH (000) | E-Series (001) | TMI (002) |
//! | --- | --- | --- | --- |
//! | stroke | 25…7620 mm (§3.1 c, §4.1, §8) | 50…2540 mm (§3.1–3.3 c, §4.1, §8) | not stated; canpos: 50…4500 mm (fits product-code bits 16..0) |
//! | magnets | 1; Z02/Z03/Z04 → 2/3/4 (§3.1 j, §8) | 1; Z02 → 2 (§3.1–3.3 j) | 1 or 2 channels (§1.6, §1.8) |
//! | min. magnet distance | 75 mm (§4.3) | 75 mm (§4.5) | 100 mm (§4.3 "Several position markers") |
//! | cycle time | 1 ms ≤ 2400 mm, 2 ms ≤ 4800 mm, 4 ms ≤ 7620 mm (§8) | 1 ms (§8) | not stated; SPEC §1: 1 ms |
//! | linearity | < ±0.01 % F.S., min ±40 µm (§8) | ≤ ±0.02 % F.S., min ±60 µm (§8) | not stated; canpos: ±0.02 % F.S., min ±60 µm |
//! | repeatability | < ±0.001 % F.S., min ±2.5 µm (§8) | ≤ ±0.005 % F.S., min ±20 µm (§8) | not stated; canpos: ±0.001 % F.S., min ±5 µm |
//! | hysteresis | < 4 µm typical (§8) | not stated; canpos: 4 µm | not stated; canpos: 4 µm |
//! | temperature coefficient | < 15 ppm/K typical (§8) | not stated; canpos: 15 ppm/K | not stated; canpos: 15 ppm/K |
//! | supply | +24 VDC −15/+20 % (§8) | +24 VDC −15/+20 % (§8) | 24 VDC ± 20 % (§6) |
//! | operating temperature | −40…+75 °C (§8) | −40…+75 °C (§8) | not stated; canpos: −40…+85 °C |
//! | null / dead zone | in drawing Fig. 18 only (numbers lost in the text); canpos: 51 / 63.5 mm | in drawing Fig. 14 only; canpos: 25 / 66 mm (EP, EL), 30 / 63.5 mm (EH) | in drawing only; canpos: 30 / 60 mm |
//! | self-heating (electronics) | not stated; canpos: +10 K, τ = 600 s (90 mA × 24 V) | not stated; canpos: +6 K, τ = 600 s (40…60 mA) | not stated; canpos: +10 K, τ = 600 s (≤ 100 mA) |
//! | waveguide temperature | not stated; canpos: +3 K, τ = 1200 s | not stated; canpos: +2 K, τ = 1200 s | not stated; canpos: +3 K, τ = 1200 s |
//! | soft stroke edge | "can be exceeded" (§4.3), no distance; canpos: 10 mm each end | "can be exceeded" (§4.5), no distance; canpos: 5 mm each end | not stated; canpos: 2 mm each end |
//! | processing after the last pulse | not stated; canpos: 50 µs | not stated; canpos: 50 µs | not stated; canpos: 50 µs |
//! | noise | repeatability "typical" (§8); canpos: [`NoiseSpec::DEFAULT`] | canpos: [`NoiseSpec::DEFAULT`] | canpos: [`NoiseSpec::DEFAULT`] |
//!
//! Values marked "canpos" are choices where the manual is silent; they are plausible for the
//! product class and are documented on the constants below and in `docs/MEASUREMENT.md`.

use core::fmt;
use core::str::FromStr;

use crate::error::{Error, Result};

/// Speed of the torsional strain pulse along the waveguide, in mm/µs (≈ 2800 m/s, SPEC §2).
pub const WAVEGUIDE_SPEED_MM_PER_US: f64 = 2.8;

/// Reference temperature of the temperature coefficient, °C.
pub const REFERENCE_TEMPERATURE_C: f64 = 20.0;

/// The three modelled products.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Model {
    /// Temposonics TH CANbus (`th`).
    Th,
    /// Temposonics E-Series EP/EL/EH CANopen (`e-series`).
    ESeries,
    /// Novotechnik TMI CANopen (`tmi`).
    Tmi,
}

impl Model {
    /// All models, in SPEC order.
    pub const ALL: [Model; 3] = [Model::Th, Model::ESeries, Model::Tmi];

    /// The canpos model name: `"th"`, `"e-series"` or `"tmi"`.
    pub fn name(self) -> &'static str {
        match self {
            Model::Th => "th",
            Model::ESeries => "e-series",
            Model::Tmi => "tmi",
        }
    }

    /// Orderable stroke range in mm (inclusive).
    pub fn stroke_range_mm(self) -> (f64, f64) {
        match self {
            Model::Th => (25.0, 7620.0),
            Model::ESeries => (50.0, 2540.0),
            Model::Tmi => (50.0, 4500.0),
        }
    }

    /// Highest number of magnets (position channels) the product can be ordered with.
    pub fn max_magnets(self) -> usize {
        match self {
            Model::Th => 4,
            Model::ESeries | Model::Tmi => 2,
        }
    }
}

impl fmt::Display for Model {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Model {
    type Err = Error;

    /// Accepts `th`, `e-series` (also `eseries`, `e_series`, `e`) and `tmi`, case-insensitive.
    fn from_str(s: &str) -> Result<Self> {
        match s.trim().to_ascii_lowercase().as_str() {
            "th" => Ok(Model::Th),
            "e-series" | "eseries" | "e_series" | "e" => Ok(Model::ESeries),
            "tmi" => Ok(Model::Tmi),
            other => Err(Error::Spec(format!(
                "unknown model \"{other}\" (expected th, e-series or tmi)"
            ))),
        }
    }
}

/// Housing variant within a product.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Variant {
    /// Temposonics TH rod sensor (all flange types behave alike).
    Th,
    /// E-Series EP, profile housing.
    Ep,
    /// E-Series EL, low profile housing.
    El,
    /// E-Series EH, rod housing.
    Eh,
    /// Novotechnik TMI rod transducer.
    Tmi,
}

impl Variant {
    /// The model this variant belongs to.
    pub fn model(self) -> Model {
        match self {
            Variant::Th => Model::Th,
            Variant::Ep | Variant::El | Variant::Eh => Model::ESeries,
            Variant::Tmi => Model::Tmi,
        }
    }

    /// The two/three letters of the order code (`"TH"`, `"EP"`, `"EL"`, `"EH"`, `"TMI"`).
    pub fn code(self) -> &'static str {
        match self {
            Variant::Th => "TH",
            Variant::Ep => "EP",
            Variant::El => "EL",
            Variant::Eh => "EH",
            Variant::Tmi => "TMI",
        }
    }
}

impl fmt::Display for Variant {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.code())
    }
}

/// A datasheet error figure of the form "±p % F.S. (minimum ±m µm)".
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ErrorBound {
    /// Percentage of full scale (the stroke length).
    pub percent_fs: f64,
    /// Lower limit of the bound in µm.
    pub min_um: f64,
}

impl ErrorBound {
    /// The bound in µm for a stroke: `max(percent_fs % × stroke, min_um)`.
    pub fn bound_um(&self, stroke_mm: f64) -> f64 {
        (self.percent_fs / 100.0 * stroke_mm * 1000.0).max(self.min_um)
    }
}

/// Permitted supply voltage range.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SupplyRange {
    /// Nominal supply voltage in V.
    pub nominal_v: f64,
    /// Lowest permitted voltage in V.
    pub min_v: f64,
    /// Highest permitted voltage in V.
    pub max_v: f64,
}

impl SupplyRange {
    /// Whether `v` lies within `[min_v, max_v]`.
    pub fn contains(&self, v: f64) -> bool {
        v >= self.min_v && v <= self.max_v
    }
}

/// Shape of the repeatability noise, relative to the datasheet repeatability bound `b`
/// ([`SensorSpec::repeatability_bound_um`]).
///
/// Per sample and channel the noise is `drift + white`, clipped to `±b`:
///
/// * `white`: Gaussian, σ = `white_sigma_fraction × b`, independent per sample and channel
///   (flat spectrum up to the Nyquist frequency of the cycle); with probability
///   `outlier_probability` per sample it is replaced by an outlier of magnitude uniform in
///   `[b / 2, b]` and random sign (a disturbed return pulse), so the bound is a rare extreme;
/// * `drift`: one Ornstein–Uhlenbeck process shared by all channels (electronics timing drift),
///   stationary σ = `drift_sigma_fraction × b`, correlation time `drift_time_constant_s`
///   (Lorentzian spectrum, corner `1 / (2π τ)`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NoiseSpec {
    /// σ of the white component as a fraction of the repeatability bound.
    pub white_sigma_fraction: f64,
    /// Probability per sample and channel of an outlier in `[b / 2, b]`.
    pub outlier_probability: f64,
    /// Stationary σ of the drift component as a fraction of the repeatability bound.
    pub drift_sigma_fraction: f64,
    /// Correlation time of the drift component, s.
    pub drift_time_constant_s: f64,
}

impl NoiseSpec {
    /// canpos default (no manual gives a spectrum): white σ = b / 8, outliers 1 in 10⁴ samples,
    /// drift σ = b / 10 with τ = 10 s. Total σ ≈ 0.16 b: the spread is well inside the bound,
    /// which only outliers approach.
    pub const DEFAULT: NoiseSpec = NoiseSpec {
        white_sigma_fraction: 0.125,
        outlier_probability: 1e-4,
        drift_sigma_fraction: 0.1,
        drift_time_constant_s: 10.0,
    };

    /// No noise at all.
    pub const OFF: NoiseSpec = NoiseSpec {
        white_sigma_fraction: 0.0,
        outlier_probability: 0.0,
        drift_sigma_fraction: 0.0,
        drift_time_constant_s: 10.0,
    };
}

/// Everything the measurement model needs to know about one sensor unit type.
///
/// Positions are measured from the sensor's zero point (start of the active stroke). The sensor
/// head (electronics) is at `-null_zone_mm`; the rod ends at `stroke_mm + dead_zone_mm`.
#[derive(Clone, Debug, PartialEq)]
pub struct SensorSpec {
    /// Product.
    pub model: Model,
    /// Housing variant.
    pub variant: Variant,
    /// Active stroke (measuring range) in mm.
    pub stroke_mm: f64,
    /// Number of magnets / position channels the unit was ordered with.
    pub magnets: usize,
    /// Null zone: inactive length between the sensor head and the zero point, mm.
    pub null_zone_mm: f64,
    /// Dead zone: inactive length between the end of the stroke and the rod end, mm.
    pub dead_zone_mm: f64,
    /// Minimum distance between two magnets (front face to front face), mm.
    pub min_magnet_distance_mm: f64,
    /// Measurement cycle in µs.
    pub cycle_time_us: u32,
    /// Linearity deviation bound.
    pub linearity: ErrorBound,
    /// Repeatability bound.
    pub repeatability: ErrorBound,
    /// Hysteresis bound in µm (difference between approaching from either direction).
    pub hysteresis_um: f64,
    /// Temperature coefficient bound in ppm/K (of the measured position, relative to 20 °C).
    pub tempco_ppm_per_k: f64,
    /// Supply voltage range.
    pub supply: SupplyRange,
    /// Operating temperature range in °C, `(min, max)`.
    pub operating_temperature_c: (f64, f64),
    /// Steady-state self-heating of the electronics above ambient, K.
    pub self_heating_k: f64,
    /// Thermal time constant of the electronics (first-order lag toward ambient + self-heating),
    /// s.
    pub thermal_time_constant_s: f64,
    /// Steady-state rise of the waveguide above ambient (heat from the electronics and the
    /// current pulses), K.
    pub waveguide_heating_k: f64,
    /// Thermal time constant of the waveguide (first-order lag toward ambient + its rise), s.
    pub waveguide_time_constant_s: f64,
    /// How far before the zero point a magnet is still measured (soft stroke edge), mm.
    pub soft_edge_start_mm: f64,
    /// How far past the end of the active stroke a magnet is still measured, mm.
    pub soft_edge_end_mm: f64,
    /// Time the electronics need after the last return pulse before the value is ready, µs.
    pub processing_us: f64,
    /// Shape of the repeatability noise.
    pub noise: NoiseSpec,
}

/// Evaluation time after the last return pulse, µs (no manual states it; short enough that
/// every TH / E-Series stroke fits its cycle time).
const PROCESSING_US: f64 = 50.0;

/// TH: +24 VDC −15 / +20 % (000 §8).
const SUPPLY_TEMPOSONICS: SupplyRange = SupplyRange {
    nominal_v: 24.0,
    min_v: 20.4,
    max_v: 28.8,
};
/// TMI: 24 VDC ± 20 % (002 §6).
const SUPPLY_TMI: SupplyRange = SupplyRange {
    nominal_v: 24.0,
    min_v: 19.2,
    max_v: 28.8,
};

fn check_stroke(model: Model, stroke_mm: f64) -> Result<()> {
    let (lo, hi) = model.stroke_range_mm();
    if !stroke_mm.is_finite() || stroke_mm < lo || stroke_mm > hi {
        return Err(Error::Spec(format!(
            "stroke {stroke_mm} mm is outside the {} range {lo}…{hi} mm",
            model.name()
        )));
    }
    Ok(())
}

fn check_magnets(model: Model, magnets: usize) -> Result<()> {
    let max = model.max_magnets();
    if magnets == 0 || magnets > max {
        return Err(Error::Spec(format!(
            "{} supports 1…{max} magnets, not {magnets}",
            model.name()
        )));
    }
    Ok(())
}

impl SensorSpec {
    /// Temposonics TH with `stroke_mm` (25…7620) and `magnets` (1…4: standard or Z02…Z04).
    ///
    /// Cycle time 1 ms up to 2400 mm, 2 ms up to 4800 mm, 4 ms up to 7620 mm (000 §8).
    pub fn th(stroke_mm: f64, magnets: usize) -> Result<Self> {
        check_stroke(Model::Th, stroke_mm)?;
        check_magnets(Model::Th, magnets)?;
        let cycle_time_us = if stroke_mm <= 2400.0 {
            1000
        } else if stroke_mm <= 4800.0 {
            2000
        } else {
            4000
        };
        Ok(SensorSpec {
            model: Model::Th,
            variant: Variant::Th,
            stroke_mm,
            magnets,
            // canpos choice: the zones are only drawn in Fig. 18 (numbers lost in the text).
            null_zone_mm: 51.0,
            dead_zone_mm: 63.5,
            min_magnet_distance_mm: 75.0,
            cycle_time_us,
            linearity: ErrorBound {
                percent_fs: 0.01,
                min_um: 40.0,
            },
            repeatability: ErrorBound {
                percent_fs: 0.001,
                min_um: 2.5,
            },
            hysteresis_um: 4.0,
            tempco_ppm_per_k: 15.0,
            supply: SUPPLY_TEMPOSONICS,
            operating_temperature_c: (-40.0, 75.0),
            self_heating_k: 10.0,
            thermal_time_constant_s: 600.0,
            waveguide_heating_k: 3.0,
            waveguide_time_constant_s: 1200.0,
            // 000 §4.3: "the active stroke length can be exceeded" (no distance given).
            soft_edge_start_mm: 10.0,
            soft_edge_end_mm: 10.0,
            processing_us: PROCESSING_US,
            noise: NoiseSpec::DEFAULT,
        })
    }

    /// Temposonics E-Series in housing `variant` (EP, EL or EH) with `stroke_mm` (50…2540)
    /// and `magnets` (1, or 2 with option Z02). Cycle time 1 ms (001 §8).
    pub fn e_series(variant: Variant, stroke_mm: f64, magnets: usize) -> Result<Self> {
        let (null_zone_mm, dead_zone_mm) = match variant {
            Variant::Ep | Variant::El => (25.0, 66.0),
            Variant::Eh => (30.0, 63.5),
            other => {
                return Err(Error::Spec(format!(
                    "{other} is not an E-Series variant (EP, EL, EH)"
                )))
            }
        };
        check_stroke(Model::ESeries, stroke_mm)?;
        check_magnets(Model::ESeries, magnets)?;
        Ok(SensorSpec {
            model: Model::ESeries,
            variant,
            stroke_mm,
            magnets,
            null_zone_mm,
            dead_zone_mm,
            min_magnet_distance_mm: 75.0,
            cycle_time_us: 1000,
            linearity: ErrorBound {
                percent_fs: 0.02,
                min_um: 60.0,
            },
            repeatability: ErrorBound {
                percent_fs: 0.005,
                min_um: 20.0,
            },
            hysteresis_um: 4.0,
            tempco_ppm_per_k: 15.0,
            supply: SUPPLY_TEMPOSONICS,
            operating_temperature_c: (-40.0, 75.0),
            self_heating_k: 6.0,
            thermal_time_constant_s: 600.0,
            waveguide_heating_k: 2.0,
            waveguide_time_constant_s: 1200.0,
            // 001 §4.5: "the active stroke length can be exceeded" (no distance given).
            soft_edge_start_mm: 5.0,
            soft_edge_end_mm: 5.0,
            processing_us: PROCESSING_US,
            noise: NoiseSpec::DEFAULT,
        })
    }

    /// Novotechnik TMI with `stroke_mm` (defined electrical range, 50…4500) and `channels`
    /// (1 or 2 position markers). Cycle time not stated in the manual: 1 ms (SPEC §1).
    pub fn tmi(stroke_mm: f64, channels: usize) -> Result<Self> {
        check_stroke(Model::Tmi, stroke_mm)?;
        check_magnets(Model::Tmi, channels)?;
        Ok(SensorSpec {
            model: Model::Tmi,
            variant: Variant::Tmi,
            stroke_mm,
            magnets: channels,
            null_zone_mm: 30.0,
            dead_zone_mm: 60.0,
            min_magnet_distance_mm: 100.0,
            cycle_time_us: 1000,
            linearity: ErrorBound {
                percent_fs: 0.02,
                min_um: 60.0,
            },
            repeatability: ErrorBound {
                percent_fs: 0.001,
                min_um: 5.0,
            },
            hysteresis_um: 4.0,
            tempco_ppm_per_k: 15.0,
            supply: SUPPLY_TMI,
            operating_temperature_c: (-40.0, 85.0),
            self_heating_k: 10.0,
            thermal_time_constant_s: 600.0,
            waveguide_heating_k: 3.0,
            waveguide_time_constant_s: 1200.0,
            // The manual says nothing about exceeding the defined electrical range.
            soft_edge_start_mm: 2.0,
            soft_edge_end_mm: 2.0,
            processing_us: PROCESSING_US,
            noise: NoiseSpec::DEFAULT,
        })
    }

    /// The default variant of `model` (TH, EP or TMI) with the given stroke and magnets.
    pub fn for_model(model: Model, stroke_mm: f64, magnets: usize) -> Result<Self> {
        match model {
            Model::Th => Self::th(stroke_mm, magnets),
            Model::ESeries => Self::e_series(Variant::Ep, stroke_mm, magnets),
            Model::Tmi => Self::tmi(stroke_mm, magnets),
        }
    }

    /// Measurement cycle in seconds.
    pub fn cycle_time_s(&self) -> f64 {
        f64::from(self.cycle_time_us) * 1e-6
    }

    /// Linearity bound in µm for this stroke.
    pub fn linearity_bound_um(&self) -> f64 {
        self.linearity.bound_um(self.stroke_mm)
    }

    /// Repeatability bound in µm for this stroke.
    pub fn repeatability_bound_um(&self) -> f64 {
        self.repeatability.bound_um(self.stroke_mm)
    }

    /// Whether a magnet at `pos_mm` (from the zero point) lies in the active stroke.
    pub fn in_active_stroke(&self, pos_mm: f64) -> bool {
        pos_mm >= 0.0 && pos_mm <= self.stroke_mm
    }

    /// Whether a magnet at `pos_mm` gives a usable pulse: the active stroke widened by the soft
    /// edges ([`SensorSpec::soft_edge_start_mm`], [`SensorSpec::soft_edge_end_mm`]). Outside
    /// the active stroke but inside this range the position is reported (work-area bit 0 set by
    /// the encoder); beyond it the magnet is missing.
    pub fn measurable(&self, pos_mm: f64) -> bool {
        pos_mm >= -self.soft_edge_start_mm && pos_mm <= self.stroke_mm + self.soft_edge_end_mm
    }

    /// Whether a magnet at `pos_mm` lies on the rod at all (active stroke, null or dead zone).
    /// A magnet off the rod has no effect on the waveguide.
    pub fn on_rod(&self, pos_mm: f64) -> bool {
        pos_mm >= -self.null_zone_mm && pos_mm <= self.stroke_mm + self.dead_zone_mm
    }

    /// Distance of a magnet at `pos_mm` from the sensor head, mm.
    pub fn head_distance_mm(&self, pos_mm: f64) -> f64 {
        pos_mm + self.null_zone_mm
    }

    /// Time of flight of the strain pulse from a magnet at `pos_mm` to the head, µs.
    pub fn pulse_delay_us(&self, pos_mm: f64) -> f64 {
        self.head_distance_mm(pos_mm) / WAVEGUIDE_SPEED_MM_PER_US
    }

    /// Time from the start of a measurement until its value is ready, µs: the pulse's time of
    /// flight from `farthest_mm` (the farthest magnet the electronics wait for; `None`: no
    /// magnet, the whole rod is waited for) plus [`SensorSpec::processing_us`].
    pub fn ready_after_us(&self, farthest_mm: Option<f64>) -> f64 {
        let rod_end = self.stroke_mm + self.dead_zone_mm;
        let x = farthest_mm.map_or(rod_end, |x| x.clamp(-self.null_zone_mm, rod_end));
        self.pulse_delay_us(x) + self.processing_us
    }

    /// Output delay, µs: a value ready [`SensorSpec::ready_after_us`] after the start of its
    /// cycle is published at the first cycle boundary at or after that moment (a whole number
    /// of cycles, at least one).
    pub fn output_delay_us(&self, farthest_mm: Option<f64>) -> u64 {
        let cycle = u64::from(self.cycle_time_us.max(1));
        let ready = self.ready_after_us(farthest_mm).max(0.0).ceil() as u64;
        ready.div_ceil(cycle).max(1) * cycle
    }

    /// Output delay with a magnet at the far end of the rod (the largest possible), µs.
    pub fn max_output_delay_us(&self) -> u64 {
        self.output_delay_us(None)
    }

    /// Worst-case deviation in µm of a reported position at `pos_mm` with the waveguide at
    /// `temperature_c` ([`crate::Sensor::waveguide_temperature_c`]): linearity + repeatability
    /// + half the hysteresis + tempco term.
    pub fn max_error_um(&self, pos_mm: f64, temperature_c: f64) -> f64 {
        self.linearity_bound_um()
            + self.repeatability_bound_um()
            + self.hysteresis_um / 2.0
            + (pos_mm.abs() * 1000.0)
                * self.tempco_ppm_per_k
                * 1e-6
                * (temperature_c - REFERENCE_TEMPERATURE_C).abs()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn th_cycle_time_by_stroke() {
        assert_eq!(SensorSpec::th(25.0, 1).unwrap().cycle_time_us, 1000);
        assert_eq!(SensorSpec::th(2400.0, 1).unwrap().cycle_time_us, 1000);
        assert_eq!(SensorSpec::th(2405.0, 1).unwrap().cycle_time_us, 2000);
        assert_eq!(SensorSpec::th(4800.0, 1).unwrap().cycle_time_us, 2000);
        assert_eq!(SensorSpec::th(4900.0, 4).unwrap().cycle_time_us, 4000);
        assert_eq!(SensorSpec::th(7620.0, 4).unwrap().cycle_time_us, 4000);
    }

    #[test]
    fn bounds() {
        let th = SensorSpec::th(1000.0, 1).unwrap();
        assert_eq!(th.linearity_bound_um(), 100.0);
        assert_eq!(SensorSpec::th(100.0, 1).unwrap().linearity_bound_um(), 40.0);
        assert_eq!(th.repeatability_bound_um(), 10.0);
        assert_eq!(
            SensorSpec::th(100.0, 1).unwrap().repeatability_bound_um(),
            2.5
        );
        let e = SensorSpec::e_series(Variant::Eh, 1000.0, 2).unwrap();
        assert_eq!(e.linearity_bound_um(), 200.0);
        assert_eq!(
            SensorSpec::e_series(Variant::Ep, 100.0, 1)
                .unwrap()
                .linearity_bound_um(),
            60.0
        );
        assert_eq!(e.min_magnet_distance_mm, 75.0);
        assert_eq!(
            SensorSpec::tmi(500.0, 2).unwrap().min_magnet_distance_mm,
            100.0
        );
    }

    #[test]
    fn rejects_bad_values() {
        assert!(SensorSpec::th(20.0, 1).is_err());
        assert!(SensorSpec::th(7625.0, 1).is_err());
        assert!(SensorSpec::th(f64::NAN, 1).is_err());
        assert!(SensorSpec::th(500.0, 5).is_err());
        assert!(SensorSpec::th(500.0, 0).is_err());
        assert!(SensorSpec::e_series(Variant::Ep, 3000.0, 1).is_err());
        assert!(SensorSpec::e_series(Variant::Ep, 500.0, 3).is_err());
        assert!(SensorSpec::e_series(Variant::Th, 500.0, 1).is_err());
        assert!(SensorSpec::tmi(500.0, 3).is_err());
    }

    #[test]
    fn output_delay_by_stroke() {
        // Time of flight from the rod end plus 50 µs fits one cycle on every TH / E-Series.
        for (spec, cycle) in [
            (SensorSpec::th(25.0, 1).unwrap(), 1000u32),
            (SensorSpec::th(2400.0, 1).unwrap(), 1000),
            (SensorSpec::th(4800.0, 1).unwrap(), 2000),
            (SensorSpec::th(7620.0, 1).unwrap(), 4000),
            (SensorSpec::e_series(Variant::Ep, 2540.0, 1).unwrap(), 1000),
            (SensorSpec::e_series(Variant::Eh, 2540.0, 1).unwrap(), 1000),
            (SensorSpec::tmi(2000.0, 1).unwrap(), 1000),
        ] {
            let far = spec.ready_after_us(None);
            assert!(far < f64::from(cycle), "{:?} {far}", spec.variant);
            assert_eq!(spec.max_output_delay_us(), u64::from(cycle));
        }
        let th = SensorSpec::th(7620.0, 1).unwrap();
        // 7620 mm + 51 mm null zone at 2.8 mm/µs ≈ 2740 µs.
        assert!((th.ready_after_us(Some(7620.0)) - (7671.0 / 2.8 + 50.0)).abs() < 1e-9);
        assert!((th.ready_after_us(Some(0.0)) - (51.0 / 2.8 + 50.0)).abs() < 1e-9);
        // A long TMI at SPEC's 1 ms cycle: the far end takes longer than one cycle.
        let tmi = SensorSpec::tmi(4500.0, 1).unwrap();
        assert_eq!(tmi.output_delay_us(Some(100.0)), 1000);
        assert!(tmi.ready_after_us(Some(4500.0)) > 1000.0);
        assert_eq!(tmi.output_delay_us(Some(4500.0)), 2000);
    }

    #[test]
    fn soft_edge() {
        let th = SensorSpec::th(1000.0, 1).unwrap();
        assert!(th.measurable(-10.0) && th.measurable(1010.0));
        assert!(!th.measurable(-10.01) && !th.measurable(1010.01));
        let e = SensorSpec::e_series(Variant::El, 500.0, 1).unwrap();
        assert!(e.measurable(505.0) && !e.measurable(505.1) && !e.measurable(-5.1));
        let t = SensorSpec::tmi(500.0, 1).unwrap();
        assert!(t.measurable(-2.0) && !t.measurable(502.1));
        // The soft edges end well inside the null and dead zones.
        for s in [th, e, t] {
            assert!(s.soft_edge_start_mm < s.null_zone_mm && s.soft_edge_end_mm < s.dead_zone_mm);
        }
    }

    #[test]
    fn model_names_round_trip() {
        for m in Model::ALL {
            assert_eq!(m.name().parse::<Model>().unwrap(), m);
        }
        assert!("xyz".parse::<Model>().is_err());
    }
}
