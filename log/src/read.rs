//! Bounded readers of recorded session logs.
//!
//! Contract: [`read_mcap_session`] returns a daemon session log's received raw frames
//! ([`Topic::CanRx`]) in file order, as the bus delivered them (kernel receive time where there
//! is one, else the host's), the end of its collection window ([`Topic::Collection`]) and the
//! push outcome of its last [`Topic::Calibration`] record that has one (protobuf logs). It
//! neither decodes the frames nor reorders them. It reads through [`crate::scan`]: one record
//! at a time, every length and chunk checked, so its memory is one chunk plus the frames it
//! keeps, each of which the caller admits (or refuses, ending the read) as it comes, told
//! whether it came before or after the collection end ([`Phase`]). A finished
//! log must be whole; one cut short (no end magic: a killed daemon's) is read up to where it
//! stops, and [`McapSession::cut`] says where. Bad input is a [`ReadError`] naming what is
//! wrong, never a panic.

use std::collections::HashMap;
use std::fmt;
use std::io::Read;
use std::time::Duration;

use exocal_dbc::Received;

use crate::scan::{self, McapRecord, Scan};
use crate::Topic;

/// A session log that does not read: what is wrong.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ReadError {
    /// What is wrong.
    pub what: String,
}

impl fmt::Display for ReadError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "MCAP log: {}", self.what)
    }
}

impl std::error::Error for ReadError {}

/// A daemon session log, as the offline replay needs it.
#[derive(Debug, Clone, PartialEq)]
pub struct McapSession {
    /// Received raw frames (topic [`Topic::CanRx`]), in file order.
    pub frames: Vec<Received>,
    /// When the collection window closed (the log's `crate::CollectionEnd`), if the
    /// session got that far.
    pub collection_end: Option<Duration>,
    /// How many received frames the live session had ingested when collection ended: it
    /// calibrated on exactly the first that many frames of `frames`, so a replay that must agree
    /// with it stops there. Frames after them arrived during calibration and push. (A cut by
    /// time would not do: frames still queued in the receiver at the end carry earlier
    /// timestamps but were not used.)
    pub collection_frames: Option<u64>,
    /// The stream gate's record of the collection (`None`: streams taken unverified).
    pub stream: Option<crate::proto::StreamVerification>,
    /// The push outcome per node, from the last `/calibration` record that carries one (empty
    /// when nothing was pushed, or in a log written before the log was binary).
    pub push: Vec<crate::proto::NodePush>,
    /// For a log cut short (no end magic): what was read and where it stops.
    pub cut: Option<Scan>,
}

const RX: &str = Topic::CanRx.name();

/// What a channel carries, for this reader.
enum Carries {
    /// `/can/rx`: its schema's name and message encoding.
    Rx(String, String),
    Collection(String),
    /// `/calibration` in protobuf (its push outcome).
    Calibration,
    Other,
}

/// When a frame was received, as the log tells it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Phase {
    /// Before the collection end record (or in a log without one).
    Collection,
    /// After it: during calibration and push.
    After,
}

/// Reads a daemon session log from `input` (see the module docs). Each received frame is passed
/// to `admit`, with its [`Phase`], before it is kept: its error ends the read, as the
/// [`ReadError`] naming the message.
pub fn read_mcap_session(
    input: impl Read,
    admit: impl FnMut(&Received, Phase) -> Result<(), String>,
) -> Result<McapSession, ReadError> {
    read(input, admit, true)
}

/// What [`read_mcap_session`] reads except the frames ([`McapSession::frames`] is empty): the
/// collection end, the stream gate's record and the push outcome, in the memory of one chunk
/// whatever the log's length (`exocald nodes` reads the last push of logs of any size).
pub fn read_mcap_record(input: impl Read) -> Result<McapSession, ReadError> {
    read(input, admit_all, false)
}

