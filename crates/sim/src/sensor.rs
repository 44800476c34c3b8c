//! The measurement model: true magnet positions in, [`Sample`] out, once per cycle.

use canpos_core::encoder::{Sample, MAX_CHANNELS};
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
    /// u = position / stroke.
    pub linearity_harmonics: Vec<(f64, f64)>,
    /// Hysteresis of this unit, µm (difference between the two directions).
    pub hysteresis_um: f64,
    /// Temperature coefficient of this unit, ppm/K (signed).
    pub tempco_ppm_per_k: f64,
}

impl UnitErrors {
    fn draw(spec: &SensorSpec, rng: &mut ChaCha8Rng) -> Self {
        let bound = spec.linearity_bound_um();
        let mut h: Vec<(f64, f64)> = (1..=LINEARITY_HARMONICS)
            .map(|k| {
                let a: f64 = rng.random_range(-1.0..1.0) / k as f64;
                let phi: f64 = rng.random_range(0.0..core::f64::consts::TAU);
                (a, phi)
            })
            .collect();
        // Σ|a_k| bounds the curve, so scaling it to a fill factor < 1 keeps the unit within the
        // datasheet bound everywhere.
        let sum: f64 = h.iter().map(|(a, _)| a.abs()).sum();
        let fill: f64 = rng.random_range(0.6..0.95);
        let scale = if sum > 0.0 { bound * fill / sum } else { 0.0 };
        for (a, _) in &mut h {
            *a *= scale;
        }
        UnitErrors {
            linearity_harmonics: h,
            hysteresis_um: spec.hysteresis_um * rng.random_range(0.5..0.9),
            tempco_ppm_per_k: spec.tempco_ppm_per_k * rng.random_range(-0.9..0.9),
        }
    }

    /// Linearity deviation at `pos_mm` for a stroke of `stroke_mm`, µm.
    pub fn linearity_um(&self, pos_mm: f64, stroke_mm: f64) -> f64 {
        let u = pos_mm / stroke_mm;
        self.linearity_harmonics
            .iter()
            .enumerate()
            .map(|(i, (a, phi))| a * ((i + 1) as f64 * core::f64::consts::PI * u + phi).sin())
            .sum()
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

/// One magnetostrictive sensor unit.
///
/// Call [`Sensor::measure`] once per measurement cycle ([`SensorSpec::cycle_time_s`]) with the
/// true magnet positions; it returns the [`Sample`] the electronics would deliver:
///
/// 1. Magnets on the rod are ordered by their distance from the head (ascending position);
///    channel n reports the n-th of them. Magnets off the rod (beyond the null or dead zone),
///    `None` and non-finite inputs take no channel.
/// 2. A magnet in the null zone, in the dead zone, or closer than the minimum distance to its
///    neighbour gives no usable pulse: its channel is `None` (missing magnet).
/// 3. Channels beyond the unit's magnet count are always `None`.
/// 4. Unless the sensor is ideal, the reported position is the true position plus the error
///    budget: a smooth unit-specific linearity curve within the datasheet bound, repeatability
///    noise (Gaussian, σ = bound / 3, clipped to the bound), hysteresis (± half the unit's
///    hysteresis, by the magnet's last direction of motion) and the temperature coefficient ×
///    (ambient − 20 °C) × position. Ideal sensors report the true position, rounded to the nm.
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
    trackers: Vec<Tracker>,
    extra_tracker: Tracker,
    faults: Faults,
    ambient_c: f64,
    /// Current self-heating above ambient, K.
    rise_k: f64,
    last_t: Option<f64>,
    temp_min_c: f64,
    temp_max_c: f64,
    last_sample: Sample,
}

impl Sensor {
    /// A sensor of type `spec` whose unit-specific errors and noise derive from `seed`; `ideal`
    /// turns the whole error budget off. It starts cold (internal temperature = ambient =
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
            trackers: Vec::new(),
            extra_tracker: Tracker::default(),
            faults: Faults::default(),
            ambient_c: DEFAULT_AMBIENT_C,
            rise_k: 0.0,
            last_t: None,
            temp_min_c: DEFAULT_AMBIENT_C,
            temp_max_c: DEFAULT_AMBIENT_C,
            last_sample: Sample {
                positions_nm: [None; MAX_CHANNELS],
                temperature_c: 20,
            },
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

    /// Sets the ambient temperature, °C (must be finite).
    pub fn set_ambient_temperature_c(&mut self, t: f64) -> Result<()> {
        if !t.is_finite() {
            return Err(Error::Request(format!(
                "ambient temperature {t} is not finite"
            )));
        }
        self.ambient_c = t;
        Ok(())
    }

