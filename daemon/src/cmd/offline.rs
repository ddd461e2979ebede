//! `exocald offline`: recalibration from a recorded session, without a bus.
//!
//! Contract:
//! - frame-level inputs — the daemon's MCAP session log (`/can/rx`) or a `candump -L` log — are
//!   replayed frame by frame, in file order and with their recorded receive times, through the
//!   live session's own collector (`exocal_session::replay`) and calibrated by [`pipeline::run`]: the live session's
//!   code path, minus the bus. The same frames give the same table, bit for bit;
//! - an MCAP log is replayed up to the end of its collection window: the live session writes
//!   an `exocal_log::CollectionEnd` record on `/collection` when it stops collecting, and
//!   calibrated on exactly the first `frames` received frames
//!   ([`exocal_log::read::McapSession::collection_frames`]); a log without the record (a session
//!   that never finished collecting) is replayed whole. A candump log is
//!   replayed whole: `--export-candump` writes exactly the frames the calibration used, so it
//!   replays to the same result;
//! - an MCAP log cut short (a killed daemon's: no summary, no footer) is read through
//!   [`crate::log::recover`]: every message of every complete chunk; the run warns how much was
//!   recovered and where the file was cut ([`read_session_log`]);
//! - CSV samples (`t,q1,…,q7,x,y,z,qw,qx,qy,qz`, see [`exocal_session::formats`]) bypass
//!   alignment; the EM steps at the file's median sample interval (`session.grid_hz` when they
//!   agree to [`exocal_session::replay::CSV_RATE_TOLERANCE`]);
//! - the recording is judged by the live session's rules (`[session]`: `min_duration_s`, give or
//!   take [`exocal_session::window::DURATION_SLACK_S`], every joint's excitation, `min_samples`): one the live daemon
//!   would not have calibrated is not calibrated here either ([`exocal_session::replay::replay`] names what it misses);
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

use exocal_log::read::{read_mcap_session, McapSession};
use exocal_session::collect::Collected;
use exocal_session::formats::{self, ReadError};
use exocal_session::pipeline::{self, Calibrated};
use exocal_session::replay::{replay_gated, Recording};
use exocal_session::verify::{RejectRun, StreamGate};
use exocal_session::Settings;

pub use crate::cli::Format;
use crate::config::Config;
use crate::exit::DaemonError;
use crate::log::recover::{self, Recovery};
use crate::shell::runner::{SessionError, SessionSummary};

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

/// A daemon session log, finished or cut short: a finished file is read as it is; one without
/// its end magic (a killed daemon's) is first recovered in memory ([`crate::log::recover`]: every
/// message of every complete chunk), and the [`Recovery`] says what was kept.
pub fn read_session_log(
    path: &Path,
    bytes: &[u8],
) -> Result<(McapSession, Option<Recovery>), DaemonError> {
    let bad =
        |e: exocal_log::read::ReadError| DaemonError::Input(format!("{}: {e}", path.display()));
    if recover::is_finished(bytes) {
        return Ok((read_mcap_session(bytes).map_err(bad)?, None));
    }
    let (recovery, complete) = recover::recover_in_memory(bytes)
        .map_err(|e| DaemonError::Input(format!("{}: {e}", path.display())))?;
    let session = read_mcap_session(&complete).map_err(|e| {
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
) -> Result<(Recording, Option<Recovery>), DaemonError> {
    read_input_gated(path, bytes, format).map(|(r, recovery, _)| (r, recovery))
}

/// [`read_input`], with the live session's stream gate to re-apply when the log has one (an
/// MCAP log of a session whose sensor streams were authenticated): the replay then takes
/// exactly the frames the live session took ([`exocal_session::verify`]).
pub fn read_input_gated(
    path: &Path,
    bytes: &[u8],
    format: Format,
) -> Result<(Recording, Option<Recovery>, Option<StreamGate>), DaemonError> {
    let bad = |e: ReadError| DaemonError::Input(format!("{}: {e}", path.display()));
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
            let gate = session.stream.map(|s| {
                let runs: Vec<RejectRun> = s
                    .rejects
                    .iter()
                    .map(|r| RejectRun {
                        node: u8::try_from(r.node).unwrap_or(u8::MAX),
                        first: r.first,
                        count: r.count,
                        stale: r.stale,
                    })
                    .collect();
                StreamGate::replaying(&runs)
            });
            Ok((Recording::Frames(frames), recovery, gate))
        }
        Format::Candump => Ok((
            Recording::Frames(formats::parse_candump(text()?).map_err(bad)?),
            None,
            None,
        )),
        Format::Csv => Ok((
            Recording::Samples(formats::parse_csv(text()?).map_err(bad)?),
            None,
            None,
        )),
    }
}

