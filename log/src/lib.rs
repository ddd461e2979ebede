//! The session log's schema, defined once: the MCAP topics of an exocald session log, their
//! message types and JSON Schemas. The daemon writes with it (`exocald::mcaplog`), every
//! reader reads with it (the offline replay and the report's readers); a change of the log's
//! layout or encoding is a change here.
//!
//! Contract:
//! - every topic of [`Topic::ALL`] is a channel of every session log, even when empty;
//!   messages are JSON ([`MESSAGE_ENCODING`]) described by a JSON Schema ([`SCHEMA_ENCODING`],
//!   [`Topic::schema`]), readable by Foxglove and by any `mcap` reader without generated code;
//! - [`CanFrameRecord`] is a raw frame on `/can/rx` and `/can/tx`;
//! - [`CollectionEnd`] on `/collection` is written once, when the session stops collecting: a
//!   replay calibrates on exactly the first [`CollectionEnd::frames`] frames of `/can/rx`, as
//!   the live session did; a log without it never finished collecting.

#![deny(unsafe_code)]
#![warn(missing_docs)]

use serde::{Deserialize, Serialize};

/// The encoding of every message.
pub const MESSAGE_ENCODING: &str = "json";
/// The encoding of every schema.
pub const SCHEMA_ENCODING: &str = "jsonschema";

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
}

impl Topic {
    /// Every topic, in channel order.
    pub const ALL: [Topic; 10] = [
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
    ];

    /// The topic name in the file.
    pub const fn name(self) -> &'static str {
        match self {
            Topic::CanRx => "/can/rx",
            Topic::CanTx => "/can/tx",
            Topic::JointStates => "/joint_states",
            Topic::EePose => "/ee_pose",
            Topic::Tf => "/tf",
            Topic::Aligned => "/aligned",
            Topic::Progress => "/progress",
            Topic::Collection => "/collection",
            Topic::Calibration => "/calibration",
            Topic::Events => "/events",
        }
    }

    /// The topic called `name` in a file.
    pub fn from_name(name: &str) -> Option<Topic> {
        Topic::ALL.into_iter().find(|t| t.name() == name)
    }

    /// Schema name and JSON Schema text.
    pub fn schema(self) -> (&'static str, &'static str) {
        match self {
            Topic::CanRx | Topic::CanTx => ("exocal.CanFrame", schemas::CAN_FRAME),
            Topic::JointStates => ("exocal.JointState", schemas::JOINT_STATE),
            Topic::EePose => ("foxglove.PoseInFrame", schemas::POSE_IN_FRAME),
            Topic::Tf => ("foxglove.FrameTransforms", schemas::FRAME_TRANSFORMS),
            Topic::Aligned => ("exocal.AlignedSample", schemas::ALIGNED),
            Topic::Progress => ("exocal.Progress", schemas::PROGRESS),
            Topic::Collection => ("exocal.CollectionEnd", schemas::COLLECTION_END),
            Topic::Calibration => ("exocal.Calibration", schemas::CALIBRATION),
            Topic::Events => ("foxglove.Log", schemas::LOG),
        }
    }

    /// Position in [`Topic::ALL`] (the channel order).
    pub fn index(self) -> usize {
        Topic::ALL.iter().position(|&t| t == self).unwrap_or(0)
    }
}

/// JSON Schemas of the messages (Foxglove's well-known ones reduced to their required fields).
pub mod schemas {

    macro_rules! with_time {
        ($head:literal, $tail:literal) => {
            concat!(
                $head,
                r#"{"type":"object","properties":{"sec":{"type":"integer","minimum":0},"nsec":{"type":"integer","minimum":0,"maximum":999999999}}}"#,
                $tail
            )
        };
    }

