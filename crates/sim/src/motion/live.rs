//! Magnets moved at run time (control interface, SPEC §12).

use std::sync::{Arc, Mutex, MutexGuard};

use super::profile::Profile;
use super::source::{in_range, Motion, MAX_MAGNITUDE};
use crate::error::{Error, Result};

/// Highest number of magnets a [`LiveMotion`] tracks (channels plus room for extra magnets).
pub const MAX_LIVE_MAGNETS: usize = 16;

#[derive(Debug)]
enum Mode {
    /// Follow the base motion source.
    Base,
    /// Run a profile whose time starts when it is first evaluated.
    Profile { profile: Profile, t0: Option<f64> },
    /// Move to a set-point, at most at `v_max` (jump when `None`).
    SetPoint { target: f64, v_max: Option<f64> },
    /// Magnet taken off the rod.
    Removed,
}

#[derive(Debug)]
struct LiveMagnet {
    mode: Mode,
    /// Last evaluated time and position.
    last: Option<(f64, Option<f64>)>,
}

struct State {
    base: Box<dyn Motion>,
    magnets: Vec<LiveMagnet>,
}

impl State {
    fn slot(&mut self, magnet: usize) -> &mut LiveMagnet {
        while self.magnets.len() <= magnet {
            self.magnets.push(LiveMagnet {
                mode: Mode::Base,
                last: None,
            });
        }
        &mut self.magnets[magnet]
    }
}

fn lock(m: &Mutex<State>) -> MutexGuard<'_, State> {
    // A panic in another thread while holding the lock cannot leave the state inconsistent
    // in a way that matters here: keep going.
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// A motion source whose magnets can be redirected while it runs: each magnet follows the base
/// source until a set-point, a profile or a removal is pushed through a [`LiveHandle`].
///
/// A set-point with a velocity limit moves the magnet from wherever it is (including the middle
/// of a profile) towards the target at that speed; without a limit it jumps. A profile pushed at
/// run time starts at its own t = 0 at the first evaluation after the push.
pub struct LiveMotion {
    shared: Arc<Mutex<State>>,
}

/// Clonable, thread-safe handle to push set-points into a [`LiveMotion`].
#[derive(Clone)]
pub struct LiveHandle {
    shared: Arc<Mutex<State>>,
}

impl LiveMotion {
    /// Wraps `base`; all magnets follow it until told otherwise.
    pub fn new(base: Box<dyn Motion>) -> Self {
        LiveMotion {
            shared: Arc::new(Mutex::new(State {
                base,
                magnets: Vec::new(),
            })),
        }
    }

    /// A handle for the control interface.
    pub fn handle(&self) -> LiveHandle {
        LiveHandle {
            shared: Arc::clone(&self.shared),
        }
    }
}

impl core::fmt::Debug for LiveMotion {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("LiveMotion").finish_non_exhaustive()
    }
}

impl core::fmt::Debug for LiveHandle {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("LiveHandle").finish_non_exhaustive()
    }
}

fn check_magnet(magnet: usize) -> Result<()> {
    if magnet >= MAX_LIVE_MAGNETS {
        return Err(Error::Request(format!(
            "magnet index {magnet} is out of range (0…{})",
            MAX_LIVE_MAGNETS - 1
        )));
    }
    Ok(())
}

impl LiveHandle {
    /// Moves `magnet` (0-based) to `pos_mm`, at most at `max_velocity_mm_s` (jump when `None`).
    pub fn set_point(
        &self,
        magnet: usize,
        pos_mm: f64,
        max_velocity_mm_s: Option<f64>,
    ) -> Result<()> {
        check_magnet(magnet)?;
        if !in_range(pos_mm) {
            return Err(Error::Request(format!(
                "set-point {pos_mm} mm is not finite or beyond ±{MAX_MAGNITUDE:e} mm"
            )));
        }
        if let Some(v) = max_velocity_mm_s {
            if !(in_range(v) && v > 0.0) {
                return Err(Error::Request(format!(
                    "velocity limit {v} mm/s must be > 0 and at most {MAX_MAGNITUDE:e}"
                )));
            }
        }
        lock(&self.shared).slot(magnet).mode = Mode::SetPoint {
            target: pos_mm,
            v_max: max_velocity_mm_s,
        };
        Ok(())
    }

    /// Starts `profile` for `magnet`; its time starts at the next evaluation.
    pub fn start_profile(&self, magnet: usize, profile: Profile) -> Result<()> {
        check_magnet(magnet)?;
        profile.validate()?;
        lock(&self.shared).slot(magnet).mode = Mode::Profile { profile, t0: None };
        Ok(())
    }