    /// Internal (electronics) temperature: ambient plus self-heating, or the forced value.
    pub fn internal_temperature_c(&self) -> f64 {
        self.faults
            .temperature_c
            .unwrap_or(self.ambient_c + self.rise_k)
    }

    /// Lowest internal temperature since start-up (power-on or [`Sensor::power_cycle`]), °C.
    pub fn temperature_min_c(&self) -> f64 {
        self.temp_min_c
    }

    /// Highest internal temperature since start-up, °C.
    pub fn temperature_max_c(&self) -> f64 {
        self.temp_max_c
    }

    /// Whether the internal temperature lies outside the operating range.
    pub fn temperature_out_of_range(&self) -> bool {
        let t = self.internal_temperature_c();
        let (lo, hi) = self.spec.operating_temperature_c;
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

    /// The sample returned by the last [`Sensor::measure`].
    pub fn last_sample(&self) -> &Sample {
        &self.last_sample
    }

    /// Power cycle (short outage): the electronics restart, min/max since start-up and the
    /// direction memory are reset; the thermal state (the housing stays warm) and the unit's
    /// errors are kept.
    pub fn power_cycle(&mut self) {
        self.trackers.clear();
        self.extra_tracker = Tracker::default();
        let t = self.internal_temperature_c();
        self.temp_min_c = t;
        self.temp_max_c = t;
    }

    fn advance_thermal(&mut self, t_s: f64) {
        if let Some(prev) = self.last_t {
            let dt = t_s - prev;
            if dt > 0.0 && dt.is_finite() {
                let tau = self.spec.thermal_time_constant_s;
                let k = if tau > 0.0 {
                    1.0 - (-dt / tau).exp()
                } else {
                    1.0
                };
                self.rise_k += (self.spec.self_heating_k - self.rise_k) * k;
            }
        }
        if t_s.is_finite() && !matches!(self.last_t, Some(p) if t_s <= p) {
            self.last_t = Some(t_s);
        }
        let t = self.internal_temperature_c();
        self.temp_min_c = self.temp_min_c.min(t);
        self.temp_max_c = self.temp_max_c.max(t);
    }

    /// Repeatability noise, µm.
    fn noise_um(&mut self) -> f64 {
        let bound = self.spec.repeatability_bound_um();
        // Box–Muller from two uniforms (rand_distr would add a dependency for one line).
        let u1: f64 = 1.0 - self.noise.random::<f64>(); // (0, 1]
        let u2: f64 = self.noise.random::<f64>();
        let z = (-2.0 * u1.ln()).sqrt() * (core::f64::consts::TAU * u2).cos();
        (z * bound / 3.0).clamp(-bound, bound)
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
            * (self.ambient_c - REFERENCE_TEMPERATURE_C);
        pos_mm + (lin + noise + hyst + temp) / 1000.0
    }

    /// One measurement cycle at time `t_s` (s, non-decreasing between calls) with the true
    /// magnet positions `true_positions_mm[i]` (mm from the zero point, `None` = magnet absent).
    pub fn measure(&mut self, t_s: f64, true_positions_mm: &[Option<f64>]) -> Sample {
        self.advance_thermal(t_s);
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

        if self.faults.transducer_error {
            self.last_sample = sample;
            return sample;
        }

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
            .map(|(x, _)| self.spec.in_active_stroke(*x))
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
            let reported = self.reported_mm(x, dir);
            sample.positions_nm[ch] = Some((reported * 1e6).round() as i64);
        }
        self.last_sample = sample;
        sample
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
        let out = s.measure(0.0, &[Some(-10.0), Some(500.0), Some(1030.0)]);
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
        s.measure(100_001.0, &[Some(1.0)]);
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
    fn tempco_scales_with_position_and_temperature() {
        let spec = th(2000.0, 1);
        let mut s = Sensor::new(spec, 3, false);
        let tc = s.unit_errors().tempco_ppm_per_k;
        let mean = |s: &mut Sensor, amb: f64| {
            s.set_ambient_temperature_c(amb).unwrap();
            let mut acc = 0.0;
            for i in 0..2000 {
                acc +=
                    s.measure(f64::from(i) * 1e-3, &[Some(2000.0)]).positions_nm[0].unwrap() as f64;
            }
            acc / 2000.0
        };
        let at20 = mean(&mut s, 20.0);
        let at70 = mean(&mut s, 70.0);
        let expect_nm = 2000.0 * 1e6 * tc * 1e-6 * 50.0;
        assert!(
            ((at70 - at20) - expect_nm).abs() < 500.0,
            "{} vs {expect_nm}",
            at70 - at20
        );
    }
}
