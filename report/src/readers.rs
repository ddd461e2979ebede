//! Offline inputs: recorded CAN frames (a `candump -L` log, or the daemon's MCAP session log)
//! and plain CSV sample files.
//!
//! Contract:
//! - frame-level readers return [`RecordedFrame`]s in file order, with receive times since the
//!   UNIX epoch; they neither decode nor reorder — the daemon's ingest does that, exactly as for
//!   a live bus;
//! - [`parse_csv`] returns calibration samples directly (no alignment) in the format below;
//! - bad input is a [`ReadError`] naming the input kind, the 1-based line (where there is one)
//!   and what is wrong; nothing here panics on any input.
//!
//! # The CSV sample format
//!
//! One header line, then one sample per line; blank lines and lines starting with `#` are
//! ignored. Columns, comma-separated, in this order:
//!
//! ```text
//! t,q1,q2,q3,q4,q5,q6,q7,x,y,z,qw,qx,qy,qz
//! ```
//!
//! `t` is the time in seconds (strictly increasing), `q1`…`q7` the seven joint readings in
//! radians (joint 1 = shoulder), `x,y,z` the measured end-effector position in metres in the
//! base frame, and `qw,qx,qy,qz` its orientation as a unit quaternion (scalar first; a norm
//! within 1e-3 of 1 is normalised, anything else is an error).

use std::fmt;
use std::time::Duration;

use calib_core::{Frame, Sample};
use nalgebra::{Quaternion, UnitQuaternion, Vector3};

use exocal_log::Topic;

use crate::input::{TimedSample, JOINTS};

/// The CSV header, exactly.
pub const CSV_HEADER: &str = "t,q1,q2,q3,q4,q5,q6,q7,x,y,z,qw,qx,qy,qz";
/// The MCAP topic of received raw frames in the daemon's session log.
pub const MCAP_RX_TOPIC: &str = exocal_log::Topic::CanRx.name();

/// A raw CAN frame as recorded.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RecordedFrame {
    /// Receive time since the UNIX epoch.
    pub t: Duration,
    /// The identifier (11 or 29 bits).
    pub id: u32,
    /// A 29-bit identifier.
    pub extended: bool,
    /// A remote-transmission request (no data).
    pub remote: bool,
    /// At most 8 bytes (classic CAN).
    pub data: Vec<u8>,
}

/// Which reader failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum InputKind {
    /// A candump log (`candump -l` format).
    Candump,
    /// CSV samples (joint angles and poses).
    Csv,
    /// An exocald session log (MCAP).
    Mcap,
}

impl fmt::Display for InputKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            InputKind::Candump => "candump log",
            InputKind::Csv => "CSV samples",
            InputKind::Mcap => "MCAP log",
        })
    }
}

/// Bad input: which kind, where (1-based line for text inputs), what.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ReadError {
    /// Which reader failed.
    pub kind: InputKind,
    /// 1-based line, for text inputs.
    pub line: Option<usize>,
    /// What is wrong.
    pub what: String,
}

impl fmt::Display for ReadError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.line {
            Some(l) => write!(f, "{}, line {l}: {}", self.kind, self.what),
            None => write!(f, "{}: {}", self.kind, self.what),
        }
    }
}

impl std::error::Error for ReadError {}

fn candump_err(line: usize, what: impl Into<String>) -> ReadError {
    ReadError {
        kind: InputKind::Candump,
        line: Some(line),
        what: what.into(),
    }
}

/// `"1700000000.123456"` → exact duration (1 to 9 fraction digits).
fn parse_time(s: &str) -> Option<Duration> {
    let (secs, frac) = s.split_once('.')?;
    if secs.is_empty()
        || frac.is_empty()
        || frac.len() > 9
        || !secs.bytes().all(|b| b.is_ascii_digit())
        || !frac.bytes().all(|b| b.is_ascii_digit())
    {
        return None;
    }
    let nanos: u32 = frac.parse::<u32>().ok()? * 10u32.pow(9 - frac.len() as u32);
    Some(Duration::new(secs.parse().ok()?, nanos))
}

fn parse_hex_bytes(s: &str) -> Option<Vec<u8>> {
    if !s.len().is_multiple_of(2) || !s.bytes().all(|b| b.is_ascii_hexdigit()) {
        return None;
    }
    (0..s.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&s[i..i + 2], 16).ok())
        .collect()
}

