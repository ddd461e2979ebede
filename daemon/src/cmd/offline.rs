//! `exocald offline`: recalibration from a recorded session, without a bus.
//!
//! Contract:
//! - frame-level inputs — the daemon's MCAP session log (`/can/rx`) or a `candump -L` log — are
//!   replayed frame by frame, in file order and with their recorded receive times, through the
//!   live session's own `Session` (`exocal_session::replay`) and calibrated by the same
//!   [`CalibrationJob`]: the live session's code path, minus the bus. The same frames give the
//!   same table, bit for bit;
//! - an MCAP log is replayed up to the end of its collection window: the live session writes
//!   an `exocal_log::CollectionEnd` record on `/collection` when it stops collecting, and
//!   calibrated on exactly the first `frames` received frames
//!   ([`exocal_log::read::McapSession::collection_frames`]); a log without the record (a session
//!   that never finished collecting) is replayed whole. A candump log is
//!   replayed whole (where it holds stream digests, each node's frames are taken at its next
//!   digest, as the live gate released them; MACs unchecked): `--export-candump` writes exactly
//!   the frames the calibration used, in receive order with the digests, so it replays to the
//!   same result;
//! - an MCAP log cut short (a killed daemon's: no summary, no footer) is read up to where it
//!   stops: every message of every complete chunk; the run warns how much was recovered and
//!   where the file was cut ([`read_session_log`]);
//! - every input is read as a stream, a record or a line at a time, and keeps at most what one
//!   session under the configuration can hold ([`Budget`]: `session.max_duration_s`, and
//!   `session.grid_hz` for samples); beyond it, or on a record, chunk or line longer than a
//!   session's log or recording can have, the input is refused at that point (65, naming the
//!   line or message and the limit). Memory is bounded by the configuration, whatever the
//!   file's size or what its lengths claim;
//! - CSV samples (`t,q1,…,qn,x,y,z,qw,qx,qy,qz` for the arm of n joints, see
//!   [`exocal_session::formats`]) bypass
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
//!   table. `--export-csv` writes the aligned samples (what the calibration was given, from any
//!   input) in the CSV format this command reads, whatever the verdict.

use std::collections::HashMap;
use std::io::{BufRead, BufReader, Read, Seek};
use std::path::{Path, PathBuf};

use exocal_dbc::Received;
use exocal_log::read::{read_mcap_session, McapSession, Phase};
use exocal_log::scan::Scan;
use exocal_session::formats::{self, CandumpReader, CsvReader, InputKind, ReadError};
use exocal_session::gate::{RejectRun, StreamGate};
use exocal_session::pipeline::{self, Calibrated};
use exocal_session::replay::{replay_gated, Recording};
use exocal_session::rules::Budget;
use exocal_session::{CalibrationJob, Settings};

pub use crate::cli::Format;
use crate::config::Config;
use crate::exit::DaemonError;
use crate::shell::summary::{SessionError, SessionSummary};

const MCAP_MAGIC: &[u8] = b"\x89MCAP";
/// Bytes from the start of the input that [`detect_format`] looks at.
const DETECT_BYTES: u64 = 4096;

/// The format of `path`: by content (the MCAP magic, a `(time)` candump line, the CSV header),
/// the extension (`.mcap`, `.csv`, `.log`/`.candump`) only where the content is none of them
/// (a damaged file then gets its format's own reader, and that reader's reason); else an error
/// saying what the start of the file looks like.
pub fn detect_format(path: &Path, bytes: &[u8]) -> Result<Format, DaemonError> {
    if bytes.starts_with(MCAP_MAGIC) {
        return Ok(Format::Mcap);
    }
    let head = &bytes[..bytes.len().min(DETECT_BYTES as usize)];
    let text = String::from_utf8_lossy(head);
    let first = text
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with('#'));
    match first {
        Some(l) if l.starts_with('(') => return Ok(Format::Candump),
        Some(l) if l.starts_with("t,") => return Ok(Format::Csv),
        _ => {}
    }
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase());
    match ext.as_deref() {
        Some("mcap") => return Ok(Format::Mcap),
        Some("csv") => return Ok(Format::Csv),
        Some("log" | "candump") => return Ok(Format::Candump),
        _ => {}
    }
    let looks = if head.is_empty() {
        "it is empty".to_string()
    } else if std::str::from_utf8(head).is_err() {
        let shown: Vec<String> = head.iter().take(8).map(|b| format!("{b:02x}")).collect();
        format!("binary, starting {}", shown.join(" "))
    } else {
        let line: String = first.unwrap_or("").chars().take(60).collect();
        format!("text, its first line {line:?}")
    };
    Err(DaemonError::Input(format!(
        "{}: cannot tell the format ({looks}: not MCAP, no `(time) iface ID#DATA` line, no CSV \
         header); pass --format mcap|candump|csv",
        path.display()
    )))
}

