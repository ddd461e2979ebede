//! The session log, in one crate: the MCAP topics of an exocald session log, their message
//! types, schemas and encoding (this module), what a session records ([`record`]), the writer
//! ([`write`](mod@write)), the readers ([`read`], and [`scan`] for files cut short) and the rewriting of a
//! cut file ([`recover`]). The daemon writes with it, every reader reads with it (the offline
//! replay and the report's readers); a change of the log's layout or encoding is a change here.
//!
//! | module | what |
//! |---|---|
//! | [`record`] | what a session records, once: frames, joints, poses, raw IMU vectors, the arm, progress, the calibration |
//! | [`write`](mod@write) | the per-session MCAP log (zstd chunks, flushed on an interval, protobuf with Foxglove's schemas) |
//! | [`read`] | bounded readers of recorded sessions (the `mcap` crate's for a whole file) |
//! | [`scan`] | the linear scan of a file cut short, record by record, with its own bounds |
//! | [`recover`] | a session log cut short (kill -9, power loss) read record by record and rewritten complete |
//!
//! Contract:
//! - every topic of [`Topic::ALL`] is a channel of every session log, even when empty;
//!   messages are protobuf ([`MESSAGE_ENCODING`]) with protobuf schemas ([`Topic::schema`]:
//!   a `FileDescriptorSet`), so Foxglove and any MCAP reader decode them without generated
//!   code. Poses, transforms, joint states and events use Foxglove's well-known schemas
//!   ([`fox`]); raw frames and the rest are ours ([`proto`], from `proto/exocal.proto`);
//! - [`CanFrameRecord`] is a raw frame on `/can/rx` and `/can/tx`, written in batches of a few
//!   milliseconds ([`proto::CanFrames`], [`CAN_BATCH_NS`]); logs written before then have one
//!   [`proto::CanFrame`] per message, and [`decode_can_frames`] reads either by the channel's
//!   schema name;
//! - [`CollectionEnd`] on `/collection` is written once, when the session stops collecting: a
//!   replay calibrates on exactly the first [`CollectionEnd::frames`] frames of `/can/rx`, as
//!   the live session did; a log without it never finished collecting;
//! - logs written before the log was binary (JSON messages, [`LEGACY_MESSAGE_ENCODING`]) stay
//!   readable: [`decode_can_frame`] and [`decode_collection_end`] read either encoding, by the
//!   channel's message encoding.

#![deny(unsafe_code)]
#![warn(missing_docs)]

use std::borrow::Cow;
use std::fmt;

use exocal_dbc::spec::Kind;
use exocal_session::stream::{self, Column, STREAMS};
use serde::{Deserialize, Serialize};

/// The encoding of every message.
pub const MESSAGE_ENCODING: &str = "protobuf";
/// A batch of raw frames ([`proto::CanFrames`]) spans at most this long (ns, host time).
pub const CAN_BATCH_NS: u64 = 10_000_000;
/// A batch of raw frames holds at most this many.
pub const CAN_BATCH_FRAMES: usize = 64;
/// The schema name of a single raw frame per message, as logs were written before the batches.
pub const SINGLE_FRAME_SCHEMA: &str = "exocal.CanFrame";
/// The encoding of every schema (a serialized `google.protobuf.FileDescriptorSet`).
pub const SCHEMA_ENCODING: &str = "protobuf";
/// The message encoding of logs written before the log was binary (JSON with JSON Schemas).
pub const LEGACY_MESSAGE_ENCODING: &str = "json";

pub mod read;
pub mod record;
pub mod recover;
pub mod scan;
pub mod write;

/// Our message types, generated from `proto/exocal.proto` (package `exocal`).
#[allow(missing_docs, clippy::doc_markdown)]
pub mod proto {
    include!(concat!(env!("OUT_DIR"), "/exocal.rs"));

