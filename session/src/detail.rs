//! What the data path produces, in the shapes every consumer reads: the samples with their
//! time, the LS and EM steps in detail, the strongest correlations and the session's data
//! quality. The report renders these, the log records them; nothing here is computed.

use calib_core::{
    DhTable, Discounted, DriftConfidence, DriftParams, JointConsistency, JointDrift, Sample,
    Scenario, ScenarioConfig, TableError,
};

use crate::{MAX_JOINTS, MAX_PARAMS};

/// A calibration sample and its time (s since the start of the session).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TimedSample {
    /// Seconds since the start of the session.
    pub t: f64,
    /// The joint angles and the measured end-effector pose.
    pub sample: Sample<MAX_JOINTS>,
}

impl TimedSample {
    /// The first `k` samples of calib-core's simulated session `cfg` with `seed`, timed at its
    /// sample period: a session for examples and tests without a suit.
    pub fn simulated(cfg: ScenarioConfig<MAX_JOINTS>, seed: u64, k: usize) -> Vec<TimedSample> {
        Scenario::new(cfg, seed)
            .take(k)
            .enumerate()
            .map(|(i, s)| TimedSample {
                t: i as f64 * cfg.drift.dt,
                sample: s.sample,
            })
            .collect()
    }
}

/// The least-squares step, as the report shows it and the outcome serializes it (there without
/// the table and the standard errors, which the node rows carry).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct LsDetail {
    /// The LS table (padded, [`crate::arm`]).
    #[serde(skip)]
    pub table: DhTable<MAX_JOINTS>,
    /// Gauss–Newton/LM trial steps taken, accepted or not.
    pub iterations: usize,
    /// Numerical rank of the column-scaled Jacobian (`4 ·` [`Calibration::joints`] when every
    /// parameter is identifiable).
    pub rank: usize,
    /// Column-scaled condition number.
    #[serde(rename = "condition_number")]
    pub condition: f64,
    /// RMS of the 6-vector pose residual at the solution (m, rad).
    pub rms: f64,
    /// 1σ of each parameter from the information matrix (white-noise model), `kind·7 + joint`
    /// (NaN past the arm's joints, [`crate::arm`]).
    #[serde(skip)]
    pub std_errors: [f64; MAX_PARAMS],
}

/// Drift EM step, as the report shows it.
#[derive(Debug, Clone, PartialEq)]
pub struct EmDetail {
    /// The EM table (padded).
    pub table: DhTable<MAX_JOINTS>,
    /// EM iterations taken.
    pub iterations: usize,
    /// Whether the EM met its tolerance (otherwise it hit its iteration limit).
    pub converged: bool,
    /// Log-likelihood at every accepted iterate, objective after objective (calib-core's
    /// `DriftEmResult::log_likelihood`): never decreasing within one objective.
    pub log_likelihood: Vec<f64>,
    /// Where in `log_likelihood` each objective after the first starts.
    pub objectives: Vec<usize>,
    /// τ and σ per joint of the arm.
    pub drift: Vec<DriftParams>,
    /// Their standard errors (calib-core's `drift_confidence`), when asked for.
    pub drift_confidence: Option<Vec<DriftConfidence>>,
    /// Cramér-Rao 1σ of every parameter under the drift model, `kind·7 + joint` (NaN past
    /// the arm's joints).
    pub std_errors: [f64; MAX_PARAMS],
    /// Expected table error (1σ) under that bound, over poses spread over the joint ranges
    /// (calib-core's `ErrorPoses::Ranges`).
    pub expected_error: TableError,
    /// The expected table error to state and validate with (1σ): the bound with the
    /// uncertainty of the drift-model choice (calib-core's `stated_error`).
    pub stated_error: TableError,
    /// What a rate bias of [`crate::rules::UNCONFIGURED_RATE_BIAS_DEG_S`] would add where the
    /// sensors' spec is not configured and the model leaves the rate bias out (calib-core's
    /// `allowance`; zero otherwise). Not part of `stated_error`.
    pub allowance: TableError,
    /// Per joint, the drift model (the paper's Gauss-Markov, or with a rate bias) and why.
    pub models: Vec<JointDrift>,
    /// The reference samples discounted as glitches: how many, runs of sample indices, ν.
    pub discounted: Discounted,
    /// How well each joint's drift follows the fitted model.
    pub consistency: Vec<JointConsistency>,
    /// Where the data contradict the model (a sensor that jumped, too many glitches, a drift
    /// grossly off its model): each refuses the session.
    pub refusals: Vec<calib_core::Refusal>,
    /// The EM's table against LS's over the same poses (calib-core's `em_versus_ls`): their RMS
    /// FK difference, what the LS table alone is expected to reach (1σ) under the drift and
    /// noise the EM fitted, and whether the two agree (where not, LS's table is the result,
    /// [`Calibration::ls_kept`]); `None` when LS's normal equations were too ill-conditioned
    /// to say.
    pub versus_ls: Option<calib_core::EmVersusLs>,
    /// Smoothed angle error (rad) per fitted sample: the Gauss-Markov drift plus, where the
    /// model has one, the integrated rate bias.
    pub drift_series: Vec<[f64; MAX_JOINTS]>,
}

