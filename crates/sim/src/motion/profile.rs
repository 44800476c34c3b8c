//! Analytic single-magnet trajectories.

use core::f64::consts::TAU;

use super::source::{in_range, MAX_MAGNITUDE, MIN_PERIOD_S};
use crate::error::{Error, Result};

/// A trapezoidal back-and-forth ramp: dwell at `from`, move to `to` with limited velocity and
/// acceleration, dwell at `to`, move back, and so on (or stop at `to` when `repeat` is false).
#[derive(Clone, Debug, PartialEq)]
pub struct Ramp {
    /// Start position, mm.
    pub from_mm: f64,
    /// End position, mm.
    pub to_mm: f64,
    /// Maximum velocity, mm/s (> 0).
    pub max_velocity_mm_s: f64,
    /// Acceleration and deceleration, mm/s² (> 0).
    pub acceleration_mm_s2: f64,
    /// Dwell at each end, s (≥ 0).
    pub dwell_s: f64,
    /// Whether the ramp goes back and forth for ever (`true`) or stops at `to_mm`.
    pub repeat: bool,
}

impl Ramp {
    /// Checks the parameters (finite, velocity and acceleration > 0, dwell ≥ 0).
    pub fn validate(&self) -> Result<()> {
        let bad = |r: &str| {
            Err(Error::MotionSpec {
                spec: format!("{self:?}"),
                reason: r.into(),
            })
        };
        let all = [
            self.from_mm,
            self.to_mm,
            self.max_velocity_mm_s,
            self.acceleration_mm_s2,
            self.dwell_s,
        ];
        if !all.iter().all(|v| in_range(*v)) {
            return bad("values must be finite and within ±1e9");
        }
        if !(self.max_velocity_mm_s.is_finite() && self.max_velocity_mm_s > 0.0) {
            return bad("v (max velocity) must be > 0");
        }
        if !(self.acceleration_mm_s2.is_finite() && self.acceleration_mm_s2 > 0.0) {
            return bad("a (acceleration) must be > 0");
        }
        if !(self.dwell_s.is_finite() && self.dwell_s >= 0.0) {
            return bad("dwell must be ≥ 0");
        }
        Ok(())
    }

    /// Duration of one move from one end to the other, s.
    pub fn move_time_s(&self) -> f64 {
        let d = (self.to_mm - self.from_mm).abs();
        let (v, a) = (self.max_velocity_mm_s, self.acceleration_mm_s2);
        if d == 0.0 {
            return 0.0;
        }
        if v * v / a >= d {
            2.0 * (d / a).sqrt()
        } else {
            v / a + d / v
        }
    }

    /// Distance travelled `tau` seconds into a move (0 ≤ tau ≤ move time).
    fn travelled(&self, tau: f64) -> f64 {
        let d = (self.to_mm - self.from_mm).abs();
        let (v, a) = (self.max_velocity_mm_s, self.acceleration_mm_s2);
        let total = self.move_time_s();
        let tau = tau.clamp(0.0, total);
        if v * v / a >= d {
            // Triangular profile: peak velocity sqrt(a d) at total / 2.
            let half = total / 2.0;
            if tau <= half {
                0.5 * a * tau * tau
            } else {
                let r = total - tau;
                d - 0.5 * a * r * r
            }
        } else {
            let t_acc = v / a;
            if tau <= t_acc {
                0.5 * a * tau * tau
            } else if tau <= total - t_acc {
                0.5 * v * t_acc + v * (tau - t_acc)
            } else {
                let r = total - tau;
                d - 0.5 * a * r * r
            }
        }
    }

    /// Position at time `t_s` (the ramp starts at t = 0 with a dwell at `from_mm`).
    pub fn at(&self, t_s: f64) -> f64 {
        let (from, to) = (self.from_mm, self.to_mm);
        let mv = self.move_time_s();
        let dwell = self.dwell_s;
        let t = t_s.max(0.0);
        let period = 2.0 * (dwell + mv);
        if period <= 0.0 {
            return if self.repeat { from } else { to };
        }
        let dir = (to - from).signum();
        if !self.repeat {
            if t < dwell {
                return from;
            }
            return from + dir * self.travelled(t - dwell);
        }
        let u = t % period;
        if u < dwell {
            from
        } else if u < dwell + mv {
            from + dir * self.travelled(u - dwell)
        } else if u < 2.0 * dwell + mv {
            to
        } else {
            to - dir * self.travelled(u - 2.0 * dwell - mv)
        }
    }
}