    /// Takes `magnet` off the rod (it reports `None` until given a new set-point or profile).
    pub fn remove(&self, magnet: usize) -> Result<()> {
        check_magnet(magnet)?;
        lock(&self.shared).slot(magnet).mode = Mode::Removed;
        Ok(())
    }

    /// Lets `magnet` follow the base motion source again.
    pub fn follow_base(&self, magnet: usize) -> Result<()> {
        check_magnet(magnet)?;
        lock(&self.shared).slot(magnet).mode = Mode::Base;
        Ok(())
    }

    /// The position of `magnet` at its last evaluation (`None`: absent or never evaluated).
    pub fn last_position_mm(&self, magnet: usize) -> Option<f64> {
        let st = lock(&self.shared);
        st.magnets
            .get(magnet)
            .and_then(|m| m.last)
            .and_then(|(_, p)| p)
    }
}

impl Motion for LiveMotion {
    fn position_mm(&mut self, magnet: usize, t_s: f64) -> Option<f64> {
        if magnet >= MAX_LIVE_MAGNETS {
            return None;
        }
        let mut guard = lock(&self.shared);
        let st = &mut *guard;
        let base_pos = st.base.position_mm(magnet, t_s);
        let m = st.slot(magnet);
        let pos = match &mut m.mode {
            Mode::Base => base_pos,
            Mode::Removed => None,
            Mode::Profile { profile, t0 } => {
                let start = *t0.get_or_insert(t_s);
                profile.at(t_s - start)
            }
            Mode::SetPoint { target, v_max } => {
                let current = m.last.and_then(|(t, p)| p.map(|p| (t, p)));
                match (current, *v_max) {
                    (Some((t_prev, p)), Some(v)) => {
                        let dt = (t_s - t_prev).max(0.0);
                        let step = v * dt;
                        let diff = *target - p;
                        if diff.abs() <= step {
                            Some(*target)
                        } else {
                            Some(p + step.copysign(diff))
                        }
                    }
                    _ => Some(*target),
                }
            }
        };
        m.last = Some((t_s, pos));
        pos
    }

    fn magnets(&self) -> usize {
        let st = lock(&self.shared);
        let highest = st
            .magnets
            .iter()
            .rposition(|m| !matches!(m.mode, Mode::Base | Mode::Removed))
            .map_or(0, |i| i + 1);
        st.base.magnets().max(highest)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::motion::Profiles;

    #[test]
    fn set_point_with_velocity_limit() {
        let mut live = LiveMotion::new(Box::new(Profiles::new(vec![Profile::Static {
            pos_mm: 100.0,
        }])));
        let h = live.handle();
        assert_eq!(live.position_mm(0, 0.0), Some(100.0));
        h.set_point(0, 200.0, Some(50.0)).unwrap();
        assert_eq!(live.position_mm(0, 1.0), Some(150.0));
        assert_eq!(h.last_position_mm(0), Some(150.0));
        assert_eq!(live.position_mm(0, 1.5), Some(175.0));
        assert_eq!(live.position_mm(0, 10.0), Some(200.0));
        h.set_point(0, 120.0, None).unwrap();
        assert_eq!(live.position_mm(0, 10.001), Some(120.0));
        h.remove(0).unwrap();
        assert_eq!(live.position_mm(0, 11.0), None);
        h.set_point(0, 300.0, Some(1.0)).unwrap();
        // from "absent" a set-point is reached at once
        assert_eq!(live.position_mm(0, 12.0), Some(300.0));
        h.follow_base(0).unwrap();
        assert_eq!(live.position_mm(0, 13.0), Some(100.0));
    }

    #[test]
    fn profile_pushed_at_run_time_starts_at_zero() {
        let mut live = LiveMotion::new(Box::new(Profiles::new(vec![])));
        let h = live.handle();
        assert_eq!(live.magnets(), 0);
        assert_eq!(live.position_mm(1, 5.0), None);
        h.start_profile(1, Profile::Steps(vec![(0.0, 10.0), (1.0, 20.0)]))
            .unwrap();
        assert_eq!(live.magnets(), 2);
        assert_eq!(live.position_mm(1, 5.0), Some(10.0));
        assert_eq!(live.position_mm(1, 5.5), Some(10.0));
        assert_eq!(live.position_mm(1, 6.0), Some(20.0));
    }

    #[test]
    fn bad_requests() {
        let live = LiveMotion::new(Box::new(Profiles::new(vec![])));
        let h = live.handle();
        assert!(h.set_point(0, f64::NAN, None).is_err());
        assert!(h.set_point(0, 1.0, Some(0.0)).is_err());
        assert!(h.set_point(MAX_LIVE_MAGNETS, 1.0, None).is_err());
        assert!(h.start_profile(0, Profile::Steps(vec![])).is_err());
    }
}
