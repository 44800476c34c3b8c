//! What every motion source is: the [`Motion`] trait and the bounds on the numbers of a
//! motion, below the sources (profiles, CSV trajectories, live set-points) that implement it.

/// Largest magnitude of any number in a motion (positions mm, times and periods s, velocities
/// mm/s, accelerations mm/s²). Far beyond any real rod or move, and small enough that the
/// arithmetic of a profile can never overflow to infinity or NaN.
pub const MAX_MAGNITUDE: f64 = 1.0e9;

/// Shortest period of a sine or triangle, s. Shorter ones make `t / period` overflow (NaN
/// positions), and no magnet on a rod oscillates at more than a kilohertz anyway.
pub const MIN_PERIOD_S: f64 = 1.0e-3;

/// Whether `v` is finite and within ±[`MAX_MAGNITUDE`].
pub fn in_range(v: f64) -> bool {
    v.is_finite() && v.abs() <= MAX_MAGNITUDE
}

/// A source of true magnet positions.
pub trait Motion: Send {
    /// True position of `magnet` (0-based, in the source's own numbering) at time `t_s`, in mm
    /// from the zero point; `None` when that magnet is not on the rod.
    ///
    /// Sources may keep state (e.g. velocity-limited set-points), so call it with
    /// non-decreasing times.
    fn position_mm(&mut self, magnet: usize, t_s: f64) -> Option<f64>;

    /// How many magnets the source drives (higher indices are always `None`).
    fn magnets(&self) -> usize;

    /// Positions of all magnets at `t_s`.
    fn positions_mm(&mut self, t_s: f64) -> Vec<Option<f64>> {
        (0..self.magnets())
            .map(|m| self.position_mm(m, t_s))
            .collect()
    }
}

impl Motion for Box<dyn Motion> {
    fn position_mm(&mut self, magnet: usize, t_s: f64) -> Option<f64> {
        (**self).position_mm(magnet, t_s)
    }

    fn magnets(&self) -> usize {
        (**self).magnets()
    }
}
