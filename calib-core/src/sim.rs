//! Seeded simulation of a calibration session (`no_std`, allocation-free): the paper's
//! Section 4 scenario, and the field conditions a real suit adds to it.
//!
//! Everything is plain data in [`ScenarioConfig`] and every random draw derives from the seed:
//! the same configuration and seed always give the same samples. With the field options off
//! ([`ScenarioConfig::paper`]) the samples are those of the paper's scenario, bit for bit.
//!
//! * **Motion.** Each joint follows a sum of [`MOTION_HARMONICS`] random sinusoids (0.05–0.6
//!   Hz, random phases and amplitudes), normalised into `[−1, 1]` and mapped into 98 % of its
//!   Table 3 range, so it is smooth and never leaves the range.
//! * **Angle error Δθ per joint** (what a joint sensor's angle is off by): the Gauss-Markov
//!   drift of [`ScenarioConfig::drift`] plus, optionally, a rate bias integrated into the angle
//!   ([`RateBias`]: a ramp, and a bias that wanders as a random walk), as an IMU's fused angle
//!   carries it. The integrated part starts at 0 with the session.
//! * **Where the error sits** ([`DriftSite`]): in the arm (the paper's convention: the sensor
//!   reports the smooth motion θ, the arm is at θ + Δθ) or in the reading (a real sensor and the
//!   emulated suit: the arm is at the smooth motion q, the sensor reports q − Δθ).
//! * **Reading noise**: white noise on every reported angle ([`ScenarioConfig::reading_noise`]).
//! * **A joint gyro** per joint: the rate of the smooth motion about the joint's axis, less
//!   the rate bias the angle integrates (so a reading that integrates its gyro reads
//!   `q + ∫ gyro bias`), plus white noise ([`ScenarioConfig::gyro_noise`], drawn from a
//!   generator of its own so that every other draw is the same with and without it).
//! * **Still at the start** ([`ScenarioConfig::still_s`]): the wearer holds the motion's first
//!   pose that long, then moves as the motion does from its start.
//! * **A slip** ([`Slip`]): one joint's angle error steps mid-session and stays.
//! * **The reference pose** is `FK(actual, arm angles)`, plus optional white noise (rotation
//!   applied in the tool frame) and **glitches** ([`Outliers`]: with a given probability a run
//!   of samples jumps by a random cm-sized offset, as an occluded or knocked tracker gives).
//!
//! [`SimSample`] keeps the hidden truth beside what a calibration sees: the angle error, the arm
//! angles and whether the pose is a glitch.

use nalgebra::{Rotation3, Vector3};

use crate::drift::GaussMarkov;
pub use crate::drift::RateBias;
use crate::model::{DhTable, Frame, JointRanges, Sample};
use crate::rng::Rng;

/// Number of sinusoids per joint in the random motion.
pub const MOTION_HARMONICS: usize = 4;
/// The motion's swing about the middle of each joint's range, as a share of the range: it
/// sweeps 98 % of it and never reaches the ends.
pub const MOTION_SWING: f64 = 0.49;

/// Smooth random joint motion inside given ranges: the suit's motion, here and in the emulated
/// suit (`exocal-hil`).
#[derive(Clone, Debug, PartialEq)]
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

    /// Joint `j`'s middle and swing (rad): its angle is `middle + swing · u` for the normalised
    /// motion `u` of [`Motion::unit`].
    pub fn middle_and_swing(&self, j: usize) -> (f64, f64) {
        let (lo, hi) = self.ranges.limits[j];
        (0.5 * (lo + hi), MOTION_SWING * (hi - lo))
    }

    /// Joint `j`'s motion at time `t` (s) normalised into `[−1, 1]`, and its rate (1/s), in
    /// closed form: [`Motion::at`] is it through [`Motion::middle_and_swing`], joint by joint. For a
    /// caller that evaluates one joint at a time, or needs the rate (an emulated gyro).
    pub fn unit(&self, j: usize, t: f64) -> (f64, f64) {
        let (mut s, mut ds, mut norm) = (0.0, 0.0, 0.0);
        for h in 0..MOTION_HARMONICS {
            let omega = 2.0 * core::f64::consts::PI * self.freq[j][h];
            let (sn, cs) = libm::sincos(omega * t + self.phase[j][h]);
            s += self.amp[j][h] * sn;
            ds += self.amp[j][h] * omega * cs;
            norm += self.amp[j][h];
        }
        (s / norm, ds / norm)
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
            0.5 * (lo + hi) + MOTION_SWING * (hi - lo) * s / norm
        })
    }
}

