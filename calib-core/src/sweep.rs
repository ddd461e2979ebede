//! The accuracy sweep: LS and our EM against the Cramér-Rao bound over the regimes a user may
//! meet, in table error ([`crate::metrics`]).
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
//! [`Simulation`] is that setup (true table, samples, fresh poses) and the calibration it is
//! judged by ([`Simulation::fit`]: LS from nominal, then our EM from LS); [`session`] adds the
//! bound and LS's expected figure.
//!
//! Stop when good enough ([`good_enough`]): one session of the cell's drift and noise,
//! `max_s` long, under the daemon's [`StopRule`]: LS + EM on the prefix at `min_s`,
//! `min_s + every_s`, …, stopping at the first whose EM expected table error is within both
//! limits, or at `max_s`. Every evaluation keeps the EM table's real table error; the prefix of a
//! fixed length (e.g. the daemon's default minute) is evaluated too, on the same samples, so
//! the comparison is paired. Unlike the daemon's, this rule has no coverage check (the daemon
//! also waits for every joint's range to be covered), and the EM table judged is fitted on the
//! whole prefix (the daemon pushes one fitted on the part it does not hold out).
//!
//! `std` only (it allocates); `cargo run -p calib-core --release --example sweep` prints the
//! whole grid, `--example stop_rule` the stop rule across it, and reduced forms run in the
//! tests.

use std::vec::Vec;

use crate::drift::{Discretisation, GaussMarkov};
use crate::drift_em::{cramer_rao, em_drift_vec, DriftEmOptions, DriftEmResult};
use crate::ls::{identify_ls, LsOptions, LsResult};
use crate::metrics::{expected_table_error, ls_expected_table_error, table_error, TableError};
use crate::model::{DhTable, JointRanges, ParamKind, Sample, SUIT_PARAMS};
use crate::reading::{separate, SeparationSlot};
use crate::rng::Rng;
use crate::sim::{DriftSite, Motion, Outliers, RateBias, Scenario, ScenarioConfig, SimSample, Slip};
use crate::versus_ls::{em_versus_ls, TableChoice};

/// Fresh poses every table error is averaged over.
pub const FRESH_POSES: usize = 200;

/// Scales of the true table's deviation from Table 1, alternating over seeds.
pub const TABLE_SCALES: [f64; 2] = [0.2, 1.0];

/// One regime of the sweep.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Cell {
    /// Drift correlation time τ (s).
    pub tau: f64,
    /// Drift σ: in the paper's convention (eq. 8) for [`Field::PAPER`], else as
    /// `field.discretisation` says (the stationary deviation in rad for `Exact`).
    pub sigma: f64,
    /// White pose noise: position (m) and rotation (rad) per axis.
    pub noise: (f64, f64),
    /// Session length (s).
    pub seconds: f64,
    /// What a real suit adds to the paper's scenario ([`Field::PAPER`]: nothing).
    pub field: Field,
}

/// The field conditions of a [`Cell`] beside its Gauss-Markov drift and pose noise (see
/// [`crate::sim`]): sample rate, where the drift sits, rate bias, reading noise, glitches.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Field {
    /// Sample period (s).
    pub dt: f64,
    /// How [`Cell::sigma`] is read.
    pub discretisation: Discretisation,
    /// Where the angle error acts.
    pub site: DriftSite,
    /// Rate bias integrated into the angle error.
    pub bias: RateBias,
    /// A constant rate bias (rad/s) per joint, its sign drawn per seed, integrated without
    /// bound ([`ScenarioConfig::heading`]); zero where a gravity reference corrects the joint.
    pub heading: [f64; 7],
    /// White noise on every reported angle (rad).
    pub reading_noise: f64,
    /// Glitches of the reference pose.
    pub outliers: Outliers,
    /// A sensor that slips during the session.
    pub slip: Option<Slip>,
    /// White noise on every joint gyro reading (rad/s).
    pub gyro_noise: f64,
    /// The wearer holds still this long at the session's start (s, part of the session); where
    /// longer than [`crate::rest::MIN_REST_S`], the gyros read then ([`crate::rest`]) take their
    /// bias out of the joints a heading or rate bias acts on, and the EM is told what is left
    /// ([`Simulation::prepared`]).
    pub still_s: f64,
}

impl Field {
    /// The paper's scenario: 100 Hz, σ in the paper's convention, the drift in the arm, nothing
    /// else.
    pub const PAPER: Field = Field {
        dt: 0.01,
        discretisation: Discretisation::Paper,
        site: DriftSite::Arm,
        bias: RateBias::NONE,
        heading: [0.0; 7],
        reading_noise: 0.0,
        outliers: Outliers::NONE,
        slip: None,
        gyro_noise: 0.0,
        still_s: 0.0,
    };

    /// A real suit's sensors: 50 Hz, σ the stationary deviation (rad), the drift in the reading,
    /// no rate bias, 0.2 mrad of reading noise, 2 mrad/s of gyro noise (the emulated suit's),
    /// no glitches, no pause.
    pub const SENSOR: Field = Field {
        dt: 0.02,
        discretisation: Discretisation::Exact,
        site: DriftSite::Reading,
        bias: RateBias::NONE,
        heading: [0.0; 7],
        reading_noise: 2e-4,
        outliers: Outliers::NONE,
        slip: None,
        gyro_noise: 2e-3,
        still_s: 0.0,
    };
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
    /// What the EM states ([`DriftEmResult::stated_error`]: the bound at its own estimates with
    /// the model choice's and the consistency's share).
    pub stated: TableError,
    /// The stated error with the allowance for [`DriftEmOptions::consider`]'s rate bias
    /// ([`DriftEmResult::stated_with_allowance`]; the stated error without one).
    pub allowed: TableError,
    /// Whether the EM refused the session ([`DriftEmResult::refusals`]).
    pub refused: bool,
    /// What LS is expected to reach under the true drift and noise
    /// ([`crate::metrics::ls_expected_table_error`]).
    pub ls_expected: TableError,
    /// The arbiter's choice between the EM's table and LS's, as the daemon makes it
    /// ([`crate::EmVersusLs::choice`]; the EM's where LS's expected error cannot be computed).
    pub choice: TableChoice,
    /// The table the daemon would push, against the truth, and what it states (the EM's stated
    /// error with its allowance, or LS's expected one); `None` where the session is refused (by
    /// the EM's refusals or the choice).
    pub pushed: Option<(TableError, TableError)>,
}

impl Session {
    /// Whether the pushed table is off by more than `times` its own stated error (position or
    /// rotation).
    pub fn pushed_beyond(&self, times: f64) -> bool {
        self.pushed.is_some_and(|(real, stated)| {
            real.position_m > times * stated.position_m || real.rotation_rad > times * stated.rotation_rad
        })
    }
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
    /// The Gauss-Markov part of the cell's drift.
    pub drift: GaussMarkov,
    /// The cell's pose noise (m, rad).
    pub noise: (f64, f64),
    /// `cell.seconds` of the suit's motion.
    pub samples: Vec<Sample<7>>,
    /// Per sample, whether its pose is a glitch.
    pub glitched: Vec<bool>,
    /// [`FRESH_POSES`] poses of another motion.
    pub fresh: Vec<[f64; 7]>,
    /// Every sample's joint gyro readings (rad/s).
    pub gyro: Vec<[f64; 7]>,
    /// The joints whose angle integrates its gyro unaided (a heading or a rate bias acts on
    /// them), which the gyro at rest corrects; none where the wearer is not still first.
    pub unaided: [bool; 7],
}

