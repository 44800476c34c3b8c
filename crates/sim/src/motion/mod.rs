//! Motion sources: where each magnet truly is at a given time.
//!
//! Positions are in mm from the sensor's zero point (start of the active stroke), increasing
//! away from the sensor head; `None` means the magnet is not on the rod.
//!
//! # Textual motion specs (CLI `--motion`)
//!
//! ```text
//! spec     := "csv:" PATH                    one CSV file drives all magnets (see CsvTrajectory)
//!           | source (";" source)*           source k drives magnet k (first = nearest the head)
//! source   := "none"                         no magnet
//!           | "static:" NUM                  e.g. static:100
//!           | "sine:" params                 center, amp, period [, phase (degrees, default 0)]
//!           | "triangle:" params             min, max, period
//!           | "ramp:" params                 from, to, v, a [, dwell (s, default 0)]
//!                                            [, repeat (1 = back and forth, default; 0 = once)]
//!           | "steps:" T "=" POS ("," T "=" POS)*     times strictly increasing
//! params   := KEY "=" NUM ("," KEY "=" NUM)*  any order, each key once
//! NUM      := a decimal number (Rust f64 syntax, e.g. 100, -2.5, 1e3)
//! ```
//!
//! Units: positions mm, times and periods s, velocity mm/s, acceleration mm/s². Spaces around
//! tokens are ignored. Examples: `static:100`, `sine:center=500,amp=200,period=4`,
//! `triangle:min=100,max=900,period=10`, `ramp:from=100,to=900,v=200,a=1000,dwell=1`,
//! `steps:0=100,2=300,4=200`, `csv:run1.csv`, `sine:center=300,amp=50,period=2;static:800`.
//!
//! [`MotionSpec`]'s `Display` prints the canonical form, which parses back to an equal value.

mod csv;
mod live;
mod profile;
mod source;

use core::fmt;
use core::str::FromStr;
use std::path::PathBuf;

pub use self::csv::CsvTrajectory;
pub use self::live::{LiveHandle, LiveMotion, MAX_LIVE_MAGNETS};
pub use self::profile::{Profile, Ramp};
pub use self::source::{in_range, Motion, MAX_MAGNITUDE, MIN_PERIOD_S};
use crate::error::{Error, Result};

impl Motion for Profile {
    fn position_mm(&mut self, magnet: usize, t_s: f64) -> Option<f64> {
        if magnet == 0 {
            self.at(t_s)
        } else {
            None
        }
    }

    fn magnets(&self) -> usize {
        1
    }
}

/// One [`Profile`] per magnet.
#[derive(Clone, Debug, PartialEq)]
pub struct Profiles(pub Vec<Profile>);

impl Profiles {
    /// Magnet k follows `profiles[k]`.
    pub fn new(profiles: Vec<Profile>) -> Self {
        Profiles(profiles)
    }
}

impl Motion for Profiles {
    fn position_mm(&mut self, magnet: usize, t_s: f64) -> Option<f64> {
        self.0.get(magnet)?.at(t_s)
    }

    fn magnets(&self) -> usize {
        self.0.len()
    }
}

/// A parsed textual motion spec (see the module documentation for the grammar).
#[derive(Clone, Debug, PartialEq)]
pub enum MotionSpec {
    /// Profiles, one per magnet.
    Profiles(Vec<Profile>),
    /// A CSV trajectory file.
    Csv(PathBuf),
}

impl MotionSpec {
    /// Parses a spec (same as `str::parse`).
    pub fn parse(s: &str) -> Result<Self> {
        s.parse()
    }

    /// Builds the motion source; reads and checks the CSV file for [`MotionSpec::Csv`].
    pub fn build(&self) -> Result<Box<dyn Motion>> {
        Ok(match self {
            MotionSpec::Profiles(p) => Box::new(Profiles(p.clone())),
            MotionSpec::Csv(path) => Box::new(CsvTrajectory::load(path)?),
        })
    }
}