fn read(
    input: impl Read,
    mut admit: impl FnMut(&Received, Phase) -> Result<(), String>,
    keep_frames: bool,
) -> Result<McapSession, ReadError> {
    let err = |what: String| ReadError { what };
    let mut frames = Vec::new();
    let mut collection_end = None;
    let mut collection_frames = None;
    let mut push = Vec::new();
    let mut gate = None;
    let mut seen_channel = false;
    let mut channels: HashMap<u16, Carries> = HashMap::new();
    let mut schemas: HashMap<u16, String> = HashMap::new();
    let mut i = 0u64;
    let scanned = scan::scan(input, |records| {
        for r in records {
            let (channel_id, data) = match *r {
                McapRecord::Schema { id, name, .. } => {
                    schemas.insert(id, name.to_string());
                    continue;
                }
                McapRecord::Channel {
                    id,
                    schema_id,
                    topic,
                    encoding,
                    ..
                } => {
                    let carries = match topic {
                        RX => Carries::Rx(
                            schemas.get(&schema_id).cloned().unwrap_or_default(),
                            encoding.to_string(),
                        ),
                        t if t == Topic::Collection.name() => {
                            Carries::Collection(encoding.to_string())
                        }
                        t if t == Topic::Calibration.name()
                            && encoding == crate::MESSAGE_ENCODING =>
                        {
                            Carries::Calibration
                        }
                        _ => Carries::Other,
                    };
                    channels.insert(id, carries);
                    continue;
                }
                McapRecord::Message {
                    channel_id, data, ..
                } => (channel_id, data),
                _ => continue,
            };
            i += 1;
            let n = i - 1;
            match channels.get(&channel_id) {
                Some(Carries::Collection(encoding)) => {
                    let end = crate::decode_collection_end(encoding, data).map_err(|e| {
                        err(format!("message {n} on {}: {e}", Topic::Collection.name()))
                    })?;
                    if collection_end.is_none() {
                        collection_end = Some(Duration::from_nanos(end.window_end_ns));
                        collection_frames = Some(end.frames);
                        gate = end.stream;
                    }
                }
                Some(Carries::Calibration) => {
                    let c = <crate::proto::Calibration as prost::Message>::decode(data).map_err(
                        |e| err(format!("message {n} on {}: {e}", Topic::Calibration.name())),
                    )?;
                    if !c.push.is_empty() {
                        push = c.push;
                    }
                }
                Some(Carries::Rx(schema, encoding)) => {
                    seen_channel = true;
                    let batch = crate::decode_can_frames(schema, encoding, data)
                        .map_err(|e| err(format!("message {n} on {RX}: {e}")))?;
                    for f in batch {
                        if f.data.len() > 8 {
                            return Err(err(format!(
                                "message {n} on {RX}: {} data bytes",
                                f.data.len()
                            )));
                        }
                        let frame = f.frame().ok_or_else(|| {
                            err(format!(
                                "message {n} on {RX}: identifier {:#x} invalid",
                                f.id
                            ))
                        })?;
                        let rx = Received {
                            frame,
                            timestamp: Duration::from_nanos(f.kernel_ns.unwrap_or(f.host_ns)),
                        };
                        let phase = match collection_end {
                            None => Phase::Collection,
                            Some(_) => Phase::After,
                        };
                        admit(&rx, phase).map_err(|e| err(format!("message {n} on {RX}: {e}")))?;
                        if keep_frames {
                            frames.push(rx);
                        }
                    }
                }
                _ => {}
            }
        }
        Ok(())
    })?;
    let cut = match (&scanned.end, scanned.finished) {
        (scan::End::NotMcap, _) => return Err(err(scanned.end.to_string())),
        (scan::End::Complete, true) => None,
        (_, true) => return Err(err(scanned.end.to_string())),
        (_, false) => Some(scanned),
    };
    if !seen_channel {
        return Err(err(format!(
            "no message on {RX}: not an exocald session log?"
        )));
    }
    Ok(McapSession {
        frames,
        collection_end,
        collection_frames,
        stream: gate,
        push,
        cut,
    })
}

