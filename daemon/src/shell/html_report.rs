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
use exocal_session::{Settings, MAX_JOINTS};

use exocal_log::write::Level;

use crate::config::Config;

/// The report next to a session log: same folder and stem, extension `html`.
pub fn report_path_for_log(log: &Path) -> PathBuf {
    log.with_extension("html")
}

/// A live session's report file, next to its log ([`report_path_for_log`]): its titles, its
/// writes, and the calibration report kept to be rewritten with the push. A report that cannot
/// be written is a warning in the session, never a reason to withhold a validated table.
pub struct ReportFile {
    log: PathBuf,
    /// The source line: the interface, the start, the log and the configuration.
    source: String,
    /// The calibration report as written before the push ([`ReportFile::with_push`]).
    before_push: Option<String>,
    /// The report, once written.
    pub path: Option<PathBuf>,
}

impl ReportFile {
    /// The report of the live session logged to `log`, started at bus time `start`.
    pub fn new(log: &Path, start: Duration, config: &Config) -> ReportFile {
        let source = format!(
            "live session on {}, started {}, logged to {}; {}",
            config.interface,
            exocal_log::write::utc_time(crate::log::records::ns(start)),
            log.display(),
            config_line(&config.calibration)
        );
        ReportFile {
            log: log.to_path_buf(),
            source,
            before_push: None,
            path: None,
        }
    }

    /// The title (`what`: "calibration" or "session") and source line.
    pub fn titles(&self, what: &str) -> (String, String) {
        let name = (self.log.file_name()).map_or_else(String::new, |n| n.to_string_lossy().into());
        (format!("exocald {what} — {name}"), self.source.clone())
    }

    /// Writes `html` (`what` the report is) next to the log; the line to log.
    pub fn write(&mut self, html: &str, what: &str) -> (Level, String) {
        let path = report_path_for_log(&self.log);
        match std::fs::write(&path, html) {
            Ok(()) => {
                let line = format!("{what}: {}", path.display());
                self.path = Some(path);
                (Level::Info, line)
            }
            Err(e) => {
                let line = format!("cannot write the report {}: {e}", path.display());
                (Level::Warning, line)
            }
        }
    }

    /// Writes the calibration report `html` and keeps it for [`ReportFile::with_push`].
    pub fn write_calibration(&mut self, html: String) -> (Level, String) {
        let line = self.write(&html, "calibration report");
        self.before_push = Some(html);
        line
    }

    /// Once pushed (completely or not), the calibration report with the push's outcome per
    /// node: its banner replaced and the push table added (`exocal_report::html::with_push`:
    /// string work, no plot re-rendered, so it costs the slowest controller nothing). `None`
    /// when there is nothing to rewrite; a report that cannot be written leaves the first.
    pub fn with_push(&mut self, push: &[exocal_report::NodePush]) -> Option<(Level, String)> {
        let html = exocal_report::html::with_push(&self.before_push.take()?, push)?;
        Some(self.write(&html, "calibration report, with the push"))
    }
}

/// The report of a session stopped `seconds` into its collection: when and with how many
/// frames (`stats`), and that the log has them. Rendered without aligning what was collected: a
/// stop is given seconds (the unit's `TimeoutStopSec`), which aligning a long collection on a
/// slow controller could exceed; `exocald offline` on the log shows the rest. Its excitation
/// figure has a bar per joint of the arm of `settings`.
pub fn interrupted(
    title: String,
    source: String,
    stats: &FrameStats,
    seconds: f64,
    settings: &Settings,
) -> String {
    let reasons = vec![format!(
        "stopped {seconds:.1} s into the collection, with {} frames received ({} decoded)",
        stats.received, stats.decoded
    )];
    let quality = Quality {
        joint_ranges: settings.bounds.joint_range.limits[..settings.joints.min(MAX_JOINTS)]
            .to_vec(),
        ..Quality::default()
    };
    let mut input = session_input(title, source, &[], reasons, quality);
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
        at_rest: calibrated.outcome.at_rest.clone(),
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_report_file_sits_beside_its_log_and_a_failed_write_is_a_warning() {
        let dir = std::env::temp_dir().join(format!("exocal-report-file-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let log = dir.join("exocal-20261129T100000Z.mcap");
        let config = Config::default_config();
        let mut file = ReportFile::new(&log, Duration::from_secs(1_764_410_400), &config);
        let (title, source) = file.titles("session");
        assert_eq!(title, "exocald session — exocal-20261129T100000Z.mcap");
        assert!(source.starts_with("live session on "), "{source}");
        assert!(source.contains("started 2025-11-29"), "{source}");
        assert!(
            file.with_push(&[]).is_none(),
            "no calibration report to rewrite"
        );
        let (level, line) = file.write_calibration("<html>".into());
        assert_eq!(level, Level::Info);
        assert!(line.starts_with("calibration report: "), "{line}");
        let written = dir.join("exocal-20261129T100000Z.html");
        assert_eq!(file.path.as_deref(), Some(written.as_path()));
        assert_eq!(std::fs::read_to_string(&written).unwrap(), "<html>");
        // A page without the report's push marks is left as it was.
        assert!(file.with_push(&[]).is_none());
        let mut lost = ReportFile::new(&dir.join("gone/x.mcap"), Duration::ZERO, &config);
        let (level, line) = lost.write("<html>", "session report");
        assert_eq!(level, Level::Warning);
        assert!(line.starts_with("cannot write the report "), "{line}");
        assert!(lost.path.is_none());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