impl Simulation {
    /// Simulates `cell` for `seed`. A longer session of the same cell and seed starts with the
    /// same samples: a prefix of it is the shorter session.
    pub fn new(cell: &Cell, seed: u64) -> Simulation {
        Simulation::reaching(cell, seed, [1.0; 7])
    }

    /// [`Simulation::new`] with a wearer whose motion uses `reach[j]` of joint `j`'s range, about
    /// its middle (a lazy wrist: `[1, 1, 1, 1, 0.6, 0.6, 0.6]`); the fresh poses still span the
    /// whole ranges.
    pub fn reaching(cell: &Cell, seed: u64, reach: [f64; 7]) -> Simulation {
        let f = cell.field;
        let drift = GaussMarkov {
            dt: f.dt,
            tau: cell.tau,
            sigma: cell.sigma,
            discretisation: f.discretisation,
        };
        let truth = true_table(seed);
        // The heading's signs from a draw of their own: the other draws are the same with and
        // without it.
        let mut signs = Rng::new(seed ^ 0x4EAD_1460);
        let heading = f.heading.map(|h| if signs.uniform() < 0.5 { -h } else { h });
        let whole = ScenarioConfig::paper().ranges;
        let ranges = JointRanges {
            limits: core::array::from_fn(|j| {
                let ((lo, hi), r) = (whole.limits[j], reach[j]);
                let mid = 0.5 * (lo + hi);
                if r >= 1.0 {
                    (lo, hi)
                } else {
                    (mid - 0.5 * r * (hi - lo), mid + 0.5 * r * (hi - lo))
                }
            }),
        };
        let cfg = ScenarioConfig {
            actual: truth,
            drift,
            bias: f.bias,
            heading,
            site: f.site,
            reading_noise: f.reading_noise,
            gyro_noise: f.gyro_noise,
            still_s: f.still_s,
            position_noise: cell.noise.0,
            rotation_noise: cell.noise.1,
            outliers: f.outliers,
            slip: f.slip,
            ranges,
        };
        let k = (cell.seconds / drift.dt).round() as usize;
        let run: Vec<SimSample<7>> = Scenario::new(cfg, seed).take(k).collect();
        // Fresh drift-free poses: the smooth motion of another seed, every 17th step.
        let motion = Motion::random(&whole, &mut Rng::new(seed ^ 0xF2E5_4000));
        Simulation {
            truth,
            drift,
            noise: cell.noise,
            samples: run.iter().map(|s| s.sample).collect(),
            glitched: run.iter().map(|s| s.outlier).collect(),
            fresh: (0..FRESH_POSES).map(|i| motion.at((17 * i) as f64 * drift.dt)).collect(),
            gyro: run.iter().map(|s| s.gyro).collect(),
            unaided: core::array::from_fn(|j| f.still_s >= crate::rest::MIN_REST_S && (f.heading[j] != 0.0 || !f.bias.is_none())),
        }
    }

    /// The first `seconds` of the session (all of it if shorter).
    pub fn prefix(&self, seconds: f64) -> &[Sample<7>] {
        let k = (seconds / self.drift.dt).round() as usize;
        &self.samples[..k.min(self.samples.len())]
    }

    /// LS from nominal on `samples`, then our EM from LS: the calibration the daemon runs.
    pub fn fit(&self, samples: &[Sample<7>]) -> Result<(LsResult<7, SUIT_PARAMS>, DriftEmResult<7>), crate::CalibError> {
        self.fit_with(samples, &DriftEmOptions::new(self.drift.dt))
    }

    /// [`Simulation::fit`] with other EM options (e.g. [`DriftEmOptions::plain`], to measure
    /// what a part of the model is worth).
    pub fn fit_with(
        &self,
        samples: &[Sample<7>],
        opts: &DriftEmOptions<7>,
    ) -> Result<(LsResult<7, SUIT_PARAMS>, DriftEmResult<7>), crate::CalibError> {
        let (samples, opts) = self.prepared(samples, opts);
        let ls = identify_ls::<7, SUIT_PARAMS>(&DhTable::paper_nominal(), &samples, &LsOptions::new())?;
        let (em, _) = em_drift_vec::<7, SUIT_PARAMS>(&ls.table, &samples, &opts)?;
        Ok((ls, em))
    }

    /// What the daemon fits of `samples` (a prefix of the session) and how: where the wearer
    /// held still first, the gyros' bias then ([`crate::rest`]) taken out of the
    /// [`Simulation::unaided`] joints and what is left of it given to the EM as the sensors'
    /// rate-bias spec (unless `opts` has one); then [`Simulation::separated`].
    pub fn prepared(&self, samples: &[Sample<7>], opts: &DriftEmOptions<7>) -> (Vec<Sample<7>>, DriftEmOptions<7>) {
        let mut samples = samples.to_vec();
        let mut opts = *opts;
        if let Some(bias) = self.gyro_at_rest(samples.len()) {
            for (k, s) in samples.iter_mut().enumerate() {
                bias.correct(s, k as f64 * self.drift.dt, &self.unaided);
            }
            if opts.rate_bias_spec.is_none() {
                opts.rate_bias_spec = bias.residual(&self.unaided);
            }
        }
        (self.separated(&samples), opts)
    }

    /// The gyros' bias measured while still in the first `k` samples, where some joint is
    /// [`Simulation::unaided`].
    pub fn gyro_at_rest(&self, k: usize) -> Option<crate::rest::GyroBias<7>> {
        if !self.unaided.iter().any(|&u| u) {
            return None;
        }
        let mut rest = crate::rest::GyroAtRest::new(self.drift.dt);
        for (s, g) in self.samples.iter().zip(&self.gyro).take(k) {
            rest.push(&s.pose, g);
        }
        rest.estimate()
    }

    /// The daemon's step 0 on `samples`: each reading off the rough part of its drift (a no-op
    /// on smooth readings, e.g. the paper's cells). What [`Simulation::fit_with`] fits.
    pub fn separated(&self, samples: &[Sample<7>]) -> Vec<Sample<7>> {
        let mut samples = samples.to_vec();
        let mut slots = std::vec![SeparationSlot::default(); samples.len()];
        separate(
            &mut samples,
            &DhTable::paper_nominal(),
            self.drift.dt,
            DriftEmOptions::<7>::new(self.drift.dt).initial_tau,
            &mut slots,
        );
        samples
    }

    /// Table error of `table` against the truth on the fresh poses.
    pub fn table_error(&self, table: &DhTable<7>) -> TableError {
        table_error(table, &self.truth, &self.fresh)
    }

