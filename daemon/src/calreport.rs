//! The HTML calibration report of a session, for live and offline runs alike.
//!
//! Contract:
//! - [`report_input`] turns what the daemon computed — the samples the calibration ran on, its
//!   [`Outcome`] and the detail from [`crate::calibrate::run_detailed`] — into an
//!   [`exocal_report::ReportInput`]; the fit/held-out split is the one the calibration used
//!   (`validation.holdout_fraction`), so the figures show exactly the calibrated data;
//! - [`frame_quality`] fills the data-quality part from ingest's counters, clock reports and
//!   stream rates (frame-level inputs: a live bus, an MCAP or candump log); [`sample_quality`]
//!   from plain samples (CSV, no frames, no clocks);
//! - a live session writes its report next to its MCAP log ([`report_path_for_log`]:
//!   `exocal-….mcap` → `exocal-….html`); a report that cannot be written is a warning in the
//!   session, never a reason to withhold a validated table.

use std::path::{Path, PathBuf};

use exocal_report::{
    Calibration, Quality, ReportInput, SessionInput, StreamQuality, TimedSample, VerdictSummary,
};

use crate::align::AlignedSample;
use crate::calibrate::{to_sample, Outcome};
use crate::config::Config;
use crate::ingest::{ClockReport, FrameStats, StallReport};
use crate::validate::{split_holdout, table_from_rows};

/// The report next to a session log: same folder and stem, extension `html`.
pub fn report_path_for_log(log: &Path) -> PathBuf {
    log.with_extension("html")
}

/// Samples with their time, as the report takes them.
pub fn timed(samples: &[AlignedSample]) -> Vec<TimedSample> {
    samples
        .iter()
        .map(|s| TimedSample {
            t: s.t,
            sample: to_sample(s),
        })
        .collect()
}

/// The report of a calibration of `samples` (see the module docs).
pub fn report_input(
    title: String,
    source: String,
    config: &Config,
    samples: &[AlignedSample],
    outcome: &Outcome,
    detail: Calibration,
    quality: Quality,
) -> ReportInput {
    let all = timed(samples);
    let (fit, held) = split_holdout(&all, config.validation.holdout_fraction);
    ReportInput {
        title,
        source,
        nominal: table_from_rows(&config.nominal),
        calibration: detail,
        fit: fit.to_vec(),
        held_out: held.to_vec(),
        quality,
        verdict: Some(VerdictSummary {
            accepted: outcome.verdict.accepted(),
            reasons: outcome.verdict.reasons.clone(),
        }),
    }
}

fn ranges(config: &Config) -> [(f64, f64); crate::config::JOINTS] {
    config.bounds.joint_range.map(|r| (r.min, r.max))
}

fn duration(samples: &[AlignedSample]) -> f64 {
    match (samples.first(), samples.last()) {
        (Some(a), Some(b)) => b.t - a.t,
        _ => 0.0,
    }
}

/// Data quality of a frame-level session: counters, per-node rate, loss and clock, alignment.
/// `rates` is [`crate::ingest::Ingest::stream_rates`], in the order of `clocks` (joints, then
/// the end effector).
pub fn frame_quality(
    config: &Config,
    stats: &FrameStats,
    clocks: &[ClockReport],
    stalls: StallReport,
    rates: &[(Option<f64>, Option<f64>)],
    samples: &[AlignedSample],
    gaps: usize,
) -> Quality {
    let counters = [
        ("received", stats.received),
        ("decoded", stats.decoded),
        ("unknown", stats.unknown),
        ("malformed", stats.malformed),
        ("invalid angles", stats.invalid_angles),
        ("bad poses", stats.bad_poses),
        ("poses", stats.poses),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), v))
    .collect();
    let streams = clocks
        .iter()
        .zip(rates.iter().chain(std::iter::repeat(&(None, None))))
        .map(|(c, &(rate, loss))| StreamQuality {
            name: c.node.clone(),
            samples: c.samples,
            rate_hz: rate.unwrap_or(0.0),
            loss,
            excluded: c.unmapped,
            jumps: c.jumps,
            skew_ppm: c.skew_ppm,
            jitter_us: c.residual_rms_us,
        })
        .collect();
    Quality {
        duration_s: duration(samples),
        grid_hz: config.session.grid_hz,
        gaps,
        counters,
        streams,
        joint_ranges: ranges(config),
        excitation_required: Some(config.session.excitation_required),
        receiver_stalls: stalls.count,
        longest_stall_ms: stalls.longest_ms,
    }
}

/// Data quality of plain samples (CSV): span, the grid rate they were calibrated at, no
/// frame counters or clocks.
pub fn sample_quality(config: &Config, samples: &[AlignedSample]) -> Quality {
    let span = duration(samples);
    let rate = if span > 0.0 {
        (samples.len() - 1) as f64 / span
    } else {
        0.0
    };
    Quality {
        duration_s: span,
        grid_hz: config.session.grid_hz,
        gaps: 0,
        counters: Vec::new(),
        streams: vec![StreamQuality {
            name: "CSV samples".into(),
            samples: samples.len(),
            rate_hz: rate,
            loss: None,
            excluded: 0,
            jumps: 0,
            skew_ppm: None,
            jitter_us: None,
        }],
        joint_ranges: ranges(config),
        excitation_required: Some(config.session.excitation_required),
        receiver_stalls: 0,
        longest_stall_ms: None,
    }
}

/// Renders `input` and writes it to `path`.
pub fn write(path: &Path, input: &ReportInput) -> std::io::Result<()> {
    std::fs::write(path, exocal_report::html::render(input))
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
        samples: timed(samples),
        quality,
    }
}
