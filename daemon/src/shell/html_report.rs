//! The HTML calibration report of a session, for live and offline runs alike.
//!
//! Contract:
//! - [`report_input`] turns what the pipeline computed ([`Calibrated`]: the samples, the split,
//!   the summary and the detail) into an [`exocal_report::ReportInput`]: the report shows
//!   exactly the data and the split the calibration used, and computes no calibration itself;
//! - [`render`] renders a session's report: its calibration's, or why there is none; the
//!   data-quality part comes with what was collected ([`Collected::quality`]);
//! - a live session writes its report next to its MCAP log ([`report_path_for_log`]:
//!   `exocal-….mcap` → `exocal-….html`); a report that cannot be written is a warning in the
//!   session, never a reason to withhold a validated table.

use std::path::{Path, PathBuf};
use std::time::Duration;

use exocal_report::{Quality, ReportInput, SessionInput, VerdictSummary};

use exocal_session::align::AlignedSample;
use exocal_session::collect::Collected;
use exocal_session::ingest::FrameStats;
use exocal_session::pipeline::{timed, Calibrated};
use exocal_session::Settings;

use crate::config::Config;

/// The report next to a session log: same folder and stem, extension `html`.
pub fn report_path_for_log(log: &Path) -> PathBuf {
    log.with_extension("html")
}

/// Writes a session's report `html` next to its log (see [`report_path_for_log`]); the error
/// names the file and why.
pub fn write_next_to(log: &Path, html: &str) -> Result<PathBuf, String> {
    let path = report_path_for_log(log);
    match std::fs::write(&path, html) {
        Ok(()) => Ok(path),
        Err(e) => Err(format!("cannot write the report {}: {e}", path.display())),
    }
}

/// The title and source line of a live session's report (`what`: "calibration" or "session"):
/// its log, its interface, its start (`start`: bus time) and its configuration.
pub fn live_titles(what: &str, log: &Path, start: Duration, config: &Config) -> (String, String) {
    let name = log
        .file_name()
        .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
    let started = exocal_log::write::utc_time(start.as_nanos().min(u128::from(u64::MAX)) as u64);
    (
        format!("exocald {what} — {name}"),
        format!(
            "live session on {}, started {started}, logged to {}; {}",
            config.interface,
            log.display(),
            config_line(&config.calibration)
        ),
    )
}

/// The report of a session stopped `seconds` into its collection: when and with how many
/// frames (`stats`), and that the log has them. Rendered without aligning what was collected: a
/// stop is given seconds (the unit's `TimeoutStopSec`), which aligning a long collection on a
/// slow controller could exceed; `exocald offline` on the log shows the rest.
pub fn interrupted(title: String, source: String, stats: &FrameStats, seconds: f64) -> String {
    let reasons = vec![format!(
        "stopped {seconds:.1} s into the collection, with {} frames received ({} decoded)",
        stats.received, stats.decoded
    )];
    let mut input = session_input(title, source, &[], reasons, Quality::default());
    input.interrupted = true;
    exocal_report::html::render_session(&input)
}

/// The configuration a report was made under, in a line: the window, its stop target, the
/// limits a pushed table must meet, the unaided joints.
pub fn config_line(c: &exocal_session::Settings) -> String {
    let w = &c.window;
    let v = &c.validation;
    let mut line = format!(
        "configured: window {}–{} s on a {} Hz grid",
        w.min_duration_s, w.max_duration_s, w.grid_hz
    );
    if let Some((mm, mrad)) = w.stop_at_expected_error {
        line += &format!(", stops within ±{mm} mm, ±{mrad} mrad");
    }
    line += &format!(
        ", pushes within ±{} mm, ±{} mrad and condition number {}",
        v.max_expected_position_error_mm,
        v.max_expected_rotation_error_mrad,
        v.max_condition_number
    );
    let unaided = exocal_session::rules::joint_list(&c.sensors.unaided);
    if !unaided.is_empty() {
        line += &format!(", unaided joints {unaided}");
    }
    line
}

/// The report of a calibration (see the module docs).
pub fn report_input(
    title: String,
    source: String,
    settings: &Settings,
    calibrated: &Calibrated,
    quality: Quality,
    push: Option<Vec<exocal_report::NodePush>>,
) -> ReportInput {
    let verdict = &calibrated.outcome.verdict;
    ReportInput {
        title,
        source,
        nominal: settings.nominal,
        calibration: calibrated.detail.clone(),
        judged: Some(calibrated.judged),
        fit: calibrated.fit().to_vec(),
        held_out: calibrated.held_out().to_vec(),
        quality,
        verdict: Some(VerdictSummary {
            accepted: verdict.accepted(),
            reasons: verdict.reasons.iter().map(ToString::to_string).collect(),
            onto_bounds: (calibrated.outcome.onto_bounds.iter())
                .map(ToString::to_string)
                .collect(),
        }),
        at_rest: calibrated.outcome.at_rest,
        push,
    }
}

/// The HTML report of a session, live or offline: its calibration's when there is one (`Ok`),
/// else (`Err`: why not, one line per reason) what the session had.
pub fn render(
    title: String,
    source: String,
    settings: &Settings,
    collected: &Collected,
    calibrated: Result<&Calibrated, &[String]>,
) -> String {
    let quality = collected.quality.clone();
    match calibrated {
        Ok(c) => {
            exocal_report::html::render(&report_input(title, source, settings, c, quality, None))
        }
        Err(why) => {
            let input = session_input(title, source, &collected.samples, why.to_vec(), quality);
            exocal_report::html::render_session(&input)
        }
    }
}

/// The report of a session that was not calibrated (`reasons`: the session rules it did not
/// meet), with the data it had.
pub fn session_input(
    title: String,
    source: String,
    samples: &[AlignedSample],
    reasons: Vec<String>,
    quality: Quality,
) -> SessionInput {
    SessionInput {
        title,
        source,
        reasons,
        interrupted: false,
        samples: timed(samples),
        quality,
    }
}