/// Parses a `candump -L` log: `(seconds.fraction) iface ID#DATA` per line (see the module docs).
pub fn parse_candump(text: &str) -> Result<Vec<RecordedFrame>, ReadError> {
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let n = n + 1;
        let line = line.trim();
        if line.is_empty() {
            continue;
        }
        let mut parts = line.split_whitespace();
        let (Some(time), Some(_iface), Some(frame), None) =
            (parts.next(), parts.next(), parts.next(), parts.next())
        else {
            return Err(candump_err(n, "expected `(time) interface ID#DATA`"));
        };
        let t = time
            .strip_prefix('(')
            .and_then(|t| t.strip_suffix(')'))
            .and_then(parse_time)
            .ok_or_else(|| candump_err(n, format!("bad timestamp {time:?}")))?;
        let (id, data) = frame
            .split_once('#')
            .ok_or_else(|| candump_err(n, format!("no `#` in frame {frame:?}")))?;
        if data.starts_with('#') {
            return Err(candump_err(n, "CAN FD frames (`##`) are not supported"));
        }
        let extended = match id.len() {
            3 => false,
            8 => true,
            _ => {
                return Err(candump_err(
                    n,
                    format!("identifier {id:?} is neither 3 nor 8 hex digits"),
                ))
            }
        };
        let id_value = u32::from_str_radix(id, 16)
            .ok()
            .filter(|&v| {
                if extended {
                    v <= 0x1FFF_FFFF
                } else {
                    v <= 0x7FF
                }
            })
            .ok_or_else(|| candump_err(n, format!("bad identifier {id:?}")))?;
        let (remote, bytes) = if let Some(rest) = data.strip_prefix('R') {
            if !(rest.is_empty() || (rest.len() == 1 && rest.as_bytes()[0].is_ascii_digit())) {
                return Err(candump_err(n, format!("bad remote frame {data:?}")));
            }
            (true, Vec::new())
        } else {
            let bytes = parse_hex_bytes(data)
                .ok_or_else(|| candump_err(n, format!("bad data {data:?}")))?;
            if bytes.len() > 8 {
                return Err(candump_err(
                    n,
                    format!("{} data bytes, at most 8", bytes.len()),
                ));
            }
            (false, bytes)
        };
        out.push(RecordedFrame {
            t,
            id: id_value,
            extended,
            remote,
            data: bytes,
        });
    }
    Ok(out)
}

/// A daemon session log, as the offline replay needs it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct McapSession {
    /// Received raw frames (topic [`MCAP_RX_TOPIC`]), in file order.
    pub frames: Vec<RecordedFrame>,
    /// When the collection window closed (the log's `exocal_log::CollectionEnd`), if the
    /// session got that far.
    pub collection_end: Option<Duration>,
    /// How many received frames the live session had ingested when collection ended: it
    /// calibrated on exactly the first that many frames of `frames`, so a replay that must agree
    /// with it stops there. Frames after them arrived during calibration and push. (A cut by
    /// time would not do: frames still queued in the receiver at the end carry earlier
    /// timestamps but were not used.)
    pub collection_frames: Option<u64>,
}

/// Reads a daemon session log: its received raw frames (the time is the kernel receive
/// timestamp where there is one, else the host's) and the end of its collection window.
pub fn read_mcap_session(bytes: &[u8]) -> Result<McapSession, ReadError> {
    let err = |what: String| ReadError {
        kind: InputKind::Mcap,
        line: None,
        what,
    };
    let stream = mcap::MessageStream::new(bytes).map_err(|e| err(e.to_string()))?;
    let mut frames = Vec::new();
    let mut collection_end = None;
    let mut collection_frames = None;
    let mut seen_channel = false;
    for (i, message) in stream.enumerate() {
        let m = message.map_err(|e| err(e.to_string()))?;
        if m.channel.topic == Topic::Collection.name() {
            let end = exocal_log::decode_collection_end(&m.channel.message_encoding, &m.data)
                .map_err(|e| err(format!("message {i} on {}: {e}", Topic::Collection.name())))?;
            if collection_end.is_none() {
                collection_end = Some(Duration::from_nanos(end.window_end_ns));
                collection_frames = Some(end.frames);
            }
            continue;
        }
        if m.channel.topic != MCAP_RX_TOPIC {
            continue;
        }
        seen_channel = true;
        let f = exocal_log::decode_can_frame(&m.channel.message_encoding, &m.data)
            .map_err(|e| err(format!("message {i} on {MCAP_RX_TOPIC}: {e}")))?;
        if f.data.len() > 8 {
            return Err(err(format!(
                "message {i} on {MCAP_RX_TOPIC}: {} data bytes",
                f.data.len()
            )));
        }
        frames.push(RecordedFrame {
            t: Duration::from_nanos(f.kernel_ns.unwrap_or(f.host_ns)),
            id: f.id,
            extended: f.extended,
            remote: f.remote,
            data: f.data,
        });
    }
    if !seen_channel {
        return Err(err(format!(
            "no message on {MCAP_RX_TOPIC}: not an exocald session log?"
        )));
    }
    Ok(McapSession {
        frames,
        collection_end,
        collection_frames,
    })
}

