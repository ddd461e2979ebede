//! Least squares with the base and tool frames identified too (`4N + 12` parameters).
//!
//! In practice the reference pose is measured from a base frame that is not exactly D-H frame
//! 0, and the reference IMU does not sit exactly at frame N. The model becomes
//! `T = B · T_dh(q) · E`, with B and E small rigid corrections identified alongside the D-H
//! errors. Parameters `4N .. 4N+6` are the base twist (x, y, z translation, then rotation vector
//! about x, y, z, applied on the left in the base frame), `4N+6 .. 4N+12` the tool twist (applied
//! on the right, in the tool frame).
//!
//! Six of the `4N + 12` parameters are redundant: `d_1` and the `θ_1` offset duplicate the base
//! z-translation and z-rotation, and `a_N`, `α_N`, `d_N`, the `θ_N` offset are absorbed by the
//! tool frame. The SVD finds exactly these ([`LsResult::unidentifiable`], named with
//! [`Param`]); the minimum-norm step leaves them at their starting values, so the identified
//! set is the base-parameter set of robot-calibration toolboxes.

use core::fmt;

use nalgebra::{Rotation3, Vector3, Vector6};

use crate::error::CalibError;
use crate::linalg::QrAccumulator;
use crate::ls::{finish, levenberg_marquardt, validate_samples, Linearised, LsOptions, LsResult, NullDirection};
use crate::model::{error_jacobian, pose_error, DhTable, Frame, ParamKind, Sample};

/// Number of frame parameters (base 6 + tool 6).
pub const FRAME_PARAMS: usize = 12;

/// Base and tool corrections: the model pose is `base · FK(q) · tool`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Mounting {
    /// Pose of D-H frame 0 in the measurement base frame.
    pub base: Frame,
    /// Pose of the measured tool in D-H frame N.
    pub tool: Frame,
}

impl Mounting {
    /// No correction.
    pub fn identity() -> Self {
        Mounting {
            base: Frame::identity(),
            tool: Frame::identity(),
        }
    }

    /// The model pose `base · FK(table, q) · tool`.
    pub fn fk<const N: usize>(&self, table: &DhTable<N>, joints: &[f64; N]) -> Frame {
        self.base.compose(&table.fk(joints)).compose(&self.tool)
    }
}

/// A named parameter of the extended vector.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Param {
    /// A D-H parameter (kind, joint 0-based).
    Dh(ParamKind, usize),
    /// Base twist component 0..6 (x, y, z, rx, ry, rz).
    Base(usize),
    /// Tool twist component 0..6 (x, y, z, rx, ry, rz).
    Tool(usize),
}

impl Param {
    /// The parameter at `index` of a chain of `n` joints with frames.
    pub fn of_index(index: usize, n: usize) -> Param {
        if index < 4 * n {
            let (k, j) = ParamKind::of_index(index, n);
            Param::Dh(k, j)
        } else if index < 4 * n + 6 {
            Param::Base(index - 4 * n)
        } else {
            Param::Tool(index - 4 * n - 6)
        }
    }
}

const AXES: [&str; 6] = ["x", "y", "z", "rx", "ry", "rz"];

impl fmt::Display for Param {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Param::Dh(k, j) => write!(f, "{}{}", k.name(), j + 1),
            Param::Base(c) => write!(f, "base.{}", AXES[c % 6]),
            Param::Tool(c) => write!(f, "tool.{}", AXES[c % 6]),
        }
    }
}

impl<const P: usize> NullDirection<P> {
    /// Like [`NullDirection::terms`] but named with [`Param`] (D-H and frame parameters).
    pub fn named_terms<const N: usize>(&self, min_abs: f64) -> heapless::Vec<(Param, f64), P> {
        let mut out = heapless::Vec::new();
        for (p, c) in self.coeffs.iter().enumerate() {
            if c.abs() >= min_abs {
                // Capacity P: one entry per parameter.
                let _ = out.push((Param::of_index(p, N), *c));
            }
        }
        out.sort_unstable_by(|a, b| b.1.abs().total_cmp(&a.1.abs()));
        out
    }
}

/// Result of [`identify_ls_frames`].
#[derive(Clone, Debug)]
pub struct LsFramesResult<const N: usize, const P: usize> {
    /// D-H table, statistics and unidentifiable directions (over all `P` parameters).
    pub ls: LsResult<N, P>,
    /// Identified base and tool corrections.
    pub mounting: Mounting,
}

