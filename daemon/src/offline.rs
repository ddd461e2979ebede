//! `exocald offline`: recalibration from a recorded session, without a bus.
//!
//! Contract:
//! - frame-level inputs — the daemon's MCAP session log (`/can/rx`) or a `candump -L` log — are
//!   replayed frame by frame, in file order and with their recorded receive times, through the
//!   live session's own [`Collector`] and calibrated by [`pipeline::run`]: the live session's
//!   code path, minus the bus. The same frames give the same table, bit for bit;
//! - an MCAP log is replayed up to the end of its collection window: the live session writes
//!   an `exocal_log::CollectionEnd` record on `/collection` when it stops collecting, and
//!   calibrated on exactly the first `frames` received frames
//!   ([`exocal_report::McapSession::collection_frames`]); a log without the record (a session
//!   that never finished collecting) is replayed whole. A candump log is
//!   replayed whole: `--export-candump` writes exactly the frames the calibration used, so it
//!   replays to the same result;
//! - an MCAP log cut short (a killed daemon's: no summary, no footer) is read through
//!   [`crate::recover`]: every message of every complete chunk; the run warns how much was
//!   recovered and where the file was cut ([`read_session_log`]);
//! - CSV samples (`t,q1,…,q7,x,y,z,qw,qx,qy,qz`, see [`exocal_report::readers`]) bypass
//!   alignment; the EM steps at the file's median sample interval (`session.grid_hz` when they
//!   agree to [`CSV_RATE_TOLERANCE`]);
//! - the recording is judged by the live session's rules (`[session]`: `min_duration_s`, give or
//!   take [`DURATION_SLACK_S`], every joint's excitation, `min_samples`): one the live daemon
//!   would not have calibrated is not calibrated here either ([`replay`] names what it misses);
//! - the outcome is judged as live: [`DaemonError::Validation`] (65) if validation refuses,
//!   [`DaemonError::Session`] (66) if the session rules are not met,
//!   [`DaemonError::Calibration`] (66) if the samples do not calibrate; unreadable input is
//!   [`DaemonError::Io`] (74), bad input [`DaemonError::Input`] (65) naming the file, the line
//!   and the problem. Nothing here panics on any input;
//! - the report is always written once the input is read: for a refused table it shows the
//!   table as refused, for a recording that misses the session rules (66) it says which and
//!   shows the data's quality and excitation; the TOML and URDF exports only for a validated
//!   table.

use std::path::{Path, PathBuf};

use exocal_bus::embedded_can::{ExtendedId, Frame as _, Id, StandardId};
use exocal_bus::{Frame, Received};
use exocal_report::readers::{self, RecordedFrame};
use exocal_report::TimedSample;
use nalgebra::UnitQuaternion;

use crate::align::{AlignedSample, Pose};
use crate::collect::{Collected, Collector};
use crate::config::Config;
use crate::exit::DaemonError;
use crate::pipeline::{self, Calibrated};
use crate::recover::{self, Recovery};
use crate::runner::{SessionError, SessionSummary};
use crate::session::{Phase, Session};

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

/// A daemon session log, finished or cut short: a finished file is read as it is; one without
/// its end magic (a killed daemon's) is first recovered in memory ([`crate::recover`]: every
/// message of every complete chunk), and the [`Recovery`] says what was kept.
pub fn read_session_log(
    path: &Path,
    bytes: &[u8],
) -> Result<(readers::McapSession, Option<Recovery>), DaemonError> {
    let bad = |e: readers::ReadError| DaemonError::Input(format!("{}: {e}", path.display()));
    if recover::is_finished(bytes) {
        return Ok((readers::read_mcap_session(bytes).map_err(bad)?, None));
    }
    let (recovery, complete) = recover::recover_in_memory(bytes)
        .map_err(|e| DaemonError::Input(format!("{}: {e}", path.display())))?;
    let session = readers::read_mcap_session(&complete).map_err(|e| {
        DaemonError::Input(format!(
            "{}: {e} (the log was cut short: {recovery})",
            path.display()
        ))
    })?;
    Ok((session, Some(recovery)))
}

