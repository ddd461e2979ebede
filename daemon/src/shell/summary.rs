//! What a session did ([`SessionSummary`], or [`SessionError`] when it failed) and how it goes
//! to stdout: what the user reads after a session (log path, frames, clocks, expected table
//! error, push), one line per fact, and last the verdict ([`verdict`]); or only the verdict
//! (`--quiet`), or one JSON object (`--json`, [`json`]). Used by every subcommand that runs a
//! session and by the serve loop; it imports nothing of theirs.

use std::path::PathBuf;
use std::time::Duration;

use serde::Serialize;

use exocal_session::collect::Collected;
use exocal_session::gate::GateStats;
use exocal_session::ingest::{ClockReport, FrameStats, StallReport};
use exocal_session::pipeline::Outcome;

use crate::exit::DaemonError;
use crate::push::PushReport;

/// What a session did (also when it failed: see [`SessionError`]).
#[derive(Debug, Clone, Serialize)]
pub struct SessionSummary {
    /// The session log (for an offline run, the input).
    pub log_path: PathBuf,
    /// Messages written to the log, per topic: `(topic, count)`.
    pub log_counts: Vec<(String, u64)>,
    /// Frames received in the collection window: those the calibration used (frames that
    /// arrive while calibrating and pushing are not counted), as an offline replay of the log
    /// counts them.
    pub frames: FrameStats,
    /// One report per node clock (joints, then the end effector).
    pub clocks: Vec<ClockReport>,
    /// Receiver stalls (not counted in any node's clock jumps).
    pub stalls: StallReport,
    /// Samples on the common grid.
    pub aligned_samples: usize,
    /// Grid points excluded as gaps.
    pub gaps: usize,
    /// The calibration; `None` when none was computed.
    pub outcome: Option<Outcome>,
    /// The push, per node; `None` when nothing was pushed.
    pub push: Option<PushReport>,
    /// The HTML calibration report, once written (next to the log for a live session).
    pub report_path: Option<PathBuf>,
    /// Stream verification: spans verified and dropped; `None` when the streams were not
    /// authenticated (`[push] authenticate = false`, or an offline replay).
    pub stream: Option<GateStats>,
    /// What the user waited after the collection window, when every node's table was verified.
    pub latency: Option<Latency>,
}

/// The power-up latency: from the end of the collection window until every node's table was
/// verified (CRC read back) — alignment, calibration, validation, report and push.
///
/// `real` is this machine's monotonic clock over that span; `session` the session clock's. On
/// the wall clock (SocketCAN) the two agree and the latency is `real`. On simulated time (the
/// demo) the session clock stands still while the daemon computes and the real clock hardly
/// moves while the emulated bus and nodes answer, so the latency a suit on a real bus would see
/// is their sum: this machine's computing plus the bus's and the nodes' time as emulated.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Latency {
    /// This machine's monotonic clock from the end of the window to the last verified table.
    pub real: Duration,
    /// The session clock over the same span.
    pub session: Duration,
    /// Whether the session clock was simulated.
    pub simulated: bool,
}

impl Latency {
    /// The latency a user waits: see [`Latency`].
    pub fn total(&self) -> Duration {
        if self.simulated {
            self.real + self.session
        } else {
            self.real
        }
    }
}

impl SessionSummary {
    /// The summary of a session logged to `log_path` (or replayed from it) that did nothing yet.
    pub fn new(log_path: PathBuf) -> SessionSummary {
        SessionSummary {
            log_path,
            log_counts: Vec::new(),
            frames: FrameStats::default(),
            clocks: Vec::new(),
            stalls: StallReport::default(),
            aligned_samples: 0,
            gaps: 0,
            outcome: None,
            push: None,
            report_path: None,
            latency: None,
            stream: None,
        }
    }

    /// Records what the session collected.
    pub fn collected(&mut self, c: &Collected) {
        self.frames = c.frames.clone();
        self.clocks = c.clocks.clone();
        self.stalls = c.stalls;
        self.aligned_samples = c.samples.len();
        self.gaps = c.gaps;
    }
}

