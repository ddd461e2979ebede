//! Seeded simulation of the paper's Section 4 scenario (`no_std`, allocation-free).
//!
//! Motion: each joint follows a sum of [`MOTION_HARMONICS`] random sinusoids (0.05–0.6 Hz,
//! random phases and amplitudes), normalised into `[−1, 1]` and mapped into 98 % of its Table 3
//! range, so it is smooth and never leaves the range. The "actual" arm is Table 4 with
//! Gauss-Markov drift added to every joint angle; the measured pose is
//! `FK(actual, θ + Δθ)` (plus optional white noise, rotation applied in the tool frame); the
//! reported joint angles are θ. The same seed always gives the same samples.

use nalgebra::{Rotation3, Vector3};

use crate::drift::GaussMarkov;
use crate::model::{DhTable, Frame, JointRanges, Sample};
use crate::rng::Rng;

/// Number of sinusoids per joint in the random motion.
pub const MOTION_HARMONICS: usize = 4;

/// Smooth random joint motion inside given ranges.
#[derive(Clone, Debug)]
pub struct Motion<const N: usize> {
    freq: [[f64; MOTION_HARMONICS]; N],
    phase: [[f64; MOTION_HARMONICS]; N],
    amp: [[f64; MOTION_HARMONICS]; N],
    ranges: JointRanges<N>,
}

impl<const N: usize> Motion<N> {
    /// Draws a random motion from `rng`.
    pub fn random(ranges: &JointRanges<N>, rng: &mut Rng) -> Self {
        let mut m = Motion {
            freq: [[0.0; MOTION_HARMONICS]; N],
            phase: [[0.0; MOTION_HARMONICS]; N],
            amp: [[0.0; MOTION_HARMONICS]; N],
            ranges: *ranges,
        };
        for j in 0..N {
            for h in 0..MOTION_HARMONICS {
                m.freq[j][h] = 0.05 + 0.55 * rng.uniform();
                m.phase[j][h] = 2.0 * core::f64::consts::PI * rng.uniform();
                m.amp[j][h] = 0.2 + rng.uniform();
            }
        }
        m
    }

    /// Joint angles at time `t` (s).
    pub fn at(&self, t: f64) -> [f64; N] {
        core::array::from_fn(|j| {
            let (mut s, mut norm) = (0.0, 0.0);
            for h in 0..MOTION_HARMONICS {
                s += self.amp[j][h] * libm::sin(2.0 * core::f64::consts::PI * self.freq[j][h] * t + self.phase[j][h]);
                norm += self.amp[j][h];
            }
            let (lo, hi) = self.ranges.limits[j];
            0.5 * (lo + hi) + 0.49 * (hi - lo) * s / norm
        })
    }
}

/// Settings of the simulated session.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScenarioConfig<const N: usize> {
    /// The true arm.
    pub actual: DhTable<N>,
    /// Joint ranges the motion stays inside.
    pub ranges: JointRanges<N>,
    /// Drift of every joint angle (also fixes the sample period `drift.dt`).
    pub drift: GaussMarkov,
    /// Standard deviation of white position noise on the measured pose (m); 0 = none.
    pub position_noise: f64,
    /// Standard deviation of white rotation noise per axis (rad); 0 = none.
    pub rotation_noise: f64,
}

impl ScenarioConfig<7> {
    /// Section 4: Table 4 arm, Table 3 ranges, Δt = 0.01 s, τ = 1 s, σ = 1, no pose noise.
    pub fn paper() -> Self {
        ScenarioConfig {
            actual: DhTable::paper_actual(),
            ranges: JointRanges::paper(),
            drift: GaussMarkov::paper(),
            position_noise: 0.0,
            rotation_noise: 0.0,
        }
    }
}

/// One simulated sample with its hidden truth.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SimSample<const N: usize> {
    /// What a calibration sees.
    pub sample: Sample<N>,
    /// The true drift Δθ_k added to the joint angles.
    pub drift: [f64; N],
}

/// An endless iterator of simulated samples at `config.drift.dt`.
#[derive(Clone, Debug)]
pub struct Scenario<const N: usize> {
    config: ScenarioConfig<N>,
    motion: Motion<N>,
    rng: Rng,
    drift: [f64; N],
    k: u64,
}

impl<const N: usize> Scenario<N> {
    /// A session for `seed` (motion, drift and noise all derive from it).
    pub fn new(config: ScenarioConfig<N>, seed: u64) -> Self {
        let mut rng = Rng::new(seed);
        let motion = Motion::random(&config.ranges, &mut rng);
        let drift = core::array::from_fn(|_| config.drift.initial(&mut rng));
        Scenario {
            config,
            motion,
            rng,
            drift,
            k: 0,
        }
    }
}

impl<const N: usize> Iterator for Scenario<N> {
    type Item = SimSample<N>;

    fn next(&mut self) -> Option<SimSample<N>> {
        let t = self.k as f64 * self.config.drift.dt;
        let joints = self.motion.at(t);
        let drift = self.drift;
        let true_q: [f64; N] = core::array::from_fn(|j| joints[j] + drift[j]);
        let mut pose: Frame = self.config.actual.fk(&true_q);
        if self.config.position_noise > 0.0 {
            let n = self.config.position_noise;
            pose.p += Vector3::new(n * self.rng.normal(), n * self.rng.normal(), n * self.rng.normal());
        }
        if self.config.rotation_noise > 0.0 {
            let n = self.config.rotation_noise;
            let w = Vector3::new(n * self.rng.normal(), n * self.rng.normal(), n * self.rng.normal());
            pose.r *= Rotation3::new(w).into_inner();
        }
        for x in self.drift.iter_mut() {
            *x = self.config.drift.step(*x, &mut self.rng);
        }
        self.k += 1;
        Some(SimSample {
            sample: Sample { joints, pose },
            drift,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn motion_stays_in_range_moves_and_is_seeded() {
        let cfg = ScenarioConfig::paper();
        let a: [SimSample<7>; 50] = {
            let mut s = Scenario::new(cfg, 3).step_by(100);
            core::array::from_fn(|_| s.next().unwrap())
        };
        let b = Scenario::new(cfg, 3).step_by(100).nth(49).unwrap();
        assert_eq!(a[49], b);
        for j in 0..7 {
            let (lo, hi) = cfg.ranges.limits[j];
            let (mn, mx) = a.iter().fold((f64::MAX, f64::MIN), |(mn, mx), s| {
                (mn.min(s.sample.joints[j]), mx.max(s.sample.joints[j]))
            });
            assert!(mn >= lo && mx <= hi, "joint {j}");
            assert!(mx - mn > 0.2 * (hi - lo), "joint {j} barely moves");
        }
        let c = Scenario::new(cfg, 4).next().unwrap();
        assert_ne!(c.sample.joints, Scenario::new(cfg, 3).next().unwrap().sample.joints);
    }

    #[test]
    fn measured_pose_is_fk_of_actual_with_drift() {
        let cfg = ScenarioConfig::paper();
        for s in Scenario::new(cfg, 1).take(10) {
            let q: [f64; 7] = core::array::from_fn(|j| s.sample.joints[j] + s.drift[j]);
            let t = cfg.actual.fk(&q);
            assert!((t.p - s.sample.pose.p).norm() < 1e-15);
            assert!(s.drift.iter().any(|d| *d != 0.0));
        }
    }
}
