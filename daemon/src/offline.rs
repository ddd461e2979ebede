//! `exocald offline`: recalibration from a recorded session, without a bus.
//!
//! Contract:
//! - frame-level inputs — the daemon's MCAP session log (`/can/rx`) or a `candump -L` log — are
//!   replayed frame by frame, in file order and with their recorded receive times, through the
//!   daemon's own [`Ingest::on_frame`], aligned by [`crate::runner::align_session`] and
//!   calibrated by [`crate::calibrate::run_detailed`]: the live session's code path, minus the
//!   bus. The same frames give the same table, bit for bit;
//! - an MCAP log is replayed up to the end of its collection window: the live session logs
//!   `collection done: N frames` when it stops collecting, and calibrated on exactly the first
//!   `N` received frames ([`exocal_report::McapSession::collection_frames`]); a log without
//!   the marker (a session that never finished collecting) is replayed whole. A candump log is
//!   replayed whole: `--export-candump` writes exactly the frames the calibration used, so it
//!   replays to the same result;
//! - CSV samples (`t,q1,…,q7,x,y,z,qw,qx,qy,qz`, see [`exocal_report::readers`]) bypass
//!   alignment; the EM steps at the file's median sample interval (`session.grid_hz` when they
//!   agree to [`CSV_RATE_TOLERANCE`]);
//! - the outcome is judged as live: [`DaemonError::Validation`] (65) if validation refuses,
//!   [`DaemonError::Session`] (66) if there are too few samples; unreadable input is
//!   [`DaemonError::Io`] (74), bad input [`DaemonError::Input`] (65) naming the file, the line
//!   and the problem. Nothing here panics on any input;
//! - the report is always written (also for a refused table, which it shows as refused); the
//!   TOML and URDF exports only for a validated table.

use std::path::{Path, PathBuf};

use exocal_bus::embedded_can::{ExtendedId, Frame as _, Id, StandardId};
use exocal_bus::{Frame, Received};
use exocal_report::readers::{self, RecordedFrame};
use exocal_report::{Calibration, Quality, TimedSample};
use nalgebra::UnitQuaternion;

use crate::align::{AlignedSample, Pose};
use crate::calibrate::{self, Outcome};
use crate::config::Config;
use crate::exit::DaemonError;
use crate::ingest::{ClockReport, FrameStats, Ingest};
use crate::runner::{SessionError, SessionSummary};

/// What the input file is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    /// The daemon's MCAP session log (`/can/rx` frames).
    Mcap,
    /// A `candump -L` log.
    Candump,
    /// CSV samples: `t,q1,q2,q3,q4,q5,q6,q7,x,y,z,qw,qx,qy,qz`.
    Csv,
}

impl std::fmt::Display for Format {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Format::Mcap => "MCAP",
            Format::Candump => "candump",
            Format::Csv => "CSV",
        })
    }
}

/// Relative difference between a CSV file's sample rate and `session.grid_hz` below which the
/// configured rate is kept (the `t` column's decimal rounding, not a different rate).
pub const CSV_RATE_TOLERANCE: f64 = 1e-6;

const MCAP_MAGIC: &[u8] = b"\x89MCAP";

/// The format of `path`: by extension (`.mcap`, `.csv`, `.log`/`.candump`), else by content
/// (the MCAP magic, a `(time)` candump line, the CSV header).
pub fn detect_format(path: &Path, bytes: &[u8]) -> Result<Format, DaemonError> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase());
    match ext.as_deref() {
        Some("mcap") => return Ok(Format::Mcap),
        Some("csv") => return Ok(Format::Csv),
        Some("log" | "candump") => return Ok(Format::Candump),
        _ => {}
    }
    if bytes.starts_with(MCAP_MAGIC) {
        return Ok(Format::Mcap);
    }
    let text = String::from_utf8_lossy(&bytes[..bytes.len().min(4096)]);
    let first = text
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with('#'));
    match first {
        Some(l) if l.starts_with('(') => Ok(Format::Candump),
        Some(l) if l.starts_with("t,") => Ok(Format::Csv),
        _ => Err(DaemonError::Input(format!(
            "{}: cannot tell the format (not MCAP, no `(time) iface ID#DATA` line, no CSV \
             header); pass --format mcap|candump|csv",
            path.display()
        ))),
    }
}

/// The input, read.
#[derive(Debug, Clone)]
pub enum Input {
    /// Frames to replay (already cut at the collection end for an MCAP log).
    Frames(Vec<RecordedFrame>),
    /// Samples that bypass alignment.
    Samples(Vec<TimedSample>),
}