/// The received raw frames of a daemon session log (all of them; see [`read_mcap_session`]).
pub fn read_mcap_frames(bytes: &[u8]) -> Result<Vec<RecordedFrame>, ReadError> {
    read_mcap_session(bytes).map(|s| s.frames)
}

fn csv_err(line: usize, what: impl Into<String>) -> ReadError {
    ReadError {
        kind: InputKind::Csv,
        line: Some(line),
        what: what.into(),
    }
}

/// Parses CSV samples (format in the module docs).
pub fn parse_csv(text: &str) -> Result<Vec<TimedSample>, ReadError> {
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(n, l)| (n + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'));
    let (n, header) = lines.next().ok_or_else(|| ReadError {
        kind: InputKind::Csv,
        line: None,
        what: "empty file: no header".into(),
    })?;
    let header: String = header
        .split(',')
        .map(str::trim)
        .collect::<Vec<_>>()
        .join(",");
    if header != CSV_HEADER {
        return Err(csv_err(n, format!("header must be `{CSV_HEADER}`")));
    }
    let names: Vec<&str> = CSV_HEADER.split(',').collect();
    let mut out: Vec<TimedSample> = Vec::new();
    for (n, line) in lines {
        let fields: Vec<&str> = line.split(',').map(str::trim).collect();
        if fields.len() != names.len() {
            return Err(csv_err(
                n,
                format!("{} columns, expected {}", fields.len(), names.len()),
            ));
        }
        let mut v = [0.0; 15];
        for ((x, field), name) in v.iter_mut().zip(&fields).zip(&names) {
            *x = field
                .parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| csv_err(n, format!("{name} = {field:?} is not a finite number")))?;
        }
        let t = v[0];
        if let Some(prev) = out.last() {
            if t <= prev.t {
                return Err(csv_err(
                    n,
                    format!("t = {t} does not increase (previous {})", prev.t),
                ));
            }
        }
        let q = Quaternion::new(v[11], v[12], v[13], v[14]);
        let norm = q.norm();
        if (norm - 1.0).abs() > 1e-3 {
            return Err(csv_err(n, format!("quaternion norm {norm:.6}, expected 1")));
        }
        let rot = UnitQuaternion::from_quaternion(q);
        out.push(TimedSample {
            t,
            sample: Sample {
                joints: std::array::from_fn(|j| v[1 + j]),
                pose: Frame {
                    r: rot.to_rotation_matrix().into_inner(),
                    p: Vector3::new(v[8], v[9], v[10]),
                },
            },
        });
    }
    if out.is_empty() {
        return Err(ReadError {
            kind: InputKind::Csv,
            line: None,
            what: "no samples after the header".into(),
        });
    }
    Ok(out)
}