    /// The Cramér-Rao bound of the table error on the fresh poses for `samples` (a prefix of
    /// this session), at the true table, drift and pose noise: what no unbiased calibration
    /// of those samples beats, in the paper's model.
    pub fn bound(&self, samples: &[Sample<7>]) -> Result<TableError, crate::CalibError> {
        // No drift: the bound of white pose noise alone (a drift too small to matter).
        let q = self.drift.process_variance().max(1e-30);
        let (pn, rn) = (self.noise.0 * self.noise.0, self.noise.1 * self.noise.1);
        let noise = [pn, pn, pn, rn, rn, rn];
        let crb = cramer_rao::<7, SUIT_PARAMS>(&self.truth, samples, [self.drift.phi(); 7], [q; 7], noise, 1e-14)?;
        Ok(expected_table_error::<7, SUIT_PARAMS>(&self.truth, &self.fresh, |u| {
            crb.variance_along(u)
        }))
    }
}

/// Runs one session of `cell` for `seed`.
pub fn session(cell: &Cell, seed: u64) -> Result<Session, crate::CalibError> {
    session_with(cell, seed, |o| o)
}

/// [`session`] with the EM's options changed by `options` (from the defaults at the cell's Δt).
pub fn session_with(
    cell: &Cell,
    seed: u64,
    options: impl Fn(DriftEmOptions<7>) -> DriftEmOptions<7>,
) -> Result<Session, crate::CalibError> {
    session_of(&Simulation::new(cell, seed), cell, options)
}

/// [`session_with`] on a given simulation of `cell` (e.g. one whose
/// [`Simulation::unaided`] was cleared, to measure what the gyro at rest is worth).
pub fn session_of(
    sim: &Simulation,
    cell: &Cell,
    options: impl Fn(DriftEmOptions<7>) -> DriftEmOptions<7>,
) -> Result<Session, crate::CalibError> {
    let (drift, samples, fresh) = (sim.drift, &sim.samples, &sim.fresh);
    let (separated, opts) = sim.prepared(samples, &options(DriftEmOptions::new(drift.dt)));
    let ls = identify_ls::<7, SUIT_PARAMS>(&DhTable::paper_nominal(), &separated, &LsOptions::new())?;
    let (em, _) = em_drift_vec::<7, SUIT_PARAMS>(&ls.table, &separated, &opts)?;
    let versus = em_versus_ls::<7, SUIT_PARAMS>(&ls.table, &em, &separated, &opts.error_poses);
    let choice = versus.map_or(TableChoice::Em, |v| v.choice());
    let pushed = match (em.refusals.is_empty(), choice, versus) {
        (false, _, _) | (_, TableChoice::Neither, _) => None,
        (true, TableChoice::Ls, Some(v)) => Some((sim.table_error(&ls.table), v.ls_expected)),
        (true, _, _) => Some((sim.table_error(&em.table), em.stated_with_allowance())),
    };
    let q = drift.process_variance().max(1e-30);
    let (pn, rn) = (cell.noise.0 * cell.noise.0, cell.noise.1 * cell.noise.1);
    Ok(Session {
        choice,
        pushed,
        ls: sim.table_error(&ls.table),
        em: sim.table_error(&em.table),
        bound: sim.bound(samples)?,
        reported: em.expected_error,
        stated: em.stated_error,
        allowed: em.stated_with_allowance(),
        refused: !em.refusals.is_empty(),
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

/// The daemon's "stop when good enough" rule (`session.stop_at_expected_error`): from
/// `min_s`, every `every_s` seconds of the window, LS + our EM on the motion so far; the window
/// closes at the first evaluation whose EM expected table error
/// ([`DriftEmResult::expected_error`]) is within both limits, or at `max_s`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StopRule {
    /// Position (m) and rotation (rad) limits of the expected table error (1σ), inclusive.
    pub limits: TableError,
    /// First evaluation (s).
    pub min_s: f64,
    /// The window closes here at the latest (s).
    pub max_s: f64,
    /// Between evaluations (s).
    pub every_s: f64,
}

impl StopRule {
    /// The daemon's defaults with limits of `mm` and `mrad`: 15 s, 120 s, every 5 s.
    pub fn new(mm: f64, mrad: f64) -> StopRule {
        StopRule {
            limits: TableError {
                position_m: mm * 1e-3,
                rotation_rad: mrad * 1e-3,
            },
            min_s: 15.0,
            max_s: 120.0,
            every_s: 5.0,
        }
    }

    /// The evaluation times: `min_s`, `min_s + every_s`, … up to `max_s` (included; the last
    /// one is `max_s` itself if the steps do not land on it).
    pub fn times(&self) -> Vec<f64> {
        let steps = ((self.max_s - self.min_s) / self.every_s + 1e-9).floor() as usize;
        let mut t: Vec<f64> = (0..=steps).map(|i| self.min_s + i as f64 * self.every_s).collect();
        if t.last().is_none_or(|&l| l < self.max_s - 1e-9) {
            t.push(self.max_s);
        }
        t
    }

    /// Whether an expected table error is within both limits.
    pub fn within(&self, e: &TableError) -> bool {
        e.position_m <= self.limits.position_m && e.rotation_rad <= self.limits.rotation_rad
    }
}

/// One evaluation of the rule: LS + EM on the first `seconds` of the session.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Evaluation {
    /// Length of the prefix (s).
    pub seconds: f64,
    /// The EM's expected table error (`None` where LS or the EM failed: the daemon then
    /// has no estimate and goes on collecting).
    pub expected: Option<TableError>,
    /// The EM table's real table error (against the truth, on the fresh poses).
    pub real: Option<TableError>,
}

/// One session under the stop rule, and the fixed window it is compared with.
#[derive(Clone, Debug, PartialEq)]
pub struct GoodEnough {
    /// Every evaluation until the stop, in time order; the last is the stop.
    pub evaluations: Vec<Evaluation>,
    /// The fixed window's evaluation (the same session's prefix of that length).
    pub fixed: Evaluation,
}

impl GoodEnough {
    /// The evaluation the window closed at.
    pub fn stop(&self) -> &Evaluation {
        self.evaluations.last().expect("at least one evaluation")
    }

    /// Whether the expected error was within the limits when the window closed (false when it
    /// closed at `max_s` without).
    pub fn met(&self, rule: &StopRule) -> bool {
        self.stop().expected.is_some_and(|e| rule.within(&e))
    }
}

/// LS + EM on the first `seconds` of `sim`.
pub fn evaluate(sim: &Simulation, seconds: f64) -> Evaluation {
    let fit = sim.fit(sim.prefix(seconds)).ok();
    Evaluation {
        seconds,
        expected: fit.as_ref().map(|(_, em)| em.expected_error),
        real: fit.as_ref().map(|(_, em)| sim.table_error(&em.table)),
    }
}

/// Runs the stop rule on one session of `cell`'s drift and noise with `seed`'s true table,
/// `rule.max_s` long (`cell.seconds` is not used), and evaluates the prefix of `fixed_s` too
/// (the fixed window on the same motion, drift and noise: a paired comparison).
pub fn good_enough(cell: &Cell, seed: u64, rule: &StopRule, fixed_s: f64) -> GoodEnough {
    let seconds = rule.max_s.max(fixed_s);
    let sim = Simulation::new(&Cell { seconds, ..*cell }, seed);
    let mut evaluations = Vec::new();
    for t in rule.times() {
        let e = evaluate(&sim, t);
        evaluations.push(e);
        if e.expected.is_some_and(|e| rule.within(&e)) {
            break;
        }
    }
    let fixed = match evaluations.iter().find(|e| (e.seconds - fixed_s).abs() < 1e-9) {
        Some(e) => *e,
        None => evaluate(&sim, fixed_s),
    };
    GoodEnough { evaluations, fixed }
}

/// `√(Σ a² / Σ b²)` over sessions, per component (position, rotation): the ratio of two RMS
/// errors, e.g. real ÷ stated (`|s| s.em`, `|s| s.stated`) or our table against LS's.
pub fn pooled(sessions: &[Session], a: impl Fn(&Session) -> TableError, b: impl Fn(&Session) -> TableError) -> (f64, f64) {
    let sum = |f: &dyn Fn(&Session) -> TableError| {
        sessions.iter().fold((0.0, 0.0), |(p, r), x| {
            let e = f(x);
            (p + e.position_m * e.position_m, r + e.rotation_rad * e.rotation_rad)
        })
    };
    let (ap, ar) = sum(&a);
    let (bp, br) = sum(&b);
    ((ap / bp).sqrt(), (ar / br).sqrt())
}

/// The field cell whose name contains `name` ([`field_grid`]).
pub fn field_cell(name: &str) -> Option<Cell> {
    field_grid().into_iter().find(|(n, _)| n.contains(name)).map(|(_, c)| c)
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

/// The full grid: τ × σ × pose noise × session length.
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
                        field: Field::PAPER,
                    });
                }
            }
        }
    }
    cells
}