    /// [`CanFrame::flags`] bit: a 29-bit identifier.
    pub const FLAG_EXTENDED: u32 = 1;
    /// [`CanFrame::flags`] bit: a remote-transmission request.
    pub const FLAG_REMOTE: u32 = 2;
    /// [`BatchedFrame::flags`] bit: the frame has a kernel receive time.
    pub const FLAG_KERNEL_TIME: u32 = 4;

    /// The `FileDescriptorSet` of `exocal.proto`: the schema data of every `exocal.*` message.
    pub const DESCRIPTOR_SET: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/exocal.bin"));
}

/// Foxglove's well-known message types the log uses.
pub mod fox {
    pub use foxglove::schemas::log::Level as LogLevel;
    pub use foxglove::schemas::{
        FrameTransform, FrameTransforms, JointState, JointStates, Log, Pose, PoseInFrame,
        Quaternion, Timestamp, Vector3,
    };
}

/// The log's topics.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Topic {
    /// Every raw frame received.
    CanRx,
    /// Every raw frame sent.
    CanTx,
    /// Each decoded joint state.
    JointStates,
    /// Each assembled end-effector reference pose.
    EePose,
    /// A raw IMU vector stream (an index of [`STREAMS`] whose column is
    /// [`Column::Vector`]), on the stream's own topic.
    Vector(usize),
    /// The arm's link frames.
    Tf,
    /// Samples on the common time grid, as fed to the calibration.
    Aligned,
    /// Collection progress.
    Progress,
    /// The end of the collection window ([`CollectionEnd`]).
    Collection,
    /// Tables, drift, metrics, verdict, push report.
    Calibration,
    /// What happened, human-readable.
    Events,
    /// The arm's URDF: the nominal table's, then the calibrated one's.
    RobotDescription,
}

/// A channel's schema: name, encoding and data, as MCAP stores it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Schema {
    /// The fully qualified message name (`foxglove.JointStates`, `exocal.CanFrame`).
    pub name: &'static str,
    /// [`SCHEMA_ENCODING`].
    pub encoding: &'static str,
    /// A serialized `FileDescriptorSet` that defines `name`.
    pub data: Cow<'static, [u8]>,
}

fn ours(name: &'static str) -> Schema {
    Schema {
        name,
        encoding: SCHEMA_ENCODING,
        data: Cow::Borrowed(proto::DESCRIPTOR_SET),
    }
}

fn foxglove_schema<T: foxglove::Encode>(name: &'static str) -> Schema {
    let s = T::get_schema().expect("Foxglove's well-known types have a schema");
    debug_assert_eq!(s.name, name);
    debug_assert_eq!(s.encoding, SCHEMA_ENCODING);
    Schema {
        name,
        encoding: SCHEMA_ENCODING,
        data: s.data,
    }
}

/// The topics that are not a raw IMU stream's, in channel order.
const FIXED: [Topic; 11] = [
    Topic::CanRx,
    Topic::CanTx,
    Topic::JointStates,
    Topic::EePose,
    Topic::Tf,
    Topic::Aligned,
    Topic::Progress,
    Topic::Collection,
    Topic::Calibration,
    Topic::Events,
    Topic::RobotDescription,
];

/// The raw IMU streams of [`STREAMS`]: their indices in table order (the first `.1` of the
/// array) and how many. Each is checked, at compile time, to be an IMU message's, so each has a
/// vector type.
const VECTOR_STREAMS: ([usize; STREAMS.len()], usize) = {
    let mut at = [0; STREAMS.len()];
    let (mut n, mut i) = (0, 0);
    while i < STREAMS.len() {
        if matches!(STREAMS[i].column, Column::Vector) {
            let kind = STREAMS[i].message;
            assert!(matches!(
                kind,
                Kind::ImuGyro | Kind::ImuAccel | Kind::ImuMag
            ));
            at[n] = i;
            n += 1;
        }
        i += 1;
    }
    (at, n)
};

/// How many raw IMU streams [`STREAMS`] has.
const VECTORS: usize = VECTOR_STREAMS.1;