/// A failed session: why, and what it did up to then (the log is finished).
#[derive(Debug)]
pub struct SessionError {
    /// Why the session failed.
    pub error: DaemonError,
    /// What it did up to then; `None` when it failed before it started.
    pub summary: Option<SessionSummary>,
}

impl From<DaemonError> for SessionError {
    fn from(error: DaemonError) -> Self {
        SessionError {
            error,
            summary: None,
        }
    }
}

impl From<DaemonError> for Box<SessionError> {
    fn from(error: DaemonError) -> Self {
        Box::new(SessionError::from(error))
    }
}

/// How a session's result goes to stdout.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Output {
    /// The summary, one line per fact, then the verdict.
    #[default]
    Text,
    /// The verdict line only.
    Quiet,
    /// One JSON object ([`json`]).
    Json,
}

impl Output {
    /// From the `--quiet` and `--json` flags (clap keeps them apart).
    pub fn from_flags(quiet: bool, json: bool) -> Output {
        match (quiet, json) {
            (_, true) => Output::Json,
            (true, false) => Output::Quiet,
            (false, false) => Output::Text,
        }
    }
}

/// Prints a session's result as `output` says: with [`Output::Text`] the summary, then `extra`
/// lines (the demo's flash check), then the verdict; `error` is how the run ends, if it fails.
pub fn print_result(
    summary: Option<&SessionSummary>,
    error: Option<&DaemonError>,
    extra: &[String],
    output: Output,
) {
    match output {
        Output::Text => {
            if let Some(s) = summary {
                print_summary(s);
            }
            for line in extra {
                println!("{line}");
            }
            println!("{}", verdict(summary, error));
        }
        Output::Quiet => println!("{}", verdict(summary, error)),
        Output::Json => println!("{}", json(summary, error)),
    }
}

