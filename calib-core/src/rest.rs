//! The gyro at rest (`no_std`, allocation-free): where the suit holds still, each joint's gyro
//! reads its own rate bias, and so measures the heading a joint's angle integrates where no
//! gravity reference corrects it (Xsens' "no rotation" update does the same on the MTi).
//!
//! [`GyroAtRest`] is fed, sample by sample, the measured end-effector pose and each joint's
//! gyro rate about its axis (rad/s). A sample is *still* when every joint's gyro reads below
//! [`STILL_RATE_RAD_S`] and the pose is within [`STILL_POSITION_M`] and [`STILL_ROTATION_RAD`]
//! of the pose that began the run of still samples. A run of at least [`MIN_REST_S`] counts,
//! less [`EDGE_S`] at each end (where the wearer settles and starts again); the counted samples
//! of every run are averaged into [`GyroBias`], the bias with its standard error (the gyro's
//! white noise over the samples averaged). Time is the sample period, passed in.
//!
//! What the bias is for ([`GyroBias::correct`]): a joint whose angle integrates its gyro
//! unaided reads `q + b·t` after `t` seconds; its angles less `b̂·t` leave a residual rate bias
//! of `b − b̂`, whose standard error [`GyroBias::residual`] gives as the sensors' rate-bias spec
//! ([`crate::DriftEmOptions::rate_bias_spec`]), the prior of the EM's rate bias.

use crate::drift::RateBias;
use crate::model::{Frame, Sample};

/// A gyro reading above this (rad/s, about 3 °/s) on any joint is motion.
pub const STILL_RATE_RAD_S: f64 = 0.05;
/// The pose's reach from the run's first pose while still (m): about seven times the
/// difference of two poses with 0.5 mm of noise per axis.
pub const STILL_POSITION_M: f64 = 5e-3;
/// The pose's turn from the run's first pose while still (rad).
pub const STILL_ROTATION_RAD: f64 = 0.02;
/// The shortest run of still samples that counts (s, after its edges).
pub const MIN_REST_S: f64 = 1.0;
/// Left out at each end of a run (s).
pub const EDGE_S: f64 = 0.2;
/// The most samples an edge holds (the trailing edge waits in a fixed buffer of this size).
pub const MAX_EDGE: usize = 64;
/// The standard error never goes below this (rad/s): a gyro whose readings do not vary (a
/// simulation without noise) still has a bias known only this well.
pub const BIAS_SE_FLOOR_RAD_S: f64 = 1e-6;

/// Running mean and sum of squared deviations per joint (Welford; merged by Chan's rule).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Moments<const N: usize> {
    count: usize,
    mean: [f64; N],
    m2: [f64; N],
}

impl<const N: usize> Moments<N> {
    const EMPTY: Moments<N> = Moments {
        count: 0,
        mean: [0.0; N],
        m2: [0.0; N],
    };

    fn push(&mut self, x: &[f64; N]) {
        self.count += 1;
        let n = self.count as f64;
        for ((x, mean), m2) in x.iter().zip(&mut self.mean).zip(&mut self.m2) {
            let d = x - *mean;
            *mean += d / n;
            *m2 += d * (x - *mean);
        }
    }

    fn merge(&self, o: &Moments<N>) -> Moments<N> {
        if o.count == 0 {
            return *self;
        }
        if self.count == 0 {
            return *o;
        }
        let (na, nb) = (self.count as f64, o.count as f64);
        let n = na + nb;
        let mut m = Moments {
            count: self.count + o.count,
            ..Moments::EMPTY
        };
        for j in 0..N {
            let d = o.mean[j] - self.mean[j];
            m.mean[j] = self.mean[j] + d * nb / n;
            m.m2[j] = self.m2[j] + o.m2[j] + d * d * na * nb / n;
        }
        m
    }
}