/// What a recalibration produced.
#[derive(Debug, Clone)]
pub struct Recalibration {
    /// What the replay gathered: the aligned samples and their quality.
    pub collected: Collected,
    /// The settings the calibration ran with (for CSV, `session.grid_hz` is the file's).
    pub settings: Settings,
    /// What the pipeline computed from them.
    pub calibrated: Calibrated,
}

/// Runs the pipeline on `input` behind `gate` (see the module docs and [`read_input_gated`]):
/// [`replay_gated`], then, if the recording meets
/// the session rules, the calibration; [`DaemonError::Session`] naming every rule it misses
/// otherwise.
pub fn recalibrate(
    input: &Recording,
    gate: Option<StreamGate>,
    config: &Config,
) -> Result<Recalibration, DaemonError> {
    let r = replay_gated(input, &config.calibration, gate);
    if !r.shortfalls.is_empty() {
        return Err(DaemonError::Session(r.shortfalls));
    }
    let calibrated = pipeline::run(&r.collected.samples, &r.settings)?;
    Ok(Recalibration {
        collected: r.collected,
        settings: r.settings,
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
    let (input, recovery, gate) = read_input_gated(path, &bytes, format)?;
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
    if let (Recording::Samples(_), Some(_)) = (&input, &opts.export_candump) {
        return Err(DaemonError::Usage(
            "--export-candump needs a frame input (MCAP or candump), not CSV samples".into(),
        )
        .into());
    }
    if let Recording::Frames(frames) = &input {
        eprintln!(
            "exocald: replaying {} frames from {} ({format})",
            frames.len(),
            path.display()
        );
    }
    let export_gate = gate.clone();
    let replayed = replay_gated(&input, &config.calibration, gate);
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
        pipeline::run(&replayed.collected.samples, &replayed.settings).map_err(DaemonError::from)
    } else {
        Err(DaemonError::Session(replayed.shortfalls.clone()))
    };
    // The report is written whatever happened once the input was read: the calibration's, or
    // (the session rules, or samples that would not calibrate) why not, with the data.
    let reasons = match &calibrated {
        Err(DaemonError::Session(why)) => why.iter().map(ToString::to_string).collect(),
        Err(e) => vec![e.to_string()],
        Ok(_) => Vec::new(),
    };
    let html = crate::shell::html_report::render(
        title,
        source,
        &replayed.settings,
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
    if let (Recording::Frames(frames), Some(out)) = (&input, &opts.export_candump) {
        // Behind the stream gate, the frames it passed, in the order ingest took them: a
        // candump replay (ungated) then takes exactly what the calibration used.
        let passed = export_gate.map(|mut g| {
            let mut pass = Vec::new();
            for rx in frames {
                g.on_frame(rx, &mut pass);
            }
            pass
        });
        let text = formats::candump_text(passed.as_deref().unwrap_or(frames), &config.interface);
        write_file(out, "candump log", text.as_bytes())?;
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
            let limits = &replayed.settings.bounds.joint_range.limits;
            exocal_report::export::urdf("exocal_suit", &table, limits).map_err(|e| e.to_string())
        } else {
            crate::config::with_nominal(config_text, &table).map_err(|e| e.to_string())
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