/// Writes `samples` in the CSV format [`parse_csv`] reads (full precision).
pub fn write_csv(samples: &[TimedSample], out: &mut impl std::io::Write) -> std::io::Result<()> {
    writeln!(out, "{CSV_HEADER}")?;
    for s in samples {
        let q = UnitQuaternion::from_matrix(&s.sample.pose.r);
        let p = s.sample.pose.p;
        write!(out, "{}", s.t)?;
        for j in s.sample.joints.iter().take(JOINTS) {
            write!(out, ",{j}")?;
        }
        writeln!(
            out,
            ",{},{},{},{},{},{},{}",
            p.x, p.y, p.z, q.w, q.i, q.j, q.k
        )?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use calib_core::{Scenario, ScenarioConfig};

    #[test]
    fn candump_lines_parse_exactly() {
        let log = "(1700000000.123456) vcan0 123#DEADBEEF\n\n(1700000001.5) can1 1ABCDEF0#\n(1700000002.000000001) vcan0 7FF#R\n";
        let f = parse_candump(log).unwrap();
        assert_eq!(f.len(), 3);
        assert_eq!(f[0].t, Duration::new(1_700_000_000, 123_456_000));
        assert_eq!((f[0].id, f[0].extended, f[0].remote), (0x123, false, false));
        assert_eq!(f[0].data, vec![0xDE, 0xAD, 0xBE, 0xEF]);
        assert_eq!(f[1].t, Duration::new(1_700_000_001, 500_000_000));
        assert_eq!((f[1].id, f[1].extended), (0x1ABC_DEF0, true));
        assert!(f[1].data.is_empty());
        assert!(f[2].remote);
        assert_eq!(f[2].t.subsec_nanos(), 1);
    }

    #[test]
    fn candump_errors_name_the_line_and_the_problem() {
        let cases = [
            ("(1.0) vcan0", "expected"),
            ("1.0 vcan0 123#00", "timestamp"),
            ("(1.0) vcan0 12300", "no `#`"),
            ("(1.0) vcan0 123##100", "CAN FD"),
            ("(1.0) vcan0 12#00", "neither 3 nor 8"),
            ("(1.0) vcan0 800#00", "bad identifier"),
            ("(1.0) vcan0 123#0", "bad data"),
            ("(1.0) vcan0 123#000102030405060708", "9 data bytes"),
            ("(1.0) vcan0 123#Rx", "remote"),
        ];
        for (line, what) in cases {
            let e = parse_candump(&format!("(0.5) vcan0 001#\n{line}\n")).unwrap_err();
            assert_eq!(e.line, Some(2), "{line}");
            assert_eq!(e.kind, InputKind::Candump);
            assert!(e.to_string().contains(what), "{line}: {e}");
            assert!(e.to_string().starts_with("candump log, line 2: "), "{e}");
        }
    }

    #[test]
    fn a_written_candump_log_reads_back_to_the_same_frames() {
        let frames: Vec<RecordedFrame> = (0..100u32)
            .map(|i| RecordedFrame {
                t: Duration::new(1_700_000_000 + u64::from(i / 10), i * 9_876_000),
                id: if i % 3 == 0 { 0x1000 + i } else { 0x100 + i },
                extended: i % 3 == 0,
                remote: i % 17 == 5,
                data: if i % 17 == 5 {
                    vec![]
                } else {
                    (0..(i % 9) as u8).collect()
                },
            })
            .collect();
        let mut out = Vec::new();
        crate::export::write_candump(&frames, "vcan0", &mut out).unwrap();
        assert_eq!(
            parse_candump(&String::from_utf8(out).unwrap()).unwrap(),
            frames
        );
    }

    fn samples(k: usize) -> Vec<TimedSample> {
        Scenario::new(ScenarioConfig::paper(), 2)
            .take(k)
            .enumerate()
            .map(|(i, s)| TimedSample {
                t: i as f64 * 0.01,
                sample: s.sample,
            })
            .collect()
    }

    #[test]
    fn csv_round_trips_through_write_csv() {
        let s = samples(50);
        let mut buf = Vec::new();
        write_csv(&s, &mut buf).unwrap();
        let text = format!("# a comment\n\n{}", String::from_utf8(buf).unwrap());
        let back = parse_csv(&text).unwrap();
        assert_eq!(back.len(), s.len());
        for (a, b) in back.iter().zip(&s) {
            assert_eq!(a.t, b.t);
            assert_eq!(a.sample.joints, b.sample.joints);
            assert_eq!(a.sample.pose.p, b.sample.pose.p);
            assert!((a.sample.pose.r - b.sample.pose.r).norm() < 1e-14);
        }
    }

    #[test]
    fn csv_errors_name_the_line_and_column() {
        let ok = "0.1,0,0,0,0,0,0,0,0.1,0.2,0.3,1,0,0,0";
        let cases = [
            (format!("t,q1\n{ok}"), 1, "header"),
            (format!("{CSV_HEADER}\n{ok},9"), 2, "16 columns"),
            (
                format!("{CSV_HEADER}\n{}", ok.replace("0.2", "nan")),
                2,
                "y = \"nan\"",
            ),
            (format!("{CSV_HEADER}\n{ok}\n{ok}"), 3, "does not increase"),
            (
                format!("{CSV_HEADER}\n{}", ok.replace(",1,0,0,0", ",2,0,0,0")),
                2,
                "quaternion norm",
            ),
        ];
        for (text, line, what) in cases {
            let e = parse_csv(&text).unwrap_err();
            assert_eq!(e.line, Some(line), "{text}");
            assert!(e.to_string().contains(what), "{e}");
        }
        assert!(parse_csv("").unwrap_err().to_string().contains("no header"));
        assert!(parse_csv(CSV_HEADER)
            .unwrap_err()
            .to_string()
            .contains("no samples"));
    }

    /// A log as written before the log was binary (JSON messages): still read.
    #[test]
    fn mcap_frames_are_read_from_the_rx_topic_only() {
        let mut buf = std::io::Cursor::new(Vec::new());
        {
            let mut w = mcap::Writer::new(&mut buf).unwrap();
            let schema = w
                .add_schema("exocal.CanFrame", "jsonschema", b"{}")
                .unwrap();
            let rx = w
                .add_channel(schema, MCAP_RX_TOPIC, "json", &Default::default())
                .unwrap();
            let tx = w
                .add_channel(schema, "/can/tx", "json", &Default::default())
                .unwrap();
            let msg = |id: u32, kernel: Option<u64>| {
                serde_json::json!({"id": id, "extended": false, "dlc": 2, "data": [1, 2],
                    "host_ns": 5_000_000_007u64, "kernel_ns": kernel})
                .to_string()
            };
            for (seq, (ch, id, k)) in [(rx, 0x10, Some(7u64)), (tx, 0x11, None), (rx, 0x12, None)]
                .into_iter()
                .enumerate()
            {
                let header = mcap::records::MessageHeader {
                    channel_id: ch,
                    sequence: seq as u32,
                    log_time: 1,
                    publish_time: 1,
                };
                w.write_to_known_channel(&header, msg(id, k).as_bytes())
                    .unwrap();
            }
            w.finish().unwrap();
        }
        let f = read_mcap_frames(buf.get_ref()).unwrap();
        assert_eq!(f.len(), 2);
        assert_eq!((f[0].id, f[0].t), (0x10, Duration::from_nanos(7)));
        assert_eq!(
            (f[1].id, f[1].t),
            (0x12, Duration::from_nanos(5_000_000_007))
        );
        assert_eq!(f[1].data, vec![1, 2]);
        let e = read_mcap_frames(b"not mcap").unwrap_err();
        assert_eq!(e.kind, InputKind::Mcap);
    }

    /// A log with `frames` received frames and, if given, a collection-end record after
    /// `end_after` of them, written with the schema's names, types and encoding.
    fn session_log(frames: u64, end: Option<(u64, &[u8])>) -> Vec<u8> {
        use prost::Message as _;
        let mut buf = std::io::Cursor::new(Vec::new());
        {
            let mut w = mcap::Writer::new(&mut buf).unwrap();
            let mut channel = |t: Topic| {
                let schema = t.schema();
                let id = w
                    .add_schema(schema.name, schema.encoding, &schema.data)
                    .unwrap();
                w.add_channel(
                    id,
                    t.name(),
                    exocal_log::MESSAGE_ENCODING,
                    &Default::default(),
                )
                .unwrap()
            };
            let (rx, collection) = (channel(Topic::CanRx), channel(Topic::Collection));
            let mut seq = 0;
            let mut put = |w: &mut mcap::Writer<_>, ch: u16, t: u64, body: &[u8]| {
                seq += 1;
                let header = mcap::records::MessageHeader {
                    channel_id: ch,
                    sequence: seq,
                    log_time: t,
                    publish_time: t,
                };
                w.write_to_known_channel(&header, body).unwrap();
            };
            for i in 0..frames {
                let f = exocal_log::CanFrameRecord {
                    id: 0x100 + i as u32,
                    extended: false,
                    remote: false,
                    dlc: 1,
                    data: vec![i as u8],
                    host_ns: 1_000 + i,
                    kernel_ns: None,
                };
                put(&mut w, rx, f.host_ns, &f.to_proto().encode_to_vec());
                if let Some((after, body)) = end {
                    if i + 1 == after {
                        put(&mut w, collection, 5_000, body);
                    }
                }
            }
            w.finish().unwrap();
        }
        buf.into_inner()
    }

    #[test]
    fn the_collection_end_is_the_structured_record_not_prose() {
        use prost::Message as _;
        let end = exocal_log::CollectionEnd {
            frames: 3,
            window_end_ns: 4_999,
            unknown: 0,
            malformed: 0,
            invalid_angles: 0,
            dropped: 0,
        };
        let body = end.encode_to_vec();
        let s = read_mcap_session(&session_log(5, Some((3, &body)))).unwrap();
        assert_eq!(s.frames.len(), 5);
        assert_eq!(s.frames[4].data, vec![4]);
        assert_eq!(s.frames[4].t, Duration::from_nanos(1_004));
        assert_eq!(s.collection_frames, Some(3));
        assert_eq!(s.collection_end, Some(Duration::from_nanos(4_999)));
        // A session that never finished collecting has no record: replayed whole.
        let s = read_mcap_session(&session_log(5, None)).unwrap();
        assert_eq!((s.collection_frames, s.collection_end), (None, None));
        // A damaged record is an error naming the topic, not a silent whole replay.
        let e = read_mcap_session(&session_log(5, Some((2, &[0xFF, 0xFF])))).unwrap_err();
        assert!(e.to_string().contains("/collection"), "{e}");
    }
}
