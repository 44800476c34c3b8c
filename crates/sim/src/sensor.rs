//! The measurement model: true magnet positions in, [`Sample`] out, once per cycle.

use std::collections::VecDeque;

use canpos_encoder::{Sample, MAX_CHANNELS};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::error::{Error, Result};
use crate::spec::{SensorSpec, REFERENCE_TEMPERATURE_C};

/// Number of sine harmonics of the unit's linearity curve.
const LINEARITY_HARMONICS: usize = 5;

/// Motion smaller than this (mm) between two cycles does not change the hysteresis direction.
const DIRECTION_EPSILON_MM: f64 = 1e-6;

/// Default ambient temperature, °C: the reference temperature of the temperature coefficient,
/// so that a sensor left alone has no temperature error.
pub const DEFAULT_AMBIENT_C: f64 = REFERENCE_TEMPERATURE_C;

/// Injected faults at the level of the sensing element.
///
/// What surfaces where:
///
/// | fault | here (`canpos-sim`) | in the CANopen core |
/// | --- | --- | --- |
/// | missing magnet (`missing_channels`) | the channel's position is `None` | 0x6503 bit 0, EMCY 0x5000 / clear (D13), position holds |
/// | extra magnet (`extra_magnet_mm`) | one more magnet on the rod: channels re-order; the farthest may fall off the channel list | whatever the resulting `Sample` implies |
/// | magnets too close (`too_close_channel`) | channels n and n+1 are `None` | as missing magnet |
/// | transducer error (`transducer_error`) | all channels `None`; [`Sensor::transducer_error`] is true | the model's EMCY / alarm for a sensor error |
/// | temperature (`temperature_c`) | internal temperature forced (also min/max tracking) | 0x2901, over-temperature EMCY / warning |
/// | supply voltage (`supply_voltage_v`) | [`Sensor::supply_voltage_v`], [`Sensor::supply_voltage_ok`]; measurement goes on | EMCY 0x3100 etc. |
///
/// Stored-data corruption, CAN error states, overrun, event-timer and power-cycle faults are the
/// core's and the host's business.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Faults {
    /// Channels (0-based) forced to report no usable pulse.
    pub missing_channels: [bool; MAX_CHANNELS],
    /// An additional magnet at this position (mm from the zero point).
    pub extra_magnet_mm: Option<f64>,
    /// Channels n and n+1 (0-based n) behave as if their magnets were closer than the minimum
    /// distance: both report `None`.
    pub too_close_channel: Option<usize>,
    /// The transducer (waveguide / pulse detection) reports an error: no positions at all.
    pub transducer_error: bool,
    /// Internal temperature forced to this value, °C.
    pub temperature_c: Option<f64>,
    /// Supply voltage forced to this value, V (the nominal voltage otherwise).
    pub supply_voltage_v: Option<f64>,
}

impl Faults {
    /// Checks the values (finite numbers, channel indices in range).
    pub fn validate(&self) -> Result<()> {
        let finite = |name: &str, v: Option<f64>| match v {
            Some(x) if !x.is_finite() => Err(Error::Request(format!("{name} {x} is not finite"))),
            _ => Ok(()),
        };
        finite("extra magnet position", self.extra_magnet_mm)?;
        finite("temperature", self.temperature_c)?;
        finite("supply voltage", self.supply_voltage_v)?;
        if let Some(n) = self.too_close_channel {
            if n + 1 >= MAX_CHANNELS {
                return Err(Error::Request(format!(
                    "too-close channel pair {n}/{} is out of range (0…{})",
                    n + 1,
                    MAX_CHANNELS - 2
                )));
            }
        }
        Ok(())
    }

    /// Whether any fault is set.
    pub fn any(&self) -> bool {
        *self != Faults::default()
    }
}

/// The unit-specific, seeded deviations of one sensor (its "calibration certificate").
#[derive(Clone, Debug, PartialEq)]
pub struct UnitErrors {
    /// Amplitude (µm) and phase (rad) of the linearity harmonics `sin(k π u + φ)`, k = 1…,
    /// u = position / stroke, before the end-point calibration (see
    /// [`UnitErrors::linearity_um`]).
    pub linearity_harmonics: Vec<(f64, f64)>,
    /// Hysteresis of this unit, µm (difference between the two directions).
    pub hysteresis_um: f64,
    /// Temperature coefficient of this unit, ppm/K (signed).
    pub tempco_ppm_per_k: f64,
}

/// Grid on which the calibrated linearity curve is scaled to its fill factor.
const LINEARITY_GRID: usize = 1000;

impl UnitErrors {
    fn draw(spec: &SensorSpec, rng: &mut ChaCha8Rng) -> Self {
        let bound = spec.linearity_bound_um();
        let h: Vec<(f64, f64)> = (1..=LINEARITY_HARMONICS)
            .map(|k| {
                let a: f64 = rng.random_range(-1.0..1.0) / k as f64;
                let phi: f64 = rng.random_range(0.0..core::f64::consts::TAU);
                (a, phi)
            })
            .collect();
        let fill: f64 = rng.random_range(0.6..0.9);
        let mut unit = UnitErrors {
            linearity_harmonics: h,
            hysteresis_um: spec.hysteresis_um * rng.random_range(0.5..0.9),
            tempco_ppm_per_k: spec.tempco_ppm_per_k * rng.random_range(-0.9..0.9),
        };
        // Scale the calibrated curve so that its largest deviation over the stroke is `fill` of
        // the bound. Five harmonics change little between grid points 1/1000 stroke apart, and
        // the fill factor stays below 0.9, so the curve stays inside the bound everywhere.
        let peak = (0..=LINEARITY_GRID)
            .map(|i| unit.linearity_u(i as f64 / LINEARITY_GRID as f64).abs())
            .fold(0.0, f64::max);
        let scale = if peak > 0.0 { bound * fill / peak } else { 0.0 };
        for (a, _) in &mut unit.linearity_harmonics {
            *a *= scale;
        }
        unit
    }

    fn raw_u(&self, u: f64) -> f64 {
        self.linearity_harmonics
            .iter()
            .enumerate()
            .map(|(i, (a, phi))| a * ((i + 1) as f64 * core::f64::consts::PI * u + phi).sin())
            .sum()
    }