impl EmDetail {
    /// Whether LS's table is the result (calib-core's `EmVersusLs::choice`): the EM's table
    /// disagrees with LS's beyond LS's own error, and the EM's Gauss-Markov model does not hold
    /// for the session.
    pub fn ls_kept(&self) -> bool {
        self.versus_ls
            .is_some_and(|v| v.choice() == calib_core::TableChoice::Ls)
    }

    /// The log-likelihoods of the final objective: never decreasing.
    pub fn last_objective(&self) -> &[f64] {
        &self.log_likelihood[self.objectives.last().copied().unwrap_or(0)..]
    }
}

/// One entry of the strongest-correlations list.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Correlation {
    /// Parameter indices (`kind·7 + joint`), `first < second`.
    pub first: usize,
    /// The other parameter index.
    pub second: usize,
    /// Correlation coefficient in [−1, 1].
    pub r: f64,
}

/// What the calibration produced.
#[derive(Debug, Clone, PartialEq)]
pub struct Calibration {
    /// Joints of the arm calibrated: the tables' first rows, the parameters `kind·7 + joint`
    /// with `joint` below it ([`crate::arm`]).
    pub joints: usize,
    /// The least-squares step.
    pub ls: LsDetail,
    /// The EM, or why it failed (the LS table is then the result).
    pub em: Result<EmDetail, calib_core::CalibError>,
    /// The resulting table: the EM's; the LS's when the EM failed or its table disagrees with
    /// LS's ([`Calibration::ls_kept`]).
    pub calibrated: DhTable<MAX_JOINTS>,
    /// The expected table error (1σ) of `calibrated` to state: the EM's stated error; where
    /// LS's table was kept for disagreeing, LS's expected error under the drift the EM fitted;
    /// where the EM failed, what LS alone is worth with white residuals (calib-core's
    /// `ls_white_expected_error`): a session always has one unless LS's normal equations are
    /// too ill-conditioned to say.
    pub stated: Option<TableError>,
    /// Strongest parameter correlations at the calibrated table, strongest first.
    pub correlations: Vec<Correlation>,
}

impl Calibration {
    /// Whether LS's table is the result because the EM's disagrees with it beyond LS's own
    /// error (calib-core's `EmVersusLs::agrees`): the EM's model does not hold for the session.
    pub fn ls_kept(&self) -> bool {
        self.em.as_ref().is_ok_and(EmDetail::ls_kept)
    }
}

/// One data stream (a node) of the session.
#[derive(Debug, Clone, PartialEq)]
pub struct StreamQuality {
    /// `Joint1`…`Joint7`, `EndEffector`, or a CSV column group.
    pub name: String,
    /// Samples in the stream.
    pub samples: usize,
    /// Mean sample rate (Hz) over the stream's span.
    pub rate_hz: f64,
    /// Estimated fraction of samples lost (from the median sample interval), if known.
    pub loss: Option<f64>,
    /// Samples the alignment could not map to host time (excluded).
    pub excluded: usize,
    /// The node's own clock jumps or reboots detected.
    pub jumps: usize,
    /// Node clock skew against the host (ppm), if fitted.
    pub skew_ppm: Option<f64>,
    /// RMS residual of the clock fit (µs), if fitted.
    pub jitter_us: Option<f64>,
}

/// Data-quality summary of a session.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Quality {
    /// Session length (s).
    pub duration_s: f64,
    /// Rate of the common grid (Hz); for CSV the file's own mean rate.
    pub grid_hz: f64,
    /// Grid points excluded as gaps.
    pub gaps: usize,
    /// Frame counters, in display order (`("received", n)`, `("unknown", n)`, …); empty for CSV.
    pub counters: Vec<(String, u64)>,
    /// Every data stream, in display order.
    pub streams: Vec<StreamQuality>,
    /// Anatomical range of each joint (rad), for the excitation figures.
    pub joint_ranges: Vec<(f64, f64)>,
    /// The excitation the session rules require (fraction of each range), if any.
    pub excitation_required: Option<f64>,
    /// Times the receiver stalled (every node's frames late together; not counted as any
    /// stream's clock jumps), and the longest stall's lateness (ms).
    pub receiver_stalls: usize,
    /// The longest receiver stall's lateness (ms), if there was one.
    pub longest_stall_ms: Option<f64>,
}
