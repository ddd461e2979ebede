//! Smooth random joint motion with analytic rates, and a D-H chain with cached link constants.
//!
//! Contract: like calib-core's `Motion` (a sum of [`HARMONICS`] random sinusoids per joint,
//! 0.05–0.6 Hz, normalised into `[−1, 1]` and mapped into 98 % of the joint's range, so it is
//! smooth and never leaves the range), but each joint is evaluated on its own, with its rate in
//! closed form: a node samples only what it needs. This matters in slow environments (the vcan
//! harness runs under QEMU's software floating point).

use calib_core::{DhTable, Frame, JointRanges, Rng};
use nalgebra::{Matrix3, Vector3};
use std::f64::consts::TAU;

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

/// Smooth random motion of seven joints.
#[derive(Clone, Debug, PartialEq)]
pub struct Motion {
    joints: [Joint; 7],
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
        }
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
        (m.mid + m.half * s, m.half * ds)
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
    fn chain_matches_calib_core_fk() {
        let table = DhTable::paper_actual();
        let chain = Chain::new(&table);
        let q = [0.1, -0.5, 0.7, 1.2, -0.2, 0.3, 0.9];
        let fk = table.fk(&q);
        let ours = chain.frames(&q, 7)[6];
        assert!((fk.r - ours.r).norm() < 1e-14 && (fk.p - ours.p).norm() < 1e-14);
    }
}