/// Each joint's gyro bias measured while still.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GyroBias<const N: usize> {
    /// The mean gyro reading while still (rad/s): the bias.
    pub bias: [f64; N],
    /// Its standard error (rad/s): the readings' spread over √ of their count, at least
    /// [`BIAS_SE_FLOOR_RAD_S`].
    pub se: [f64; N],
    /// How long the suit was counted still (s).
    pub seconds: f64,
    /// In how many runs.
    pub runs: usize,
}

impl<const N: usize> GyroBias<N> {
    /// `sample`, taken `t` seconds after some reference time, with the bias taken out of the
    /// joints `unaided` marks (those whose angle integrates the gyro with nothing to correct
    /// its heading): joint `j` less `bias[j]·t`. Which reference does not matter (the offset at
    /// it is the joint's θ offset's business), as long as a session's samples share it.
    pub fn correct(&self, sample: &mut Sample<N>, t: f64, unaided: &[bool; N]) {
        for j in (0..N).filter(|&j| unaided[j]) {
            sample.joints[j] -= self.bias[j] * t;
        }
    }

    /// The rate bias left on the corrected joints, as a spec for the EM: a constant rate bias
    /// of the largest standard error among them ([`RateBias::NONE`] where none is unaided).
    pub fn residual(&self, unaided: &[bool; N]) -> RateBias {
        let ramp = (0..N).filter(|&j| unaided[j]).map(|j| self.se[j]).fold(0.0, f64::max);
        RateBias { ramp, walk: 0.0 }
    }
}

/// The rest detector and the bias it averages (module docs).
#[derive(Clone, Debug)]
pub struct GyroAtRest<const N: usize> {
    dt: f64,
    edge: usize,
    min_run: usize,
    /// The pose that began the current run, and how many samples the run has had.
    anchor: Option<(Frame, usize)>,
    /// The current run's counted samples (past its leading edge, before its trailing one).
    run: Moments<N>,
    /// Its newest `edge` samples, counted only once newer ones follow.
    tail: heapless::Deque<[f64; N], MAX_EDGE>,
    /// Every finished run that counted.
    total: Moments<N>,
    runs: usize,
}

impl<const N: usize> GyroAtRest<N> {
    /// A detector for samples `dt` seconds apart.
    pub fn new(dt: f64) -> Self {
        let edge = (libm::round(EDGE_S / dt) as usize).clamp(1, MAX_EDGE);
        GyroAtRest {
            dt,
            edge,
            min_run: libm::ceil(MIN_REST_S / dt) as usize,
            anchor: None,
            run: Moments::EMPTY,
            tail: heapless::Deque::new(),
            total: Moments::EMPTY,
            runs: 0,
        }
    }

    /// One sample: the measured pose and every joint's gyro rate (rad/s).
    pub fn push(&mut self, pose: &Frame, gyro: &[f64; N]) {
        let quiet = gyro.iter().all(|g| g.abs() < STILL_RATE_RAD_S);
        let near = |a: &Frame| {
            let dp = (pose.p - a.p).norm();
            let dr = crate::model::log_so3(&(a.r.transpose() * pose.r)).norm();
            dp <= STILL_POSITION_M && dr <= STILL_ROTATION_RAD
        };
        match self.anchor {
            Some((a, n)) if quiet && near(&a) => {
                self.anchor = Some((a, n + 1));
                if n + 1 > self.edge {
                    if self.tail.is_full() || self.tail.len() == self.edge {
                        if let Some(old) = self.tail.pop_front() {
                            self.run.push(&old);
                        }
                    }
                    // Room is kept: the tail never holds more than `edge ≤ MAX_EDGE`.
                    let _ = self.tail.push_back(*gyro);
                }
            }
            _ => {
                self.end_run();
                self.anchor = quiet.then_some((*pose, 1));
            }
        }
    }

    /// Closes the current run: it counts if long enough.
    fn end_run(&mut self) {
        if self.run.count >= self.min_run {
            self.total = self.total.merge(&self.run);
            self.runs += 1;
        }
        self.run = Moments::EMPTY;
        self.tail.clear();
        self.anchor = None;
    }