    /// The curve after the end-point calibration: the line through the raw curve's values at
    /// the start and the end is taken off (start and end are adjusted at final inspection,
    /// 001 "Active measuring range").
    fn linearity_u(&self, u: f64) -> f64 {
        // r(0) = Σ a_k sin φ_k, r(1) = Σ (−1)^k a_k sin φ_k.
        let (r0, r1) = self.linearity_harmonics.iter().enumerate().fold(
            (0.0, 0.0),
            |(r0, r1), (i, (a, phi))| {
                let v = a * phi.sin();
                let sign = if i % 2 == 0 { -1.0 } else { 1.0 }; // k = i + 1
                (r0 + v, r1 + sign * v)
            },
        );
        self.raw_u(u) - (r0 + (r1 - r0) * u)
    }

    /// Linearity deviation at `pos_mm` for a stroke of `stroke_mm`, µm: smooth, zero at the
    /// calibrated start (0) and end (`stroke_mm`) of the active stroke, within the datasheet
    /// bound between them. Past the ends (soft stroke edge) the same curve continues.
    pub fn linearity_um(&self, pos_mm: f64, stroke_mm: f64) -> f64 {
        self.linearity_u(pos_mm / stroke_mm)
    }
}

#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct Tracker {
    last_mm: Option<f64>,
    /// +1 moving away from the head, −1 towards it, 0 not moved yet.
    direction: i8,
}

impl Tracker {
    fn update(&mut self, pos: Option<f64>) {
        if let (Some(prev), Some(now)) = (self.last_mm, pos) {
            let d = now - prev;
            if d > DIRECTION_EPSILON_MM {
                self.direction = 1;
            } else if d < -DIRECTION_EPSILON_MM {
                self.direction = -1;
            }
        }
        if pos.is_some() {
            self.last_mm = pos;
        }
    }
}

/// Tolerance when comparing a publication time with a cycle boundary, s (the runtime's
/// boundaries are whole µs; sums of f64 seconds differ from them by far less).
const TIME_EPSILON_S: f64 = 1e-7;

/// Timing of one measurement cycle (see [`Sensor::cycle`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CycleTiming {
    /// Start of the measurement (the pulse is launched), s.
    pub measured_at_s: f64,
    /// Time of flight of the strain pulse from the farthest magnet the electronics waited
    /// for (the rod end when there was none), µs.
    pub time_of_flight_us: f64,
    /// Time of flight plus processing: when the value is ready, µs after `measured_at_s`.
    pub ready_after_us: f64,
    /// Publication delay: the first cycle boundary at or after `ready_after_us`, µs.
    pub output_delay_us: u64,
}

/// One magnetostrictive sensor unit.
///
/// Call [`Sensor::cycle`] once per measurement cycle ([`SensorSpec::cycle_time_s`]) with the
/// true magnet positions; it measures them and returns the [`Sample`] the electronics publish
/// at that cycle boundary: the newest earlier measurement whose value is ready
/// ([`SensorSpec::output_delay_us`], one cycle on every TH / E-Series stroke). The measurement
/// itself ([`Sensor::measure`]):
///
/// 1. Magnets on the rod are ordered by their distance from the head (ascending position);
///    channel n reports the n-th of them. Magnets off the rod (beyond the null or dead zone),
///    `None` and non-finite inputs take no channel.
/// 2. A magnet outside the measurable range (active stroke plus the soft edges,
///    [`SensorSpec::measurable`]) or closer than the minimum distance to its neighbour gives
///    no usable pulse: its channel is `None` (missing magnet).
/// 3. Channels beyond the unit's magnet count are always `None`.
/// 4. Unless the sensor is ideal, the reported position is the true position plus the error
///    budget: a smooth unit-specific linearity curve, zero at the calibrated ends and within
///    the datasheet bound; repeatability noise ([`crate::NoiseSpec`]: white + slow drift, rare
///    outliers, clipped to the bound); hysteresis (± half the unit's hysteresis, by the
///    magnet's last direction of motion); the unit's temperature coefficient × (waveguide
///    temperature − 20 °C) × position. Ideal sensors report the true position, rounded to the
///    nm.
///
/// Temperatures: electronics and waveguide are first-order lags toward ambient plus their
/// self-heating ([`SensorSpec::thermal_time_constant_s`],
/// [`SensorSpec::waveguide_time_constant_s`]); the sample carries the electronics temperature.
///
/// Everything random derives from the seed: the same seed, inputs and call sequence give the
/// same samples.
#[derive(Clone, Debug)]
pub struct Sensor {
    spec: SensorSpec,
    seed: u64,
    ideal: bool,
    unit: UnitErrors,
    noise: ChaCha8Rng,
    /// Drift component of the noise, µm (`None` until the first noisy measurement).
    drift_um: Option<f64>,
    /// Time of the last drift update, s.
    drift_t: Option<f64>,
    trackers: Vec<Tracker>,
    extra_tracker: Tracker,
    faults: Faults,
    ambient_c: f64,
    electronics_c: f64,
    waveguide_c: f64,
    last_t: Option<f64>,
    temp_min_c: f64,
    temp_max_c: f64,
    last_sample: Sample,
    last_timing: Option<CycleTiming>,
    /// Measurements not yet published: (publication time s, timing, sample).
    pending: VecDeque<(f64, CycleTiming, Sample)>,
    published: Option<(CycleTiming, Sample)>,
}

impl Sensor {
    /// A sensor of type `spec` whose unit-specific errors and noise derive from `seed`; `ideal`
    /// turns the whole error budget off. It starts cold (electronics and waveguide at ambient =
    /// [`DEFAULT_AMBIENT_C`]).
    pub fn new(spec: SensorSpec, seed: u64, ideal: bool) -> Self {
        let mut unit_rng = ChaCha8Rng::seed_from_u64(seed);
        unit_rng.set_stream(1);
        let unit = UnitErrors::draw(&spec, &mut unit_rng);
        let mut noise = ChaCha8Rng::seed_from_u64(seed);
        noise.set_stream(2);
        Sensor {
            spec,
            seed,
            ideal,
            unit,
            noise,
            drift_um: None,
            drift_t: None,
            trackers: Vec::new(),
            extra_tracker: Tracker::default(),
            faults: Faults::default(),
            ambient_c: DEFAULT_AMBIENT_C,
            electronics_c: DEFAULT_AMBIENT_C,
            waveguide_c: DEFAULT_AMBIENT_C,
            last_t: None,
            temp_min_c: DEFAULT_AMBIENT_C,
            temp_max_c: DEFAULT_AMBIENT_C,
            last_sample: Sample {
                positions_nm: [None; MAX_CHANNELS],
                temperature_c: 20,
            },
            last_timing: None,
            pending: VecDeque::new(),
            published: None,
        }
    }

