//! Which motion would most reduce the expected table error: guidance while collecting.
//!
//! Contract: [`guidance`] takes the table so far, configurations the arm visited (a subsample
//! of the session: each stands for `per_config` samples), each pose component's noise variance,
//! the joint ranges and how many samples of motion to add. It returns the expected table error
//! (1σ, RMS over [`GUIDANCE_POSES`] poses spread evenly over the joint ranges: the poses a
//! wearer will take, not only those of this session) of the motion so far, and per joint the expected
//! table error after that much more motion in which that joint sweeps its whole range while the
//! others keep to configurations already visited. The model is the linearised, white-noise one
//! (the information `Σ JᵀWJ` of the 4N parameters), with a weak prior per parameter
//! ([`PRIOR_SD`], the size of a manufacturing error a calibration exists to find) so that a joint
//! never moved has a large but finite error, not a singular problem: its figures rank the joints
//! and give the relative gain; a caller that states an error (the drift EM's) scales them to it
//! ([`Guidance::ratio`]).
//!
//! No allocation; `O((V + N·M)·N)` FK Jacobians and `N + 1` Cholesky factorisations of a
//! `4N × 4N` matrix, for `V` visited and `M = min(V, `[`GUIDANCE_CONFIGS`]`)` added configurations.

use nalgebra::{Cholesky, Const, SMatrix, SVector};

use crate::metrics::{expected_table_error, TableError};
use crate::model::{DhTable, JointRanges, ParamKind};

/// Prior standard deviation of each kind of parameter (`a`, `d` in m; `α`, θ offset in rad), in
/// [`ParamKind`] order: what is known of a table before any motion.
pub const PRIOR_SD: [f64; 4] = [0.05, 0.05, 0.17, 0.26];
/// Added configurations per joint (at most): the joint's range swept in this many steps.
pub const GUIDANCE_CONFIGS: usize = 100;
/// Poses (spread over the joint ranges) the expected error is averaged over.
pub const GUIDANCE_POSES: usize = 200;

/// The expected table error now, and after more motion of each joint.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Guidance<const N: usize> {
    /// Expected table error of the motion so far.
    pub now: TableError,
    /// Expected table error after the added motion of joint `j` (0-based).
    pub after: [TableError; N],
}

impl<const N: usize> Guidance<N> {
    /// The joint (0-based) whose motion would most reduce the expected position error (the
    /// rotation error breaks ties).
    pub fn best(&self) -> usize {
        let key = |e: &TableError| (e.position_m, e.rotation_rad);
        (0..N)
            .min_by(|&a, &b| {
                key(&self.after[a])
                    .partial_cmp(&key(&self.after[b]))
                    .unwrap_or(core::cmp::Ordering::Equal)
            })
            .unwrap_or(0)
    }

    /// Per joint, the expected position error after its motion as a fraction of now's (1: no
    /// gain): what a stated error is multiplied by.
    pub fn ratio(&self) -> [f64; N] {
        core::array::from_fn(|j| {
            if self.now.position_m > 0.0 {
                (self.after[j].position_m / self.now.position_m).min(1.0)
            } else {
                1.0
            }
        })
    }
}

/// Adds the information of configuration `q`, weighted by `weight` samples, to `h`.
fn absorb<const N: usize, const P: usize>(
    h: &mut SMatrix<f64, P, P>,
    table: &DhTable<N>,
    q: &[f64; N],
    inv_var: &[f64; 6],
    weight: f64,
) {
    let (_, cols) = table.fk_jacobian(q);
    for (r, w) in inv_var.iter().enumerate() {
        let row = SVector::<f64, P>::from_fn(|p, _| cols[p / N][p % N][r]);
        h.ger(weight * w, &row, &row, 1.0);
    }
}

/// The expected table error of `table` for information `h`, over `poses`; `None` if `h` is not
/// positive definite.
fn expected<'a, const N: usize, const P: usize>(
    table: &DhTable<N>,
    h: SMatrix<f64, P, P>,
    poses: impl IntoIterator<Item = &'a [f64; N]>,
) -> Option<TableError> {
    let chol = Cholesky::<f64, Const<P>>::new(h)?;
    Some(expected_table_error::<N, P>(table, poses, |u| {
        let u = SVector::<f64, P>::from_column_slice(u);
        u.dot(&chol.solve(&u))
    }))
}

