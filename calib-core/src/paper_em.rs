//! The paper's EM (eqs. 11, 33–36), literally, with the fixes of paper notes 7–8.
//!
//! After LS, the geometric errors Δζ (a, d, α) are compensated and the remaining pose error of
//! eq. (37), `z_k = pose_error(FK(ζ + Δζ, θ_k), measured_k)`, is modelled as a mixture over the
//! joints: `p(z_k) = Σ_i π_i N(z_k | μ_i κ_{k,i}, Σ_i)`, κ_{k,i} being column i of the joint
//! Jacobian J2 (same tool frame as z). Two forms:
//! * [`PaperEmForm::Scalar`]: z_k and κ_{k,i} are the first row (the paper's reading of eq. 11);
//! * [`PaperEmForm::Vector`]: the whole 6-vector with a full 6 × 6 Σ_i.
//!
//! E-step: responsibilities (33). M-step: π_i = N_i / K (36); the mean uses the exact
//! weighted-least-squares update of paper note 8, `μ_i = Σγ κᵀ W z / Σγ κᵀ W κ` with `W = 1`
//! (scalar) or `W = Σ_i⁻¹` of the previous iteration (vector form: an ECM step, still
//! monotone); Σ_i from (35) with the new mean, its eigenvalues floored at `variance_floor`
//! times the data variance. The initial means are the LS Δθ, the final estimate is the paper's
//! `Δθ_i = π_i μ_i`. The log-likelihood (11) of every iteration is recorded; EM guarantees it
//! never decreases.

use nalgebra::{Matrix6, SymmetricEigen, Vector6};

use crate::drift_em::MAX_EM_ITERATIONS;
use crate::error::CalibError;
use crate::ls::{validate_samples, InputChecks};
use crate::model::{pose_error, DhTable, Sample};

const LN_2PI: f64 = 1.837_877_066_409_345_3;

/// Which reading of eq. (11).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum PaperEmForm {
    /// z_k is the first row of the pose error (the paper's text).
    #[default]
    Scalar,
    /// z_k is the whole 6-vector.
    Vector,
}

/// Options of [`paper_em`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PaperEmOptions<const N: usize> {
    /// Scalar or vector form.
    pub form: PaperEmForm,
    /// Iteration limit (at most [`MAX_EM_ITERATIONS`]).
    pub max_iterations: usize,
    /// Converged when the log-likelihood changes by less than this (relative).
    pub tolerance: f64,
    /// Floor of every variance, relative to the data variance.
    pub variance_floor: f64,
    /// Input validation.
    pub checks: InputChecks<N>,
}

impl<const N: usize> Default for PaperEmOptions<N> {
    fn default() -> Self {
        PaperEmOptions {
            form: PaperEmForm::Scalar,
            max_iterations: 200,
            tolerance: 1e-10,
            variance_floor: 1e-9,
            checks: InputChecks::new(None),
        }
    }
}

/// Result of [`paper_em`].
#[derive(Clone, Debug)]
pub struct PaperEmResult<const N: usize> {
    /// LS geometry with θ offsets `nominal + π_i μ_i`.
    pub table: DhTable<N>,
    /// Mixture means μ_i (rad).
    pub mu: [f64; N],
    /// Mixture variances Σ_i (scalar form) or `trace(Σ_i)/6` (vector form).
    pub variance: [f64; N],
    /// Mixing coefficients π_i (responsibilities of Table 6).
    pub pi: [f64; N],
    /// The paper's estimate Δθ_i = π_i μ_i.
    pub delta_theta: [f64; N],
    /// Log-likelihood (11) before each M-step, then at the final parameters.
    pub log_likelihood: heapless::Vec<f64, MAX_EM_ITERATIONS>,
    /// Whether the tolerance was reached.
    pub converged: bool,
}

struct Component {
    mu: f64,
    var: f64,
    cov: Matrix6<f64>,
    cov_inv: Matrix6<f64>,
    log_det: f64,
    pi: f64,
}

fn set_cov(c: &mut Component, cov: Matrix6<f64>, floor: f64) {
    let eig = SymmetricEigen::new(cov);
    let vals = eig.eigenvalues.map(|l| l.max(floor));
    let v = eig.eigenvectors;
    c.cov = v * Matrix6::from_diagonal(&vals) * v.transpose();
    c.cov_inv = v * Matrix6::from_diagonal(&vals.map(|l| 1.0 / l)) * v.transpose();
    c.log_det = vals.iter().map(|l| libm::log(*l)).sum();
    c.var = vals.sum() / 6.0;
}

