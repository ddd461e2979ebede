//! The accuracy sweep: LS and our EM against the Cramér-Rao bound over the regimes a user may
//! meet (issue 18), in table error ([`crate::metrics`]).
//!
//! One [`Cell`] is a drift process (τ, σ in the paper's convention), a pose noise and a session
//! length. Each seed draws a true table around Table 1 (every parameter moved by
//! `scale × N(0, 1) ×` the size of the paper's Table 1 → Table 4 change of its kind: 30 mm for
//! `a`, `d`, 5° for α, 2° for the joint offsets; the scale alternates between
//! [`TABLE_SCALES`]), simulates a session, identifies LS from nominal, runs our EM from LS, and
//! compares both tables with the truth on [`FRESH_POSES`] fresh poses of another motion. The
//! bound is [`crate::cramer_rao`] at the true table, drift and noise of that session, as an
//! expected table error over the same fresh poses.
//!
//! `std` only (it allocates); `cargo run -p calib-core --release --example sweep` prints the
//! whole grid, and a reduced form runs in the tests.

use std::vec::Vec;

use crate::drift::{Discretisation, GaussMarkov};
use crate::drift_em::{cramer_rao, em_drift_vec, DriftEmOptions, DriftEmResult};
use crate::ls::{identify_ls, LsOptions, LsResult};
use crate::metrics::{expected_table_error, ls_expected_table_error, table_error, TableError};
use crate::model::{DhTable, ParamKind, Sample, SUIT_PARAMS};
use crate::rng::Rng;
use crate::sim::{Scenario, ScenarioConfig};

/// Fresh poses every table error is averaged over.
pub const FRESH_POSES: usize = 200;

/// Scales of the true table's deviation from Table 1, alternating over seeds.
pub const TABLE_SCALES: [f64; 2] = [0.2, 1.0];

/// One regime of the sweep.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Cell {
    /// Drift correlation time τ (s).
    pub tau: f64,
    /// Drift σ in the paper's convention (eq. 8).
    pub sigma: f64,
    /// White pose noise: position (m) and rotation (rad) per axis.
    pub noise: (f64, f64),
    /// Session length (s) at the paper's 100 Hz.
    pub seconds: f64,
}

/// Table errors of one session.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Session {
    /// LS from nominal.
    pub ls: TableError,
    /// Our EM from LS.
    pub em: TableError,
    /// The Cramér-Rao bound at the truth, as an expected table error.
    pub bound: TableError,
    /// What the EM itself reported (its bound at its own estimates).
    pub reported: TableError,
    /// What LS is expected to reach under the true drift and noise
    /// ([`crate::metrics::ls_expected_table_error`]).
    pub ls_expected: TableError,
}

/// A true table for `seed` (see the module docs).
pub fn true_table(seed: u64) -> DhTable<7> {
    let mut rng = Rng::new(seed ^ 0x7AB1_E000);
    let scale = TABLE_SCALES[(seed % TABLE_SCALES.len() as u64) as usize];
    let mut t = DhTable::paper_nominal();
    for p in 0..SUIT_PARAMS {
        let (kind, _) = ParamKind::of_index(p, 7);
        let size = match kind {
            ParamKind::A | ParamKind::D => 0.03,
            ParamKind::Alpha => 5f64.to_radians(),
            ParamKind::Theta => 2f64.to_radians(),
        };
        *t.param_mut(p) += scale * size * rng.normal();
    }
    t
}

/// One simulated session: the true table, drift and pose noise of a cell for a seed, the
/// session's samples and the fresh poses its tables are judged on.
#[derive(Clone, Debug)]
pub struct Simulation {
    /// The seed's true table ([`true_table`]).
    pub truth: DhTable<7>,
    /// The cell's drift at the paper's 100 Hz.
    pub drift: GaussMarkov,
    /// The cell's pose noise (m, rad).
    pub noise: (f64, f64),
    /// `cell.seconds` of the suit's motion.
    pub samples: Vec<Sample<7>>,
    /// [`FRESH_POSES`] poses of another motion.
    pub fresh: Vec<[f64; 7]>,
}

impl Simulation {
    /// Simulates `cell` for `seed`. A longer session of the same cell and seed starts with the
    /// same samples: a prefix of it is the shorter session.
    pub fn new(cell: &Cell, seed: u64) -> Simulation {
        let drift = GaussMarkov {
            dt: 0.01,
            tau: cell.tau,
            sigma: cell.sigma,
            discretisation: Discretisation::Paper,
        };
        let truth = true_table(seed);
        let cfg = ScenarioConfig {
            actual: truth,
            drift,
            position_noise: cell.noise.0,
            rotation_noise: cell.noise.1,
            ..ScenarioConfig::paper()
        };
        let k = (cell.seconds / drift.dt).round() as usize;
        Simulation {
            truth,
            drift,
            noise: cell.noise,
            samples: Scenario::new(cfg, seed).take(k).map(|s| s.sample).collect(),
            fresh: Scenario::new(cfg, seed ^ 0xF2E5_4000)
                .step_by(17)
                .take(FRESH_POSES)
                .map(|s| s.sample.joints)
                .collect(),
        }
    }