impl FromStr for MotionSpec {
    type Err = Error;

    fn from_str(s: &str) -> Result<Self> {
        let t = s.trim();
        if let Some(path) = t.strip_prefix("csv:") {
            let path = path.trim();
            if path.is_empty() {
                return Err(spec_err(t, "csv: needs a file path"));
            }
            return Ok(MotionSpec::Csv(PathBuf::from(path)));
        }
        if t.is_empty() {
            return Err(spec_err(t, "empty motion spec"));
        }
        let profiles = t
            .split(';')
            .map(|p| p.parse::<Profile>())
            .collect::<Result<Vec<_>>>()?;
        Ok(MotionSpec::Profiles(profiles))
    }
}

impl fmt::Display for MotionSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            MotionSpec::Csv(p) => write!(f, "csv:{}", p.display()),
            MotionSpec::Profiles(ps) => {
                for (i, p) in ps.iter().enumerate() {
                    if i > 0 {
                        f.write_str(";")?;
                    }
                    write!(f, "{p}")?;
                }
                Ok(())
            }
        }
    }
}

fn spec_err(spec: &str, reason: impl Into<String>) -> Error {
    Error::MotionSpec {
        spec: spec.to_string(),
        reason: reason.into(),
    }
}

fn num(spec: &str, what: &str, text: &str) -> Result<f64> {
    let text = text.trim();
    match text.parse::<f64>() {
        Ok(v) if in_range(v) => Ok(v),
        Ok(v) if v.is_finite() => Err(spec_err(
            spec,
            format!("{what}: {text} is out of range (±{MAX_MAGNITUDE:e})"),
        )),
        _ => Err(spec_err(
            spec,
            format!("{what}: \"{text}\" is not a finite number"),
        )),
    }
}

/// Parses `key=value,...` for the given keys (required ones first in `required`).
fn params<const N: usize>(
    spec: &str,
    body: &str,
    required: &[&str],
    optional: &[(&str, f64)],
) -> Result<[f64; N]> {
    let mut keys: Vec<&str> = required.to_vec();
    keys.extend(optional.iter().map(|(k, _)| *k));
    debug_assert_eq!(keys.len(), N);
    let mut vals: [Option<f64>; N] = [None; N];
    for item in body.split(',') {
        let item = item.trim();
        if item.is_empty() {
            return Err(spec_err(spec, "empty parameter (stray comma?)"));
        }
        let Some((k, v)) = item.split_once('=') else {
            return Err(spec_err(spec, format!("\"{item}\" is not key=value")));
        };
        let k = k.trim();
        let Some(i) = keys.iter().position(|x| *x == k) else {
            return Err(spec_err(
                spec,
                format!("unknown parameter \"{k}\" (expected {})", keys.join(", ")),
            ));
        };
        if vals[i].is_some() {
            return Err(spec_err(spec, format!("parameter \"{k}\" given twice")));
        }
        vals[i] = Some(num(spec, k, v)?);
    }
    let mut out = [0.0; N];
    for (i, k) in keys.iter().enumerate() {
        out[i] = match vals[i] {
            Some(v) => v,
            None => match optional.iter().find(|(o, _)| o == k) {
                Some((_, d)) => *d,
                None => return Err(spec_err(spec, format!("missing parameter \"{k}\""))),
            },
        };
    }
    Ok(out)
}

impl FromStr for Profile {
    type Err = Error;

