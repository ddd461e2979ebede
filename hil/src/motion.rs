//! The suit's motion: calib-core's motion generator ([`calib_core::Motion`], the one its
//! simulation and sweep use), evaluated joint by joint with its rate in closed form, as the
//! wearer shapes it.
//!
//! Contract: [`Motion::random`] draws calib-core's motion (a sum of
//! [`calib_core::sim::MOTION_HARMONICS`] random sinusoids per joint, 0.05–0.6 Hz, normalised into
//! `[−1, 1]` and mapped into 98 % of the joint's range), so a seed gives the same motion here and
//! there. Each joint is evaluated on its own, with its rate: a node samples only what it needs
//! (this matters in slow environments: the vcan harness runs under QEMU's software floating
//! point). Kinematics are calib-core's too ([`calib_core::PreparedTable::frames`]).
//!
//! The wearer ([`crate::wearer`]) shapes it: each joint's free motion uses a fraction of its
//! range (`reach`, about the middle), and a joint the wearer moves as advised blends from its
//! free motion into sweeps of its whole range ([`Motion::sweep`]) and back, smoothly, its rate
//! still in closed form.

use calib_core::{JointRanges, Rng};
use std::f64::consts::TAU;

/// Full-range sweeps per second of a joint the wearer moves as advised ([`Motion::sweep`]).
pub const SWEEP_HZ: f64 = 0.25;
/// Seconds a joint takes to blend into an advised sweep, and back.
pub const RAMP_S: f64 = 1.0;

/// A joint the wearer moves as advised, over `[from, until]` (s).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Sweep {
    joint: usize,
    from: f64,
    until: f64,
    phase: f64,
}

/// Smooth random motion of seven joints.
#[derive(Clone, Debug, PartialEq)]
pub struct Motion {
    free: calib_core::Motion<7>,
    /// Fraction of each joint's half-range the free motion uses.
    reach: [f64; 7],
    /// Advised sweeps, in the order heard.
    sweeps: Vec<Sweep>,
    /// The wearer holds the free motion's first pose this long (s), then moves from there.
    still_s: f64,
}

/// `3x² − 2x³` on `[0, 1]` (clamped) and its derivative.
fn smoothstep(x: f64) -> (f64, f64) {
    if x >= 1.0 {
        (1.0, 0.0)
    } else if x <= 0.0 {
        (0.0, 0.0)
    } else {
        (x * x * (3.0 - 2.0 * x), 6.0 * x * (1.0 - x))
    }
}

impl Motion {
    /// Draws a motion inside `ranges`: calib-core's for the same generator state.
    pub fn random(ranges: &JointRanges<7>, rng: &mut Rng) -> Motion {
        Motion {
            free: calib_core::Motion::random(ranges, rng),
            reach: [1.0; 7],
            sweeps: Vec::new(),
            still_s: 0.0,
        }
    }

    /// This motion held still at its first pose for `seconds` first.
    pub fn with_still(mut self, seconds: f64) -> Motion {
        self.still_s = seconds;
        self
    }

    /// This motion with the free motion of joint `j` using `reach[j]` of its range (in (0, 1]).
    pub fn with_reach(mut self, reach: [f64; 7]) -> Motion {
        self.reach = reach;
        self
    }

    /// From `from` to `until` (s, at least `2 ·` [`RAMP_S`] apart), joint `j` blends into
    /// sweeps of its whole range at [`SWEEP_HZ`] starting at `phase` (rad) and back. Sweeps of
    /// one joint must not overlap (the wearer follows one piece of advice at a time).
    pub fn sweep(&mut self, j: usize, from: f64, until: f64, phase: f64) {
        self.sweeps.push(Sweep {
            joint: j,
            from,
            until,
            phase,
        });
    }

    /// Angle (rad) and rate (rad/s) of joint `j` at time `t` (s).
    pub fn joint(&self, j: usize, t: f64) -> (f64, f64) {
        let (s, ds) = if self.still_s > 0.0 && t < self.still_s {
            (self.free.unit(j, 0.0).0, 0.0)
        } else {
            self.free.unit(j, t - self.still_s)
        };
        let (mut u, mut du) = (self.reach[j] * s, self.reach[j] * ds);
        if let Some(w) = self
            .sweeps
            .iter()
            .find(|w| w.joint == j && w.from < t && t < w.until)
        {
            // The blend g: up over RAMP_S after `from`, down over RAMP_S before `until`.
            let (up, dup) = smoothstep((t - w.from) / RAMP_S);
            let (down, ddown) = smoothstep((w.until - t) / RAMP_S);
            let (g, dg) = (up * down, (dup * down - up * ddown) / RAMP_S);
            let omega = TAU * SWEEP_HZ;
            let (sn, cs) = (omega * t + w.phase).sin_cos();
            (u, du) = (
                (1.0 - g) * u + g * sn,
                (1.0 - g) * du - dg * u + dg * sn + g * omega * cs,
            );
        }
        let (middle, swing) = self.free.middle_and_swing(j);
        (middle + swing * u, swing * du)
    }

    /// All seven angles at `t`.
    pub fn at(&self, t: f64) -> [f64; 7] {
        std::array::from_fn(|j| self.joint(j, t).0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_free_motion_is_calib_cores() {
        let ranges = JointRanges::paper();
        let ours = Motion::random(&ranges, &mut Rng::new(5));
        let theirs = calib_core::Motion::random(&ranges, &mut Rng::new(5));
        for k in 0..1000 {
            let t = k as f64 * 0.071;
            for (a, b) in ours.at(t).iter().zip(theirs.at(t)) {
                assert!((a - b).abs() < 1e-12, "{a} vs {b} at {t}");
            }
        }
    }

    #[test]
    fn a_joint_moved_as_advised_sweeps_its_range_smoothly_and_the_rate_is_the_derivative() {
        let ranges = JointRanges::paper();
        let mut reach = [1.0; 7];
        reach[6] = 0.2;
        let free = Motion::random(&ranges, &mut Rng::new(9)).with_reach(reach);
        let mut m = free.clone();
        m.sweep(6, 10.0, 20.0, 0.3);
        let (lo, hi) = ranges.limits[6];
        let (mut min, mut max) = (f64::INFINITY, f64::NEG_INFINITY);
        for k in 0..30_000 {
            let t = k as f64 * 0.001;
            for j in 0..7 {
                let (q, qd) = m.joint(j, t);
                assert!(q > ranges.limits[j].0 && q < ranges.limits[j].1);
                let h = 1e-6;
                let fd = (m.joint(j, t + h).0 - m.joint(j, t - h).0) / (2.0 * h);
                assert!((fd - qd).abs() < 1e-5, "joint {j} at {t}: {fd} vs {qd}");
                if j != 6 || !(10.0..20.0).contains(&t) {
                    assert_eq!(m.joint(j, t), free.joint(j, t), "joint {j} at {t}");
                }
            }
            let q = m.joint(6, t).0;
            if (11.0..19.0).contains(&t) {
                (min, max) = (min.min(q), max.max(q));
            } else if !(10.0..=20.0).contains(&t) {
                // The lazy wrist keeps to a fifth of its range about the middle.
                assert!((q - 0.5 * (lo + hi)).abs() <= 0.2 * 0.49 * (hi - lo) + 1e-12);
            }
        }
        // As advised: the whole range (98 %), two sweeps in 8 s.
        assert!(
            min < lo + 0.03 * (hi - lo) && max > hi - 0.03 * (hi - lo),
            "{min} {max}"
        );
    }
}