fn twist(v: Vector3<f64>, w: Vector3<f64>) -> Vector6<f64> {
    Vector6::new(v.x, v.y, v.z, w.x, w.y, w.z)
}

/// Tool-frame twist of a left perturbation `(v, ω)` of `frame`'s parent, seen at `frame`.
fn to_frame(frame: &Frame, v: Vector3<f64>, w: Vector3<f64>) -> Vector6<f64> {
    let rt = frame.r.transpose();
    twist(rt * (w.cross(&frame.p) + v), rt * w)
}

fn linearise<const N: usize, const P: usize>(state: &(DhTable<N>, Mounting), samples: &[Sample<N>]) -> (QrAccumulator<P>, f64) {
    let (table, mount) = state;
    let mut acc = QrAccumulator::<P>::new();
    let mut cost = 0.0;
    for s in samples {
        let (t_dh, cols) = table.fk_jacobian(&s.joints);
        let t = mount.base.compose(&t_dh).compose(&mount.tool);
        let e = pose_error(&t, &s.pose);
        cost += e.norm_squared();
        let m = error_jacobian(&e);
        let mut rows = [[0.0; P]; 6];
        for (p, col) in (0..P).map(|p| {
            let c = match Param::of_index(p, N) {
                Param::Dh(k, j) => {
                    let c = cols[k as usize][j];
                    to_frame(&mount.tool, Vector3::new(c[0], c[1], c[2]), Vector3::new(c[3], c[4], c[5]))
                }
                Param::Base(c) => {
                    let mut u = Vector6::zeros();
                    u[c] = 1.0;
                    to_frame(&t, Vector3::new(u[0], u[1], u[2]), Vector3::new(u[3], u[4], u[5]))
                }
                Param::Tool(c) => {
                    let mut u = Vector6::zeros();
                    u[c] = 1.0;
                    u
                }
            };
            (p, m * c)
        }) {
            for r in 0..6 {
                rows[r][p] = col[r];
            }
        }
        for (r, row) in rows.iter().enumerate() {
            acc.add_row(row, e[r]);
        }
    }
    (acc, cost)
}

/// The cost Σ‖e‖² alone, bit-identical to that of [`linearise`].
fn cost_at<const N: usize>(state: &(DhTable<N>, Mounting), samples: &[Sample<N>]) -> f64 {
    let (table, mount) = state;
    let table = table.prepare();
    samples
        .iter()
        .map(|s| {
            let t = mount.base.compose(&table.pose(&s.joints)).compose(&mount.tool);
            pose_error(&t, &s.pose).norm_squared()
        })
        .fold(0.0, |acc, c| acc + c)
}

fn apply<const N: usize, const P: usize>(state: &(DhTable<N>, Mounting), step: &[f64; P]) -> (DhTable<N>, Mounting) {
    let (table, mount) = state;
    let b = &step[4 * N..4 * N + 6];
    let t = &step[4 * N + 6..4 * N + 12];
    let rb = Rotation3::new(Vector3::new(b[3], b[4], b[5])).into_inner();
    let rt = Rotation3::new(Vector3::new(t[3], t[4], t[5])).into_inner();
    let base = Frame {
        r: rb * mount.base.r,
        p: rb * mount.base.p + Vector3::new(b[0], b[1], b[2]),
    };
    let tool = Frame {
        r: mount.tool.r * rt,
        p: mount.tool.p + mount.tool.r * Vector3::new(t[0], t[1], t[2]),
    };
    (table.perturbed(&step[..4 * N]), Mounting { base, tool })
}