/// The field cells: a real suit's sensors ([`Field::SENSOR`]: 50 Hz, the drift in
/// the reading, reading noise), 0.5 mm / 1 mrad pose noise, 30 s, τ = 1 s and σ = 7 mrad unless
/// the cell's name says otherwise. Each with its name.
pub fn field_grid() -> Vec<(&'static str, Cell)> {
    let base = Cell {
        tau: 1.0,
        sigma: 7e-3,
        noise: (5e-4, 1e-3),
        seconds: 30.0,
        field: Field::SENSOR,
    };
    let with = |f: Field| Cell { field: f, ..base };
    let bias = |ramp: f64, walk: f64| {
        with(Field {
            bias: RateBias { ramp, walk },
            ..Field::SENSOR
        })
    };
    // A heading drift: a constant rate bias on the joints whose axis turns about the vertical
    // (1, 3 and 5: no gravity reference corrects their angle), integrated without bound.
    let heading = |deg_s: f64, seconds: f64| {
        let h = deg_s.to_radians();
        Cell {
            seconds,
            ..with(Field {
                heading: [h, 0.0, h, 0.0, h, 0.0, 0.0],
                ..Field::SENSOR
            })
        }
    };
    // The same, the wearer still for the first 5 s: the gyros read then measure the bias.
    let still = |deg_s: f64, seconds: f64| {
        let c = heading(deg_s, seconds);
        Cell {
            field: Field { still_s: 5.0, ..c.field },
            ..c
        }
    };
    let glitch = |probability: f64| {
        with(Field {
            outliers: Outliers {
                probability,
                burst: 1,
                position: 0.02,
                rotation: 0.02,
            },
            ..Field::SENSOR
        })
    };
    std::vec![
        (
            "the paper's Section 4 (100 Hz, drift in the arm, no noise, 20 s)",
            Cell {
                tau: 1.0,
                sigma: 1.0,
                noise: (0.0, 0.0),
                seconds: 20.0,
                field: Field::PAPER,
            },
        ),
        (
            "the paper's Section 4 with the drift in the reading (60 s)",
            Cell {
                tau: 1.0,
                sigma: 1.0,
                noise: (0.0, 0.0),
                seconds: 60.0,
                field: Field {
                    site: DriftSite::Reading,
                    ..Field::PAPER
                },
            },
        ),
        ("paper-like (τ 1 s, σ 7 mrad)", base),
        (
            "no pose noise",
            Cell {
                noise: (0.0, 0.0),
                ..base
            }
        ),
        ("15 s session", Cell { seconds: 15.0, ..base }),
        ("fast drift τ 0.3 s", Cell { tau: 0.3, ..base }),
        ("slow drift τ 3 s", Cell { tau: 3.0, ..base }),
        ("slow drift τ 10 s", Cell { tau: 10.0, ..base }),
        ("bias ramp 0.005 °/s", bias(0.005f64.to_radians(), 0.0)),
        ("bias ramp 0.02 °/s", bias(0.02f64.to_radians(), 0.0)),
        ("bias walk 2e-5 rad/s/√s", bias(0.0, 2e-5)),
        ("bias walk 1e-4 rad/s/√s", bias(0.0, 1e-4)),
        ("ramp 0.01 °/s + walk 5e-5", bias(0.01f64.to_radians(), 5e-5)),
        ("heading 0.01 °/s on joints 1, 3, 5", heading(0.01, 30.0)),
        ("heading 0.02 °/s on joints 1, 3, 5 (40 s)", heading(0.02, 40.0)),
        ("heading 0.02 °/s on joints 1, 3, 5 (60 s)", heading(0.02, 60.0)),
        ("heading 0.05 °/s on joints 1, 3, 5", heading(0.05, 30.0)),
        ("heading 0.05 °/s on joints 1, 3, 5 (40 s)", heading(0.05, 40.0)),
        ("heading 0.05 °/s on joints 1, 3, 5 (60 s)", heading(0.05, 60.0)),
        (
            "paper-like, still 5 s first",
            with(Field {
                still_s: 5.0,
                ..Field::SENSOR
            })
        ),
        ("heading 0.01 °/s, still 5 s first (30 s)", still(0.01, 30.0)),
        ("heading 0.02 °/s, still 5 s first (40 s)", still(0.02, 40.0)),
        ("heading 0.05 °/s, still 5 s first (30 s)", still(0.05, 30.0)),
        ("heading 0.05 °/s, still 5 s first (60 s)", still(0.05, 60.0)),
        (
            "bias ramp 0.02 °/s, still 5 s first",
            with(Field {
                still_s: 5.0,
                ..bias(0.02f64.to_radians(), 0.0).field
            })
        ),
        (
            "ramp 0.01 °/s + walk 5e-5, still 5 s first",
            with(Field {
                still_s: 5.0,
                ..bias(0.01f64.to_radians(), 5e-5).field
            })
        ),
        (
            "bias walk 1e-4 rad/s/√s (40 s)",
            Cell {
                seconds: 40.0,
                ..bias(0.0, 1e-4)
            }
        ),
        (
            "slow drift τ 10 s (40 s)",
            Cell {
                tau: 10.0,
                seconds: 40.0,
                ..base
            }
        ),
        ("glitches 1% (2 cm, 20 mrad)", glitch(0.01)),
        ("glitches 5% (2 cm, 20 mrad)", glitch(0.05)),
        ("no drift", Cell { sigma: 0.0, ..base }),
        (
            "a sensor slips 20 mrad mid-session (joint 2)",
            with(Field {
                slip: Some(Slip {
                    joint: 1,
                    time: 15.0,
                    angle: 0.02,
                }),
                ..Field::SENSOR
            }),
        ),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The paper's scenario with drift `tau`, `sigma` and 1 mm / 2 mrad pose noise, `seconds`
    /// long.
    fn paper_cell(tau: f64, sigma: f64, seconds: f64) -> Cell {
        Cell {
            tau,
            sigma,
            noise: (1e-3, 2e-3),
            seconds,
            field: Field::PAPER,
        }
    }

    /// The summary of `cell`'s sessions with seeds 1 to `seeds`.
    fn summary(cell: &Cell, seeds: u64) -> Summary {
        let sessions: Vec<Session> = (1..=seeds).map(|seed| session(cell, seed).unwrap()).collect();
        Summary::of(&sessions)
    }

    #[test]
    fn the_bound_at_the_truth_is_below_what_ls_reaches_and_true_tables_vary() {
        assert_ne!(true_table(1), true_table(2));
        let cell = paper_cell(1.0, 1.0, 10.0);
        let s = session(&cell, 1).unwrap();
        assert!(s.bound.position_m > 0.0 && s.bound.rotation_rad > 0.0, "{s:?}");
        assert!(s.ls.position_m > s.bound.position_m, "{s:?}");
    }

    /// The reduced sweep: three 20 s cells with pose noise, where the sweep shows the
    /// EM at the bound (BENCHMARKS.md's record of `cargo run -p calib-core --release --example
    /// sweep -- --seconds 20`, 5 seeds). Over 4 seeds each, the EM's RMS table error stays within 1.10 × the
    /// bound's and below LS's, in position and rotation.
    #[test]
    fn reduced_sweep_em_at_the_bound_and_better_than_ls() {
        for (tau, sigma) in [(0.1, 1.0), (1.0, 1.0), (0.3, 4.0)] {
            let cell = paper_cell(tau, sigma, 20.0);
            let s = summary(&cell, 4);
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

    /// The bound cross-checked by Monte Carlo: 50 sessions of 10 s, each with its own true
    /// table around Table 1, τ = 1 s, σ = 1, 1 mm / 2 mrad pose noise. Measured (the test's 50
    /// sessions, printed): EM / bound 1.06 (position) and 1.03 (rotation), LS / bound 1.56 and
    /// 1.29; what the EM reports (its bound at its own estimates) is 1.04 and 0.96 of the
    /// bound at the truth; LS / its sandwich expectation 1.03 and 0.97.
    #[test]
    fn monte_carlo_agrees_with_the_bound_and_ls_does_not_reach_it() {
        let cell = paper_cell(1.0, 1.0, 10.0);
        let s = summary(&cell, 50);
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

    /// The stop rule on one cheap case (τ = 0.3 s, σ = 1, 1 mm / 2 mrad noise, seed 1,
    /// evaluations at 4, 8 and 12 s), under three limits on the same session. Measured: the
    /// expected error is 2.26 / 9.40 at 4 s, 1.50 / 5.95 at 8 s, 1.62 / 5.44 at 12 s (mm / mrad),
    /// so [2, 7] stops at 8 s, [1, 5] never, anything at 4 s.
    #[test]
    fn the_stop_rule_stops_at_the_first_evaluation_within_the_limits() {
        let cell = paper_cell(0.3, 1.0, 0.0);
        let rule = |mm, mrad| StopRule {
            min_s: 4.0,
            max_s: 12.0,
            every_s: 4.0,
            ..StopRule::new(mm, mrad)
        };
        let sim = Simulation::new(&Cell { seconds: 12.0, ..cell }, 1);
        let fixed_s = 8.0;
        let mut stops = Vec::new();
        for rule in [rule(1e3, 1e3), rule(2.0, 7.0), rule(1.0, 5.0)] {
            let g = good_enough(&cell, 1, &rule, fixed_s);
            let stop = *g.stop();
            std::eprintln!("{:?}: {:?}", rule.limits, g.evaluations);
            let steps = (stop.seconds - rule.min_s) / rule.every_s;
            assert!(
                steps.fract() == 0.0 && (rule.min_s..=rule.max_s).contains(&stop.seconds),
                "{stop:?}"
            );
            // What the rule saw is what LS + EM give on that prefix of the same session.
            assert_eq!(stop, evaluate(&sim, stop.seconds));
            assert_eq!(
                g.fixed,
                evaluate(&sim, fixed_s),
                "the fixed window is the same session's prefix"
            );
            if stop.seconds < rule.max_s {
                assert!(g.met(&rule) && rule.within(&stop.expected.unwrap()), "{stop:?}");
            }
            for e in &g.evaluations[..g.evaluations.len() - 1] {
                assert!(!e.expected.is_some_and(|x| rule.within(&x)), "went on past {e:?}");
            }
            if stop.seconds > rule.min_s {
                let previous = evaluate(&sim, stop.seconds - rule.every_s);
                assert!(!previous.expected.is_some_and(|x| rule.within(&x)), "{previous:?}");
            }
            stops.push(stop.seconds);
        }
        // Laxer limits never stop later, and this case covers stopping at min_s, between and
        // at max_s without meeting the limits.
        assert_eq!(stops, [4.0, 8.0, 12.0]);
        assert!(stops.windows(2).all(|w| w[0] <= w[1]));
    }

    #[test]
    fn stop_rule_times_land_on_max() {
        assert_eq!(StopRule::new(2.0, 6.0).times().len(), 22);
        let odd = StopRule {
            max_s: 22.0,
            ..StopRule::new(2.0, 6.0)
        };
        assert_eq!(odd.times(), [15.0, 20.0, 22.0]);
    }
}

/// The stated accuracy holds on the field cells (a real suit's sensors: 50 Hz, the
/// drift in the reading, 30 s). 8 seeds per cell (`cargo run -p calib-core --release --example
/// field` has the whole table); each test fails without the part of the model it names.
#[cfg(test)]
mod field_tests {
    use super::*;
    use crate::drift_em::{DriftEmOptions, DriftModel, Refusal};

    const SEEDS: u64 = 8;

    fn sessions(name: &str, options: impl Fn(DriftEmOptions<7>) -> DriftEmOptions<7>) -> Vec<Session> {
        let cell = field_cell(name).expect("a field cell");
        (1..=SEEDS).map(|seed| session_with(&cell, seed, &options).unwrap()).collect()
    }

    fn accepted(s: &[Session]) -> Vec<Session> {
        s.iter().filter(|s| !s.refused).copied().collect()
    }

    /// The reduced field sweep: on the paper-like, slow-drift, glitching
    /// and rate-bias (with the sensors' spec) cells, real ÷ stated ≤ 1.25 and our table no worse
    /// than LS's. Measured (8 seeds; position / rotation): real ÷ stated 0.89 / 1.03, 0.72 / 0.96,
    /// 1.02 / 1.01, 0.77 / 0.89; ours ÷ LS 0.66 / 0.75, 0.86 / 0.96, 0.67 / 0.82, 0.49 / 0.55.
    #[test]
    fn reduced_field_sweep_the_stated_error_holds_and_beats_ls() {
        for (name, spec) in [
            ("paper-like", false),
            ("slow drift τ 10 s", false),
            ("glitches 5%", false),
            ("bias ramp 0.02", true),
        ] {
            let cell = field_cell(name).unwrap();
            let all = sessions(name, |o| {
                if spec {
                    DriftEmOptions {
                        rate_bias_spec: cell.field.bias,
                        ..o
                    }
                } else {
                    o
                }
            });
            let ok = accepted(&all);
            assert_eq!(ok.len(), all.len(), "{name}: refused");
            let (rp, rr) = pooled(&ok, |s| s.em, |s| s.stated);
            let (lp, lr) = pooled(&ok, |s| s.em, |s| s.ls);
            std::eprintln!("{name}: real / stated {rp:.2} / {rr:.2}, ours / LS {lp:.2} / {lr:.2}");
            assert!(rp <= 1.25 && rr <= 1.25, "{name}: real / stated {rp:.2} / {rr:.2}");
            assert!(lp <= 1.0 && lr <= 1.0, "{name}: ours / LS {lp:.2} / {lr:.2}");
        }
    }

    /// The reduced sweep of what the daemon pushes: where the gyro does
    /// what gyros do (a heading of 0.05 °/s on joints 1, 3, 5 over 30 and 60 s; one of 0.02 °/s
    /// over 40 s and a ramp of 0.02 °/s on every joint, each with the gyros read while still
    /// for 5 s first; a bias that wanders, 40 s) and on slow drift (τ 10 s, 40 s) and the
    /// paper-like cell, the table the arbiter keeps holds its statement (real ÷ stated ≤ 1.25),
    /// is no worse than LS's, and no session pushes a table more than 3× its own stated error.
    /// Measured (8 seeds; position / rotation), in that order: real ÷ stated 1.09 / 0.95,
    /// 1.04 / 0.94, 0.83 / 0.91, 1.03 / 1.00, 0.96 / 0.91, 0.59 / 0.80, 0.89 / 1.03; ours ÷ LS
    /// 0.39 / 0.39, 0.14 / 0.15, 0.87 / 0.92, 0.80 / 0.78, 0.62 / 0.47, 1.05 / 1.02 (τ 10 s: LS's
    /// white-noise model is nearly right there; the bound is met, 1.00 / 1.03), 0.66 / 0.75.
    /// An arbiter keeping LS's table wherever the tables disagree, with the EM started from a
    /// 20 mrad drift, fails this on the 60-s heading's first 8 seeds: LS's table pushed on 6,
    /// the EM's (the heading absorbed) on 2; the pushed tables 5.0× their statement in position
    /// over the 8 (RMS), 6 of them beyond 3×.
    #[test]
    fn reduced_sweep_what_is_pushed_holds_its_statement() {
        for name in [
            "heading 0.05 °/s on joints 1, 3, 5",
            "heading 0.05 °/s on joints 1, 3, 5 (60 s)",
            "heading 0.02 °/s, still 5 s first (40 s)",
            "bias ramp 0.02 °/s, still 5 s first",
            "bias walk 1e-4 rad/s/√s (40 s)",
            "slow drift τ 10 s (40 s)",
            "paper-like (τ 1 s, σ 7 mrad)",
        ] {
            let cell = field_grid().into_iter().find(|(n, _)| *n == name).expect("a cell").1;
            let all: Vec<Session> = (1..=SEEDS).map(|seed| session(&cell, seed).unwrap()).collect();
            let pushed: Vec<Session> = all.iter().filter(|s| s.pushed.is_some()).copied().collect();
            assert_eq!(pushed.len(), all.len(), "{name}: refused");
            let (rp, rr) = pooled(&pushed, |s| s.pushed.unwrap().0, |s| s.pushed.unwrap().1);
            let (lp, lr) = pooled(&pushed, |s| s.pushed.unwrap().0, |s| s.ls);
            let beyond = all.iter().filter(|s| s.pushed_beyond(3.0)).count();
            std::eprintln!("{name}: real / stated {rp:.2} / {rr:.2}, ours / LS {lp:.2} / {lr:.2}, beyond 3× {beyond}");
            assert!(rp <= 1.25 && rr <= 1.25, "{name}: real / stated {rp:.2} / {rr:.2}");
            // τ 10 s over 40 s: LS's white-noise model is nearly right, the two are level.
            assert!(lp <= 1.1 && lr <= 1.1, "{name}: ours / LS {lp:.2} / {lr:.2}");
            assert_eq!(beyond, 0, "{name}: pushed tables beyond 3× their statement");
        }
    }

    /// The gyro at rest: a heading of 0.02 °/s on joints 1, 3, 5 over 40 s is what the
    /// session alone cannot tell from the geometry (the EM keeps the paper's model, its table and
    /// LS's equally off). With the wearer still for the first 5 s, the gyros read then take the
    /// bias out of those joints and the EM is told what is left; the same sessions without that
    /// (the gyros ignored) push tables beyond their statement. Measured (8 seeds; position /
    /// rotation): real ÷ stated 0.85 / 0.92 with the gyros, real 2.2 mm; without, 2.26 / 1.77,
    /// real 4.9 mm, 2 sessions beyond 3×.
    #[test]
    fn the_gyro_at_rest_measures_a_heading_the_session_cannot_see() {
        let cell = field_cell("heading 0.02 °/s, still 5 s first (40 s)").unwrap();
        let (mut with, mut without) = (Vec::new(), Vec::new());
        for seed in 1..=SEEDS {
            let sim = Simulation::new(&cell, seed);
            let bias = sim.gyro_at_rest(sim.samples.len()).expect("still at the start");
            // 5 s less its edges, at 2 mrad/s of noise: 4.6 s of 50 Hz samples.
            assert!((bias.seconds - 4.6).abs() < 0.05, "{bias:?}");
            with.push(session_of(&sim, &cell, |o| o).unwrap());
            let blind = Simulation {
                unaided: [false; 7],
                ..sim
            };
            without.push(session_of(&blind, &cell, |o| o).unwrap());
        }
        let real = |s: &Session| s.pushed.unwrap().0;
        let (wp, wr) = pooled(&with, real, |s| s.pushed.unwrap().1);
        let (bp, br) = pooled(&without, real, |s| s.pushed.unwrap().1);
        let beyond = |v: &[Session]| v.iter().filter(|s| s.pushed_beyond(3.0)).count();
        let rms = |v: &[Session]| (v.iter().map(|s| real(s).position_m.powi(2)).sum::<f64>() / v.len() as f64).sqrt();
        std::eprintln!(
            "real / stated with the gyros {wp:.2} / {wr:.2} ({:.1} mm), without {bp:.2} / {br:.2} ({:.1} mm, {} beyond 3×)",
            rms(&with) * 1e3,
            rms(&without) * 1e3,
            beyond(&without)
        );
        assert!(wp <= 1.15 && wr <= 1.15, "with the gyros: {wp:.2} / {wr:.2}");
        assert_eq!(beyond(&with), 0);
        assert!(bp > 1.5 && br > 1.3, "without: {bp:.2} / {br:.2}");
        assert!(rms(&with) < 0.6 * rms(&without));
    }

    /// A heading (a steady rate bias on joints 1, 3, 5, integrated without bound) is found from
    /// the EM's default start: on seed 2 of the 60-s cell, started from a 20 mrad drift, τ and σ
    /// grow to absorb the ramp first (τ 7–9 s, σ 18–20 mrad on those joints, `2 Δ ln L` 0.0) and
    /// the table is 23.8 mm off with ±6.3 mm stated; from 5 mrad the rate bias is in the model
    /// on every joint, and the angle it integrated on the heading joints more than half the
    /// truth's and 3 standard errors (measured: 37–54 mrad of 52).
    #[test]
    fn a_heading_is_found_before_the_drift_absorbs_it() {
        let cell = field_cell("heading 0.05 °/s on joints 1, 3, 5 (60 s)").unwrap();
        let sim = Simulation::new(&cell, 2);
        let (_, em) = sim.fit(&sim.samples).unwrap();
        assert!(em.models.iter().all(|m| m.model == DriftModel::RateBias), "{}", em.models[0]);
        // The angle it integrated by the end: 0.05 °/s for 60 s is 52 mrad.
        let truth = 0.05f64.to_radians() * 60.0;
        for j in [0, 2, 4] {
            let m = em.models[j];
            assert!(
                m.angle.abs() > 0.5 * truth && m.angle.abs() > 3.0 * m.angle_se,
                "joint {}: {:.1} ± {:.1} mrad",
                j + 1,
                m.angle * 1e3,
                m.angle_se * 1e3
            );
        }
        let (real, stated) = (sim.table_error(&em.table), em.stated_error);
        assert!(real.position_m < 2.0 * stated.position_m, "{real:?} against {stated:?}");
    }

    /// A lazy wrist (joints 5–7 through 60% of their ranges) on the paper's cell with the drift
    /// in the reading (60 s): the table is used over the whole ranges, where its error is larger
    /// than over the session's own poses. Stated over the session's poses the error is
    /// optimistic there; stated over the ranges ([`crate::ErrorPoses::Ranges`], what the daemon
    /// states) it holds. The table is the same. Measured (8 seeds, real ÷ stated, position /
    /// rotation): 1.28 / 1.44 over the session's poses, 1.05 / 1.09 over the ranges (the whole
    /// reach, for comparison: 1.12 / 1.37 and 1.02 / 1.20).
    #[test]
    fn a_lazy_wrist_is_stated_over_the_ranges_it_did_not_visit() {
        let cell = field_cell("drift in the reading (60 s)").unwrap();
        let lazy = [1.0, 1.0, 1.0, 1.0, 0.6, 0.6, 0.6];
        let (mut session, mut ranges) = (Vec::new(), Vec::new());
        for seed in 1..=SEEDS {
            let sim = Simulation::reaching(&cell, seed, lazy);
            let opts = DriftEmOptions::new(sim.drift.dt);
            let (_, own) = sim.fit_with(&sim.samples, &opts).unwrap();
            let (_, spread) = sim
                .fit_with(
                    &sim.samples,
                    &DriftEmOptions {
                        error_poses: crate::ErrorPoses::Ranges(JointRanges::paper()),
                        ..opts
                    },
                )
                .unwrap();
            assert_eq!(own.table, spread.table, "where the error is stated changes no table");
            let real = sim.table_error(&own.table);
            session.push((real, own.stated_error));
            ranges.push((real, spread.stated_error));
        }
        let ratio = |v: &[(TableError, TableError)]| {
            let sum = |f: fn(&(TableError, TableError)) -> TableError| {
                v.iter()
                    .map(f)
                    .fold((0.0, 0.0), |(p, r), e| (p + e.position_m.powi(2), r + e.rotation_rad.powi(2)))
            };
            let ((rp, rr), (sp, sr)) = (sum(|x| x.0), sum(|x| x.1));
            ((rp / sp).sqrt(), (rr / sr).sqrt())
        };
        let ((op, or), (rp, rr)) = (ratio(&session), ratio(&ranges));
        std::eprintln!("real / stated over the session's poses {op:.2} / {or:.2}, over the ranges {rp:.2} / {rr:.2}");
        assert!(op > 1.2 && or > 1.2, "over the session's poses: {op:.2} / {or:.2}");
        assert!(rp <= 1.15 && rr <= 1.15, "over the ranges: {rp:.2} / {rr:.2}");
    }

    /// Without the sensors' spec, a 0.02 °/s rate bias is too small for a 30-s session to show
    /// (the data keep the paper's model) and the stated error is too small by 1.4–1.7; the
    /// consider allowance at the bias's size covers what it does to the table (measured, 8
    /// seeds: real ÷ stated 1.66 / 1.79 alone, 0.86 / 0.89 with the allowance), it changes
    /// neither the table nor the stated error, and it is zero without a considered bias.
    #[test]
    fn the_allowance_covers_a_rate_bias_the_session_cannot_show() {
        let cell = field_cell("bias ramp 0.02").unwrap();
        let plain = sessions("bias ramp 0.02", |o| o);
        let weighed = sessions("bias ramp 0.02", |o| DriftEmOptions {
            consider: cell.field.bias,
            ..o
        });
        let (sp, sr) = pooled(&plain, |s| s.em, |s| s.stated);
        let (ap, ar) = pooled(&weighed, |s| s.em, |s| s.allowed);
        std::eprintln!("real / stated {sp:.2} / {sr:.2}; with the allowance {ap:.2} / {ar:.2}");
        assert!(sp > 1.3 && sr > 1.3, "stated alone: {sp:.2} / {sr:.2}");
        assert!(ap <= 1.15 && ar <= 1.15, "with the allowance: {ap:.2} / {ar:.2}");
        for (p, w) in plain.iter().zip(&weighed) {
            assert_eq!((p.em, p.stated), (w.em, w.stated), "the allowance changes nothing else");
            assert_eq!(p.allowed, p.stated, "no allowance without a considered bias");
        }
    }

    /// The drift model as IMUs have it: with a rate bias of 0.02 °/s per joint and the
    /// sensors' spec, the rate-bias model states what it reaches; the Gauss-Markov model alone,
    /// told the same spec, states too little by 1.67 / 1.82 (measured) and its table is no
    /// better than LS's.
    #[test]
    fn a_rate_bias_is_modelled_and_its_stated_error_holds() {
        let cell = field_cell("bias ramp 0.02").unwrap();
        let with_spec = |o: DriftEmOptions<7>| DriftEmOptions {
            rate_bias_spec: cell.field.bias,
            ..o
        };
        let rich = sessions("bias ramp 0.02", with_spec);
        let plain = sessions("bias ramp 0.02", |o| DriftEmOptions {
            rate_bias: false,
            ..with_spec(o)
        });
        let (rp, rr) = pooled(&rich, |s| s.em, |s| s.stated);
        let (pp, pr) = pooled(&plain, |s| s.em, |s| s.stated);
        std::eprintln!("real / stated: rate bias {rp:.2} / {rr:.2}, Gauss-Markov {pp:.2} / {pr:.2}");
        assert!(rp <= 1.15 && rr <= 1.15, "rate bias: {rp:.2} / {rr:.2}");
        assert!(pp > 1.4 && pr > 1.4, "Gauss-Markov alone: {pp:.2} / {pr:.2}");
        // A rate bias large enough to see is found without a spec, on every joint.
        let big = Cell {
            field: Field {
                bias: RateBias {
                    ramp: 0.1f64.to_radians(),
                    walk: 0.0,
                },
                ..Field::SENSOR
            },
            ..cell
        };
        let sim = Simulation::new(&big, 1);
        let (_, em) = sim.fit(&sim.samples).unwrap();
        assert!(
            em.models.iter().all(|m| m.model == DriftModel::RateBias),
            "{:?}",
            em.models[0]
        );
    }

    /// A reference that glitches: 5% of the poses 2 cm / 20 mrad off. The heavy-tailed
    /// model discounts exactly the glitched samples and the stated error holds; a Gaussian
    /// reference takes the glitches for jumps of the joints and every session is refused; with
    /// more glitches than `max_discounted_share` (10%) the session is refused for that.
    #[test]
    fn glitches_are_discounted_counted_and_too_many_refused() {
        let cell = field_cell("glitches 5%").unwrap();
        for seed in 1..=3 {
            let sim = Simulation::new(&cell, seed);
            let mut ws = std::vec![crate::DriftSlot::default(); sim.samples.len()];
            let ls = identify_ls::<7, SUIT_PARAMS>(&DhTable::paper_nominal(), &sim.samples, &LsOptions::new()).unwrap();
            let em =
                crate::em_drift::<7, SUIT_PARAMS>(&ls.table, &sim.samples, &DriftEmOptions::new(sim.drift.dt), &mut ws).unwrap();
            let discounted: Vec<usize> = crate::discounted_samples(&ws).collect();
            let glitched: Vec<usize> = sim.glitched.iter().enumerate().filter(|(_, g)| **g).map(|(k, _)| k).collect();
            assert_eq!(discounted, glitched, "seed {seed}");
            assert_eq!(em.discounted.count, glitched.len());
            assert!(em.refusals.is_empty(), "{:?}", em.refusals);
        }
        let gaussian = sessions("glitches 5%", |o| DriftEmOptions { robust: false, ..o });
        assert!(
            gaussian.iter().all(|s| s.refused),
            "a Gaussian reference accepted a glitching session"
        );
        let many = Cell {
            field: Field {
                outliers: Outliers {
                    probability: 0.15,
                    ..cell.field.outliers
                },
                ..cell.field
            },
            ..cell
        };
        let sim = Simulation::new(&many, 1);
        let (_, em) = sim.fit(&sim.samples).unwrap();
        assert!(
            matches!(em.refusals[0], Refusal::TooManyDiscounted { count, .. } if count > 150),
            "{:?}",
            em.refusals
        );
        std::eprintln!("{}", em.refusals[0]);
    }

    /// A stated error that holds where the drift is slow (τ = 10 s over 30 s): the
    /// restricted (REML) drift parameters count the θ offsets' uncertainty; maximum likelihood
    /// fits τ and σ low and states too little (measured 1.58 / 1.85 against 0.72 / 0.96).
    #[test]
    fn with_slow_drift_the_restricted_drift_parameters_state_what_is_reached() {
        let reml = sessions("slow drift τ 10 s", |o| o);
        let ml = sessions("slow drift τ 10 s", |o| DriftEmOptions { restricted: false, ..o });
        let (rp, rr) = pooled(&reml, |s| s.em, |s| s.stated);
        let (mp, mr) = pooled(&ml, |s| s.em, |s| s.stated);
        std::eprintln!("real / stated: REML {rp:.2} / {rr:.2}, ML {mp:.2} / {mr:.2}");
        assert!(rp <= 1.15 && rr <= 1.15, "REML {rp:.2} / {rr:.2}");
        assert!(mp > 1.3 && mr > 1.3, "ML {mp:.2} / {mr:.2}");
    }

    /// The data contradicting the model: a joint sensor that slips 20 mrad mid-session
    /// is refused, naming the joint and the sample.
    #[test]
    fn a_sensor_that_slips_is_refused_naming_the_joint() {
        let cell = field_cell("slips").unwrap();
        for seed in 1..=2 {
            let sim = Simulation::new(&cell, seed);
            let (_, em) = sim.fit(&sim.samples).unwrap();
            let jump = em.refusals.iter().find_map(|r| match *r {
                Refusal::Jump { joint, sample, .. } => Some((joint, sample)),
                _ => None,
            });
            let (joint, sample) = jump.unwrap_or_else(|| panic!("not refused: {:?}", em.consistency));
            assert_eq!(joint, 1);
            assert!((sample as f64 * sim.drift.dt - 15.0).abs() < 0.1, "sample {sample}");
            std::eprintln!("{}", em.refusals[0]);
        }
    }

    /// Degenerate drift never leaves a session without an expected accuracy: no drift, no pose
    /// noise, no reading noise at all (the EM's drift and noise go to their floors).
    #[test]
    fn a_session_without_drift_or_noise_has_an_expected_accuracy() {
        let cell = Cell {
            sigma: 0.0,
            noise: (0.0, 0.0),
            field: Field {
                reading_noise: 0.0,
                ..Field::SENSOR
            },
            ..field_cell("no drift").unwrap()
        };
        for seed in 1..=3 {
            let sim = Simulation::new(&cell, seed);
            let (ls, em) = sim.fit(&sim.samples).unwrap();
            let e = em.stated_error;
            assert!(
                e.position_m.is_finite() && e.rotation_rad.is_finite() && e.position_m > 0.0,
                "{e:?}"
            );
            assert!(sim.table_error(&em.table).position_m < 1e-6);
            let white =
                crate::ls_white_expected_error::<7, SUIT_PARAMS>(&ls.table, &sim.samples, &crate::ErrorPoses::Session).unwrap();
            assert!(white.position_m.is_finite() && white.position_m < 1e-6, "{white:?}");
        }
    }
}