    /// The first `seconds` of the session (all of it if shorter).
    pub fn prefix(&self, seconds: f64) -> &[Sample<7>] {
        let k = (seconds / self.drift.dt).round() as usize;
        &self.samples[..k.min(self.samples.len())]
    }

    /// LS from nominal on `samples`, then our EM from LS: the calibration the daemon runs.
    pub fn fit(&self, samples: &[Sample<7>]) -> Result<(LsResult<7, SUIT_PARAMS>, DriftEmResult<7>), crate::CalibError> {
        let ls = identify_ls::<7, SUIT_PARAMS>(&DhTable::paper_nominal(), samples, &LsOptions::new())?;
        let (em, _) = em_drift_vec::<7, SUIT_PARAMS>(&ls.table, samples, &DriftEmOptions::new(self.drift.dt))?;
        Ok((ls, em))
    }

    /// Table error of `table` against the truth on the fresh poses.
    pub fn table_error(&self, table: &DhTable<7>) -> TableError {
        table_error(table, &self.truth, &self.fresh)
    }
}

/// Runs one session of `cell` for `seed`.
pub fn session(cell: &Cell, seed: u64) -> Result<Session, crate::CalibError> {
    let sim = Simulation::new(cell, seed);
    let (truth, drift, samples, fresh) = (&sim.truth, sim.drift, &sim.samples, &sim.fresh);
    let (ls, em) = sim.fit(samples)?;
    let q = drift.process_variance();
    let (pn, rn) = (cell.noise.0 * cell.noise.0, cell.noise.1 * cell.noise.1);
    let crb = cramer_rao::<7, SUIT_PARAMS>(truth, samples, [drift.phi(); 7], [q; 7], [pn, pn, pn, rn, rn, rn], 1e-14)?;
    Ok(Session {
        ls: sim.table_error(&ls.table),
        em: sim.table_error(&em.table),
        bound: expected_table_error::<7, SUIT_PARAMS>(truth, fresh, |u| crb.variance_along(u)),
        reported: em.expected_error,
        ls_expected: ls_expected_table_error::<7, SUIT_PARAMS>(
            &ls.table,
            samples,
            &[drift.phi(); 7],
            &[q / (1.0 - drift.phi() * drift.phi()); 7],
            &[pn, pn, pn, rn, rn, rn],
            fresh,
        )
        .unwrap_or(TableError {
            position_m: f64::NAN,
            rotation_rad: f64::NAN,
        }),
    })
}

/// RMS over sessions of each figure (position, rotation), and the spread of EM / bound.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Summary {
    /// RMS table error of LS.
    pub ls: TableError,
    /// RMS table error of our EM.
    pub em: TableError,
    /// RMS of the bound.
    pub bound: TableError,
    /// RMS of what the EM reported.
    pub reported: TableError,
    /// RMS of what LS was expected to reach.
    pub ls_expected: TableError,
    /// Smallest and largest single-session EM / bound ratio (position, rotation).
    pub em_ratio_range: ((f64, f64), (f64, f64)),
}

impl Summary {
    /// Summarises sessions (at least one).
    pub fn of(sessions: &[Session]) -> Summary {
        let n = sessions.len().max(1) as f64;
        let rms = |f: &dyn Fn(&Session) -> TableError| TableError {
            position_m: (sessions.iter().map(|s| f(s).position_m.powi(2)).sum::<f64>() / n).sqrt(),
            rotation_rad: (sessions.iter().map(|s| f(s).rotation_rad.powi(2)).sum::<f64>() / n).sqrt(),
        };
        let range = |f: &dyn Fn(&Session) -> f64| {
            sessions
                .iter()
                .map(f)
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), r| (lo.min(r), hi.max(r)))
        };
        Summary {
            ls: rms(&|s| s.ls),
            em: rms(&|s| s.em),
            bound: rms(&|s| s.bound),
            reported: rms(&|s| s.reported),
            ls_expected: rms(&|s| s.ls_expected),
            em_ratio_range: (
                range(&|s| s.em.position_m / s.bound.position_m),
                range(&|s| s.em.rotation_rad / s.bound.rotation_rad),
            ),
        }
    }

    /// EM / bound of the RMS (position, rotation).
    pub fn em_ratio(&self) -> (f64, f64) {
        (
            self.em.position_m / self.bound.position_m,
            self.em.rotation_rad / self.bound.rotation_rad,
        )
    }

    /// LS / bound of the RMS (position, rotation).
    pub fn ls_ratio(&self) -> (f64, f64) {
        (
            self.ls.position_m / self.bound.position_m,
            self.ls.rotation_rad / self.bound.rotation_rad,
        )
    }
}