/// Longest line of a text input (bytes): a candump line is under 60, a CSV row under 500.
pub const MAX_LINE_BYTES: usize = 4096;

/// A daemon session log read from `input` (`path` names it in the messages), finished or cut
/// short ([`exocal_log::read`]: record by record, every length and chunk checked; one without
/// its end magic, a killed daemon's, is read up to where it stops and
/// [`McapSession::cut`] says where). Each received frame is passed to `admit` first.
pub fn read_session_log(
    path: &Path,
    input: impl Read,
    admit: impl FnMut(&Received, Phase) -> Result<(), String>,
) -> Result<McapSession, DaemonError> {
    read_mcap_session(input, admit)
        .map_err(|e| DaemonError::Input(format!("{}: {e}", path.display())))
}

/// Calls `f` on each line of `input` (without its line ending), in order; a line longer than
/// [`MAX_LINE_BYTES`] or not UTF-8 is an error naming it, so a file of any size is read with
/// bounded memory.
fn each_line(
    path: &Path,
    kind: InputKind,
    mut input: impl BufRead,
    mut f: impl FnMut(&str) -> Result<(), ReadError>,
) -> Result<(), DaemonError> {
    let mut buf = Vec::new();
    for n in 1.. {
        buf.clear();
        let bad = |what: String| {
            let e = ReadError {
                kind,
                line: Some(n),
                what,
            };
            DaemonError::Input(format!("{}: {e}", path.display()))
        };
        let got = (&mut input)
            .take(MAX_LINE_BYTES as u64 + 1)
            .read_until(b'\n', &mut buf)
            .map_err(|source| DaemonError::Io {
                what: format!("reading {}", path.display()),
                source,
            })?;
        if got == 0 {
            break;
        }
        if buf.last() == Some(&b'\n') {
            buf.pop();
        } else if got > MAX_LINE_BYTES {
            return Err(bad(format!(
                "longer than {MAX_LINE_BYTES} bytes, more than any line of this format"
            )));
        }
        let line = std::str::from_utf8(&buf).map_err(|e| {
            bad(format!(
                "not UTF-8 text (byte {} of the line)",
                e.valid_up_to() + 1
            ))
        })?;
        f(line).map_err(|e| DaemonError::Input(format!("{}: {e}", path.display())))?;
    }
    Ok(())
}

/// Reads `input` (from `path`, for the messages) as `format`, keeping at most what one session
/// under `settings`' window rules can hold ([`Budget`]), CSV samples of the arm of
/// `settings.joints` joints; for an MCAP log cut short, also what was read of it and where it
/// stops.
pub fn read_input(
    path: &Path,
    input: impl Read,
    format: Format,
    settings: &Settings,
) -> Result<(Recording, Option<Scan>), DaemonError> {
    read_input_gated(path, input, format, settings).map(|(r, cut, _)| (r, cut))
}