/// Where a joint's angle error acts.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum DriftSite {
    /// The paper's Section 4: the sensor reports the smooth motion θ, the arm is at θ + Δθ.
    #[default]
    Arm,
    /// A real joint sensor (and the emulated suit): the arm is at the smooth motion q, the
    /// sensor reports q − Δθ.
    Reading,
}

/// Glitches of the reference pose: a run of `burst` samples starts with probability
/// `probability / burst` at every sample that is not already in one (so about `probability` of
/// the samples are glitched), and every sample of the run is moved by the same random offset:
/// `N(0, position²)` per axis (m) and a rotation of `N(0, rotation²)` per axis (rad, tool frame).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Outliers {
    /// Share of glitched samples (0: none).
    pub probability: f64,
    /// Samples per glitch (at least 1).
    pub burst: usize,
    /// Standard deviation of the position offset per axis (m).
    pub position: f64,
    /// Standard deviation of the rotation offset per axis (rad).
    pub rotation: f64,
}

impl Outliers {
    /// No glitches.
    pub const NONE: Outliers = Outliers {
        probability: 0.0,
        burst: 1,
        position: 0.0,
        rotation: 0.0,
    };
}

/// A joint sensor that slips: from `time` (s) on, its angle error is `angle` (rad) larger (a
/// strap that moves on the limb, a sensor re-zeroed mid-session).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Slip {
    /// The joint (0-based).
    pub joint: usize,
    /// When (s from the session's start).
    pub time: f64,
    /// By how much (rad).
    pub angle: f64,
}

/// Settings of the simulated session (module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScenarioConfig<const N: usize> {
    /// The true arm.
    pub actual: DhTable<N>,
    /// Joint ranges the motion stays inside.
    pub ranges: JointRanges<N>,
    /// Gauss-Markov part of every joint's angle error (also fixes the sample period `drift.dt`).
    pub drift: GaussMarkov,
    /// Rate bias integrated into every joint's angle error.
    pub bias: RateBias,
    /// A constant rate bias per joint (rad/s) beside [`ScenarioConfig::bias`], integrated from the
    /// session's start without bound: the heading drift of a joint whose angle no gravity
    /// reference corrects (an IMU without magnetometer).
    pub heading: [f64; N],
    /// Where the angle error acts.
    pub site: DriftSite,
    /// Standard deviation of white noise on every reported joint angle (rad); 0 = none.
    pub reading_noise: f64,
    /// Standard deviation of white noise on every joint gyro reading (rad/s); 0 = none.
    pub gyro_noise: f64,
    /// The wearer holds still this long at the start (s); 0 = moves from the first sample.
    pub still_s: f64,
    /// Standard deviation of white position noise on the measured pose (m); 0 = none.
    pub position_noise: f64,
    /// Standard deviation of white rotation noise per axis (rad); 0 = none.
    pub rotation_noise: f64,
    /// Glitches of the measured pose.
    pub outliers: Outliers,
    /// A sensor that slips during the session.
    pub slip: Option<Slip>,
}

impl<const N: usize> ScenarioConfig<N> {
    /// The same session on the arm of the first `M` joints (`M ≤ N`, checked at compile
    /// time): the table, ranges and headings of those joints, a slip only where it is one of
    /// them, the rest as it is.
    pub fn first<const M: usize>(&self) -> ScenarioConfig<M> {
        ScenarioConfig {
            actual: self.actual.first(),
            ranges: self.ranges.first(),
            heading: core::array::from_fn(|j| self.heading[j]),
            slip: self.slip.filter(|s| s.joint < M),
            drift: self.drift,
            bias: self.bias,
            site: self.site,
            reading_noise: self.reading_noise,
            gyro_noise: self.gyro_noise,
            still_s: self.still_s,
            position_noise: self.position_noise,
            rotation_noise: self.rotation_noise,
            outliers: self.outliers,
        }
    }
}

impl ScenarioConfig<7> {
    /// Section 4: Table 4 arm, Table 3 ranges, Δt = 0.01 s, τ = 1 s, σ = 1, the drift in the
    /// arm, no rate bias, no noise, no glitches.
    pub fn paper() -> Self {
        ScenarioConfig {
            actual: DhTable::paper_actual(),
            ranges: JointRanges::paper(),
            drift: GaussMarkov::paper(),
            bias: RateBias::NONE,
            heading: [0.0; 7],
            site: DriftSite::Arm,
            reading_noise: 0.0,
            gyro_noise: 0.0,
            still_s: 0.0,
            position_noise: 0.0,
            rotation_noise: 0.0,
            outliers: Outliers::NONE,
            slip: None,
        }
    }
}