impl Topic {
    /// Every topic, in channel order: the fixed topics, then one per raw IMU stream in
    /// [`STREAMS`] order.
    pub const ALL: [Topic; FIXED.len() + VECTORS] = {
        let mut all = [Topic::CanRx; FIXED.len() + VECTORS];
        let mut n = 0;
        while n < FIXED.len() {
            all[n] = FIXED[n];
            n += 1;
        }
        let mut k = 0;
        while k < VECTORS {
            all[n + k] = Topic::Vector(VECTOR_STREAMS.0[k]);
            k += 1;
        }
        all
    };

    /// The topic name in the file.
    pub const fn name(self) -> &'static str {
        match self {
            Topic::CanRx => "/can/rx",
            Topic::CanTx => "/can/tx",
            Topic::JointStates => STREAMS[stream::angle(0)].topic,
            Topic::EePose => STREAMS[stream::POSE].topic,
            Topic::Vector(i) => STREAMS[i].topic,
            Topic::Tf => "/tf",
            Topic::Aligned => "/aligned",
            Topic::Progress => "/progress",
            Topic::Collection => "/collection",
            Topic::Calibration => "/calibration",
            Topic::Events => "/events",
            Topic::RobotDescription => "/robot_description",
        }
    }

    /// The topic called `name` in a file.
    pub fn from_name(name: &str) -> Option<Topic> {
        Topic::ALL.into_iter().find(|t| t.name() == name)
    }

    /// The fully qualified name of the topic's message type.
    pub const fn message_type(self) -> &'static str {
        match self {
            Topic::CanRx | Topic::CanTx => "exocal.CanFrames",
            Topic::JointStates => "foxglove.JointStates",
            Topic::EePose => "foxglove.PoseInFrame",
            Topic::Vector(i) => vector_type(STREAMS[i].message),
            Topic::Tf => "foxglove.FrameTransforms",
            Topic::Aligned => "exocal.AlignedSample",
            Topic::Progress => "exocal.Progress",
            Topic::Collection => "exocal.CollectionEnd",
            Topic::Calibration => "exocal.Calibration",
            Topic::Events => "foxglove.Log",
            Topic::RobotDescription => "exocal.RobotDescription",
        }
    }

    /// The topic's schema.
    pub fn schema(self) -> Schema {
        let name = self.message_type();
        match self {
            Topic::JointStates => foxglove_schema::<fox::JointStates>(name),
            Topic::EePose => foxglove_schema::<fox::PoseInFrame>(name),
            Topic::Tf => foxglove_schema::<fox::FrameTransforms>(name),
            Topic::Events => foxglove_schema::<fox::Log>(name),
            _ => ours(name),
        }
    }

    /// Position in [`Topic::ALL`] (the channel order). A [`Topic::Vector`] of a stream that is
    /// not a raw IMU stream has none: a caller's bug, never a frame's (the stream comes from
    /// the table, not from the bus).
    pub fn index(self) -> usize {
        let i = Topic::ALL.iter().position(|&t| t == self);
        debug_assert!(i.is_some(), "{self:?} is not a topic of the log");
        i.unwrap_or(0)
    }
}

/// The message type of a raw IMU vector of `message` (`ImuGyro`, `ImuAccel`, `ImuMag`).
/// Only raw IMU kinds are [`Column::Vector`] streams (checked at compile time above).
const fn vector_type(message: Kind) -> &'static str {
    match message {
        Kind::ImuGyro => "exocal.AngularRate",
        Kind::ImuMag => "exocal.MagneticField",
        Kind::ImuAccel => "exocal.Acceleration",
        _ => panic!("a raw IMU stream is an ImuGyro, ImuAccel or ImuMag stream"),
    }
}