/// Reads `bytes` (from `path`, for the messages) as `format`; for an MCAP log cut short, also
/// what was recovered of it ([`read_session_log`]).
pub fn read_input(
    path: &Path,
    bytes: &[u8],
    format: Format,
) -> Result<(Input, Option<Recovery>), DaemonError> {
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
            let (session, recovery) = read_session_log(path, bytes)?;
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
            Ok((Input::Frames(frames), recovery))
        }
        Format::Candump => Ok((
            Input::Frames(readers::parse_candump(text()?).map_err(bad)?),
            None,
        )),
        Format::Csv => Ok((
            Input::Samples(readers::parse_csv(text()?).map_err(bad)?),
            None,
        )),
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

/// How much shorter than `session.min_duration_s` a recording may be and still count as that
/// long: a live window runs from the daemon's start to the tick that ends it, a recording from
/// its first to its last frame (or CSV sample), which starts a little later.
pub const DURATION_SLACK_S: f64 = 1.0;

/// The input as the live session would have collected it, before calibrating.
#[derive(Debug, Clone)]
pub struct Replay {
    /// What the live session would have gathered (for CSV: the file's samples, unaligned).
    pub collected: Collected,
    /// The configuration the calibration runs with (for CSV, `session.grid_hz` is the file's).
    pub config: Config,
    /// First to last frame (or CSV sample), seconds.
    pub duration_s: f64,
    /// The session rules (`[session]`) the recording does not meet, one line each: empty when
    /// the live daemon would have calibrated it.
    pub shortfalls: Vec<String>,
}