/// A single-magnet trajectory, evaluated at an absolute time.
#[derive(Clone, Debug, PartialEq)]
pub enum Profile {
    /// No magnet on the rod.
    Absent,
    /// A magnet standing still.
    Static {
        /// Position, mm.
        pos_mm: f64,
    },
    /// `center + amp · sin(2π t / period + phase)`.
    Sine {
        /// Centre, mm.
        center_mm: f64,
        /// Amplitude, mm.
        amplitude_mm: f64,
        /// Period, s (> 0).
        period_s: f64,
        /// Phase, degrees.
        phase_deg: f64,
    },
    /// Constant-speed zig-zag: `min` at t = 0, `max` at period / 2, `min` at period.
    Triangle {
        /// Lower turning point, mm.
        min_mm: f64,
        /// Upper turning point, mm.
        max_mm: f64,
        /// Period, s (> 0).
        period_s: f64,
    },
    /// Trapezoidal ramp.
    Ramp(Ramp),
    /// Jumps: position `pos` from time `t` on (the first position also before its time).
    /// Times strictly increasing.
    Steps(Vec<(f64, f64)>),
}

impl Profile {
    /// Checks the parameters; the text parser calls it, hand-built profiles should too.
    pub fn validate(&self) -> Result<()> {
        let bad = |r: String| {
            Err(Error::MotionSpec {
                spec: self.to_string(),
                reason: r,
            })
        };
        // Finite and bounded, so that evaluating the profile never overflows.
        let finite = |vals: &[f64]| vals.iter().all(|v| in_range(*v));
        match self {
            Profile::Absent => Ok(()),
            Profile::Static { pos_mm } => {
                if finite(&[*pos_mm]) {
                    Ok(())
                } else {
                    bad(format!(
                        "position must be finite and within ±{MAX_MAGNITUDE:e} mm"
                    ))
                }
            }
            Profile::Sine {
                center_mm,
                amplitude_mm,
                period_s,
                phase_deg,
            } => {
                if !finite(&[*center_mm, *amplitude_mm, *period_s, *phase_deg]) {
                    bad(format!(
                        "values must be finite and within ±{MAX_MAGNITUDE:e}"
                    ))
                } else if *period_s < MIN_PERIOD_S {
                    bad(format!("period must be ≥ {MIN_PERIOD_S} s"))
                } else {
                    Ok(())
                }
            }
            Profile::Triangle {
                min_mm,
                max_mm,
                period_s,
            } => {
                if !finite(&[*min_mm, *max_mm, *period_s]) {
                    bad(format!(
                        "values must be finite and within ±{MAX_MAGNITUDE:e}"
                    ))
                } else if *period_s < MIN_PERIOD_S {
                    bad(format!("period must be ≥ {MIN_PERIOD_S} s"))
                } else {
                    Ok(())
                }
            }
            Profile::Ramp(r) => r.validate(),
            Profile::Steps(steps) => {
                if steps.is_empty() {
                    return bad("at least one step is needed".into());
                }
                for (i, (t, p)) in steps.iter().enumerate() {
                    if !finite(&[*t, *p]) {
                        return bad(format!(
                            "step {} is not finite or beyond ±{MAX_MAGNITUDE:e}",
                            i + 1
                        ));
                    }
                    if i > 0 && *t <= steps[i - 1].0 {
                        return bad(format!(
                            "step times must increase strictly ({} after {})",
                            t,
                            steps[i - 1].0
                        ));
                    }
                }
                Ok(())
            }
        }
    }