    /// Parses one `source` of the grammar in the [module documentation](self).
    fn from_str(s: &str) -> Result<Self> {
        let spec = s.trim();
        if spec == "none" {
            return Ok(Profile::Absent);
        }
        let Some((kind, body)) = spec.split_once(':') else {
            return Err(spec_err(
                spec,
                "expected none, static:, sine:, triangle:, ramp:, steps: or csv:",
            ));
        };
        let body = body.trim();
        let p = match kind.trim() {
            "static" => Profile::Static { pos_mm: num(spec, "position", body)? },
            "sine" => {
                let [center_mm, amplitude_mm, period_s, phase_deg] =
                    params::<4>(spec, body, &["center", "amp", "period"], &[("phase", 0.0)])?;
                Profile::Sine { center_mm, amplitude_mm, period_s, phase_deg }
            }
            "triangle" => {
                let [min_mm, max_mm, period_s] =
                    params::<3>(spec, body, &["min", "max", "period"], &[])?;
                Profile::Triangle { min_mm, max_mm, period_s }
            }
            "ramp" => {
                let [from_mm, to_mm, v, a, dwell_s, repeat] = params::<6>(
                    spec,
                    body,
                    &["from", "to", "v", "a"],
                    &[("dwell", 0.0), ("repeat", 1.0)],
                )?;
                let repeat = if repeat == 1.0 {
                    true
                } else if repeat == 0.0 {
                    false
                } else {
                    return Err(spec_err(spec, "repeat must be 0 or 1"));
                };
                Profile::Ramp(Ramp {
                    from_mm,
                    to_mm,
                    max_velocity_mm_s: v,
                    acceleration_mm_s2: a,
                    dwell_s,
                    repeat,
                })
            }
            "steps" => {
                let mut steps = Vec::new();
                for item in body.split(',') {
                    let item = item.trim();
                    let Some((t, p)) = item.split_once('=') else {
                        return Err(spec_err(spec, format!("\"{item}\" is not time=position")));
                    };
                    steps.push((num(spec, "step time", t)?, num(spec, "step position", p)?));
                }
                Profile::Steps(steps)
            }
            "csv" => {
                return Err(spec_err(spec, "csv: must be the whole motion spec, not one of several"))
            }
            other => {
                return Err(spec_err(
                    spec,
                    format!(
                        "unknown motion \"{other}\" (expected none, static, sine, triangle, ramp, steps or csv)"
                    ),
                ))
            }
        };
        p.validate().map_err(|e| match e {
            Error::MotionSpec { reason, .. } => spec_err(spec, reason),
            other => other,
        })?;
        Ok(p)
    }
}

