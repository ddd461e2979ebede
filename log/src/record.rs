//! What a session records, defined once: the writer ([`crate::write`]) writes each [`Record`]
//! on its topic, the daemon's other observers (the live view) take the same records.

use exocal_session::align::AlignedSample;
use exocal_session::window::Progress;

use crate::{proto, CanFrameRecord, CollectionEnd, Level};

/// The root of the arm's frames (frame 0 of the D-H table), as in the exported URDF.
pub const BASE_FRAME: &str = "base_link";
/// The tool frame (after the last row), as in the exported URDF.
pub const TOOL_FRAME: &str = "tool0";

/// A rigid transform: translation (m) and unit quaternion `[w, x, y, z]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Transform {
    /// Translation (m).
    pub translation: [f64; 3],
    /// Rotation, unit quaternion `[w, x, y, z]`.
    pub rotation_wxyz: [f64; 4],
}

/// One frame of the arm relative to its parent.
#[derive(Debug, Clone, PartialEq)]
pub struct Link {
    /// The parent frame's name.
    pub parent: String,
    /// This frame's name.
    pub child: String,
    /// Pose of `child` in `parent`.
    pub transform: Transform,
}

/// One thing a session records.
#[derive(Debug, Clone, Copy)]
pub enum Record<'a> {
    /// A raw frame received (`sent == false`) or sent.
    Frame {
        /// Whether the daemon sent it (`false`: received).
        sent: bool,
        /// The frame and its timestamps.
        frame: &'a CanFrameRecord,
    },
    /// A decoded joint reading: joint `joint` (1-based), angle (rad) and rate (rad/s).
    Joint {
        /// Joint number, 1-based.
        joint: usize,
        /// Joint angle (rad).
        angle: f64,
        /// Joint rate (rad/s).
        rate: f64,
    },
    /// A measured end-effector pose in [`BASE_FRAME`].
    EePose(&'a Transform),
    /// A raw IMU vector of a stream of `exocal_session::stream::STREAMS` (its column
    /// `Column::Vector`), on the stream's topic: the low 16 bits of the node's clock (µs) and
    /// the vector in the sensor's frame, in its message's unit.
    Vector {
        /// The stream, an index of `STREAMS`.
        stream: usize,
        /// The low 16 bits of the node's clock at sampling (µs).
        node_timestamp_lo_us: u32,
        /// x, y, z.
        xyz: [f64; 3],
    },
    /// The arm's frames (`calib_core::DhTable::links`, link by link).
    Arm(&'a [Link]),
    /// A sample on the common grid, as fed to the calibration, of an arm of `joints` joints
    /// (its readings past them are the padding, not logged).
    Aligned {
        /// The sample.
        sample: &'a AlignedSample,
        /// Joints of the arm.
        joints: usize,
    },
    /// Collection progress.
    Progress(&'a Progress),
    /// The end of the collection window.
    CollectionEnd(&'a CollectionEnd),
    /// The calibration result (and, once pushed, the push report).
    Calibration(&'a proto::Calibration),
    /// The arm's URDF: the nominal table's at the session's start, the calibrated
    /// table's with the calibration.
    RobotDescription(&'a str),
    /// What happened, human-readable.
    Event {
        /// Severity.
        level: Level,
        /// The text.
        message: &'a str,
    },
}