/// Encodes a sample of raw IMU stream `stream` (an index of [`STREAMS`]; the low 16 bits of
/// its node's clock, µs, and the vector in the sensor's frame) as its topic's message
/// ([`Topic::Vector`]), into `out` (cleared first).
pub fn encode_vector(stream: usize, node_timestamp_lo_us: u32, xyz: [f64; 3], out: &mut Vec<u8>) {
    use prost::Message as _;
    let s = &STREAMS[stream];
    let frame_id = s.name.to_string();
    let [x, y, z] = xyz;
    out.clear();
    // One message per quantity (each with its unit in its schema), all of one layout.
    macro_rules! vector {
        ($message:ident) => {
            proto::$message {
                frame_id,
                x,
                y,
                z,
                node_timestamp_lo_us,
            }
            .encode(out)
        };
    }
    let encoded = match s.message {
        Kind::ImuMag => vector!(MagneticField),
        Kind::ImuAccel => vector!(Acceleration),
        Kind::ImuGyro => vector!(AngularRate),
        other => unreachable!("{other:?} is not a raw IMU vector (see vector_type)"),
    };
    encoded.expect("a Vec grows to fit any message");
}

/// Nanoseconds since the epoch as a Foxglove timestamp (saturating after 2106).
pub fn timestamp(ns: u64) -> fox::Timestamp {
    let sec = u32::try_from(ns / 1_000_000_000).unwrap_or(u32::MAX);
    fox::Timestamp::new(sec, (ns % 1_000_000_000) as u32)
}

/// A raw CAN frame as logged.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct CanFrameRecord {
    /// The identifier (11 or 29 bits).
    pub id: u32,
    /// A 29-bit identifier.
    pub extended: bool,
    /// A remote-transmission request (no data).
    #[serde(default)]
    pub remote: bool,
    /// Data length code.
    pub dlc: u8,
    /// The data bytes (at most 8: classic CAN).
    pub data: Vec<u8>,
    /// Host time (ns since the epoch) the daemon saw the frame.
    pub host_ns: u64,
    /// Kernel receive timestamp (ns since the epoch), when the socket provides one.
    pub kernel_ns: Option<u64>,
}

impl CanFrameRecord {
    /// The frame recorded, `None` when its identifier or length is not a classic CAN frame's.
    pub fn frame(&self) -> Option<exocal_dbc::Frame> {
        use embedded_can::{ExtendedId, Frame as _, Id, StandardId};
        let id: Id = if self.extended {
            ExtendedId::new(self.id)?.into()
        } else {
            StandardId::new(u16::try_from(self.id).ok()?)?.into()
        };
        if self.remote {
            exocal_dbc::Frame::new_remote(id, usize::from(self.dlc))
        } else {
            exocal_dbc::Frame::new(id, &self.data)
        }
    }

    /// The message as written.
    pub fn to_proto(&self) -> proto::CanFrame {
        let mut flags = 0;
        if self.extended {
            flags |= proto::FLAG_EXTENDED;
        }
        if self.remote {
            flags |= proto::FLAG_REMOTE;
        }
        proto::CanFrame {
            id: self.id,
            flags,
            dlc: u32::from(self.dlc),
            data: self.data.clone(),
            kernel_ns: self.kernel_ns.unwrap_or(0),
            host_ns: self.host_ns,
        }
    }

    /// The record of a message as read; `None` for a DLC above 15.
    pub fn from_proto(m: proto::CanFrame) -> Option<CanFrameRecord> {
        Some(CanFrameRecord {
            id: m.id,
            extended: m.flags & proto::FLAG_EXTENDED != 0,
            remote: m.flags & proto::FLAG_REMOTE != 0,
            dlc: u8::try_from(m.dlc).ok().filter(|&d| d <= 15)?,
            data: m.data,
            host_ns: m.host_ns,
            kernel_ns: (m.kernel_ns != 0).then_some(m.kernel_ns),
        })
    }
}

/// A batch of raw frames as written ([`proto::CanFrames`]): their times as offsets from the
/// first frame's host time.
pub fn can_batch(frames: &[CanFrameRecord]) -> proto::CanFrames {
    let base_ns = frames.first().map_or(0, |f| f.host_ns);
    proto::CanFrames {
        base_ns,
        frames: frames
            .iter()
            .map(|f| {
                let mut flags = f.to_proto().flags;
                if f.kernel_ns.is_some() {
                    flags |= proto::FLAG_KERNEL_TIME;
                }
                proto::BatchedFrame {
                    id: f.id,
                    flags,
                    dlc: u32::from(f.dlc),
                    data: f.data.clone(),
                    host_offset_ns: f.host_ns.saturating_sub(base_ns),
                    kernel_offset_ns: f.kernel_ns.map_or(0, |k| k.wrapping_sub(f.host_ns) as i64),
                }
            })
            .collect(),
    }
}