    /// The bias so far (the current run too, if it already counts); `None` before any run of
    /// [`MIN_REST_S`].
    pub fn estimate(&self) -> Option<GyroBias<N>> {
        let current = self.run.count >= self.min_run;
        let m = if current { self.total.merge(&self.run) } else { self.total };
        if m.count == 0 {
            return None;
        }
        let n = m.count as f64;
        Some(GyroBias {
            bias: m.mean,
            se: core::array::from_fn(|j| {
                let var = if m.count > 1 { m.m2[j] / (n - 1.0) } else { 0.0 };
                libm::sqrt(var / n).max(BIAS_SE_FLOOR_RAD_S)
            }),
            seconds: n * self.dt,
            runs: self.runs + usize::from(current),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::DhTable;
    use crate::rng::Rng;

    /// Still for 3 s, moving for 2 s, still for 2 s, moving: both still runs count less their
    /// edges, the motion and its onset do not, and the bias is the mean within its error.
    #[test]
    fn still_runs_measure_the_bias_and_motion_does_not() {
        let dt = 0.02;
        let table = DhTable::paper_nominal();
        let bias = [1e-3, -2e-3, 5e-4];
        let mut rng = Rng::new(3);
        let mut rest = GyroAtRest::<3>::new(dt);
        let mut q = [0.1; 7];
        for k in 0..500 {
            let t = k as f64 * dt;
            let moving = (3.0..5.0).contains(&t) || t >= 7.0;
            let rate = if moving { 0.8 } else { 0.0 };
            q[0] += rate * dt;
            let gyro = core::array::from_fn(|j| rate + bias[j] + 2e-3 * rng.normal());
            rest.push(&table.fk(&q), &gyro);
        }
        let b = rest.estimate().expect("a bias");
        assert_eq!(b.runs, 2);
        // 3 s and 2 s, less 0.2 s at each end of each.
        assert!((b.seconds - 4.2).abs() < 2.5 * dt, "{b:?}");
        for (j, truth) in bias.iter().enumerate() {
            assert!((b.bias[j] - truth).abs() < 4.0 * b.se[j], "{b:?}");
            let se = 2e-3 / libm::sqrt(b.seconds / dt);
            assert!((b.se[j] / se - 1.0).abs() < 0.2, "{b:?}");
        }
    }

    /// A slow turn no gyro threshold sees (a drifting pose) and a pause of 0.5 s (with the turn
    /// before it, shorter than [`MIN_REST_S`] and two edges) are not rest.
    #[test]
    fn a_slow_turn_and_a_short_pause_are_not_rest() {
        let dt = 0.01;
        let table = DhTable::paper_nominal();
        let mut rest = GyroAtRest::<7>::new(dt);
        let mut q = [0.1; 7];
        for k in 0..3000 {
            // 0.03 rad/s: under the gyro threshold, but the pose leaves its tolerance in < 1 s.
            q[0] += 0.03 * dt;
            let pause = (1000..1050).contains(&k);
            let gyro = [if pause { 0.0 } else { 0.03 }; 7];
            if pause {
                q[0] -= 0.03 * dt;
            }
            rest.push(&table.fk(&q), &gyro);
        }
        assert_eq!(rest.estimate(), None);
    }

    #[test]
    fn correcting_takes_the_slope_out_of_the_unaided_joints_only() {
        let b = GyroBias::<2> {
            bias: [1e-3, 2e-3],
            se: [1e-4, 3e-4],
            seconds: 5.0,
            runs: 1,
        };
        let mut s = [Sample {
            joints: [0.0; 2],
            pose: Frame::identity(),
        }; 3];
        for (k, s) in s.iter_mut().enumerate() {
            b.correct(s, 0.5 * k as f64, &[true, false]);
        }
        assert_eq!(s.map(|s| s.joints), [[0.0, 0.0], [-5e-4, 0.0], [-1e-3, 0.0]]);
        assert_eq!(b.residual(&[true, false]).ramp, 1e-4);
        assert_eq!(b.residual(&[false, false]), RateBias::NONE);
    }
}
