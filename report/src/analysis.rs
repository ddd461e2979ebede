//! The calibration detail a report shows, computed with calib-core.
//!
//! Contract: [`calibrate`] runs exactly what the daemon's pipeline runs — `identify_ls` from the
//! nominal table, then `em_drift` from the LS table, with the options the caller passes — and
//! keeps what the daemon's summary drops: the EM's likelihood history, the smoothed drift, the
//! standard deviations of both steps and the parameter correlations. Same inputs and options,
//! same tables (calib-core is deterministic). When the EM fails, the LS table is the result and
//! the EM's error is kept as text, as in the daemon.
//!
//! The correlations are those of the linearised problem at the calibrated table (information
//! matrix `Σ JᵀJ` of the tool-frame pose Jacobian over the fitted samples, pseudo-inverted in
//! column-scaled coordinates; directions outside the numerical rank are left out).

use calib_core::{
    em_drift_vec, identify_ls, CalibError, DhTable, DriftEmOptions, LsOptions, Sample,
};
use nalgebra::{DMatrix, SMatrix};

use crate::input::{Calibration, Correlation, EmDetail, LsDetail, JOINTS, PARAMS};

/// How many correlations the report lists.
pub const TOP_CORRELATIONS: usize = 10;

/// Runs LS then drift EM on `fit` (see the module docs).
pub fn calibrate(
    nominal: &DhTable<JOINTS>,
    fit: &[Sample<JOINTS>],
    ls_opts: &LsOptions<JOINTS>,
    em_opts: &DriftEmOptions<JOINTS>,
) -> Result<Calibration, CalibError> {
    let ls = identify_ls::<JOINTS, PARAMS>(nominal, fit, ls_opts)?;
    let ls = LsDetail {
        table: ls.table,
        iterations: ls.iterations,
        rank: ls.rank,
        condition: ls.condition,
        rms: ls.rms,
        std_errors: ls.std_errors,
    };
    let em = em_drift_vec::<JOINTS, PARAMS>(&ls.table, fit, em_opts)
        .map(|(r, drift_series)| EmDetail {
            table: r.table,
            iterations: r.iterations,
            converged: r.converged,
            log_likelihood: r.log_likelihood.to_vec(),
            drift: r.drift,
            std_errors: std::array::from_fn(|p| r.std_errors[p / JOINTS][p % JOINTS]),
            expected_error: r.expected_error,
            drift_series,
        })
        .map_err(|e| e.to_string());
    let calibrated = em.as_ref().map_or(ls.table, |em| em.table);
    let correlations = strongest_correlations(&calibrated, fit, TOP_CORRELATIONS);
    Ok(Calibration {
        ls,
        em,
        calibrated,
        correlations,
    })
}

/// The `top` strongest parameter correlations of the linearised problem at `table`.
pub fn strongest_correlations(
    table: &DhTable<JOINTS>,
    samples: &[Sample<JOINTS>],
    top: usize,
) -> Vec<Correlation> {
    let mut info = SMatrix::<f64, PARAMS, PARAMS>::zeros();
    for s in samples {
        let (_, cols) = table.fk_jacobian(&s.joints);
        let mut j = SMatrix::<f64, 6, PARAMS>::zeros();
        for p in 0..PARAMS {
            j.set_column(p, &cols[p / JOINTS][p % JOINTS]);
        }
        info += j.transpose() * j;
    }
    let scale: Vec<f64> = (0..PARAMS)
        .map(|p| {
            let d = info[(p, p)];
            if d > 0.0 {
                1.0 / d.sqrt()
            } else {
                0.0
            }
        })
        .collect();
    let scaled = DMatrix::from_fn(PARAMS, PARAMS, |r, c| info[(r, c)] * scale[r] * scale[c]);
    let eig = scaled.symmetric_eigen();
    let max = eig.eigenvalues.iter().fold(0.0f64, |m, &v| m.max(v));
    let mut cov = DMatrix::<f64>::zeros(PARAMS, PARAMS);
    for (k, &lambda) in eig.eigenvalues.iter().enumerate() {
        if lambda > 1e-10 * max {
            let v = eig.eigenvectors.column(k);
            cov += (v * v.transpose()) / lambda;
        }
    }
    let mut out = Vec::new();
    for a in 0..PARAMS {
        for b in a + 1..PARAMS {
            let denom = (cov[(a, a)] * cov[(b, b)]).sqrt();
            if denom > 0.0 && denom.is_finite() {
                let r = (cov[(a, b)] / denom).clamp(-1.0, 1.0);
                out.push(Correlation {
                    first: a,
                    second: b,
                    r,
                });
            }
        }
    }
    out.sort_by(|x, y| y.r.abs().total_cmp(&x.r.abs()));
    out.truncate(top);
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use calib_core::{Scenario, ScenarioConfig};

    fn samples(k: usize, seed: u64) -> Vec<Sample<JOINTS>> {
        Scenario::new(ScenarioConfig::paper(), seed)
            .take(k)
            .map(|s| s.sample)
            .collect()
    }

    #[test]
    fn calibrate_matches_calib_core_and_keeps_the_detail() {
        let fit = samples(800, 3);
        let nominal = DhTable::paper_nominal();
        let ls_opts = LsOptions::new();
        let em_opts = DriftEmOptions {
            max_iterations: 15,
            ..DriftEmOptions::new(0.01)
        };
        let c = calibrate(&nominal, &fit, &ls_opts, &em_opts).unwrap();
        let ls = identify_ls::<JOINTS, PARAMS>(&nominal, &fit, &ls_opts).unwrap();
        assert_eq!(c.ls.table, ls.table);
        let em = c.em.as_ref().unwrap();
        assert_eq!(c.calibrated, em.table);
        assert_eq!(em.drift_series.len(), fit.len());
        assert!(em.log_likelihood.len() >= 2);
        assert!(em.std_errors.iter().all(|s| s.is_finite() && *s > 0.0));
        assert!(c.ls.std_errors.iter().all(|s| s.is_finite() && *s > 0.0));
        assert_eq!(c.correlations.len(), TOP_CORRELATIONS);
        assert!(c
            .correlations
            .windows(2)
            .all(|w| w[0].r.abs() >= w[1].r.abs()));
    }

    #[test]
    fn a_still_joint_shows_as_perfectly_correlated_parameters() {
        // Joint 7 still at θ7 + offset7 = 0: Tx(a6) Rx(α6) Tx(a7) Rx(α7) = Tx(a6 + a7)
        // Rx(α6 + α7), so only the sums are identifiable (calib-core README) and the
        // pseudo-inverse leaves each pair fully correlated.
        let mut fit = samples(400, 5);
        for s in &mut fit {
            s.joints[6] = 0.0;
        }
        let c = strongest_correlations(&DhTable::paper_nominal(), &fit, 3);
        assert!(c[0].r.abs() > 0.999, "{c:?}");
        let moving = strongest_correlations(&DhTable::paper_nominal(), &samples(400, 5), 1);
        assert!(moving[0].r.abs() < c[0].r.abs());
    }

    #[test]
    fn bad_input_is_calib_core_error() {
        let nominal = DhTable::paper_nominal();
        let err = calibrate(
            &nominal,
            &samples(3, 1),
            &LsOptions::new(),
            &DriftEmOptions::new(0.01),
        );
        assert!(err.is_err());
    }
}