/// Severity of an event (foxglove.Log levels).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Level {
    /// Detail.
    Debug = 1,
    /// What happened.
    Info = 2,
    /// Something worth a look.
    Warning = 3,
    /// A failure.
    Error = 4,
}

impl From<Level> for fox::LogLevel {
    fn from(l: Level) -> Self {
        match l {
            Level::Debug => fox::LogLevel::Debug,
            Level::Info => fox::LogLevel::Info,
            Level::Warning => fox::LogLevel::Warning,
            Level::Error => fox::LogLevel::Error,
        }
    }
}

/// The end of the collection window, on `/collection` (see the crate docs and
/// `proto/exocal.proto`).
pub type CollectionEnd = proto::CollectionEnd;

/// A message that does not decode: which encoding, and why.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DecodeError {
    /// The channel's message encoding.
    pub encoding: String,
    /// What is wrong.
    pub what: String,
}

impl fmt::Display for DecodeError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} message: {}", self.encoding, self.what)
    }
}

impl std::error::Error for DecodeError {}

/// Decodes a message of a channel whose message encoding is `encoding`: protobuf as written
/// now, JSON as written before (`legacy` reads the JSON shape).
fn decode<T: prost::Message + Default, J: serde::de::DeserializeOwned>(
    encoding: &str,
    data: &[u8],
    legacy: impl FnOnce(J) -> Option<T>,
) -> Result<T, DecodeError> {
    let err = |what: String| DecodeError {
        encoding: encoding.to_string(),
        what,
    };
    match encoding {
        MESSAGE_ENCODING => T::decode(data).map_err(|e| err(e.to_string())),
        LEGACY_MESSAGE_ENCODING => {
            let j: J = serde_json::from_slice(data).map_err(|e| err(e.to_string()))?;
            legacy(j).ok_or_else(|| err("out of range".into()))
        }
        other => Err(err(format!(
            "unknown encoding {other:?} (expected {MESSAGE_ENCODING:?}, or {LEGACY_MESSAGE_ENCODING:?} for older logs)"
        ))),
    }
}

/// A raw frame of `/can/rx` or `/can/tx`, in either encoding (see the crate docs).
pub fn decode_can_frame(encoding: &str, data: &[u8]) -> Result<CanFrameRecord, DecodeError> {
    let m: proto::CanFrame = decode(encoding, data, |r: CanFrameRecord| Some(r.to_proto()))?;
    let dlc = m.dlc;
    CanFrameRecord::from_proto(m).ok_or_else(|| DecodeError {
        encoding: encoding.to_string(),
        what: format!("DLC {dlc} (at most 15)"),
    })
}