    /// The sensor type.
    pub fn spec(&self) -> &SensorSpec {
        &self.spec
    }

    /// The seed it was created with.
    pub fn seed(&self) -> u64 {
        self.seed
    }

    /// Whether the error budget is off.
    pub fn is_ideal(&self) -> bool {
        self.ideal
    }

    /// The unit-specific deviations drawn from the seed (used even when they are switched off
    /// by `ideal`, so that switching does not change the unit).
    pub fn unit_errors(&self) -> &UnitErrors {
        &self.unit
    }

    /// The currently injected faults.
    pub fn faults(&self) -> &Faults {
        &self.faults
    }

    /// Replaces the injected faults (checked with [`Faults::validate`]).
    pub fn set_faults(&mut self, faults: Faults) -> Result<()> {
        faults.validate()?;
        self.faults = faults;
        Ok(())
    }

    /// Removes all injected faults.
    pub fn clear_faults(&mut self) {
        self.faults = Faults::default();
    }

    /// Ambient temperature, °C.
    pub fn ambient_temperature_c(&self) -> f64 {
        self.ambient_c
    }

    /// Sets the ambient temperature, °C (must be finite). Electronics and waveguide follow it
    /// with their time constants.
    pub fn set_ambient_temperature_c(&mut self, t: f64) -> Result<()> {
        if !t.is_finite() {
            return Err(Error::Request(format!(
                "ambient temperature {t} is not finite"
            )));
        }
        self.ambient_c = t;
        Ok(())
    }

    /// Internal (electronics) temperature, or the value forced by a fault, °C. This is what
    /// the sample (and so TH 0x2901) carries.
    pub fn internal_temperature_c(&self) -> f64 {
        self.faults.temperature_c.unwrap_or(self.electronics_c)
    }

    /// Modelled electronics temperature (ignores a forced value), °C.
    pub fn electronics_temperature_c(&self) -> f64 {
        self.electronics_c
    }

    /// Waveguide temperature, °C: what the temperature coefficient acts on.
    pub fn waveguide_temperature_c(&self) -> f64 {
        self.waveguide_c
    }

    /// Lowest internal temperature since start-up (power-on or [`Sensor::power_cycle`]), °C.
    pub fn temperature_min_c(&self) -> f64 {
        self.temp_min_c
    }

    /// Highest internal temperature since start-up, °C.
    pub fn temperature_max_c(&self) -> f64 {
        self.temp_max_c
    }

    /// Limits of the internal temperature beyond which the unit reports a temperature error,
    /// °C: the operating range's lower end, and its upper end plus the steady self-heating (the
    /// operating range is ambient; warm electronics at the hottest allowed ambient are fine).
    pub fn temperature_limits_c(&self) -> (f64, f64) {
        let (lo, hi) = self.spec.operating_temperature_c;
        (lo, hi + self.spec.self_heating_k.max(0.0))
    }

    /// Whether the internal temperature lies outside [`Sensor::temperature_limits_c`] (the
    /// over- / under-temperature condition the host reports through the CANopen core).
    pub fn temperature_out_of_range(&self) -> bool {
        let t = self.internal_temperature_c();
        let (lo, hi) = self.temperature_limits_c();
        t < lo || t > hi
    }

    /// Supply voltage, V (nominal unless overridden by a fault).
    pub fn supply_voltage_v(&self) -> f64 {
        self.faults
            .supply_voltage_v
            .unwrap_or(self.spec.supply.nominal_v)
    }

    /// Whether the supply voltage is within the permitted range.
    pub fn supply_voltage_ok(&self) -> bool {
        self.spec.supply.contains(self.supply_voltage_v())
    }

    /// Whether the transducer reports an error (injected fault).
    pub fn transducer_error(&self) -> bool {
        self.faults.transducer_error
    }

    /// The sample of the last measurement ([`Sensor::measure`]), published or not.
    pub fn last_sample(&self) -> &Sample {
        &self.last_sample
    }

    /// Timing of the last measurement.
    pub fn last_timing(&self) -> Option<CycleTiming> {
        self.last_timing
    }

    /// The last sample [`Sensor::cycle`] published, with its timing.
    pub fn last_published(&self) -> Option<&(CycleTiming, Sample)> {
        self.published.as_ref()
    }

    /// Power cycle (short outage): the electronics restart, min/max since start-up, the
    /// direction memory and the measurements in flight are dropped; the thermal state (the
    /// housing stays warm) and the unit's errors are kept.
    pub fn power_cycle(&mut self) {
        self.trackers.clear();
        self.extra_tracker = Tracker::default();
        self.pending.clear();
        self.published = None;
        let t = self.internal_temperature_c();
        self.temp_min_c = t;
        self.temp_max_c = t;
    }

    fn advance_thermal(&mut self, t_s: f64) {
        if let Some(prev) = self.last_t {
            let dt = t_s - prev;
            if dt > 0.0 && dt.is_finite() {
                let lag = |tau: f64| {
                    if tau > 0.0 {
                        1.0 - (-dt / tau).exp()
                    } else {
                        1.0
                    }
                };
                let amb = self.ambient_c;
                let e_target = amb + self.spec.self_heating_k;
                let w_target = amb + self.spec.waveguide_heating_k;
                self.electronics_c +=
                    (e_target - self.electronics_c) * lag(self.spec.thermal_time_constant_s);
                self.waveguide_c +=
                    (w_target - self.waveguide_c) * lag(self.spec.waveguide_time_constant_s);
            }
        }
        if t_s.is_finite() && !matches!(self.last_t, Some(p) if t_s <= p) {
            self.last_t = Some(t_s);
        }
        let t = self.internal_temperature_c();
        self.temp_min_c = self.temp_min_c.min(t);
        self.temp_max_c = self.temp_max_c.max(t);
    }