/// [`read_input`], with the live session's stream gate to re-apply when the log has one (an
/// MCAP log of a session whose sensor streams were authenticated): the replay then takes
/// exactly the frames the live session took ([`exocal_session::gate`]).
pub fn read_input_gated(
    path: &Path,
    input: impl Read,
    format: Format,
    settings: &Settings,
) -> Result<(Recording, Option<Scan>, Option<StreamGate>), DaemonError> {
    let rules = &settings.window;
    let input = BufReader::new(input);
    match format {
        Format::Mcap => {
            // The collection's frames are one session's; the frames after it (calibration and
            // push) are counted against as many again.
            let mut collection = Budget::frames(rules);
            let (mut after, most_after) = (0usize, rules.max_frames());
            let session = read_session_log(path, input, |rx, phase| match phase {
                Phase::Collection => collection
                    .admit(rx.timestamp.as_secs_f64())
                    .map_err(|e| e.to_string()),
                Phase::After if after >= most_after => Err(format!(
                    "more than {most_after} frames after the collection end (as many as the \
                     longest session this configuration collects may hold)"
                )),
                Phase::After => {
                    after += 1;
                    Ok(())
                }
            })?;
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
            let gate = session
                .stream
                .map(|s| replay_gate(&s))
                .transpose()
                .map_err(|e| DaemonError::Input(format!("{}: MCAP log: {e}", path.display())))?;
            Ok((Recording::Frames(frames), session.cut, gate))
        }
        Format::Candump => {
            let mut reader = CandumpReader::new(rules);
            each_line(path, InputKind::Candump, input, |l| reader.line(l))?;
            let frames = reader.finish();
            // The stream digests of an authenticated session (a daemon's export, or
            // `candump -l` of its bus): each node's frames are taken at its next digest, as the
            // live gate released them, so ingest sees them in the same order. MACs are not
            // checked (no keys offline); frames after a node's last digest are not taken.
            let digests = frames.iter().any(|rx| {
                exocal_dbc::decode_frame(&rx.frame)
                    .is_ok_and(|m| matches!(m, exocal_dbc::Message::StreamDigest(_)))
            });
            let gate = digests.then(|| StreamGate::replaying(&[]));
            Ok((Recording::Frames(frames), None, gate))
        }
        Format::Csv => {
            let mut reader = CsvReader::new(rules, settings.joints);
            each_line(path, InputKind::Csv, input, |l| reader.line(l))?;
            let samples = reader
                .finish()
                .map_err(|e| DaemonError::Input(format!("{}: {e}", path.display())))?;
            Ok((Recording::Samples(samples), None, None))
        }
    }
}

/// The live stream gate's verdicts as a replaying gate ([`StreamGate::replaying`]); an error
/// where the record is incomplete (`rejects_truncated`): the replay would pass frames the live
/// gate dropped.
fn replay_gate(s: &exocal_log::proto::StreamVerification) -> Result<StreamGate, String> {
    if s.rejects_truncated {
        return Err(format!(
            "the stream gate's record of rejected digests is incomplete (more than {} runs): a \
             replay cannot take the frames the live session took",
            exocal_session::gate::MAX_REJECT_RUNS
        ));
    }
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
    Ok(StreamGate::replaying(&runs))
}

/// The frames `--export-candump` writes: behind the stream gate (where the session had one),
/// the frames it passed — exactly what the calibration used — in the order they were received,
/// as `candump -l` writes them (the gate releases a node's frames a span at a time, at its
/// digest, which the export keeps: its replay releases them the same way); with how many it
/// did not pass.
fn export_frames(frames: &[Received], gate: Option<StreamGate>) -> (Vec<Received>, usize) {
    let Some(mut gate) = gate else {
        return (frames.to_vec(), 0);
    };
    let mut passed = Vec::new();
    for rx in frames {
        gate.on_frame(rx, &mut passed);
    }
    let mut left: HashMap<Received, usize> = HashMap::new();
    for rx in &passed {
        *left.entry(*rx).or_default() += 1;
    }
    let exported: Vec<Received> = frames
        .iter()
        .filter(|rx| {
            left.get_mut(*rx).is_some_and(|n| {
                let take = *n > 0;
                *n = n.saturating_sub(1);
                take
            })
        })
        .copied()
        .collect();
    let held = frames.len() - exported.len();
    (exported, held)
}

