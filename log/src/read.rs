//! Bounded readers of recorded session logs.
//!
//! Contract: [`read_mcap_session`] returns a daemon session log's received raw frames
//! ([`Topic::CanRx`]) in file order, as the bus delivered them (kernel receive time where there
//! is one, else the host's), and the end of its collection window ([`Topic::Collection`]). It
//! neither decodes the frames nor reorders them; bad input is a [`ReadError`] naming what is
//! wrong, never a panic.

use std::fmt;
use std::time::Duration;

use exocal_dbc::Received;

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
}

const RX: &str = Topic::CanRx.name();

/// Reads a daemon session log: its received raw frames (the time is the kernel receive
/// timestamp where there is one, else the host's) and the end of its collection window.
pub fn read_mcap_session(bytes: &[u8]) -> Result<McapSession, ReadError> {
    let err = |what: String| ReadError { what };
    let stream = mcap::MessageStream::new(bytes).map_err(|e| err(e.to_string()))?;
    let mut frames = Vec::new();
    let mut collection_end = None;
    let mut collection_frames = None;
    let mut gate = None;
    let mut seen_channel = false;
    for (i, message) in stream.enumerate() {
        let m = message.map_err(|e| err(e.to_string()))?;
        if m.channel.topic == Topic::Collection.name() {
            let end = crate::decode_collection_end(&m.channel.message_encoding, &m.data)
                .map_err(|e| err(format!("message {i} on {}: {e}", Topic::Collection.name())))?;
            if collection_end.is_none() {
                collection_end = Some(Duration::from_nanos(end.window_end_ns));
                collection_frames = Some(end.frames);
                gate = end.stream;
            }
            continue;
        }
        if m.channel.topic != RX {
            continue;
        }
        seen_channel = true;
        let f = crate::decode_can_frame(&m.channel.message_encoding, &m.data)
            .map_err(|e| err(format!("message {i} on {RX}: {e}")))?;
        if f.data.len() > 8 {
            return Err(err(format!(
                "message {i} on {RX}: {} data bytes",
                f.data.len()
            )));
        }
        let frame = f.frame().ok_or_else(|| {
            err(format!(
                "message {i} on {RX}: identifier {:#x} invalid",
                f.id
            ))
        })?;
        frames.push(Received {
            frame,
            timestamp: Duration::from_nanos(f.kernel_ns.unwrap_or(f.host_ns)),
        });
    }
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
    })
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
        let f = read_mcap_session(buf.get_ref()).map(|s| s.frames).unwrap();
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
        let e = read_mcap_session(b"not mcap").unwrap_err();
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
        let s = read_mcap_session(&session_log(5, Some((3, &body)))).unwrap();
        assert_eq!(s.frames.len(), 5);
        assert_eq!(s.frames[4].frame.data(), &[4]);
        assert_eq!(s.frames[4].timestamp, Duration::from_nanos(1_004));
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