/// Identifies the `4N` D-H errors and the base and tool frames (`P = 4N + 12`, checked at
/// compile time; `identify_ls_frames::<7, 40>` for the suit). Six parameters are redundant and
/// reported in `ls.unidentifiable` (see the module docs).
pub fn identify_ls_frames<const N: usize, const P: usize>(
    start: &DhTable<N>,
    mounting: &Mounting,
    samples: &[Sample<N>],
    opts: &LsOptions<N>,
) -> Result<LsFramesResult<N, P>, CalibError> {
    const { assert!(P == 4 * N + FRAME_PARAMS, "P must be 4N + 12") };
    if !start.is_finite() || !mounting.base.is_finite() || !mounting.tool.is_finite() {
        return Err(CalibError::InvalidInput {
            what: "starting table or mounting",
        });
    }
    crate::ls::check_options(opts)?;
    validate_samples(samples, &opts.checks)?;
    let ((table, mounting), cost, iterations, analysis) = levenberg_marquardt::<N, P, _>(
        (*start, *mounting),
        |s, out| {
            let (acc, cost) = linearise::<N, P>(s, samples);
            *out = Linearised::Qr(acc);
            cost
        },
        |s| linearise::<N, P>(s, samples).0,
        |s| cost_at(s, samples),
        apply::<N, P>,
        opts,
    )?;
    let ls = finish(table, cost, iterations, &analysis, opts)?;
    Ok(LsFramesResult { ls, mounting })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::{Scenario, ScenarioConfig};

    fn offset_mounting() -> Mounting {
        Mounting {
            base: Frame {
                r: Rotation3::new(Vector3::new(0.02, -0.03, 0.05)).into_inner(),
                p: Vector3::new(0.01, -0.02, 0.015),
            },
            tool: Frame {
                r: Rotation3::new(Vector3::new(-0.04, 0.01, 0.03)).into_inner(),
                p: Vector3::new(0.005, 0.01, -0.02),
            },
        }
    }

    #[test]
    fn frames_and_dh_fit_noise_free_with_exactly_the_six_redundancies() {
        let truth = offset_mounting();
        let arm = DhTable::paper_actual();
        let mut cfg = ScenarioConfig::paper();
        cfg.drift.sigma = 0.0;
        let samples: std::vec::Vec<Sample<7>> = Scenario::new(cfg, 8)
            .step_by(10)
            .take(300)
            .map(|s| Sample {
                joints: s.sample.joints,
                pose: truth.fk(&arm, &s.sample.joints),
            })
            .collect();
        let r = identify_ls_frames::<7, 40>(
            &DhTable::paper_nominal(),
            &Mounting::identity(),
            &samples,
            &LsOptions::paper(),
        )
        .unwrap();
        assert_eq!(r.ls.rank, 34, "{:?}", r.ls.singular_values);
        // Poses are reproduced exactly.
        for s in &samples {
            assert!(pose_error(&r.mounting.fk(&r.ls.table, &s.joints), &s.pose).norm() < 1e-9);
        }
        // The identifiable D-H parameters (links 1..6 except d1 and θ1) match the truth.
        for j in 0..6 {
            for k in ParamKind::ALL {
                if j == 0 && matches!(k, ParamKind::D | ParamKind::Theta) {
                    continue;
                }
                let (est, tru) = (r.ls.table.rows[j].get(k), arm.rows[j].get(k));
                assert!((est - tru).abs() < 1e-9, "{}{}: {est} vs {tru}", k.name(), j + 1);
            }
        }
        // Each null direction only involves the redundant parameters.
        let redundant = |p: Param| {
            matches!(
                p,
                Param::Dh(ParamKind::D | ParamKind::Theta, 0) | Param::Dh(_, 6) | Param::Base(_) | Param::Tool(_)
            )
        };
        assert_eq!(r.ls.unidentifiable.len(), 6);
        assert!(
            r.ls.condition > 1e12 && r.ls.condition_identifiable < 1e4,
            "{} {}",
            r.ls.condition,
            r.ls.condition_identifiable
        );
        for n in &r.ls.unidentifiable {
            for (p, c) in n.named_terms::<7>(1e-6) {
                assert!(redundant(p), "{p} ({c}) in a null direction");
            }
        }
    }

    #[test]
    fn param_names_and_bad_mounting() {
        assert_eq!(std::format!("{}", Param::of_index(7, 7)), "d1");
        assert_eq!(std::format!("{}", Param::of_index(28 + 2, 7)), "base.z");
        assert_eq!(std::format!("{}", Param::of_index(28 + 6 + 5, 7)), "tool.rz");
        let mut m = Mounting::identity();
        m.tool.p.x = f64::NAN;
        let samples: std::vec::Vec<_> = Scenario::new(ScenarioConfig::paper(), 1)
            .take(100)
            .map(|s| s.sample)
            .collect();
        let e = identify_ls_frames::<7, 40>(&DhTable::paper_nominal(), &m, &samples, &LsOptions::paper()).unwrap_err();
        assert!(matches!(e, CalibError::InvalidInput { .. }));
    }
}