    /// A standard normal deviate (Box–Muller; rand_distr would add a dependency for one line).
    fn gaussian(&mut self) -> f64 {
        let u1: f64 = 1.0 - self.noise.random::<f64>(); // (0, 1]
        let u2: f64 = self.noise.random::<f64>();
        (-2.0 * u1.ln()).sqrt() * (core::f64::consts::TAU * u2).cos()
    }

    /// Advances the drift component to `t_s` (exact discretisation of the Ornstein–Uhlenbeck
    /// process, so the statistics do not depend on the call rate).
    fn advance_drift(&mut self, t_s: f64) {
        let n = self.spec.noise;
        let sigma = n.drift_sigma_fraction * self.spec.repeatability_bound_um();
        let x = match (self.drift_um, self.drift_t) {
            // Start in the stationary distribution.
            (None, _) | (_, None) => sigma * self.gaussian(),
            (Some(x), Some(prev)) => {
                let dt = t_s - prev;
                if !(dt > 0.0 && dt.is_finite()) {
                    return;
                }
                let a = if n.drift_time_constant_s > 0.0 {
                    (-dt / n.drift_time_constant_s).exp()
                } else {
                    0.0
                };
                x * a + sigma * (1.0 - a * a).sqrt() * self.gaussian()
            }
        };
        self.drift_um = Some(x);
        if t_s.is_finite() {
            self.drift_t = Some(t_s);
        }
    }

    /// Repeatability noise of one channel's sample, µm (drift already advanced).
    fn noise_um(&mut self) -> f64 {
        let n = self.spec.noise;
        let bound = self.spec.repeatability_bound_um();
        let z = self.gaussian();
        let outlier: f64 = self.noise.random();
        let white = if outlier < n.outlier_probability {
            let mag: f64 = self.noise.random_range(0.5..=1.0);
            mag.copysign(z) * bound
        } else {
            z * n.white_sigma_fraction * bound
        };
        (self.drift_um.unwrap_or(0.0) + white).clamp(-bound, bound)
    }

    /// The reported position (µm error included) for a magnet at `pos_mm` moving in
    /// `direction`.
    fn reported_mm(&mut self, pos_mm: f64, direction: i8) -> f64 {
        if self.ideal {
            return pos_mm;
        }
        let lin = self.unit.linearity_um(pos_mm, self.spec.stroke_mm);
        let noise = self.noise_um();
        let hyst = f64::from(direction) * self.unit.hysteresis_um / 2.0;
        let temp = pos_mm
            * 1000.0
            * self.unit.tempco_ppm_per_k
            * 1e-6
            * (self.waveguide_c - REFERENCE_TEMPERATURE_C);
        pos_mm + (lin + noise + hyst + temp) / 1000.0
    }

    /// One measurement at time `t_s` (s, non-decreasing between calls) with the true magnet
    /// positions `true_positions_mm[i]` (mm from the zero point, `None` = magnet absent): what
    /// the pulse launched at `t_s` sees. [`Sensor::cycle`] adds the output timing.
    pub fn measure(&mut self, t_s: f64, true_positions_mm: &[Option<f64>]) -> Sample {
        self.advance_thermal(t_s);
        if !self.ideal {
            self.advance_drift(t_s);
        }
        let temperature_c = self.internal_temperature_c().round().clamp(-128.0, 127.0) as i8;
        let mut sample = Sample {
            positions_nm: [None; MAX_CHANNELS],
            temperature_c,
        };

        // Direction memory per input magnet (before any filtering: a magnet keeps moving
        // through the zones).
        if self.trackers.len() < true_positions_mm.len() {
            self.trackers
                .resize(true_positions_mm.len(), Tracker::default());
        }
        let clean = |p: &Option<f64>| p.filter(|x| x.is_finite());
        for (tr, p) in self.trackers.iter_mut().zip(true_positions_mm) {
            tr.update(clean(p));
        }
        let extra = self.faults.extra_magnet_mm.filter(|x| x.is_finite());
        self.extra_tracker.update(extra);

        let mut farthest: Option<f64> = None;
        if !self.faults.transducer_error {
            // (position, direction) of every magnet on the rod, ordered from the head.
            let mut on_rod: Vec<(f64, i8)> = true_positions_mm
                .iter()
                .zip(&self.trackers)
                .filter_map(|(p, tr)| clean(p).map(|x| (x, tr.direction)))
                .chain(extra.map(|x| (x, self.extra_tracker.direction)))
                .filter(|(x, _)| self.spec.on_rod(*x))
                .collect();
            on_rod.sort_by(|a, b| a.0.total_cmp(&b.0));

            let mut usable: Vec<bool> = on_rod
                .iter()
                .map(|(x, _)| self.spec.measurable(*x))
                .collect();
            for i in 1..on_rod.len() {
                if on_rod[i].0 - on_rod[i - 1].0 < self.spec.min_magnet_distance_mm {
                    usable[i] = false;
                    usable[i - 1] = false;
                }
            }
            if let Some(n) = self.faults.too_close_channel {
                for i in [n, n + 1] {
                    if let Some(u) = usable.get_mut(i) {
                        *u = false;
                    }
                }
            }

            let channels = self.spec.magnets.min(MAX_CHANNELS);
            for ch in 0..channels.min(on_rod.len()) {
                if !usable[ch] || self.faults.missing_channels[ch] {
                    continue;
                }
                let (x, dir) = on_rod[ch];
                farthest = Some(x);
                let reported = self.reported_mm(x, dir);
                sample.positions_nm[ch] = Some((reported * 1e6).round() as i64);
            }
        }
        let ready = self.spec.ready_after_us(farthest);
        self.last_timing = Some(CycleTiming {
            measured_at_s: t_s,
            time_of_flight_us: ready - self.spec.processing_us,
            ready_after_us: ready,
            output_delay_us: self.spec.output_delay_us(farthest),
        });
        self.last_sample = sample;
        sample
    }