/// The full grid of issue 18: τ × σ × pose noise × session length.
pub fn grid() -> Vec<Cell> {
    let mut cells = Vec::new();
    for seconds in [20.0, 60.0, 120.0] {
        for noise in [(0.0, 0.0), (1e-3, 2e-3)] {
            for sigma in [0.25, 1.0, 4.0] {
                for tau in [0.1, 0.3, 1.0, 3.0, 10.0] {
                    cells.push(Cell {
                        tau,
                        sigma,
                        noise,
                        seconds,
                    });
                }
            }
        }
    }
    cells
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_bound_at_the_truth_is_below_what_ls_reaches_and_true_tables_vary() {
        assert_ne!(true_table(1), true_table(2));
        let cell = Cell {
            tau: 1.0,
            sigma: 1.0,
            noise: (1e-3, 2e-3),
            seconds: 10.0,
        };
        let s = session(&cell, 1).unwrap();
        assert!(s.bound.position_m > 0.0 && s.bound.rotation_rad > 0.0, "{s:?}");
        assert!(s.ls.position_m > s.bound.position_m, "{s:?}");
    }

    /// The reduced sweep (issue 18): three 20 s cells with pose noise, where the sweep shows the
    /// EM at the bound (`cargo run -p calib-core --release --example sweep`: EM / bound 0.78–0.98
    /// there over 5 seeds). Over 4 seeds each, the EM's RMS table error stays within 1.10 × the
    /// bound's and below LS's, in position and rotation.
    #[test]
    fn reduced_sweep_em_at_the_bound_and_better_than_ls() {
        for (tau, sigma) in [(0.1, 1.0), (1.0, 1.0), (0.3, 4.0)] {
            let cell = Cell {
                tau,
                sigma,
                noise: (1e-3, 2e-3),
                seconds: 20.0,
            };
            let sessions: Vec<Session> = (1..=4).map(|seed| session(&cell, seed).unwrap()).collect();
            let s = Summary::of(&sessions);
            let (ep, er) = s.em_ratio();
            std::eprintln!(
                "{cell:?}: EM/bound {ep:.3} {er:.3}, LS/bound {:.3} {:.3}",
                s.ls_ratio().0,
                s.ls_ratio().1
            );
            assert!(ep <= 1.10 && er <= 1.10, "{cell:?}: EM / bound {ep:.3}, {er:.3}");
            assert!(
                s.em.position_m <= s.ls.position_m && s.em.rotation_rad <= s.ls.rotation_rad,
                "{cell:?}: EM {:?} vs LS {:?}",
                s.em,
                s.ls
            );
        }
    }

    /// The bound cross-checked by Monte Carlo (issue 18, item 1): 50 sessions of 10 s, each
    /// with its own true table around Table 1, τ = 1 s, σ = 1, 1 mm / 2 mrad pose noise.
    /// Measured 2026-11-23 over 40 seeds: EM / bound 1.01 (position) and 1.01 (rotation), LS /
    /// bound 1.60 and 1.32; what the EM reports (its bound at its own estimates) is 0.83 and
    /// 0.78 of the bound at the truth: optimistic by about a fifth on sessions this short.
    #[test]
    fn monte_carlo_agrees_with_the_bound_and_ls_does_not_reach_it() {
        let cell = Cell {
            tau: 1.0,
            sigma: 1.0,
            noise: (1e-3, 2e-3),
            seconds: 10.0,
        };
        let sessions: Vec<Session> = (1..=50).map(|seed| session(&cell, seed).unwrap()).collect();
        let s = Summary::of(&sessions);
        let (ep, er) = s.em_ratio();
        let (lp, lr) = s.ls_ratio();
        let rp = s.reported.position_m / s.bound.position_m;
        let rr = s.reported.rotation_rad / s.bound.rotation_rad;
        let xp = s.ls.position_m / s.ls_expected.position_m;
        let xr = s.ls.rotation_rad / s.ls_expected.rotation_rad;
        std::eprintln!(
            "EM/bound {ep:.3} {er:.3}, LS/bound {lp:.3} {lr:.3}, reported/bound {rp:.3} {rr:.3}, LS/LS expected {xp:.3} {xr:.3}"
        );
        // 50 sessions estimate an RMS to about ±10% (1σ) here: the band is three of those wide
        // below (no estimator beats the bound) and allows EM's measured inefficiency above.
        assert!(
            (0.85..1.2).contains(&ep) && (0.85..1.2).contains(&er),
            "EM / bound {ep:.3}, {er:.3}"
        );
        assert!(lp > 1.2 && lr > 1.1, "LS / bound {lp:.3}, {lr:.3}");
        // What LS is expected to reach (the sandwich under the true drift) is what it reached.
        assert!(
            (0.85..1.2).contains(&xp) && (0.85..1.2).contains(&xr),
            "LS / LS expected {xp:.3}, {xr:.3}"
        );
        assert!(
            (0.65..1.05).contains(&rp) && (0.65..1.05).contains(&rr),
            "reported / bound {rp:.3}, {rr:.3}"
        );
    }
}