/// Reads `bytes` (from `path`, for the messages) as `format`.
pub fn read_input(path: &Path, bytes: &[u8], format: Format) -> Result<Input, DaemonError> {
    let bad = |e: readers::ReadError| DaemonError::Input(format!("{}: {e}", path.display()));
    let text = || {
        std::str::from_utf8(bytes).map_err(|e| {
            DaemonError::Input(format!(
                "{}: not UTF-8 text (byte {}); is it a {format} file?",
                path.display(),
                e.valid_up_to()
            ))
        })
    };
    match format {
        Format::Mcap => {
            let session = readers::read_mcap_session(bytes).map_err(bad)?;
            let mut frames = session.frames;
            if let Some(n) = session.collection_frames {
                let n = usize::try_from(n).unwrap_or(usize::MAX);
                if n > frames.len() {
                    return Err(DaemonError::Input(format!(
                        "{}: MCAP log: collection ended after {n} received frames, but the \
                         log holds only {}",
                        path.display(),
                        frames.len()
                    )));
                }
                frames.truncate(n);
            }
            Ok(Input::Frames(frames))
        }
        Format::Candump => Ok(Input::Frames(readers::parse_candump(text()?).map_err(bad)?)),
        Format::Csv => Ok(Input::Samples(readers::parse_csv(text()?).map_err(bad)?)),
    }
}

/// A recorded frame as the bus would have delivered it.
pub fn received(f: &RecordedFrame) -> Option<Received> {
    let id: Id = if f.extended {
        ExtendedId::new(f.id)?.into()
    } else {
        StandardId::new(u16::try_from(f.id).ok()?)?.into()
    };
    let frame = if f.remote {
        Frame::new_remote(id, 0)?
    } else {
        Frame::new(id, &f.data)?
    };
    Some(Received {
        frame,
        timestamp: f.t,
    })
}

/// What a recalibration produced.
#[derive(Debug, Clone)]
pub struct Recalibration {
    pub frames: FrameStats,
    pub clocks: Vec<ClockReport>,
    /// The samples the calibration ran on (aligned, or the CSV's).
    pub samples: Vec<AlignedSample>,
    pub gaps: usize,
    /// The configuration the calibration ran with (for CSV, `session.grid_hz` is the file's).
    pub config: Config,
    pub outcome: Outcome,
    pub detail: Calibration,
    pub quality: Quality,
}

/// An aligned sample from a CSV one.
fn aligned_of(s: &TimedSample) -> AlignedSample {
    let q = UnitQuaternion::from_matrix(&s.sample.pose.r);
    AlignedSample {
        t: s.t,
        joints: s.sample.joints,
        pose: Pose {
            position: s.sample.pose.p.into(),
            orientation: [q.w, q.i, q.j, q.k],
        },
    }
}

/// Runs the pipeline on `input` (see the module docs).
pub fn recalibrate(input: &Input, config: &Config) -> Result<Recalibration, DaemonError> {
    let mut config = config.clone();
    let (samples, frames, clocks, gaps, rates) = match input {
        Input::Frames(recorded) => {
            let mut ingest = Ingest::new(config.joint_nodes);
            for (i, f) in recorded.iter().enumerate() {
                let rx = received(f).ok_or_else(|| {
                    DaemonError::Input(format!("frame {}: identifier {:#x} invalid", i + 1, f.id))
                })?;
                ingest.on_frame(&rx);
            }
            let (aligned, clocks) = crate::runner::align_session(&ingest, &config);
            let rates = ingest.stream_rates();
            (
                aligned.samples,
                ingest.stats().clone(),
                clocks,
                aligned.gaps,
                Some(rates),
            )
        }
        Input::Samples(csv) => {
            let mut steps: Vec<f64> = csv.windows(2).map(|w| w[1].t - w[0].t).collect();
            steps.sort_by(f64::total_cmp);
            // The EM's step is the file's median interval, unless that is the configured grid
            // rate up to the rounding of the `t` column (then the rate is kept exactly).
            if let Some(&median) = steps.get(steps.len() / 2) {
                let hz = 1.0 / median;
                if (hz / config.session.grid_hz - 1.0).abs() > CSV_RATE_TOLERANCE {
                    config.session.grid_hz = hz;
                }
            }
            let samples: Vec<AlignedSample> = csv.iter().map(aligned_of).collect();
            (samples, FrameStats::default(), Vec::new(), 0, None)
        }
    };
    let (outcome, detail) = calibrate::run_detailed(&samples, &config)
        .map_err(|e| DaemonError::Session(e.to_string()))?;
    let quality = match rates {
        Some(rates) => {
            crate::calreport::frame_quality(&config, &frames, &clocks, &rates, &samples, gaps)
        }
        None => crate::calreport::sample_quality(&config, &samples),
    };
    Ok(Recalibration {
        frames,
        clocks,
        samples,
        gaps,
        config,
        outcome,
        detail,
        quality,
    })
}