    /// One measurement cycle at the cycle boundary `t_s`: measures ([`Sensor::measure`]) and
    /// returns what the output publishes now — the newest measurement whose publication time
    /// (its start + [`CycleTiming::output_delay_us`]) has come, or `None` when none has (the
    /// first cycle after power-on; the host then leaves the outputs alone).
    pub fn cycle(&mut self, t_s: f64, true_positions_mm: &[Option<f64>]) -> Option<Sample> {
        let sample = self.measure(t_s, true_positions_mm);
        if let Some(timing) = self.last_timing {
            let at = t_s + timing.output_delay_us as f64 * 1e-6;
            self.pending.push_back((at, timing, sample));
        }
        let due = self
            .pending
            .iter()
            .rposition(|(at, _, _)| *at <= t_s + TIME_EPSILON_S)?;
        let (_, timing, sample) = self.pending.drain(..=due).next_back()?;
        self.published = Some((timing, sample));
        Some(sample)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::spec::Variant;

    fn th(stroke: f64, magnets: usize) -> SensorSpec {
        SensorSpec::th(stroke, magnets).unwrap()
    }

    #[test]
    fn ideal_reports_exact_positions() {
        let mut s = Sensor::new(th(1000.0, 2), 1, true);
        let out = s.measure(0.0, &[Some(100.0), Some(250.5)]);
        assert_eq!(
            out.positions_nm,
            [Some(100_000_000), Some(250_500_000), None, None]
        );
        assert_eq!(out.temperature_c, 20);
    }

    #[test]
    fn channels_ordered_from_head() {
        let mut s = Sensor::new(th(2000.0, 4), 1, true);
        let out = s.measure(0.0, &[Some(900.0), Some(100.0), None, Some(500.0)]);
        assert_eq!(
            out.positions_nm,
            [
                Some(100_000_000),
                Some(500_000_000),
                Some(900_000_000),
                None
            ]
        );
    }

    #[test]
    fn zones_and_off_rod() {
        let spec = th(1000.0, 3);
        let mut s = Sensor::new(spec.clone(), 1, true);
        // null zone magnet keeps channel 1 (missing), dead zone magnet channel 3 (missing)
        let out = s.measure(0.0, &[Some(-20.0), Some(500.0), Some(1030.0)]);
        assert_eq!(out.positions_nm, [None, Some(500_000_000), None, None]);
        // off the rod: takes no channel
        let out = s.measure(0.001, &[Some(-100.0), Some(500.0), Some(2000.0)]);
        assert_eq!(out.positions_nm, [Some(500_000_000), None, None, None]);
        // boundaries of the active stroke are measurable
        let out = s.measure(0.002, &[Some(0.0), Some(1000.0)]);
        assert_eq!(out.positions_nm, [Some(0), Some(1_000_000_000), None, None]);
        assert!(spec.on_rod(-spec.null_zone_mm) && !spec.on_rod(-spec.null_zone_mm - 0.1));
    }

    #[test]
    fn min_distance() {
        let mut s = Sensor::new(th(1000.0, 3), 1, true);
        let out = s.measure(0.0, &[Some(100.0), Some(174.9), Some(600.0)]);
        assert_eq!(out.positions_nm, [None, None, Some(600_000_000), None]);
        let out = s.measure(0.0, &[Some(100.0), Some(175.0), Some(600.0)]);
        assert_eq!(
            out.positions_nm,
            [
                Some(100_000_000),
                Some(175_000_000),
                Some(600_000_000),
                None
            ]
        );
        let mut t = Sensor::new(SensorSpec::tmi(1000.0, 2).unwrap(), 1, true);
        let out = t.measure(0.0, &[Some(100.0), Some(180.0)]);
        assert_eq!(out.positions_nm, [None, None, None, None]);
    }

    #[test]
    fn more_magnets_than_channels() {
        let mut s = Sensor::new(
            SensorSpec::e_series(Variant::Ep, 1000.0, 1).unwrap(),
            1,
            true,
        );
        let out = s.measure(0.0, &[Some(700.0), Some(300.0)]);
        assert_eq!(out.positions_nm, [Some(300_000_000), None, None, None]);
    }

    #[test]
    fn faults() {
        let mut s = Sensor::new(th(1000.0, 2), 1, true);
        let mut f = Faults {
            missing_channels: [false, true, false, false],
            ..Faults::default()
        };
        s.set_faults(f.clone()).unwrap();
        let out = s.measure(0.0, &[Some(100.0), Some(500.0)]);
        assert_eq!(out.positions_nm, [Some(100_000_000), None, None, None]);
        f.missing_channels = [false; 4];
        f.extra_magnet_mm = Some(50.0);
        s.set_faults(f.clone()).unwrap();
        let out = s.measure(0.0, &[Some(300.0), Some(500.0)]);
        assert_eq!(
            out.positions_nm,
            [Some(50_000_000), Some(300_000_000), None, None]
        );
        f.extra_magnet_mm = None;
        f.too_close_channel = Some(0);
        s.set_faults(f.clone()).unwrap();
        let out = s.measure(0.0, &[Some(300.0), Some(500.0)]);
        assert_eq!(out.positions_nm, [None, None, None, None]);
        s.set_faults(Faults {
            transducer_error: true,
            ..Faults::default()
        })
        .unwrap();
        assert!(s.transducer_error());
        let out = s.measure(0.0, &[Some(300.0)]);
        assert_eq!(out.positions_nm, [None; 4]);
        s.set_faults(Faults {
            supply_voltage_v: Some(18.0),
            temperature_c: Some(90.0),
            ..Faults::default()
        })
        .unwrap();
        assert_eq!(s.supply_voltage_v(), 18.0);
        assert!(!s.supply_voltage_ok());
        let out = s.measure(0.0, &[Some(300.0)]);
        assert_eq!(out.temperature_c, 90);
        assert_eq!(out.positions_nm[0], Some(300_000_000));
        assert!(s.temperature_out_of_range());
        assert_eq!(s.temperature_max_c(), 90.0);
        s.clear_faults();
        assert_eq!(s.supply_voltage_v(), 24.0);
        assert!(s.supply_voltage_ok());
        assert!(s
            .set_faults(Faults {
                too_close_channel: Some(3),
                ..Faults::default()
            })
            .is_err());
        assert!(s
            .set_faults(Faults {
                temperature_c: Some(f64::NAN),
                ..Faults::default()
            })
            .is_err());
        assert!(s.set_ambient_temperature_c(f64::INFINITY).is_err());
    }

    #[test]
    fn self_heating_first_order() {
        let mut s = Sensor::new(th(1000.0, 1), 1, true);
        s.measure(0.0, &[Some(1.0)]);
        assert_eq!(s.internal_temperature_c(), 20.0);
        s.measure(600.0, &[Some(1.0)]);
        let expect = 20.0 + 10.0 * (1.0 - (-1.0f64).exp());
        assert!((s.internal_temperature_c() - expect).abs() < 1e-9);
        let out = s.measure(100_000.0, &[Some(1.0)]);
        assert_eq!(out.temperature_c, 30);
        s.set_ambient_temperature_c(-5.0).unwrap();
        // The electronics lag: one second later they have hardly cooled.
        s.measure(100_001.0, &[Some(1.0)]);
        assert!(s.internal_temperature_c() > 29.9);
        s.measure(200_000.0, &[Some(1.0)]);
        assert!((s.temperature_min_c() - 5.0).abs() < 1e-6);
        assert!((s.temperature_max_c() - 30.0).abs() < 1e-6);
        s.power_cycle();
        assert_eq!(s.temperature_min_c(), s.temperature_max_c());
    }

    #[test]
    fn hysteresis_follows_direction() {
        let spec = th(1000.0, 1);
        let mut s = Sensor::new(spec.clone(), 7, false);
        let h = s.unit_errors().hysteresis_um;
        assert!(h > 0.0 && h < spec.hysteresis_um);
        // Reach 500 mm from below and from above; average out the noise.
        let n = 2000;
        let mut up = 0.0;
        let mut down = 0.0;
        let mut t = 0.0;
        for _ in 0..n {
            t += 0.001;
            s.measure(t, &[Some(499.0)]);
            t += 0.001;
            up += s.measure(t, &[Some(500.0)]).positions_nm[0].unwrap() as f64;
            t += 0.001;
            s.measure(t, &[Some(501.0)]);
            t += 0.001;
            down += s.measure(t, &[Some(500.0)]).positions_nm[0].unwrap() as f64;
        }
        let diff_um = (up - down) / n as f64 / 1000.0;
        assert!(
            (diff_um - h).abs() < 0.5,
            "diff {diff_um} µm vs hysteresis {h} µm"
        );
    }

    #[test]
    fn different_seeds_different_units() {
        let a = Sensor::new(th(1000.0, 1), 1, false);
        let b = Sensor::new(th(1000.0, 1), 2, false);
        assert_ne!(a.unit_errors(), b.unit_errors());
        assert_eq!(
            a.unit_errors(),
            Sensor::new(th(1000.0, 1), 1, true).unit_errors()
        );
    }

    #[test]
    fn tempco_acts_on_the_waveguide_temperature() {
        let spec = th(2000.0, 1);
        let mut s = Sensor::new(spec, 3, false);
        let tc = s.unit_errors().tempco_ppm_per_k;
        // Settle the thermal state at `amb`, then average samples 20 s apart (longer than the
        // drift's correlation time, so the mean converges).
        s.measure(0.0, &[Some(2000.0)]);
        let mut t = 0.0;
        let mut mean = |s: &mut Sensor, amb: f64| {
            s.set_ambient_temperature_c(amb).unwrap();
            t += 100_000.0;
            s.measure(t, &[Some(2000.0)]);
            let tw = s.waveguide_temperature_c();
            let mut acc = 0.0;
            for _ in 0..2000 {
                t += 20.0;
                acc += s.measure(t, &[Some(2000.0)]).positions_nm[0].unwrap() as f64;
            }
            (acc / 2000.0, tw)
        };
        let (at20, tw20) = mean(&mut s, 20.0);
        let (at70, tw70) = mean(&mut s, 70.0);
        // Steady state: the waveguide sits its own rise above ambient.
        assert!((tw20 - 23.0).abs() < 1e-6 && (tw70 - 73.0).abs() < 1e-6);
        let expect_nm = 2000.0 * 1e6 * tc * 1e-6 * 50.0;
        assert!(
            ((at70 - at20) - expect_nm).abs() < 500.0,
            "{} vs {expect_nm}",
            at70 - at20
        );
    }

    #[test]
    fn thermal_step_responses() {
        let spec = th(1000.0, 1);
        let (tau_e, tau_w) = (spec.thermal_time_constant_s, spec.waveguide_time_constant_s);
        let mut s = Sensor::new(spec.clone(), 5, true);
        // Warm up at 20 °C (100 τ: settled), then step the ambient to 50 °C.
        s.measure(0.0, &[Some(500.0)]);
        s.measure(100.0 * tau_w, &[Some(500.0)]);
        let t0 = 100.0 * tau_w;
        assert!((s.electronics_temperature_c() - 30.0).abs() < 1e-9);
        assert!((s.waveguide_temperature_c() - 23.0).abs() < 1e-9);
        s.set_ambient_temperature_c(50.0).unwrap();
        // Nothing jumps: one cycle later both are still where they were.
        s.measure(t0 + 0.001, &[Some(500.0)]);
        assert!(s.electronics_temperature_c() - 30.0 < 0.001);
        assert_eq!(s.last_sample().temperature_c, 30);
        // Step by step on a 1 s grid; after one time constant 63.2 % of the 30 K step.
        let mut t = t0 + 0.001;
        let mut at_tau_e = None;
        while t < t0 + tau_w {
            t += 1.0;
            s.measure(t, &[Some(500.0)]);
            if at_tau_e.is_none() && t >= t0 + tau_e {
                at_tau_e = Some((t, s.electronics_temperature_c()));
            }
        }
        let (te, e) = at_tau_e.unwrap();
        let want_e = 60.0 - 30.0 * (-(te - t0) / tau_e).exp();
        assert!((e - want_e).abs() < 1e-6, "{e} vs {want_e}");
        assert!((e - (30.0 + 30.0 * (1.0 - (-1.0f64).exp()))).abs() < 0.1);
        let want_w = 53.0 - 30.0 * (-(t - t0) / tau_w).exp();
        assert!((s.waveguide_temperature_c() - want_w).abs() < 1e-6);
        assert_eq!(
            s.last_sample().temperature_c,
            s.electronics_temperature_c().round() as i8
        );
    }

    #[test]
    fn out_of_range_ambient_raises_the_temperature_condition_after_the_lag() {
        let spec = th(1000.0, 1);
        let tau = spec.thermal_time_constant_s;
        let mut s = Sensor::new(spec.clone(), 5, true);
        assert_eq!(s.temperature_limits_c(), (-40.0, 85.0));
        s.measure(0.0, &[Some(500.0)]);
        s.set_ambient_temperature_c(90.0).unwrap();
        // Electronics from 20 °C toward 100 °C: above 85 °C after τ ln(80 / 15).
        let cross = tau * (80.0f64 / 15.0).ln();
        s.measure(cross - 1.0, &[Some(500.0)]);
        assert!(!s.temperature_out_of_range());
        s.measure(cross + 1.0, &[Some(500.0)]);
        assert!(s.temperature_out_of_range());
        // Back in range: the condition ends again (by itself, no fault injected).
        s.set_ambient_temperature_c(20.0).unwrap();
        s.measure(cross + 10.0 * tau, &[Some(500.0)]);
        assert!(!s.temperature_out_of_range());
        // Cold: below −40 °C once the electronics are colder than that.
        s.set_ambient_temperature_c(-60.0).unwrap();
        s.measure(cross + 10.5 * tau, &[Some(500.0)]);
        assert!(!s.temperature_out_of_range());
        s.measure(cross + 20.0 * tau, &[Some(500.0)]);
        assert!(s.temperature_out_of_range());
        assert!((s.electronics_temperature_c() - (-50.0)).abs() < 0.01);
    }

    #[test]
    fn linearity_is_zero_at_the_calibrated_ends() {
        for spec in [
            th(1000.0, 1),
            th(7620.0, 1),
            SensorSpec::e_series(Variant::Ep, 300.0, 1).unwrap(),
            SensorSpec::tmi(4500.0, 1).unwrap(),
        ] {
            let bound = spec.linearity_bound_um();
            for seed in 0..50 {
                let u = Sensor::new(spec.clone(), seed, false);
                let e = u.unit_errors();
                assert!(e.linearity_um(0.0, spec.stroke_mm).abs() < 1e-9);
                assert!(e.linearity_um(spec.stroke_mm, spec.stroke_mm).abs() < 1e-9);
                let peak = (0..=2000)
                    .map(|i| e.linearity_um(spec.stroke_mm * f64::from(i) / 2000.0, spec.stroke_mm))
                    .fold(0.0f64, |m, v| m.max(v.abs()));
                // Uses a good part of the budget, never all of it.
                assert!(peak > 0.55 * bound && peak < bound, "{peak} vs {bound}");
                // Smooth: no step between points 1 mm apart bigger than a few % of the bound.
                let mut prev = e.linearity_um(0.0, spec.stroke_mm);
                for i in 1..=spec.stroke_mm as i32 {
                    let v = e.linearity_um(f64::from(i), spec.stroke_mm);
                    assert!((v - prev).abs() < 0.1 * bound);
                    prev = v;
                }
            }
        }
    }

    /// Noise of channel 0 at rest: reported − (true + linearity), µm, one sample per cycle.
    fn rest_noise(spec: &SensorSpec, seed: u64, n: usize, x: f64) -> Vec<f64> {
        let mut s = Sensor::new(spec.clone(), seed, false);
        let lin = s.unit_errors().linearity_um(x, spec.stroke_mm);
        let tc = s.unit_errors().tempco_ppm_per_k;
        let dt = spec.cycle_time_s();
        (0..n)
            .map(|i| {
                let nm = s.measure(i as f64 * dt, &[Some(x)]).positions_nm[0].unwrap();
                // The self-heating waveguide moves the position through the tempco.
                let temp = x * 1000.0 * tc * 1e-6 * (s.waveguide_temperature_c() - 20.0);
                nm as f64 / 1000.0 - x * 1000.0 - lin - temp
            })
            .collect()
    }

    fn std_dev(v: &[f64]) -> f64 {
        let m = v.iter().sum::<f64>() / v.len() as f64;
        (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / v.len() as f64).sqrt()
    }

    #[test]
    fn noise_spread_is_typical_and_the_bound_holds() {
        for spec in [
            th(1000.0, 1),
            SensorSpec::e_series(Variant::Eh, 1000.0, 1).unwrap(),
            SensorSpec::tmi(500.0, 1).unwrap(),
        ] {
            let b = spec.repeatability_bound_um();
            let ns = spec.noise;
            let v = rest_noise(&spec, 11, 200_000, 300.0);
            // Datasheet bound: never exceeded.
            assert!(v.iter().all(|x| x.abs() <= b + 1e-3), "bound {b}");
            // White spread from sample-to-sample differences (the drift cancels): σ_w √2.
            let d: Vec<f64> = v.windows(2).map(|w| w[1] - w[0]).collect();
            let white = std_dev(&d) / 2f64.sqrt();
            let want = ns.white_sigma_fraction * b;
            assert!((white / want - 1.0).abs() < 0.05, "white {white} vs {want}");
            // Typical spread well inside the bound: 99.9 % of the samples within b / 2.
            let inside = v.iter().filter(|x| x.abs() < b / 2.0).count();
            assert!(inside as f64 > 0.999 * v.len() as f64);
            // Rare extremes: the outliers (1 in 10⁴) do come close to the bound.
            let far = v.iter().filter(|x| x.abs() > 0.6 * b).count();
            assert!((3..=60).contains(&far), "{far} samples beyond 0.6 b");
        }
    }

    #[test]
    fn noise_has_a_slow_drift() {
        let spec = th(1000.0, 1);
        let b = spec.repeatability_bound_um();
        let ns = spec.noise;
        // 1 s means over 2000 s: white noise averages out (σ_w / √1000), the drift does not.
        let v = rest_noise(&spec, 4, 2_000_000, 300.0);
        let means: Vec<f64> = v
            .chunks(1000)
            .map(|c| c.iter().sum::<f64>() / c.len() as f64)
            .collect();
        let sd = std_dev(&means);
        let want = ns.drift_sigma_fraction * b;
        assert!((sd / want - 1.0).abs() < 0.3, "drift σ {sd} vs {want}");
        // Correlated over seconds: neighbouring 1 s means are close, distant ones independent.
        let corr = |lag: usize| {
            let m = means.iter().sum::<f64>() / means.len() as f64;
            let num: f64 = means
                .windows(lag + 1)
                .map(|w| (w[0] - m) * (w[lag] - m))
                .sum::<f64>()
                / (means.len() - lag) as f64;
            num / (sd * sd)
        };
        let tau = ns.drift_time_constant_s;
        assert!((corr(1) - (-1.0 / tau).exp()).abs() < 0.15, "{}", corr(1));
        assert!(corr(100).abs() < 0.2, "{}", corr(100));
        // Ideal has no noise at all.
        let mut ideal = Sensor::new(spec, 4, true);
        assert!((0..1000).all(|i| ideal
            .measure(f64::from(i) * 1e-3, &[Some(300.0)])
            .positions_nm[0]
            == Some(300_000_000)));
    }

    #[test]
    fn noise_is_reproducible_by_seed() {
        let spec = SensorSpec::e_series(Variant::Ep, 1000.0, 2).unwrap();
        let run = |seed| {
            let mut s = Sensor::new(spec.clone(), seed, false);
            (0..2000)
                .map(|i| s.measure(f64::from(i) * 1e-3, &[Some(100.0), Some(700.0)]))
                .collect::<Vec<_>>()
        };
        assert_eq!(run(9), run(9));
        assert_ne!(run(9), run(10));
    }

    /// Runs `cycle` at every boundary from 0 with the magnet at `before` until `t_step_s`,
    /// `after` from then on; returns (first boundary that measured `after`, first boundary
    /// that published it).
    fn first_publication(spec: &SensorSpec, before: f64, after: f64, t_step_s: f64) -> (f64, f64) {
        let mut s = Sensor::new(spec.clone(), 1, true);
        let dt = spec.cycle_time_s();
        let want = Some((after * 1e6).round() as i64);
        let mut measured = None;
        for k in 0..1000 {
            let t = k as f64 * dt;
            let x = if t >= t_step_s { after } else { before };
            let out = s.cycle(t, &[Some(x)]);
            if k == 0 {
                assert_eq!(out, None, "nothing is ready at the first boundary");
            }
            if measured.is_none() && s.last_sample().positions_nm[0] == want {
                measured = Some(t);
            }
            if out.map(|o| o.positions_nm[0]) == Some(want) {
                return (measured.unwrap(), t);
            }
        }
        panic!("never published");
    }

    #[test]
    fn output_delay_against_the_time_of_flight() {
        for (spec, x) in [
            (th(100.0, 1), 90.0),
            (th(7620.0, 1), 7600.0),
            (
                SensorSpec::e_series(Variant::Ep, 2540.0, 1).unwrap(),
                2540.0,
            ),
            (SensorSpec::tmi(4500.0, 1).unwrap(), 4500.0),
            (SensorSpec::tmi(4500.0, 1).unwrap(), 500.0),
        ] {
            let t_step = 0.0105;
            let (measured, published) = first_publication(&spec, x - 20.0, x, t_step);
            let tof_us = (x + spec.null_zone_mm) / crate::WAVEGUIDE_SPEED_MM_PER_US;
            let ready_us = tof_us + spec.processing_us;
            // Published at the first cycle boundary after the pulse returned and was evaluated.
            let want = spec.output_delay_us(Some(x)) as f64 * 1e-6;
            assert!((published - measured - want).abs() < 1e-9);
            assert!(published - measured >= ready_us * 1e-6);
            assert!(published - measured < ready_us * 1e-6 + spec.cycle_time_s());
            // Never earlier than the change plus the time of flight.
            assert!(published - t_step >= tof_us * 1e-6);
        }
        // Long TMI: two cycles from the far end, one near the head.
        let tmi = SensorSpec::tmi(4500.0, 1).unwrap();
        assert_eq!(tmi.output_delay_us(Some(4500.0)), 2000);
        assert_eq!(tmi.output_delay_us(Some(500.0)), 1000);
    }

    #[test]
    fn cycle_publishes_in_order_and_reports_its_timing() {
        let spec = th(7620.0, 2);
        let mut s = Sensor::new(spec.clone(), 1, true);
        let dt = spec.cycle_time_s();
        assert_eq!(s.cycle(0.0, &[Some(100.0), Some(7000.0)]), None);
        for k in 1..20 {
            let t = f64::from(k) * dt;
            let out = s
                .cycle(t, &[Some(100.0 + f64::from(k)), Some(7000.0)])
                .unwrap();
            // The value published at boundary k was measured at boundary k − 1.
            assert_eq!(
                out.positions_nm[0],
                Some((100.0 + f64::from(k - 1)) as i64 * 1_000_000)
            );
            let (timing, _) = s.last_published().unwrap();
            assert!((timing.measured_at_s - (t - dt)).abs() < 1e-12);
            // The farthest magnet sets the time of flight.
            let tof = (7000.0 + spec.null_zone_mm) / crate::WAVEGUIDE_SPEED_MM_PER_US;
            assert!((timing.time_of_flight_us - tof).abs() < 1e-9);
            assert_eq!(timing.output_delay_us, 4000);
        }
        // A power cycle drops the measurements in flight.
        s.power_cycle();
        assert!(s.last_published().is_none());
        assert_eq!(s.cycle(1.0, &[Some(100.0)]), None);
        assert!(s.cycle(1.0 + dt, &[Some(100.0)]).is_some());
    }

    #[test]
    fn soft_stroke_edge() {
        let spec = th(1000.0, 2);
        let mut s = Sensor::new(spec.clone(), 1, true);
        // A few mm past either end: still measured (the encoder sets work-area bit 0).
        let out = s.measure(0.0, &[Some(-8.0), Some(1008.0)]);
        assert_eq!(
            out.positions_nm,
            [Some(-8_000_000), Some(1_008_000_000), None, None]
        );
        let out = s.measure(
            0.001,
            &[
                Some(-spec.soft_edge_start_mm),
                Some(1000.0 + spec.soft_edge_end_mm),
            ],
        );
        assert!(out.positions_nm[0].is_some() && out.positions_nm[1].is_some());
        // Beyond the soft edge: missing magnet.
        let out = s.measure(0.002, &[Some(-10.5), Some(1010.5)]);
        assert_eq!(out.positions_nm, [None, None, None, None]);
        for (spec, edge) in [
            (SensorSpec::e_series(Variant::Ep, 500.0, 1).unwrap(), 5.0),
            (SensorSpec::tmi(500.0, 1).unwrap(), 2.0),
        ] {
            let mut s = Sensor::new(spec, 1, true);
            assert!(s.measure(0.0, &[Some(500.0 + edge)]).positions_nm[0].is_some());
            assert!(s.measure(0.001, &[Some(500.0 + edge + 0.5)]).positions_nm[0].is_none());
        }
    }
}