/// One simulated sample with its hidden truth.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SimSample<const N: usize> {
    /// What a calibration sees: the reported joint angles and the measured pose.
    pub sample: Sample<N>,
    /// The true angle error Δθ_k of every joint (Gauss-Markov plus integrated rate bias; the
    /// reading noise not included).
    pub drift: [f64; N],
    /// The true joint angles of the arm, which the pose follows (before pose noise).
    pub arm: [f64; N],
    /// Every joint's gyro reading about its axis (rad/s; module docs).
    pub gyro: [f64; N],
    /// Whether the measured pose is glitched.
    pub outlier: bool,
}

/// An endless iterator of simulated samples at `config.drift.dt`.
#[derive(Clone, Debug)]
pub struct Scenario<const N: usize> {
    config: ScenarioConfig<N>,
    motion: Motion<N>,
    rng: Rng,
    /// The gyros' noise.
    gyro_rng: Rng,
    /// Gauss-Markov part of the angle error.
    drift: [f64; N],
    /// Integrated rate bias and the rate bias.
    integrated: [f64; N],
    rate: [f64; N],
    /// The current glitch: samples left in it and its offset (position, rotation vector).
    glitch: (usize, Vector3<f64>, Vector3<f64>),
    k: u64,
}

impl<const N: usize> Scenario<N> {
    /// A session for `seed` (motion, drift, noise and glitches all derive from it).
    pub fn new(config: ScenarioConfig<N>, seed: u64) -> Self {
        let mut rng = Rng::new(seed);
        let motion = Motion::random(&config.ranges, &mut rng);
        let drift = core::array::from_fn(|_| config.drift.initial(&mut rng));
        let rate = core::array::from_fn(|_| {
            if config.bias.ramp > 0.0 {
                config.bias.ramp * rng.normal()
            } else {
                0.0
            }
        });
        Scenario {
            config,
            motion,
            rng,
            gyro_rng: Rng::new(seed ^ 0x6780_5EED),
            drift,
            integrated: [0.0; N],
            rate,
            glitch: (0, Vector3::zeros(), Vector3::zeros()),
            k: 0,
        }
    }

    /// The configuration.
    pub fn config(&self) -> &ScenarioConfig<N> {
        &self.config
    }

    /// The glitch offset of the next sample, if it is glitched.
    fn next_glitch(&mut self) -> Option<(Vector3<f64>, Vector3<f64>)> {
        let o = self.config.outliers;
        if o.probability <= 0.0 {
            return None;
        }
        if self.glitch.0 == 0 {
            let burst = o.burst.max(1);
            if self.rng.uniform() >= o.probability / burst as f64 {
                return None;
            }
            let mut draw = |s: f64| Vector3::new(s * self.rng.normal(), s * self.rng.normal(), s * self.rng.normal());
            let (p, r) = (draw(o.position), draw(o.rotation));
            self.glitch = (burst, p, r);
        }
        self.glitch.0 -= 1;
        Some((self.glitch.1, self.glitch.2))
    }
}

impl<const N: usize> Iterator for Scenario<N> {
    type Item = SimSample<N>;