/// Options of an offline run (the command line's).
#[derive(Debug, Clone, Default)]
pub struct OfflineOptions {
    pub input: PathBuf,
    /// `None`: detect ([`detect_format`]).
    pub format: Option<Format>,
    /// `None`: `<input>.offline.html` next to the input.
    pub report: Option<PathBuf>,
    pub export_toml: Option<PathBuf>,
    pub export_urdf: Option<PathBuf>,
    pub export_candump: Option<PathBuf>,
}

/// The report's default path: `<input stem>.offline.html` next to the input (never the live
/// session's own `<stem>.html`).
pub fn default_report_path(input: &Path) -> PathBuf {
    input.with_extension("offline.html")
}

fn write_file(path: &Path, what: &str, bytes: &[u8]) -> Result<(), DaemonError> {
    std::fs::write(path, bytes).map_err(|source| DaemonError::Io {
        what: format!("writing the {what} {}", path.display()),
        source,
    })
}

/// `exocald offline`: reads, recalibrates, writes the report and the exports. `config_text`
/// is the configuration file the daemon runs with (the TOML export rewrites its `[nominal]`).
/// Returns the summary (printed by the caller) or the error with what was done (boxed: it
/// carries the whole summary).
pub fn run(
    config: &Config,
    config_text: &str,
    opts: &OfflineOptions,
) -> Result<SessionSummary, Box<SessionError>> {
    let path = &opts.input;
    let bytes = std::fs::read(path).map_err(|source| DaemonError::Io {
        what: format!("reading {}", path.display()),
        source,
    })?;
    let format = match opts.format {
        Some(f) => f,
        None => detect_format(path, &bytes)?,
    };
    let input = read_input(path, &bytes, format)?;
    if let (Input::Samples(_), Some(_)) = (&input, &opts.export_candump) {
        return Err(DaemonError::Usage(
            "--export-candump needs a frame input (MCAP or candump), not CSV samples".into(),
        )
        .into());
    }
    if let Input::Frames(frames) = &input {
        eprintln!(
            "exocald: replaying {} frames from {} ({format})",
            frames.len(),
            path.display()
        );
    }
    let r = recalibrate(&input, config)?;
    let report_path = opts
        .report
        .clone()
        .unwrap_or_else(|| default_report_path(path));
    let name = path
        .file_name()
        .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
    let report = crate::calreport::report_input(
        format!("exocald offline recalibration — {name}"),
        format!("offline: {} ({format})", path.display()),
        &r.config,
        &r.samples,
        &r.outcome,
        r.detail.clone(),
        r.quality.clone(),
    );
    crate::calreport::write(&report_path, &report).map_err(|source| DaemonError::Io {
        what: format!("writing the report {}", report_path.display()),
        source,
    })?;
    if let (Input::Frames(frames), Some(out)) = (&input, &opts.export_candump) {
        let mut text = Vec::new();
        exocal_report::export::write_candump(frames, &config.interface, &mut text).map_err(
            |source| DaemonError::Io {
                what: "formatting the candump log".into(),
                source,
            },
        )?;
        write_file(out, "candump log", &text)?;
    }
    let accepted = r.outcome.verdict.accepted();
    let calibrated = r.detail.calibrated;
    let exports = [
        (&opts.export_toml, "TOML configuration"),
        (&opts.export_urdf, "URDF"),
    ];
    for (out, what) in exports {
        let Some(out) = out else { continue };
        if !accepted {
            eprintln!(
                "exocald: {what} not exported to {}: the calibration was refused",
                out.display()
            );
            continue;
        }
        let text = if what == "URDF" {
            exocal_report::export::urdf("exocal_suit", &calibrated, &r.quality.joint_ranges)
        } else {
            exocal_report::export::config_toml(config_text, &calibrated)
        }
        .map_err(|e| DaemonError::Input(format!("exporting the {what}: {e}")))?;
        write_file(out, what, text.as_bytes())?;
    }
    let summary = SessionSummary {
        log_path: path.clone(),
        log_counts: Vec::new(),
        frames: r.frames,
        clocks: r.clocks,
        aligned_samples: r.samples.len(),
        gaps: r.gaps,
        outcome: Some(r.outcome),
        push: None,
        report_path: Some(report_path),
    };
    if accepted {
        Ok(summary)
    } else {
        let reasons = summary
            .outcome
            .as_ref()
            .map(|o| o.verdict.reasons.clone())
            .unwrap_or_default();
        Err(Box::new(SessionError {
            error: DaemonError::Validation(reasons),
            summary: Some(summary),
        }))
    }
}