    /// Position at time `t_s`, mm; `None` for [`Profile::Absent`].
    pub fn at(&self, t_s: f64) -> Option<f64> {
        Some(match self {
            Profile::Absent => return None,
            Profile::Static { pos_mm } => *pos_mm,
            Profile::Sine {
                center_mm,
                amplitude_mm,
                period_s,
                phase_deg,
            } => center_mm + amplitude_mm * (TAU * t_s / period_s + phase_deg.to_radians()).sin(),
            Profile::Triangle {
                min_mm,
                max_mm,
                period_s,
            } => {
                let u = (t_s / period_s).rem_euclid(1.0);
                let f = if u < 0.5 { 2.0 * u } else { 2.0 - 2.0 * u };
                min_mm + (max_mm - min_mm) * f
            }
            Profile::Ramp(r) => r.at(t_s),
            Profile::Steps(steps) => {
                let i = steps.partition_point(|(t, _)| *t <= t_s);
                steps.get(i.saturating_sub(1))?.1
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(v: f64, a: f64, dwell: f64, repeat: bool) -> Ramp {
        Ramp {
            from_mm: 100.0,
            to_mm: 900.0,
            max_velocity_mm_s: v,
            acceleration_mm_s2: a,
            dwell_s: dwell,
            repeat,
        }
    }

    #[test]
    fn trapezoid_ramp() {
        let r = ramp(200.0, 1000.0, 1.0, true);
        // t_acc 0.2 s, d_acc 20 mm each, cruise 760 mm at 200 mm/s = 3.8 s.
        assert!((r.move_time_s() - 4.2).abs() < 1e-12);
        assert_eq!(r.at(0.5), 100.0);
        assert!((r.at(1.0 + 0.2) - 120.0).abs() < 1e-9);
        assert!((r.at(1.0 + 2.1) - 500.0).abs() < 1e-9);
        assert!((r.at(5.2) - 900.0).abs() < 1e-9);
        assert_eq!(r.at(5.7), 900.0);
        assert!((r.at(6.2 + 2.1) - 500.0).abs() < 1e-9);
        assert!((r.at(10.4) - 100.0).abs() < 1e-9);
        assert!((r.at(10.4 + 0.5) - 100.0).abs() < 1e-9);
        // velocity never exceeds v (finite differences)
        let mut prev = r.at(0.0);
        for i in 1..12000 {
            let t = i as f64 * 1e-3;
            let x = r.at(t);
            assert!((x - prev).abs() <= 200.0 * 1e-3 + 1e-9, "at {t}");
            prev = x;
        }
    }

    #[test]
    fn triangular_ramp_and_one_shot() {
        let r = ramp(10_000.0, 1000.0, 0.0, false);
        // triangular: 2 sqrt(800 / 1000)
        let total = 2.0 * 0.8f64.sqrt();
        assert!((r.move_time_s() - total).abs() < 1e-12);
        assert!((r.at(total / 2.0) - 500.0).abs() < 1e-9);
        assert_eq!(r.at(100.0), 900.0);
        let down = Ramp {
            from_mm: 900.0,
            to_mm: 100.0,
            ..ramp(200.0, 1000.0, 0.0, false)
        };
        assert!((down.at(0.2) - 880.0).abs() < 1e-9);
    }

    #[test]
    fn sine_triangle_steps() {
        let s = Profile::Sine {
            center_mm: 500.0,
            amplitude_mm: 200.0,
            period_s: 4.0,
            phase_deg: 0.0,
        };
        assert!((s.at(1.0).unwrap() - 700.0).abs() < 1e-9);
        assert!((s.at(3.0).unwrap() - 300.0).abs() < 1e-9);
        let t = Profile::Triangle {
            min_mm: 100.0,
            max_mm: 900.0,
            period_s: 10.0,
        };
        assert_eq!(t.at(0.0), Some(100.0));
        assert_eq!(t.at(5.0), Some(900.0));
        assert_eq!(t.at(2.5), Some(500.0));
        assert_eq!(t.at(7.5), Some(500.0));
        assert_eq!(t.at(-2.5), Some(500.0));
        let st = Profile::Steps(vec![(0.0, 100.0), (2.0, 300.0), (4.0, 200.0)]);
        assert_eq!(st.at(-1.0), Some(100.0));
        assert_eq!(st.at(1.999), Some(100.0));
        assert_eq!(st.at(2.0), Some(300.0));
        assert_eq!(st.at(100.0), Some(200.0));
        assert_eq!(Profile::Absent.at(1.0), None);
    }

    #[test]
    fn validation() {
        assert!(Profile::Steps(vec![]).validate().is_err());
        assert!(Profile::Steps(vec![(1.0, 2.0), (1.0, 3.0)])
            .validate()
            .is_err());
        assert!(Profile::Triangle {
            min_mm: 0.0,
            max_mm: 1.0,
            period_s: 0.0
        }
        .validate()
        .is_err());
        assert!(Profile::Static { pos_mm: f64::NAN }.validate().is_err());
        // Huge but finite values and tiny periods would overflow to NaN when evaluated.
        assert!(Profile::Static { pos_mm: 1e300 }.validate().is_err());
        assert!(Profile::Static { pos_mm: -1e300 }.validate().is_err());
        assert!(Profile::Sine {
            center_mm: 0.0,
            amplitude_mm: 1.0,
            period_s: 1e-300,
            phase_deg: 0.0
        }
        .validate()
        .is_err());
        assert!(Profile::Ramp(Ramp {
            from_mm: -1e308,
            to_mm: 1e308,
            ..ramp(1.0, 1.0, 0.0, true)
        })
        .validate()
        .is_err());
        assert!("static:1e300".parse::<Profile>().is_err());
        assert!("sine:center=1,amp=1e300,period=1"
            .parse::<Profile>()
            .is_err());
        assert!("triangle:min=0,max=1,period=1e-9"
            .parse::<Profile>()
            .is_err());
        assert!(Profile::Ramp(ramp(0.0, 1.0, 0.0, true)).validate().is_err());
        assert!(Profile::Ramp(ramp(1.0, -1.0, 0.0, true))
            .validate()
            .is_err());
        assert!(Profile::Ramp(ramp(1.0, 1.0, -1.0, true))
            .validate()
            .is_err());
    }
}