    fn next(&mut self) -> Option<SimSample<N>> {
        let cfg = self.config;
        let t = self.k as f64 * cfg.drift.dt;
        // The motion's own clock: held at 0 while the wearer is still.
        let moving = t >= cfg.still_s;
        let tm = if moving { t - cfg.still_s } else { 0.0 };
        let smooth = self.motion.at(tm);
        let gyro: [f64; N] = core::array::from_fn(|j| {
            let rate = if moving {
                let (_, swing) = self.motion.middle_and_swing(j);
                swing * self.motion.unit(j, tm).1
            } else {
                0.0
            };
            let noise = if cfg.gyro_noise > 0.0 {
                cfg.gyro_noise * self.gyro_rng.normal()
            } else {
                0.0
            };
            rate - (self.rate[j] + cfg.heading[j]) + noise
        });
        let slip = |j: usize| match cfg.slip {
            Some(s) if s.joint == j && t >= s.time => s.angle,
            _ => 0.0,
        };
        let error: [f64; N] = core::array::from_fn(|j| self.drift[j] + self.integrated[j] + slip(j));
        let (arm, mut joints) = match cfg.site {
            DriftSite::Arm => (core::array::from_fn(|j| smooth[j] + error[j]), smooth),
            DriftSite::Reading => (smooth, core::array::from_fn(|j| smooth[j] - error[j])),
        };
        if cfg.reading_noise > 0.0 {
            for q in joints.iter_mut() {
                *q += cfg.reading_noise * self.rng.normal();
            }
        }
        let mut pose: Frame = cfg.actual.fk(&arm);
        if cfg.position_noise > 0.0 {
            let n = cfg.position_noise;
            pose.p += Vector3::new(n * self.rng.normal(), n * self.rng.normal(), n * self.rng.normal());
        }
        if cfg.rotation_noise > 0.0 {
            let n = cfg.rotation_noise;
            let w = Vector3::new(n * self.rng.normal(), n * self.rng.normal(), n * self.rng.normal());
            pose.r *= Rotation3::new(w).into_inner();
        }
        let glitch = self.next_glitch();
        if let Some((p, r)) = glitch {
            pose.p += p;
            pose.r *= Rotation3::new(r).into_inner();
        }
        for x in self.drift.iter_mut() {
            *x = cfg.drift.step(*x, &mut self.rng);
        }
        if !cfg.bias.is_none() || cfg.heading.iter().any(|&h| h != 0.0) {
            let kick = cfg.bias.walk * libm::sqrt(cfg.drift.dt);
            for j in 0..N {
                self.integrated[j] += cfg.drift.dt * (self.rate[j] + cfg.heading[j]);
                if kick > 0.0 {
                    self.rate[j] += kick * self.rng.normal();
                }
            }
        }
        self.k += 1;
        Some(SimSample {
            sample: Sample { joints, pose },
            drift: error,
            arm,
            gyro,
            outlier: glitch.is_some(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_joint_alone_is_the_motion_and_its_rate_the_derivative() {
        let ranges = JointRanges::paper();
        let m = Motion::random(&ranges, &mut Rng::new(9));
        for k in 0..500 {
            let t = k as f64 * 0.137;
            let q = m.at(t);
            for (j, &qj) in q.iter().enumerate() {
                let (u, du) = m.unit(j, t);
                assert!(u.abs() <= 1.0);
                let (middle, swing) = m.middle_and_swing(j);
                assert!((middle + swing * u - qj).abs() < 1e-12);
                let h = 1e-6;
                let fd = (m.unit(j, t + h).0 - m.unit(j, t - h).0) / (2.0 * h);
                assert!((fd - du).abs() < 1e-7, "{fd} vs {du}");
            }
        }
    }

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

    #[test]
    fn the_field_conditions_are_where_the_config_puts_them() {
        let paper = ScenarioConfig::paper();
        let cfg = ScenarioConfig {
            drift: GaussMarkov { dt: 0.02, ..paper.drift },
            bias: RateBias { ramp: 1e-3, walk: 1e-4 },
            site: DriftSite::Reading,
            reading_noise: 1e-4,
            outliers: Outliers {
                probability: 0.05,
                burst: 3,
                position: 0.02,
                rotation: 0.0,
            },
            ..paper
        };
        let run: std::vec::Vec<SimSample<7>> = Scenario::new(cfg, 9).take(3000).collect();
        let mut glitched = 0;
        for s in &run {
            // The pose follows the arm, which is at the smooth motion; the reading is off by the
            // angle error (and the reading noise).
            let clean = cfg.actual.fk(&s.arm);
            let off = (clean.p - s.sample.pose.p).norm();
            assert_eq!(off > 0.0, s.outlier);
            glitched += s.outlier as usize;
            for j in 0..7 {
                let e = s.arm[j] - s.drift[j] - s.sample.joints[j];
                assert!(e.abs() < 6e-4, "reading noise {e}");
            }
        }
        // About 5% glitched, in runs of 3.
        assert!((100..200).contains(&glitched), "{glitched}");
        assert!(run.windows(2).filter(|w| w[1].outlier && !w[0].outlier).count() * 3 >= glitched - 3);
        // The integrated bias starts at 0 and makes the error wander far beyond the
        // Gauss-Markov part's 0.14 mrad (σ = 1 at 50 Hz) within the minute.
        let spread = (0..7)
            .map(|j| (run[2999].drift[j] - run[0].drift[j]).abs())
            .fold(0.0, f64::max);
        assert!(spread > 5e-3, "{spread}");
        // Off, the samples are the paper's (the same draws in the same order).
        let plain = ScenarioConfig {
            bias: RateBias::NONE,
            outliers: Outliers::NONE,
            reading_noise: 0.0,
            site: DriftSite::Arm,
            ..cfg
        };
        let a = Scenario::new(plain, 4).nth(77).unwrap();
        let b = Scenario::new(
            ScenarioConfig {
                drift: cfg.drift,
                ..paper
            },
            4,
        )
        .nth(77)
        .unwrap();
        assert_eq!(a, b);
    }
}