/// Runs the paper's EM on the residual left by the LS geometry.
///
/// `nominal` supplies the nominal θ offsets; `ls` is the LS table (its a, d, α are the
/// compensated geometry, its θ offsets minus nominal are the initial means).
pub fn paper_em<const N: usize>(
    nominal: &DhTable<N>,
    ls: &DhTable<N>,
    samples: &[Sample<N>],
    opts: &PaperEmOptions<N>,
) -> Result<PaperEmResult<N>, CalibError> {
    if !nominal.is_finite() || !ls.is_finite() {
        return Err(CalibError::InvalidInput { what: "paper_em table" });
    }
    if opts.max_iterations == 0
        || opts.max_iterations >= MAX_EM_ITERATIONS
        || !crate::ls::positive(opts.tolerance)
        || !crate::ls::positive(opts.variance_floor)
    {
        return Err(CalibError::InvalidInput { what: "PaperEmOptions" });
    }
    validate_samples(samples, &opts.checks)?;
    let vector = opts.form == PaperEmForm::Vector;
    let mut geometry = *ls;
    for (g, n) in geometry.rows.iter_mut().zip(&nominal.rows) {
        g.theta_offset = n.theta_offset;
    }
    // z_k and κ_k (first row or all six).
    let data = |s: &Sample<N>| -> (Vector6<f64>, [Vector6<f64>; N]) {
        let (t, cols) = geometry.fk_jacobian(&s.joints);
        let mut z = pose_error(&t, &s.pose);
        let mut kappa = cols[3];
        if !vector {
            z = Vector6::new(z[0], 0.0, 0.0, 0.0, 0.0, 0.0);
            for k in kappa.iter_mut() {
                *k = Vector6::new(k[0], 0.0, 0.0, 0.0, 0.0, 0.0);
            }
        }
        (z, kappa)
    };
    let kf = samples.len() as f64;
    let mut szz = Matrix6::zeros();
    for s in samples {
        let (z, _) = data(s);
        szz += z * z.transpose();
    }
    szz /= kf;
    let scale = if vector { szz.trace() / 6.0 } else { szz[(0, 0)] };
    let floor = (opts.variance_floor * scale).max(1e-300);
    let mut comps: [Component; N] = core::array::from_fn(|i| {
        let mut c = Component {
            mu: ls.rows[i].theta_offset - nominal.rows[i].theta_offset,
            var: 0.0,
            cov: Matrix6::zeros(),
            cov_inv: Matrix6::zeros(),
            log_det: 0.0,
            pi: 1.0 / N as f64,
        };
        if vector {
            set_cov(&mut c, szz, floor);
        } else {
            c.var = scale.max(floor);
        }
        c
    });
    let mut history: heapless::Vec<f64, MAX_EM_ITERATIONS> = heapless::Vec::new();
    let mut converged = false;
    for it in 0..=opts.max_iterations {
        // E-step with sufficient statistics for the M-step.
        let mut ll = 0.0;
        let mut n = [0.0; N];
        let mut num = [0.0; N];
        let mut den = [0.0; N];
        let mut s_zz = [Matrix6::<f64>::zeros(); N];
        let mut s_kz = [Matrix6::<f64>::zeros(); N];
        let mut s_kk = [Matrix6::<f64>::zeros(); N];
        for s in samples {
            let (z, kappa) = data(s);
            let mut logp = [f64::NEG_INFINITY; N];
            for (i, c) in comps.iter().enumerate() {
                if c.pi <= 0.0 {
                    continue;
                }
                let r = z - kappa[i] * c.mu;
                let quad_logdet = if vector {
                    (r.transpose() * c.cov_inv * r)[0] + c.log_det
                } else {
                    r[0] * r[0] / c.var + libm::log(c.var)
                };
                let dim = if vector { 6.0 } else { 1.0 };
                logp[i] = libm::log(c.pi) - 0.5 * (quad_logdet + dim * LN_2PI);
            }
            let m = logp.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            let sum: f64 = logp.iter().map(|l| libm::exp(l - m)).sum();
            ll += m + libm::log(sum);
            for i in 0..N {
                let g = libm::exp(logp[i] - m) / sum;
                if g == 0.0 {
                    continue;
                }
                n[i] += g;
                let k = kappa[i];
                let (wk, wkk) = if vector {
                    (comps[i].cov_inv * k, k.dot(&(comps[i].cov_inv * k)))
                } else {
                    (k, k[0] * k[0])
                };
                num[i] += g * wk.dot(&z);
                den[i] += g * wkk;
                s_zz[i] += g * z * z.transpose();
                s_kz[i] += g * (k * z.transpose() + z * k.transpose());
                s_kk[i] += g * k * k.transpose();
            }
        }
        if !ll.is_finite() {
            return Err(CalibError::NotConverged {
                iterations: it,
                last_change: ll,
            });
        }
        if let Some(&prev) = history.last() {
            if (ll - prev).abs() <= opts.tolerance * ll.abs().max(1.0) {
                converged = true;
            }
        }
        // Capacity is MAX_EM_ITERATIONS > max_iterations.
        let _ = history.push(ll);
        if converged || it == opts.max_iterations {
            break;
        }
        // M-step.
        for i in 0..N {
            let c = &mut comps[i];
            c.pi = n[i] / kf;
            if n[i] <= 0.0 || den[i] <= 0.0 {
                continue;
            }
            c.mu = num[i] / den[i];
            let cov = (s_zz[i] - s_kz[i] * c.mu + s_kk[i] * (c.mu * c.mu)) / n[i];
            if vector {
                set_cov(c, 0.5 * (cov + cov.transpose()), floor);
            } else {
                c.var = cov[(0, 0)].max(floor);
            }
        }
    }
    let mu = core::array::from_fn(|i| comps[i].mu);
    let pi = core::array::from_fn(|i| comps[i].pi);
    let delta_theta: [f64; N] = core::array::from_fn(|i| comps[i].pi * comps[i].mu);
    Ok(PaperEmResult {
        table: geometry.with_theta_offsets(&delta_theta),
        mu,
        variance: core::array::from_fn(|i| comps[i].var),
        pi,
        delta_theta,
        log_likelihood: history,
        converged,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ls::{identify_ls, LsOptions};
    use crate::sim::{Scenario, ScenarioConfig};

    fn setup(seed: u64, k: usize) -> (std::vec::Vec<Sample<7>>, DhTable<7>) {
        let samples: std::vec::Vec<_> = Scenario::new(ScenarioConfig::paper(), seed)
            .take(k)
            .map(|s| s.sample)
            .collect();
        let ls = identify_ls::<7, 28>(&DhTable::paper_nominal(), &samples, &LsOptions::paper()).unwrap();
        (samples, ls.table)
    }

    #[test]
    fn likelihood_never_decreases_in_both_forms() {
        let (samples, ls) = setup(3, 800);
        for form in [PaperEmForm::Scalar, PaperEmForm::Vector] {
            let opts = PaperEmOptions {
                form,
                max_iterations: 60,
                ..Default::default()
            };
            let r = paper_em(&DhTable::paper_nominal(), &ls, &samples, &opts).unwrap();
            assert!(r.log_likelihood.len() >= 3, "{form:?}");
            for w in r.log_likelihood.windows(2) {
                assert!(w[1] >= w[0] - 1e-9 * w[0].abs().max(1.0), "{form:?}: {} -> {}", w[0], w[1]);
            }
            let psum: f64 = r.pi.iter().sum();
            assert!((psum - 1.0).abs() < 1e-9);
            for i in 0..7 {
                assert!((r.delta_theta[i] - r.pi[i] * r.mu[i]).abs() < 1e-15);
                let expect = DhTable::paper_nominal().rows[i].theta_offset + r.delta_theta[i];
                assert!((r.table.rows[i].theta_offset - expect).abs() < 1e-15);
                assert_eq!(r.table.rows[i].a, ls.rows[i].a);
            }
        }
    }

    #[test]
    fn recovers_a_single_joint_offset_as_a_one_component_mixture() {
        // Pose error produced only by joint 3's offset: the mixture must put its weight there.
        let truth = DhTable::paper_actual();
        let mut moved = truth;
        moved.rows[2].theta_offset += 0.01;
        let mut cfg = ScenarioConfig::paper();
        cfg.drift.sigma = 0.0;
        let samples: std::vec::Vec<_> = Scenario::new(cfg, 5)
            .take(400)
            .map(|s| Sample {
                joints: s.sample.joints,
                pose: moved.fk(&s.sample.joints),
            })
            .collect();
        let opts = PaperEmOptions {
            form: PaperEmForm::Vector,
            ..Default::default()
        };
        let r = paper_em(&truth, &truth, &samples, &opts).unwrap();
        assert!(r.pi[2] > 0.99, "{:?}", r.pi);
        assert!((r.mu[2] - 0.01).abs() < 1e-4, "{:?}", r.mu);
    }

    #[test]
    fn bad_inputs_are_typed_errors() {
        let (samples, ls) = setup(4, 100);
        let nominal = DhTable::paper_nominal();
        let bad = PaperEmOptions {
            max_iterations: 0,
            ..Default::default()
        };
        assert!(matches!(
            paper_em(&nominal, &ls, &samples, &bad),
            Err(CalibError::InvalidInput { .. })
        ));
        let too_many = PaperEmOptions {
            max_iterations: MAX_EM_ITERATIONS,
            ..Default::default()
        };
        assert!(matches!(
            paper_em(&nominal, &ls, &samples, &too_many),
            Err(CalibError::InvalidInput { .. })
        ));
        let mut nan = samples.clone();
        nan[3].pose.p.y = f64::NAN;
        assert_eq!(
            paper_em(&nominal, &ls, &nan, &Default::default()).unwrap_err(),
            CalibError::NonFinite { sample: 3 }
        );
        assert!(matches!(
            paper_em(&nominal, &ls, &samples[..5], &Default::default()),
            Err(CalibError::TooFewSamples { .. })
        ));
        let mut nan_table = ls;
        nan_table.rows[1].d = f64::INFINITY;
        assert!(matches!(
            paper_em(&nominal, &nan_table, &samples, &Default::default()),
            Err(CalibError::InvalidInput { .. })
        ));
    }
}