/// An `admit` for [`read_mcap_session`] that keeps every frame (for inputs known to be small).
pub fn admit_all(_: &Received, _: Phase) -> Result<(), String> {
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use embedded_can::Frame as _;

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
                .add_channel(schema, RX, "json", &Default::default())
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
        let f = read_mcap_session(buf.get_ref().as_slice(), admit_all)
            .map(|s| s.frames)
            .unwrap();
        assert_eq!(f.len(), 2);
        assert_eq!(
            (f[0].frame.raw_id(), f[0].timestamp),
            (0x10, Duration::from_nanos(7))
        );
        assert_eq!(
            (f[1].frame.raw_id(), f[1].timestamp),
            (0x12, Duration::from_nanos(5_000_000_007))
        );
        assert_eq!(f[1].frame.data(), &[1, 2]);
        let e = read_mcap_session(&b"not mcap"[..], admit_all).unwrap_err();
        assert!(e.to_string().starts_with("MCAP log: "), "{e}");
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
                w.add_channel(id, t.name(), crate::MESSAGE_ENCODING, &Default::default())
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
                let f = crate::CanFrameRecord {
                    id: 0x100 + i as u32,
                    extended: false,
                    remote: false,
                    dlc: 1,
                    data: vec![i as u8],
                    host_ns: 1_000 + i,
                    kernel_ns: None,
                };
                let batch = crate::can_batch(std::slice::from_ref(&f));
                put(&mut w, rx, f.host_ns, &batch.encode_to_vec());
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
        let end = crate::CollectionEnd {
            frames: 3,
            window_end_ns: 4_999,
            unknown: 0,
            malformed: 0,
            invalid_angles: 0,
            dropped: 0,
            stream: None,
        };
        let body = end.encode_to_vec();
        let s = read_mcap_session(&session_log(5, Some((3, &body)))[..], admit_all).unwrap();
        assert_eq!(s.frames.len(), 5);
        assert_eq!(s.frames[4].frame.data(), &[4]);
        assert_eq!(s.frames[4].timestamp, Duration::from_nanos(1_004));
        assert_eq!(s.collection_frames, Some(3));
        assert_eq!(s.cut, None);
        assert_eq!(s.collection_end, Some(Duration::from_nanos(4_999)));
        // A session that never finished collecting has no record: replayed whole.
        let s = read_mcap_session(&session_log(5, None)[..], admit_all).unwrap();
        assert_eq!((s.collection_frames, s.collection_end), (None, None));
        assert_eq!(s.frames.len(), 5);
        // A damaged record is an error naming the topic, not a silent whole replay.
        let e = read_mcap_session(&session_log(5, Some((2, &[0xFF, 0xFF])))[..], admit_all)
            .unwrap_err();
        assert!(e.to_string().contains("/collection"), "{e}");
        // `nodes` reads the record without the frames, so a long log is not held in memory:
        // the same record, no frame kept.
        let log = session_log(5, Some((3, &body)));
        let (whole, record) = (
            read_mcap_session(&log[..], admit_all).unwrap(),
            read_mcap_record(&log[..]).unwrap(),
        );
        assert!(record.frames.is_empty());
        assert_eq!(
            McapSession {
                frames: whole.frames.clone(),
                ..record
            },
            whole
        );
    }

    /// A finished log must be whole: damage anywhere in its data section is an error naming the
    /// record. One without its end magic is read up to where it stops, and says so. The caller
    /// refuses frames through `admit`, which ends the read at that frame.
    #[test]
    fn damage_cuts_and_refused_frames() {
        let log = session_log(40, None);
        let whole = read_mcap_session(log.as_slice(), admit_all).unwrap();
        let mut bad = log.clone();
        // A byte of the chunk's compressed records.
        let summary = mcap::Summary::read(&log).unwrap().unwrap();
        let chunk = &summary.chunk_indexes[0];
        let at = (chunk.chunk_start_offset + chunk.chunk_length) as usize - 5;
        bad[at] ^= 0x10;
        let e = read_mcap_session(bad.as_slice(), admit_all).unwrap_err();
        assert!(e.to_string().contains("is damaged"), "{e}");
        // Cut inside the chunk: its frames are lost, the rest reads, and the cut is named.
        let s = read_mcap_session(&log[..at], admit_all);
        assert!(s.unwrap_err().to_string().contains("no message on /can/rx"));
        // Cut in the summary: every frame is there.
        let s = read_mcap_session(&log[..log.len() - 200], admit_all).unwrap();
        let scan = s.cut.expect("cut short");
        assert!(
            scan.to_string().contains("the data section is complete"),
            "{scan}"
        );
        assert_eq!(s.frames, whole.frames);
        let mut n = 0;
        let e = read_mcap_session(log.as_slice(), |rx, phase| {
            assert_eq!(phase, Phase::Collection);
            n += 1;
            if n > 10 {
                Err(format!("frame at {:?} refused", rx.timestamp))
            } else {
                Ok(())
            }
        })
        .unwrap_err();
        assert_eq!(
            e.to_string(),
            "MCAP log: message 10 on /can/rx: frame at 1.01µs refused"
        );
    }
}