/// The raw frames of a message of `/can/rx` or `/can/tx` whose channel's schema is `schema`
/// and message encoding `encoding`: a batch ([`proto::CanFrames`]) as written now, one frame
/// ([`decode_can_frame`]) as written before.
pub fn decode_can_frames(
    schema: &str,
    encoding: &str,
    data: &[u8],
) -> Result<Vec<CanFrameRecord>, DecodeError> {
    if schema == SINGLE_FRAME_SCHEMA || encoding == LEGACY_MESSAGE_ENCODING {
        return decode_can_frame(encoding, data).map(|f| vec![f]);
    }
    let err = |what: String| DecodeError {
        encoding: encoding.to_string(),
        what,
    };
    if encoding != MESSAGE_ENCODING {
        return Err(err(format!(
            "unknown encoding {encoding:?} (expected {MESSAGE_ENCODING:?})"
        )));
    }
    let batch =
        <proto::CanFrames as prost::Message>::decode(data).map_err(|e| err(e.to_string()))?;
    let base = batch.base_ns;
    batch
        .frames
        .into_iter()
        .enumerate()
        .map(|(i, m)| {
            let host_ns = base
                .checked_add(m.host_offset_ns)
                .ok_or_else(|| err(format!("frame {i}: host time beyond 2^64 ns")))?;
            let kernel_ns = match m.flags & proto::FLAG_KERNEL_TIME {
                0 => None,
                _ => Some(
                    host_ns
                        .checked_add_signed(m.kernel_offset_ns)
                        .ok_or_else(|| err(format!("frame {i}: kernel time out of range")))?,
                ),
            };
            let dlc = u8::try_from(m.dlc)
                .ok()
                .filter(|&d| d <= 15)
                .ok_or_else(|| err(format!("frame {i}: DLC {} (at most 15)", m.dlc)))?;
            Ok(CanFrameRecord {
                id: m.id,
                extended: m.flags & proto::FLAG_EXTENDED != 0,
                remote: m.flags & proto::FLAG_REMOTE != 0,
                dlc,
                data: m.data,
                host_ns,
                kernel_ns,
            })
        })
        .collect()
}

/// The `/collection` record, in either encoding (see the crate docs).
pub fn decode_collection_end(encoding: &str, data: &[u8]) -> Result<CollectionEnd, DecodeError> {
    decode(encoding, data, |r: CollectionEnd| Some(r))
}

#[cfg(test)]
mod tests {
    use super::*;
    use prost::Message as _;

    #[test]
    fn every_raw_imu_stream_has_a_topic_of_its_quantitys_type() {
        let vectors: Vec<usize> = stream::vectors().collect();
        assert!(vectors.len() >= 2, "the gyro and the magnetometer");
        for i in vectors {
            let topic = Topic::Vector(i);
            assert!(Topic::ALL.contains(&topic));
            let mut out = Vec::new();
            encode_vector(i, 7, [1.0, -2.0, 3.0], &mut out);
            let (name, xyz, ts) = match STREAMS[i].message {
                Kind::ImuGyro => {
                    assert_eq!(topic.message_type(), "exocal.AngularRate");
                    let m = proto::AngularRate::decode(&*out).unwrap();
                    (m.frame_id, [m.x, m.y, m.z], m.node_timestamp_lo_us)
                }
                Kind::ImuMag => {
                    assert_eq!(topic.message_type(), "exocal.MagneticField");
                    let m = proto::MagneticField::decode(&*out).unwrap();
                    (m.frame_id, [m.x, m.y, m.z], m.node_timestamp_lo_us)
                }
                Kind::ImuAccel => {
                    assert_eq!(topic.message_type(), "exocal.Acceleration");
                    let m = proto::Acceleration::decode(&*out).unwrap();
                    (m.frame_id, [m.x, m.y, m.z], m.node_timestamp_lo_us)
                }
                other => panic!("{}: {other:?} is not a raw IMU vector", STREAMS[i].name),
            };
            assert_eq!(
                (name.as_str(), xyz, ts),
                (STREAMS[i].name, [1.0, -2.0, 3.0], 7)
            );
        }
    }

    #[test]
    fn every_topic_has_a_unique_name_and_a_schema_that_defines_its_type() {
        let mut names: Vec<&str> = Topic::ALL.iter().map(|t| t.name()).collect();
        names.sort_unstable();
        names.dedup();
        assert_eq!(names.len(), Topic::ALL.len());
        for t in Topic::ALL {
            assert_eq!(Topic::from_name(t.name()), Some(t));
            assert_eq!(Topic::ALL[t.index()], t);
            let schema = t.schema();
            assert_eq!(schema.encoding, "protobuf");
            let fds =
                prost_types::FileDescriptorSet::decode(&*schema.data).expect("a FileDescriptorSet");
            let (package, message) = schema.name.split_once('.').unwrap();
            let defined = fds.file.iter().any(|f| {
                f.package() == package && f.message_type.iter().any(|m| m.name() == message)
            });
            assert!(defined, "{}: {} not in its schema", t.name(), schema.name);
        }
    }

