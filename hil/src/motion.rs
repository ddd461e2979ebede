//! Smooth random joint motion with analytic rates, and a D-H chain with cached link constants.
//!
//! Contract: like calib-core's `Motion` (a sum of [`HARMONICS`] random sinusoids per joint,
//! 0.05–0.6 Hz, normalised into `[−1, 1]` and mapped into 98 % of the joint's range, so it is
//! smooth and never leaves the range), but each joint is evaluated on its own, with its rate in
//! closed form: a node samples only what it needs. This matters in slow environments (the vcan
//! harness runs under QEMU's software floating point).
//!
//! The wearer ([`crate::wearer`]) shapes it: each joint's free motion uses a fraction of its
//! range (`reach`, about the middle), and a joint the wearer moves as advised blends from its
//! free motion into sweeps of its whole range ([`Motion::sweep`]) and back, smoothly, its rate
//! still in closed form.

use calib_core::{DhTable, Frame, JointRanges, Rng};
use nalgebra::{Matrix3, Vector3};
use std::f64::consts::TAU;

/// Full-range sweeps per second of a joint the wearer moves as advised ([`Motion::sweep`]).
pub const SWEEP_HZ: f64 = 0.25;
/// Seconds a joint takes to blend into an advised sweep, and back.
pub const RAMP_S: f64 = 1.0;

/// Sinusoids per joint.
pub const HARMONICS: usize = 4;

/// One joint's motion.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Joint {
    omega: [f64; HARMONICS],
    phase: [f64; HARMONICS],
    amp: [f64; HARMONICS],
    mid: f64,
    half: f64,
}

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
    joints: [Joint; 7],
    /// Fraction of each joint's half-range the free motion uses.
    reach: [f64; 7],
    /// Advised sweeps, in the order heard.
    sweeps: Vec<Sweep>,
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
    /// Draws a motion inside `ranges`.
    pub fn random(ranges: &JointRanges<7>, rng: &mut Rng) -> Motion {
        Motion {
            joints: std::array::from_fn(|j| {
                let mut m = Joint {
                    omega: [0.0; HARMONICS],
                    phase: [0.0; HARMONICS],
                    amp: [0.0; HARMONICS],
                    mid: 0.0,
                    half: 0.0,
                };
                for h in 0..HARMONICS {
                    m.omega[h] = TAU * (0.05 + 0.55 * rng.uniform());
                    m.phase[h] = TAU * rng.uniform();
                    m.amp[h] = 0.2 + rng.uniform();
                }
                let norm: f64 = m.amp.iter().sum();
                let (lo, hi) = ranges.limits[j];
                m.mid = 0.5 * (lo + hi);
                m.half = 0.49 * (hi - lo);
                for a in m.amp.iter_mut() {
                    *a /= norm;
                }
                m
            }),
            reach: [1.0; 7],
            sweeps: Vec::new(),
        }
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
        let m = &self.joints[j];
        let (mut s, mut ds) = (0.0, 0.0);
        for h in 0..HARMONICS {
            let (sn, cs) = (m.omega[h] * t + m.phase[h]).sin_cos();
            s += m.amp[h] * sn;
            ds += m.amp[h] * m.omega[h] * cs;
        }
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
        (m.mid + m.half * u, m.half * du)
    }

    /// All seven angles at `t`.
    pub fn at(&self, t: f64) -> [f64; 7] {
        std::array::from_fn(|j| self.joint(j, t).0)
    }
}

/// A D-H chain with sin/cos of every α precomputed (same convention as calib-core, eq. 1).
#[derive(Clone, Debug, PartialEq)]
pub struct Chain {
    rows: [(f64, f64, f64, f64, f64); 7],
}

impl Chain {
    /// From a table.
    pub fn new(table: &DhTable<7>) -> Chain {
        Chain {
            rows: std::array::from_fn(|i| {
                let r = table.rows[i];
                let (sa, ca) = r.alpha.sin_cos();
                (r.a, r.d, r.theta_offset, sa, ca)
            }),
        }
    }

    /// Frames after joints 1..=`n` (index i = frame after joint i+1), for angles `q[..n]`.
    pub fn frames(&self, q: &[f64], n: usize) -> [Frame; 7] {
        let mut out = [Frame::identity(); 7];
        let mut t = Frame::identity();
        for i in 0..n {
            let (a, d, off, sa, ca) = self.rows[i];
            let (st, ct) = (q[i] + off).sin_cos();
            let link = Frame {
                r: Matrix3::new(ct, -st * ca, st * sa, st, ct * ca, -ct * sa, 0.0, sa, ca),
                p: Vector3::new(a * ct, a * st, d),
            };
            t = t.compose(&link);
            out[i] = t;
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stays_in_range_and_the_rate_is_the_derivative() {
        let ranges = JointRanges::paper();
        let m = Motion::random(&ranges, &mut Rng::new(9));
        for k in 0..2000 {
            let t = k as f64 * 0.037;
            for j in 0..7 {
                let (q, qd) = m.joint(j, t);
                let (lo, hi) = ranges.limits[j];
                assert!(q > lo && q < hi);
                let h = 1e-6;
                let fd = (m.joint(j, t + h).0 - m.joint(j, t - h).0) / (2.0 * h);
                assert!((fd - qd).abs() < 1e-6, "{fd} vs {qd}");
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

    #[test]
    fn chain_matches_calib_core_fk() {
        let table = DhTable::paper_actual();
        let chain = Chain::new(&table);
        let q = [0.1, -0.5, 0.7, 1.2, -0.2, 0.3, 0.9];
        let fk = table.fk(&q);
        let ours = chain.frames(&q, 7)[6];
        assert!((fk.r - ours.r).norm() < 1e-14 && (fk.p - ours.p).norm() < 1e-14);
    }
}