/// How a session ended, classified once for the verdict line and for `--json`.
enum Ending<'a> {
    /// Validated, and every node holds the new table.
    Pushed,
    /// Validated, nothing pushed (offline, or `--dry-run`).
    Validated,
    /// Refused, for these reasons.
    Refused(&'a [exocal_session::validate::Refusal]),
    /// Validated and pushed to every node, then this went wrong.
    PushedBut(&'a DaemonError),
    /// Validated, but not every node took the table.
    PartlyPushed(&'a DaemonError),
    /// Nothing pushed, because of this.
    Failed(&'a DaemonError),
    /// No error and nothing to push.
    Nothing,
}

impl<'a> Ending<'a> {
    fn of(summary: Option<&'a SessionSummary>, error: Option<&'a DaemonError>) -> Ending<'a> {
        let outcome = summary.and_then(|s| s.outcome.as_ref());
        let push = summary.and_then(|s| s.push.as_ref());
        match (error, outcome, push) {
            (None, Some(_), Some(p)) if p.complete() => Ending::Pushed,
            (None, Some(o), None) if o.verdict.accepted() => Ending::Validated,
            (_, Some(o), _) if !o.verdict.accepted() => Ending::Refused(&o.verdict.reasons),
            (Some(e), Some(_), Some(p)) if p.complete() => Ending::PushedBut(e),
            (Some(e), Some(_), Some(_)) => Ending::PartlyPushed(e),
            (Some(e), _, _) => Ending::Failed(e),
            (None, _, _) => Ending::Nothing,
        }
    }

    /// `--json`'s `verdict`.
    fn kind(&self) -> &'static str {
        match self {
            Ending::Pushed => "pushed",
            Ending::Validated => "validated",
            Ending::Refused(_) => "refused",
            _ => "failed",
        }
    }
}

/// The last line: validated and pushed, or refused and why, with the expected table error.
pub fn verdict(summary: Option<&SessionSummary>, error: Option<&DaemonError>) -> String {
    let expected = summary
        .and_then(|s| s.outcome.as_ref())
        .and_then(|o| o.verdict.expected)
        .map(|e| format!("; expected table error {e}"))
        .unwrap_or_default();
    match Ending::of(summary, error) {
        Ending::Pushed => {
            format!("verdict: validated and pushed, every node holds the new table{expected}")
        }
        Ending::Validated => {
            format!("verdict: validated; nothing pushed (offline, or --dry-run){expected}")
        }
        Ending::Refused(reasons) => {
            let reasons: Vec<String> = reasons.iter().map(ToString::to_string).collect();
            format!("verdict: refused, nothing pushed: {}", reasons.join("; "))
        }
        Ending::PushedBut(e) => format!("verdict: validated and pushed, but {e}{expected}"),
        Ending::PartlyPushed(e) => {
            format!("verdict: validated, but not every node took the table: {e}{expected}")
        }
        Ending::Failed(e) => format!("verdict: nothing pushed: {e}"),
        Ending::Nothing => "verdict: nothing to push".into(),
    }
}

/// The result for scripts (`--json`): `verdict` (`pushed`, `validated`, `refused` or
/// `failed`) and its line, `exit` (the status the process ends with), `error`, `log`,
/// `report`, `expected_error` (1σ, mm and mrad), `heldout` (mean error of the nominal and the
/// judged table on the held-out slice, mm and mrad), `condition_number`, `refusals`, `table`
/// (the calibrated rows in SI units: m, rad, s, rad/s), `gyro_at_rest` (what the gyros read
/// while still, where joints are unaided) and `push` (per node: what it holds, the CRCs sent
/// and held, attempts, error). Absent parts are null.
pub fn json(summary: Option<&SessionSummary>, error: Option<&DaemonError>) -> serde_json::Value {
    let outcome = summary.and_then(|s| s.outcome.as_ref());
    let push = summary.and_then(|s| s.push.as_ref());
    let kind = Ending::of(summary, error).kind();
    let v = outcome.map(|o| &o.verdict);
    serde_json::json!({
        "verdict": kind,
        "line": verdict(summary, error),
        "exit": error.map_or(0, DaemonError::exit_code),
        "error": error.map(ToString::to_string),
        "log": summary.map(|s| s.log_path.display().to_string()),
        "report": summary.and_then(|s| s.report_path.as_ref()).map(|p| p.display().to_string()),
        "expected_error": v.and_then(|v| v.expected).map(|e| serde_json::json!({
            "position_mm": e.position_mm,
            "rotation_mrad": e.rotation_mrad,
        })),
        "heldout": v.map(|v| serde_json::json!({
            "samples": v.heldout_samples,
            "nominal": {
                "position_mm": v.nominal.mean_position_m * 1e3,
                "rotation_mrad": v.nominal.mean_rotation_rad * 1e3,
            },
            "calibrated": {
                "position_mm": v.candidate.mean_position_m * 1e3,
                "rotation_mrad": v.candidate.mean_rotation_rad * 1e3,
            },
        })),
        "condition_number": v.map(|v| v.condition_number),
        "refusals": v.map(|v| v.reasons.iter().map(ToString::to_string).collect::<Vec<_>>()),
        "table": outcome.map(|o| &o.node_rows),
        "gyro_at_rest": outcome.and_then(|o| o.at_rest.as_ref()),
        "push": push.map(|p| &p.nodes),
    })
}

/// The joint nodes that sent angles without being on the configured arm, in a line (`None`
/// when none did): a configuration of fewer joints than the suit, or a recording of another arm.
pub fn off_arm_line(f: &FrameStats) -> Option<String> {
    let nodes: Vec<String> = (f.off_arm.iter().enumerate())
        .filter(|&(_, &n)| n > 0)
        .filter_map(|(id, &n)| {
            let node = exocal_dbc::NodeId::new(u8::try_from(id).ok()?)?;
            Some(format!("{node} ({n} frames)"))
        })
        .collect();
    (!nodes.is_empty()).then(|| {
        format!(
            "warning: joint angles from nodes not on the configured arm, not calibrated on: {} \
             (is [nodes] joints this suit's?)",
            nodes.join(", ")
        )
    })
}

/// Prints what a session did, to stdout (one line per fact).
pub fn print_summary(summary: &SessionSummary) {
    println!("log: {}", summary.log_path.display());
    let f = &summary.frames;
    println!(
        "frames: {} received, {} unknown, {} malformed, {} invalid angles",
        f.received, f.unknown, f.malformed, f.invalid_angles
    );
    if let Some(line) = off_arm_line(f) {
        println!("{line}");
    }
    if let Some(g) = &summary.stream {
        println!(
            "streams: {} spans verified ({} frames), {} dropped unverified ({} frames, {:.1} s), \
             {} frames from before the nonce{}",
            g.verified_spans,
            g.verified_frames,
            g.dropped_spans,
            g.dropped_frames,
            g.dropped_s,
            g.start_frames,
            g.second_senders()
                .map(|(n, c)| format!("; a second sender on {n}'s identifiers ({c} spans)"))
                .chain((g.foreign_nonces > 0).then(|| format!(
                    "; {} StreamNonce frames from another sender on the bus (forged or replayed)",
                    g.foreign_nonces
                )))
                .chain((g.empty_rejects > 0).then(|| format!(
                    "; {} digests over no frames that did not verify (forged, or a keyless node)",
                    g.empty_rejects
                )))
                .chain((g.reboots > 0).then(|| format!(
                    "; {} new boot counts in heartbeats (reboots, or spoofed)",
                    g.reboots
                )))
                .collect::<String>()
        );
    }
    println!(
        "aligned samples: {} ({} grid points excluded as gaps)",
        summary.aligned_samples, summary.gaps
    );
    if summary.stalls.count > 0 {
        println!("clocks: {}", summary.stalls);
    }
    for c in &summary.clocks {
        println!(
            "clock {}: skew {} ppm, {} jump(s), {} samples excluded",
            c.node,
            c.skew_ppm
                .map_or_else(|| "?".into(), |s| format!("{s:+.1}")),
            c.jumps,
            c.unmapped
        );
    }
    if let Some(o) = &summary.outcome {
        let v = &o.verdict;
        if let Some(e) = v.expected {
            println!("expected table error: {e}");
        }
        if o.reading_drift_rms.iter().any(|&r| r > 0.0) {
            let mrad: Vec<String> = o
                .reading_drift_rms
                .iter()
                .map(|r| format!("{:.2}", r * 1e3))
                .collect();
            println!(
                "rough drift taken out of the readings, RMS per joint: {} mrad",
                mrad.join(" ")
            );
        }
        if let Some(r) = &o.at_rest {
            println!("gyro at rest: {r}");
        }
        if let Some(em) = &o.em {
            if let Some(drift) = &em.drift_95 {
                for (j, d) in drift.iter().enumerate() {
                    println!("drift joint {}: {d} (95%)", j + 1);
                }
            }
            let models: Vec<String> = em.models.iter().map(ToString::to_string).collect();
            if models.windows(2).all(|w| w[0] == w[1]) && !models.is_empty() {
                println!("drift model, every joint: {}", models[0]);
            } else {
                for (j, m) in models.iter().enumerate() {
                    println!("drift model joint {}: {m}", j + 1);
                }
            }
            if let Some(line) = rate_bias_line(em) {
                println!("{line}");
            }
            println!("{}", discounted_line(em));
            if let Some(line) = ls_kept_line(em) {
                println!("{line}");
            }
        }
        let removed = if v.nominal.mean_position_m > 0.0 {
            (1.0 - v.candidate.mean_position_m / v.nominal.mean_position_m) * 100.0
        } else {
            0.0
        };
        println!(
            "held-out mean error, nominal → calibrated: position {:.2} → {:.2} mm ({removed:.0}% \
             removed), rotation {:.1} → {:.1} mrad",
            v.nominal.mean_position_m * 1e3,
            v.candidate.mean_position_m * 1e3,
            v.nominal.mean_rotation_rad * 1e3,
            v.candidate.mean_rotation_rad * 1e3
        );
        println!("condition number: {:.1}", v.condition_number);
        for moved in &o.onto_bounds {
            println!("{}", moved.line());
        }
        for reason in &v.reasons {
            println!("refused: {reason}");
        }
    }
    if let Some(p) = &summary.push {
        for line in p.lines() {
            println!("push {line}");
        }
    }
    if let Some(l) = &summary.latency {
        if l.simulated {
            println!(
                "end of collection to every table verified: {:.3} s ({:.3} s computing on this \
                 machine + {:.3} s of emulated bus and nodes)",
                l.total().as_secs_f64(),
                l.real.as_secs_f64(),
                l.session.as_secs_f64()
            );
        } else {
            println!(
                "end of collection to every table verified: {:.3} s",
                l.total().as_secs_f64()
            );
        }
    }
    if let Some(r) = &summary.report_path {
        println!("report: {}", r.display());
    }
}

/// Prints a session result as `output` says ([`print_result`]) and returns its error.
pub fn finish(
    result: Result<SessionSummary, SessionError>,
    output: Output,
) -> Result<(), DaemonError> {
    match result {
        Ok(summary) => {
            print_result(Some(&summary), None, &[], output);
            Ok(())
        }
        Err(SessionError { error, summary }) => {
            print_result(summary.as_ref(), Some(&error), &[], output);
            Err(error)
        }
    }
}

/// Without the sensors' spec: what a rate bias too small for the session to show
/// would add to the table error, or that the data chose the rate bias themselves. `None` when
/// the spec is configured.
pub fn rate_bias_line(em: &exocal_session::pipeline::EmSummary) -> Option<String> {
    if em.models.iter().any(|m| m.by_spec) {
        return None;
    }
    Some(match &em.unmodelled_rate_bias {
        Some(u) => format!(
            "sensors' rate bias: not configured ([sensors]): one of {} °/s, too small for this \
             session to show, would add ±{:.2} mm, ±{:.2} mrad (1σ) to the table error; set it \
             from the IMUs' spec",
            u.rate_deg_s, u.position_mm, u.rotation_mrad
        ),
        None => {
            "sensors' rate bias: not configured ([sensors]); this session's data chose it (drift \
                 models above)"
                .to_string()
        }
    })
}

/// Where LS's table is the result because the EM's disagrees with it beyond LS's own error
/// (the EM's drift model does not hold for the session); `None` where they agree.
pub fn ls_kept_line(em: &exocal_session::pipeline::EmSummary) -> Option<String> {
    let v = em.versus_ls.filter(|v| v.ls_kept)?;
    Some(format!(
        "our EM's table disagrees with LS's: they differ by {:.2} mm, {:.2} mrad where LS alone \
         is expected within ±{:.2} mm, ±{:.2} mrad (statistic {:.1} > {}): the EM's drift model \
         does not hold for this session, so LS's table is the result, stated by LS's own \
         expected error",
        v.difference_mm,
        v.difference_mrad,
        v.ls_expected_mm,
        v.ls_expected_mrad,
        v.statistic,
        calib_core::MAX_EM_LS_STATISTIC
    ))
}

/// The reference samples the EM discounted as glitches, and when: `reference glitches
/// discounted: none`, or `… 12 samples at 3.10–3.14 s, 17.20 s`.
pub fn discounted_line(em: &exocal_session::pipeline::EmSummary) -> String {
    if em.discounted == 0 {
        return "reference glitches discounted: none".to_string();
    }
    let at: Vec<String> = em
        .discounted_s
        .iter()
        .map(|&[a, b]| {
            if a == b {
                format!("{a:.2} s")
            } else {
                format!("{a:.2}–{b:.2} s")
            }
        })
        .collect();
    let more = if at.len() < em.discounted
        && em.discounted_s.len() >= calib_core::drift_em::MAX_DISCOUNTED_RUNS
    {
        ", …"
    } else {
        ""
    };
    format!(
        "reference glitches discounted: {} sample(s) at {}{more}",
        em.discounted,
        at.join(", ")
    )
}