    fn frame() -> CanFrameRecord {
        CanFrameRecord {
            id: 0x1ABC_DEF0,
            extended: true,
            remote: false,
            dlc: 2,
            data: vec![1, 2],
            host_ns: 1_795_000_000_123_456_789,
            kernel_ns: Some(1_795_000_000_123_000_000),
        }
    }

    #[test]
    fn records_read_back_as_written_in_both_encodings() {
        let end = CollectionEnd {
            frames: 340_861,
            window_end_ns: 1_795_000_000_123_456_789,
            unknown: 3,
            malformed: 2,
            invalid_angles: 1,
            dropped: 0,
            stream: None,
        };
        let bin = end.encode_to_vec();
        assert_eq!(decode_collection_end("protobuf", &bin).unwrap(), end);
        let json = serde_json::to_vec(&end).unwrap();
        assert_eq!(decode_collection_end("json", &json).unwrap(), end);

        for f in [
            frame(),
            CanFrameRecord {
                remote: true,
                extended: false,
                id: 0x7FF,
                data: vec![],
                kernel_ns: None,
                ..frame()
            },
        ] {
            let bin = f.to_proto().encode_to_vec();
            assert_eq!(decode_can_frame("protobuf", &bin).unwrap(), f);
        }
        // A JSON frame as the old writer wrote it (no `remote`).
        let old =
            br#"{"id":257,"extended":false,"dlc":2,"data":[1,2],"host_ns":5,"kernel_ns":null}"#;
        let f = decode_can_frame("json", old).unwrap();
        assert_eq!(
            (f.id, f.remote, f.data, f.kernel_ns),
            (257, false, vec![1, 2], None)
        );
    }

    /// A batch reads back frame for frame (times, kernel time or none, extended and remote
    /// frames), and a log's single-frame messages (before the batches) still read by their
    /// schema's name.
    #[test]
    fn batches_read_back_as_written_and_single_frames_still_read() {
        let frames = vec![
            frame(),
            CanFrameRecord {
                id: 0x1abc_def0,
                extended: true,
                kernel_ns: None,
                host_ns: frame().host_ns + 7_000_123,
                ..frame()
            },
            CanFrameRecord {
                remote: true,
                data: vec![],
                dlc: 4,
                kernel_ns: Some(frame().host_ns + 9_000_000),
                host_ns: frame().host_ns + 8_000_000,
                ..frame()
            },
        ];
        let bin = can_batch(&frames).encode_to_vec();
        assert_eq!(
            decode_can_frames("exocal.CanFrames", "protobuf", &bin).unwrap(),
            frames
        );
        let single = frame().to_proto().encode_to_vec();
        assert_eq!(
            decode_can_frames(SINGLE_FRAME_SCHEMA, "protobuf", &single).unwrap(),
            vec![frame()]
        );
        let e = decode_can_frames("exocal.CanFrames", "protobuf", &single).unwrap_err();
        assert!(e.to_string().starts_with("protobuf message: "), "{e}");
    }

    #[test]
    fn bad_messages_name_the_encoding_and_the_problem() {
        let e = decode_can_frame("cdr", b"").unwrap_err();
        assert!(e.to_string().contains("unknown encoding \"cdr\""), "{e}");
        let e = decode_can_frame("json", b"{\"id\":1}").unwrap_err();
        assert!(e.to_string().starts_with("json message: "), "{e}");
        let e = decode_collection_end("protobuf", &[0xFF, 0xFF]).unwrap_err();
        assert!(e.to_string().starts_with("protobuf message: "), "{e}");
        let mut m = frame().to_proto();
        m.dlc = 16;
        let e = decode_can_frame("protobuf", &m.encode_to_vec()).unwrap_err();
        assert!(e.to_string().contains("DLC 16"), "{e}");
    }

    #[test]
    fn timestamps_split_nanoseconds() {
        let t = timestamp(1_500_000_001);
        assert_eq!((t.sec(), t.nsec()), (1, 500_000_001));
    }
}
