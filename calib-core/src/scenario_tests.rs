//! The "done when" targets on the paper's Section 4 scenario (60 s, seeded).

use crate::drift_em::{em_drift_vec, DriftEmOptions};
use crate::ls::{identify_ls, LsOptions};
use crate::metrics::{objective_y, objective_y_corrected};
use crate::model::{DhTable, Sample};
use crate::sim::{Scenario, ScenarioConfig};

#[test]
fn paper_scenario_60s_meets_the_ls_and_em_targets() {
    let cfg = ScenarioConfig::paper();
    let samples: std::vec::Vec<Sample<7>> = Scenario::new(cfg, 1).take(6000).map(|s| s.sample).collect();
    let held: std::vec::Vec<Sample<7>> = Scenario::new(cfg, 1001).take(6000).map(|s| s.sample).collect();
    let nominal = DhTable::paper_nominal();
    let ls = identify_ls::<7, 28>(&nominal, &samples, &LsOptions::paper()).unwrap();
    let y_nom = objective_y(&nominal, &samples);
    let y_ls = objective_y(&ls.table, &samples);
    assert!(y_ls <= 0.2 * y_nom, "LS: {y_nom} -> {y_ls}");
    // 30 iterations: the geometry has settled by then (see the example's history).
    let opts = DriftEmOptions {
        max_iterations: 30,
        ..DriftEmOptions::new(cfg.drift.dt)
    };
    let (em, drift) = em_drift_vec::<7, 28>(&ls.table, &samples, &opts).unwrap();
    let y_em = objective_y_corrected(&em.table, &samples, |k| drift[k]);
    assert!(y_em <= 0.1 * y_ls, "EM in-sample: {y_ls} -> {y_em}");
    // Held-out: the EM table is no worse than LS (the ceiling, the true table, is only a few
    // per cent better than LS: the held-out session's own drift dominates y).
    assert!(objective_y(&em.table, &held) < objective_y(&ls.table, &held));
}

#[test]
fn any_trajectory_of_200_samples_recovers_table4_to_1e9() {
    let mut cfg = ScenarioConfig::paper();
    cfg.drift.sigma = 0.0;
    // 200 consecutive samples at 100 Hz (2 s of motion) and 200 spread over 60 s.
    for (seed, stride) in [(31, 1), (32, 1), (33, 30), (34, 30)] {
        let samples: std::vec::Vec<_> = Scenario::new(cfg, seed).step_by(stride).take(200).map(|s| s.sample).collect();
        let r = identify_ls::<7, 28>(&DhTable::paper_nominal(), &samples, &LsOptions::paper()).unwrap();
        let truth = DhTable::paper_actual();
        for p in 0..28 {
            assert!(
                (r.table.param(p) - truth.param(p)).abs() < 1e-9,
                "seed {seed} stride {stride} param {p}"
            );
        }
    }
}

/// The bound cross-checked by Monte Carlo (issue 18): over 50 sessions of 10 s with pose
/// noise (1 mm, 2 mrad) on the paper's arm and drift, the RMS table error our EM reaches agrees
/// with the RMS of the expected table error it reports from the Cramér-Rao bound (measured
/// 2026-11-23: EM/bound 1.10 in position and 1.18 in rotation, LS 1.46 and 1.44; EM is not yet
/// efficient on sessions this short, so the band allows it to sit up to 40% above the bound),
/// and LS is worse than both.
#[test]
fn the_expected_table_error_matches_monte_carlo_over_50_sessions() {
    use crate::metrics::table_error;
    let mut cfg = ScenarioConfig::paper();
    cfg.position_noise = 1e-3;
    cfg.rotation_noise = 2e-3;
    let seeds = 50;
    let (mut ls, mut em, mut bound) = ([0.0; 2], [0.0; 2], [0.0; 2]);
    let add = |acc: &mut [f64; 2], e: crate::metrics::TableError| {
        acc[0] += e.position_m * e.position_m / seeds as f64;
        acc[1] += e.rotation_rad * e.rotation_rad / seeds as f64;
    };
    for seed in 0..seeds {
        let samples: std::vec::Vec<Sample<7>> = Scenario::new(cfg, 100 + seed).take(1000).map(|s| s.sample).collect();
        let l = identify_ls::<7, 28>(&DhTable::paper_nominal(), &samples, &LsOptions::paper()).unwrap();
        let opts = DriftEmOptions {
            max_iterations: 40,
            ..DriftEmOptions::new(cfg.drift.dt)
        };
        let (e, _) = em_drift_vec::<7, 28>(&l.table, &samples, &opts).unwrap();
        let poses = || samples.iter().step_by(4).map(|s| &s.joints);
        add(&mut ls, table_error(&l.table, &cfg.actual, poses()));
        add(&mut em, table_error(&e.table, &cfg.actual, poses()));
        add(&mut bound, e.expected_error);
    }
    for (i, what) in ["position", "rotation"].into_iter().enumerate() {
        let ratio = (em[i] / bound[i]).sqrt();
        std::eprintln!(
            "{what}: LS {:.3e}, EM {:.3e}, bound {:.3e}, EM/bound {ratio:.3}",
            ls[i].sqrt(),
            em[i].sqrt(),
            bound[i].sqrt()
        );
        assert!((0.85..1.4).contains(&ratio), "{what}: EM / bound = {ratio:.3}");
        assert!(
            ls[i] > em[i],
            "{what}: LS {:.3e} not worse than EM {:.3e}",
            ls[i].sqrt(),
            em[i].sqrt()
        );
    }
}