/// The guidance for a session that visited `visited` (see the module docs). `None` without
/// visited configurations or with a degenerate noise variance.
pub fn guidance<const N: usize, const P: usize>(
    table: &DhTable<N>,
    visited: &[[f64; N]],
    per_config: f64,
    noise_var: &[f64; 6],
    ranges: &JointRanges<N>,
    added_samples: f64,
) -> Option<Guidance<N>> {
    const { assert!(P == 4 * N, "P must be 4N") };
    if visited.is_empty() || noise_var.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
        return None;
    }
    let inv_var = noise_var.map(|v| 1.0 / v);
    let mut h = SMatrix::<f64, P, P>::zeros();
    for p in 0..P {
        let (kind, _) = ParamKind::of_index(p, N);
        let sd = PRIOR_SD[kind as usize];
        h[(p, p)] = 1.0 / (sd * sd);
    }
    for q in visited {
        absorb::<N, P>(&mut h, table, q, &inv_var, per_config);
    }
    let every = |n: usize| visited.len().div_ceil(n).max(1);
    let poses: heapless::Vec<[f64; N], GUIDANCE_POSES> = (0..GUIDANCE_POSES).map(|i| ranges.spread(i)).collect();
    let now = expected::<N, P>(table, h, &poses)?;
    let m = visited.len().min(GUIDANCE_CONFIGS);
    let base: heapless::Vec<[f64; N], GUIDANCE_CONFIGS> = visited.iter().step_by(every(m)).take(m).copied().collect();
    let mut after = [now; N];
    for (j, out) in after.iter_mut().enumerate() {
        let mut hj = h;
        let weight = added_samples / base.len() as f64;
        for (i, q) in base.iter().enumerate() {
            let mut q = *q;
            // The range swept evenly, in an order uncorrelated with the other joints'.
            q[j] = ranges.spread_joint(i, j);
            absorb::<N, P>(&mut hj, table, &q, &inv_var, weight);
        }
        *out = expected::<N, P>(table, hj, &poses)?;
    }
    Some(Guidance { now, after })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::{Scenario, ScenarioConfig};

    fn visited(frozen: Option<usize>) -> std::vec::Vec<[f64; 7]> {
        Scenario::new(ScenarioConfig::paper(), 4)
            .take(2000)
            .step_by(4)
            .map(|s| {
                let mut q = s.sample.joints;
                if let Some(j) = frozen {
                    q[j] = 0.1;
                }
                q
            })
            .collect()
    }

    const NOISE: [f64; 6] = [1e-6, 1e-6, 1e-6, 4e-6, 4e-6, 4e-6];

    #[test]
    fn a_joint_never_moved_is_the_one_to_move_and_motion_never_hurts() {
        let table = DhTable::paper_nominal();
        let ranges = JointRanges::paper();
        for frozen in [6, 4, 1] {
            let g = guidance::<7, 28>(&table, &visited(Some(frozen)), 4.0, &NOISE, &ranges, 1000.0).unwrap();
            assert_eq!(g.best(), frozen, "{g:?}");
            // Its motion takes most of the error away; more motion of any joint never adds any.
            assert!(g.ratio()[frozen] < 0.5, "{:?}", g.ratio());
            for e in g.after {
                assert!(e.position_m <= g.now.position_m * (1.0 + 1e-9));
                assert!(e.rotation_rad <= g.now.rotation_rad * (1.0 + 1e-9));
            }
        }
    }

    #[test]
    fn with_every_joint_moved_the_gains_are_modest_and_more_data_means_less_error() {
        let table = DhTable::paper_nominal();
        let ranges = JointRanges::paper();
        let v = visited(None);
        let g = guidance::<7, 28>(&table, &v, 4.0, &NOISE, &ranges, 1000.0).unwrap();
        assert!(g.ratio().iter().all(|&r| r > 0.5 && r <= 1.0), "{:?}", g.ratio());
        // Four times the samples halve the error (white noise), give or take the prior.
        let more = guidance::<7, 28>(&table, &v, 16.0, &NOISE, &ranges, 1000.0).unwrap();
        let r = more.now.position_m / g.now.position_m;
        assert!((r - 0.5).abs() < 0.05, "{r}");
        assert!(guidance::<7, 28>(&table, &[], 4.0, &NOISE, &ranges, 1000.0).is_none());
        assert!(guidance::<7, 28>(&table, &v, 4.0, &[0.0; 6], &ranges, 1000.0).is_none());
    }
}