    /// `exocal.CanFrame`.
    pub const CAN_FRAME: &str = r#"{"title":"exocal.CanFrame","type":"object","properties":{"id":{"type":"integer"},"extended":{"type":"boolean"},"dlc":{"type":"integer"},"data":{"type":"array","items":{"type":"integer"}},"host_ns":{"type":"integer"},"kernel_ns":{"type":["integer","null"]}},"required":["id","extended","dlc","data","host_ns"]}"#;
    /// `exocal.JointState` (ROS `sensor_msgs/JointState` shape).
    pub const JOINT_STATE: &str = with_time!(
        r#"{"title":"exocal.JointState","type":"object","properties":{"header":{"type":"object","properties":{"frame_id":{"type":"string"},"stamp":"#,
        r#"}},"name":{"type":"array","items":{"type":"string"}},"position":{"type":"array","items":{"type":"number"}},"velocity":{"type":"array","items":{"type":"number"}},"node_timestamp_us":{"type":"integer"}},"required":["header","name","position","velocity"]}"#
    );
    /// `foxglove.PoseInFrame`.
    pub const POSE_IN_FRAME: &str = with_time!(
        r#"{"title":"foxglove.PoseInFrame","type":"object","properties":{"timestamp":"#,
        r#","frame_id":{"type":"string"},"pose":{"type":"object","properties":{"position":{"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"}}},"orientation":{"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"},"w":{"type":"number"}}}}}},"required":["timestamp","frame_id","pose"]}"#
    );
    /// `foxglove.FrameTransforms`.
    pub const FRAME_TRANSFORMS: &str = with_time!(
        r#"{"title":"foxglove.FrameTransforms","type":"object","properties":{"transforms":{"type":"array","items":{"type":"object","properties":{"timestamp":"#,
        r#","parent_frame_id":{"type":"string"},"child_frame_id":{"type":"string"},"translation":{"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"}}},"rotation":{"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"},"w":{"type":"number"}}}},"required":["timestamp","parent_frame_id","child_frame_id","translation","rotation"]}}},"required":["transforms"]}"#
    );
    /// `exocal.AlignedSample`.
    pub const ALIGNED: &str = r#"{"title":"exocal.AlignedSample","type":"object","properties":{"t":{"type":"number"},"joints":{"type":"array","items":{"type":"number"}},"position":{"type":"array","items":{"type":"number"}},"orientation_wxyz":{"type":"array","items":{"type":"number"}}},"required":["t","joints","position","orientation_wxyz"]}"#;
    /// `exocal.Progress`.
    pub const PROGRESS: &str = r#"{"title":"exocal.Progress","type":"object","properties":{"elapsed_s":{"type":"number"},"samples":{"type":"integer"},"coverage":{"type":"array","items":{"type":"number"}},"condition_number":{"type":["number","null"]}},"required":["elapsed_s","samples","coverage"]}"#;
    /// `exocal.CollectionEnd`.
    pub const COLLECTION_END: &str = r#"{"title":"exocal.CollectionEnd","type":"object","properties":{"frames":{"type":"integer","minimum":0,"description":"frames received in the window: a replay calibrates on the first this many of /can/rx"},"window_end_ns":{"type":"integer","minimum":0},"unknown":{"type":"integer","minimum":0},"malformed":{"type":"integer","minimum":0},"invalid_angles":{"type":"integer","minimum":0},"dropped":{"type":"integer","minimum":0,"description":"frames the kernel dropped for this receiver (SO_RXQ_OVFL)"}},"required":["frames","window_end_ns","unknown","malformed","invalid_angles","dropped"]}"#;
    /// `exocal.Calibration` (free-form object: see the daemon's calibration report).
    pub const CALIBRATION: &str = r#"{"title":"exocal.Calibration","type":"object","description":"tables before/after, drift tau and sigma, metrics, validation verdict"}"#;
    /// `foxglove.Log`.
    pub const LOG: &str = with_time!(
        r#"{"title":"foxglove.Log","type":"object","properties":{"timestamp":"#,
        r#","level":{"type":"integer","description":"0 unknown, 1 debug, 2 info, 3 warning, 4 error, 5 fatal"},"message":{"type":"string"},"name":{"type":"string"},"file":{"type":"string"},"line":{"type":"integer","minimum":0}},"required":["timestamp","level","message","name","file","line"]}"#
    );
}

/// Foxglove/ROS time `{sec, nsec}`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Time {
    /// Whole seconds.
    pub sec: u64,
    /// Nanoseconds, below 1e9.
    pub nsec: u32,
}

impl Time {
    /// From nanoseconds.
    pub fn from_ns(ns: u64) -> Time {
        Time {
            sec: ns / 1_000_000_000,
            nsec: (ns % 1_000_000_000) as u32,
        }
    }
}

/// A raw CAN frame as logged.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CanFrameRecord {
    /// The identifier (11 or 29 bits).
    pub id: u32,
    /// A 29-bit identifier.
    pub extended: bool,
    /// Data length code.
    pub dlc: u8,
    /// The data bytes (at most 8: classic CAN).
    pub data: Vec<u8>,
    /// Host time (ns since the epoch) the daemon saw the frame.
    pub host_ns: u64,
    /// Kernel receive timestamp (ns since the epoch), when the socket provides one.
    pub kernel_ns: Option<u64>,
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

/// The end of the collection window, on `/collection` (see the crate docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct CollectionEnd {
    /// Frames received in the window: the live session calibrated on exactly the first this
    /// many frames of `/can/rx` (frames after them arrived while it calibrated and pushed).
    pub frames: u64,
    /// When the window closed (log time, ns since the epoch).
    pub window_end_ns: u64,
    /// Of `frames`, not frames of the DBC.
    pub unknown: u64,
    /// Of `frames`, DBC frames that did not decode.
    pub malformed: u64,
    /// Joint angles rejected as invalid.
    pub invalid_angles: u64,
    /// Frames the kernel dropped for this receiver (`SO_RXQ_OVFL`).
    pub dropped: u64,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_topic_has_a_unique_name_and_a_schema_that_is_json() {
        let mut names: Vec<&str> = Topic::ALL.iter().map(|t| t.name()).collect();
        names.sort_unstable();
        names.dedup();
        assert_eq!(names.len(), Topic::ALL.len());
        for t in Topic::ALL {
            assert_eq!(Topic::from_name(t.name()), Some(t));
            assert_eq!(Topic::ALL[t.index()], t);
            let (title, schema) = t.schema();
            let v: serde_json::Value = serde_json::from_str(schema).expect(title);
            assert_eq!(v["title"], title);
        }
    }

    #[test]
    fn records_read_back_as_written() {
        let end = CollectionEnd {
            frames: 340_861,
            window_end_ns: 1_795_000_000_123_456_789,
            unknown: 3,
            malformed: 2,
            invalid_angles: 1,
            dropped: 0,
        };
        let text = serde_json::to_string(&end).unwrap();
        assert_eq!(serde_json::from_str::<CollectionEnd>(&text).unwrap(), end);
        let frame = CanFrameRecord {
            id: 0x101,
            extended: false,
            dlc: 2,
            data: vec![1, 2],
            host_ns: 5,
            kernel_ns: None,
        };
        let text = serde_json::to_string(&frame).unwrap();
        assert_eq!(
            serde_json::from_str::<CanFrameRecord>(&text).unwrap(),
            frame
        );
        assert_eq!(
            Time::from_ns(1_500_000_001),
            Time {
                sec: 1,
                nsec: 500_000_001
            }
        );
    }
}