/// What a recalibration produced.
#[derive(Debug, Clone)]
pub struct Recalibration {
    /// What the replay gathered (the aligned samples and their quality) and the settings the
    /// calibration ran with (for CSV, `session.grid_hz` is the file's).
    pub job: CalibrationJob,
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
    let calibrated = r.job.run()?;
    Ok(Recalibration {
        job: r.job,
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
    /// Where to write the aligned samples as CSV (`None`: not written).
    pub export_csv: Option<PathBuf>,
    /// No progress on stderr (`--quiet`, `--json`): warnings and errors still go there.
    pub quiet: bool,
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
    let io = |source| DaemonError::Io {
        what: format!("reading {}", path.display()),
        source,
    };
    let mut file = std::fs::File::open(path).map_err(io)?;
    let format = match opts.format {
        Some(f) => f,
        None => {
            let mut head = Vec::new();
            (&mut file)
                .take(DETECT_BYTES)
                .read_to_end(&mut head)
                .and_then(|_| file.rewind())
                .map_err(io)?;
            detect_format(path, &head)?
        }
    };
    let (input, recovery, gate) = read_input_gated(path, file, format, &config.calibration)?;
    if let Some(r) = &recovery {
        eprintln!(
            "exocald: warning: {} was cut short (no summary or footer: the daemon was killed or \
             lost power): recovered {r}; `exocald recover` writes it as a complete, indexed file",
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
    let source = format!(
        "{source}; {}",
        crate::shell::html_report::config_line(&config.calibration)
    );
    if let (Recording::Samples(_), Some(_)) = (&input, &opts.export_candump) {
        return Err(DaemonError::Usage(
            "--export-candump needs a frame input (MCAP or candump), not CSV samples".into(),
        )
        .into());
    }
    if let (Recording::Frames(frames), false) = (&input, opts.quiet) {
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
    summary.collected(replayed.job.collected());
    summary.report_path = Some(report_path.clone());
    let calibrated = if replayed.shortfalls.is_empty() {
        replayed.job.run().map_err(DaemonError::from)
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
        replayed.job.settings(),
        replayed.job.collected(),
        calibrated.as_ref().map_err(|_| reasons.as_slice()),
    );
    std::fs::write(&report_path, html).map_err(|source| DaemonError::Io {
        what: format!("writing the report {}", report_path.display()),
        source,
    })?;
    if let Some(out) = &opts.export_csv {
        let samples = pipeline::timed(&replayed.job.collected().samples);
        let joints = replayed.job.settings().joints;
        let text = formats::csv_text(&samples, joints);
        write_file(out, "CSV samples", text.as_bytes())?;
    }
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
        let (exported, held) = export_frames(frames, export_gate);
        if held > 0 {
            eprintln!(
                "exocald: {} holds {} frames in receive order; {held} the stream gate did not \
                 pass (unverified, or still held at the collection's end) are left out, as the \
                 calibration left them",
                out.display(),
                exported.len()
            );
        }
        let text = formats::candump_text(&exported, &config.interface);
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
        let settings = replayed.job.settings();
        let text = if what == "URDF" {
            let limits = &settings.bounds.joint_range.limits;
            crate::log::records::urdf(&table, limits, settings.joints).map_err(|e| e.to_string())
        } else {
            let rows = &table.rows[..settings.joints];
            crate::config::with_nominal(config_text, rows).map_err(|e| e.to_string())
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

#[cfg(test)]
mod tests {
    use super::*;
    use exocal_log::proto;

    /// Where the live gate's record of rejected digests was cut short, a replay would pass
    /// the frames of the rejects left out (two injected frames, taken offline and exported
    /// into a table); such a log is refused (65), naming why.
    #[test]
    fn a_full_reject_record_is_refused_offline() {
        let full = proto::StreamVerification {
            rejects_truncated: true,
            ..Default::default()
        };
        let why = replay_gate(&full).unwrap_err();
        assert!(why.contains("incomplete"), "{why}");
        let whole = proto::StreamVerification {
            rejects: vec![proto::RejectRun {
                node: 3,
                first: 1,
                count: 2,
                stale: false,
            }],
            ..Default::default()
        };
        let gate = replay_gate(&whole).unwrap();
        assert_eq!(
            gate.rejects(),
            [RejectRun {
                node: 3,
                first: 1,
                count: 2,
                stale: false
            }]
        );
    }
}