impl fmt::Display for Profile {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Profile::Absent => f.write_str("none"),
            Profile::Static { pos_mm } => write!(f, "static:{pos_mm}"),
            Profile::Sine {
                center_mm,
                amplitude_mm,
                period_s,
                phase_deg,
            } => write!(
                f,
                "sine:center={center_mm},amp={amplitude_mm},period={period_s},phase={phase_deg}"
            ),
            Profile::Triangle {
                min_mm,
                max_mm,
                period_s,
            } => {
                write!(f, "triangle:min={min_mm},max={max_mm},period={period_s}")
            }
            Profile::Ramp(r) => write!(
                f,
                "ramp:from={},to={},v={},a={},dwell={},repeat={}",
                r.from_mm,
                r.to_mm,
                r.max_velocity_mm_s,
                r.acceleration_mm_s2,
                r.dwell_s,
                u8::from(r.repeat)
            ),
            Profile::Steps(steps) => {
                f.write_str("steps:")?;
                for (i, (t, p)) in steps.iter().enumerate() {
                    if i > 0 {
                        f.write_str(",")?;
                    }
                    write!(f, "{t}={p}")?;
                }
                Ok(())
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_the_documented_examples() {
        let s: MotionSpec = "static:100".parse().unwrap();
        assert_eq!(
            s,
            MotionSpec::Profiles(vec![Profile::Static { pos_mm: 100.0 }])
        );
        let s: MotionSpec = "sine:center=500,amp=200,period=4".parse().unwrap();
        assert_eq!(
            s,
            MotionSpec::Profiles(vec![Profile::Sine {
                center_mm: 500.0,
                amplitude_mm: 200.0,
                period_s: 4.0,
                phase_deg: 0.0
            }])
        );
        let s: MotionSpec = "triangle:min=100,max=900,period=10".parse().unwrap();
        assert_eq!(
            s,
            MotionSpec::Profiles(vec![Profile::Triangle {
                min_mm: 100.0,
                max_mm: 900.0,
                period_s: 10.0
            }])
        );
        let s: MotionSpec = "ramp:from=100,to=900,v=200,a=1000,dwell=1".parse().unwrap();
        assert_eq!(
            s,
            MotionSpec::Profiles(vec![Profile::Ramp(Ramp {
                from_mm: 100.0,
                to_mm: 900.0,
                max_velocity_mm_s: 200.0,
                acceleration_mm_s2: 1000.0,
                dwell_s: 1.0,
                repeat: true
            })])
        );
        let s: MotionSpec = "steps:0=100,2=300,4=200".parse().unwrap();
        assert_eq!(
            s,
            MotionSpec::Profiles(vec![Profile::Steps(vec![
                (0.0, 100.0),
                (2.0, 300.0),
                (4.0, 200.0)
            ])])
        );
        let s: MotionSpec = "csv:path.csv".parse().unwrap();
        assert_eq!(s, MotionSpec::Csv("path.csv".into()));
        let s: MotionSpec = " static:100 ; none ;  sine : center = 1, amp=2, period=3, phase=90"
            .parse()
            .unwrap();
        let MotionSpec::Profiles(p) = &s else {
            panic!()
        };
        assert_eq!(p.len(), 3);
        assert_eq!(p[1], Profile::Absent);
        let mut m = s.build().unwrap();
        assert_eq!(m.magnets(), 3);
        assert_eq!(m.positions_mm(0.0), vec![Some(100.0), None, Some(3.0)]);
    }

    fn reason(s: &str) -> String {
        match s.parse::<MotionSpec>() {
            Err(Error::MotionSpec { reason, .. }) => reason,
            other => panic!("expected a motion-spec error for {s:?}, got {other:?}"),
        }
    }

    #[test]
    fn errors() {
        assert!(reason("").contains("empty"));
        assert!(reason("csv:").contains("file path"));
        assert!(reason("wobble:1").contains("unknown motion \"wobble\""));
        assert!(reason("static").contains("expected none"));
        assert!(reason("static:abc").contains("not a finite number"));
        assert!(reason("static:inf").contains("not a finite number"));
        assert!(reason("sine:center=1,amp=2").contains("missing parameter \"period\""));
        assert!(reason("sine:center=1,amp=2,period=0").contains("period must be ≥ 0.001 s"));
        assert!(reason("static:1e300").contains("out of range"));
        assert!(
            reason("sine:center=1,amp=2,period=1,freq=3").contains("unknown parameter \"freq\"")
        );
        assert!(reason("sine:center=1,center=2,amp=2,period=1").contains("twice"));
        assert!(reason("sine:center=1,,amp=2,period=1").contains("stray comma"));
        assert!(reason("sine:center").contains("not key=value"));
        assert!(reason("ramp:from=1,to=2,v=0,a=1").contains("v (max velocity)"));
        assert!(reason("ramp:from=1,to=2,v=1,a=1,repeat=2").contains("repeat must be 0 or 1"));
        assert!(reason("steps:0=1,0=2").contains("increase strictly"));
        assert!(reason("steps:0").contains("time=position"));
        assert!(reason("static:1;csv:x.csv").contains("whole motion spec"));
    }

    #[test]
    fn display_round_trips() {
        for s in [
            "static:100",
            "none",
            "sine:center=500,amp=200,period=4,phase=0",
            "triangle:min=100,max=900,period=10",
            "ramp:from=100,to=900,v=200,a=1000,dwell=1,repeat=1",
            "steps:0=100,2=300,4=200",
            "static:0.1;none;static:-2.5",
            "csv:/tmp/some path.csv",
        ] {
            let spec: MotionSpec = s.parse().unwrap();
            assert_eq!(spec.to_string(), s);
            assert_eq!(spec.to_string().parse::<MotionSpec>().unwrap(), spec);
        }
    }
}