/// What a recalibration produced.
#[derive(Debug, Clone)]
pub struct Recalibration {
    /// What the replay gathered: the aligned samples and their quality.
    pub collected: Collected,
    /// The configuration the calibration ran with (for CSV, `session.grid_hz` is the file's).
    pub config: Config,
    /// What the pipeline computed from them.
    pub calibrated: Calibrated,
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

/// The session rules `session` (fed with the whole recording, `duration_s` long) does not
/// meet, as the live session would judge them when the recording ends.
fn shortfalls(session: &Session, config: &Config, duration_s: f64) -> Vec<String> {
    let rules = &config.session;
    match session.phase(duration_s + DURATION_SLACK_S) {
        Phase::Ready => Vec::new(),
        Phase::Failed(why) => why,
        Phase::Collecting => {
            let mut why = session.shortfalls();
            if duration_s + DURATION_SLACK_S < rules.min_duration_s {
                why.insert(
                    0,
                    format!(
                        "the recording is {duration_s:.1} s long; session.min_duration_s is {} s \
                         (a live session would still be collecting)",
                        rules.min_duration_s
                    ),
                );
            }
            why
        }
    }
}

/// Replays `input` through the live session's [`Collector`] (frames) or takes its samples
/// (CSV), and judges it by the session rules (see the module docs).
pub fn replay(input: &Input, config: &Config) -> Result<Replay, DaemonError> {
    let mut config = config.clone();
    match input {
        Input::Frames(recorded) => {
            let mut collector = Collector::new(&config);
            for (i, f) in recorded.iter().enumerate() {
                let rx = received(f).ok_or_else(|| {
                    DaemonError::Input(format!("frame {}: identifier {:#x} invalid", i + 1, f.id))
                })?;
                collector.on_frame(&rx);
            }
            let duration_s = match (recorded.first(), recorded.last()) {
                (Some(a), Some(b)) => b.t.saturating_sub(a.t).as_secs_f64(),
                _ => 0.0,
            };
            Ok(Replay {
                collected: collector.collected(&config),
                shortfalls: shortfalls(&collector.session, &config, duration_s),
                config,
                duration_s,
            })
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
            let mut session = Session::new(config.session.clone(), config.bounds.joint_range);
            for s in csv {
                for (j, &q) in s.sample.joints.iter().enumerate() {
                    session.joint_sample(j, q);
                }
                session.pose_sample();
            }
            let duration_s = match (csv.first(), csv.last()) {
                (Some(a), Some(b)) => (b.t - a.t).max(0.0),
                _ => 0.0,
            };
            let samples: Vec<AlignedSample> = csv.iter().map(aligned_of).collect();
            Ok(Replay {
                collected: Collected::from_samples(samples, &config),
                shortfalls: shortfalls(&session, &config, duration_s),
                config,
                duration_s,
            })
        }
    }
}

/// Runs the pipeline on `input` (see the module docs): [`replay`], then, if the recording meets
/// the session rules, the calibration; [`DaemonError::Session`] naming every rule it misses
/// otherwise.
pub fn recalibrate(input: &Input, config: &Config) -> Result<Recalibration, DaemonError> {
    calibrate_replay(replay(input, config)?)
}

fn calibrate_replay(r: Replay) -> Result<Recalibration, DaemonError> {
    if !r.shortfalls.is_empty() {
        return Err(DaemonError::Session(r.shortfalls.join("; ")));
    }
    let calibrated = pipeline::run(&r.collected.samples, &r.config)?;
    Ok(Recalibration {
        collected: r.collected,
        config: r.config,
        calibrated,
    })
}

/// Options of an offline run (the command line's).
#[derive(Debug, Clone, Default)]
pub struct OfflineOptions {
    /// The recorded session: an exocald MCAP log, a `candump -L` log or CSV samples.
    pub input: PathBuf,
    /// `None`: detect ([`detect_format`]).
    pub format: Option<Format>,
    /// `None`: `<input>.offline.html` next to the input.
    pub report: Option<PathBuf>,
    /// Where to write the calibrated table as the daemon's configuration (`None`: not written).
    pub export_toml: Option<PathBuf>,
    /// Where to write the calibrated table as URDF joint origins (`None`: not written).
    pub export_urdf: Option<PathBuf>,
    /// Where to write the replayed frames as a `candump -L` log (`None`: not written).
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
    let (input, recovery) = read_input(path, &bytes, format)?;
    if let Some(r) = &recovery {
        eprintln!(
            "exocald: warning: {} was cut short (no summary or footer: the daemon was killed or \
             lost power): {r}; `exocald recover` writes it as a complete, indexed file",
            path.display()
        );
    }
    let source = match &recovery {
        Some(r) => format!(
            "offline: {} ({format}, cut short: {} messages, {:.1} s recovered)",
            path.display(),
            r.messages,
            r.span_s()
        ),
        None => format!("offline: {} ({format})", path.display()),
    };
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
    let replayed = replay(&input, config)?;
    let report_path = opts
        .report
        .clone()
        .unwrap_or_else(|| default_report_path(path));
    let name = path
        .file_name()
        .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
    let title = format!("exocald offline recalibration — {name}");
    let mut summary = SessionSummary::new(path.clone());
    summary.collected(&replayed.collected);
    summary.report_path = Some(report_path.clone());
    let calibrated = if replayed.shortfalls.is_empty() {
        pipeline::run(&replayed.collected.samples, &replayed.config).map_err(DaemonError::from)
    } else {
        Err(DaemonError::Session(replayed.shortfalls.join("; ")))
    };
    // The report is written whatever happened once the input was read: the calibration's, or
    // (the session rules, or samples that would not calibrate) why not, with the data.
    let reasons = match &calibrated {
        Err(DaemonError::Session(_)) => replayed.shortfalls.clone(),
        Err(e) => vec![e.to_string()],
        Ok(_) => Vec::new(),
    };
    let html = crate::calreport::render(
        title,
        source,
        &replayed.config,
        &replayed.collected,
        calibrated.as_ref().map_err(|_| reasons.as_slice()),
    );
    std::fs::write(&report_path, html).map_err(|source| DaemonError::Io {
        what: format!("writing the report {}", report_path.display()),
        source,
    })?;
    let calibrated = match calibrated {
        Ok(c) => c,
        Err(error) => {
            return Err(Box::new(SessionError {
                error,
                summary: Some(summary),
            }))
        }
    };
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
    let accepted = calibrated.outcome.verdict.accepted();
    let table = calibrated.outcome.table();
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
            let limits = &replayed.config.bounds.joint_range.limits;
            exocal_report::export::urdf("exocal_suit", &table, limits)
        } else {
            exocal_report::export::config_toml(config_text, &table)
        }
        .map_err(|e| DaemonError::Input(format!("exporting the {what}: {e}")))?;
        write_file(out, what, text.as_bytes())?;
    }
    let reasons = calibrated.outcome.verdict.reasons.clone();
    summary.outcome = Some(calibrated.outcome);
    if accepted {
        Ok(summary)
    } else {
        Err(Box::new(SessionError {
            error: DaemonError::Validation(reasons),
            summary: Some(summary),
        }))
    }
}
