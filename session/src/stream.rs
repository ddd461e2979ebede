//! The streams a session takes in, declared once.
//!
//! Contract: [`STREAMS`] is the one table of what the suit sends that a session uses — which
//! node sends it (by its role on the suit), in which message of the protocol, which column of
//! the session it fills, and the log topic (and live-view channel) it is recorded on. Every
//! stage reads this table: ingest files each decoded message under its stream ([`stream_of`]),
//! alignment resamples the streams whose column is part of the calibration sample
//! ([`Column::calibrates`]), the window counts them, the log and the live view record each on
//! its [`Stream::topic`], the data-quality summary and the report list them by name.
//!
//! A raw IMU vector the suit already sends (`ImuGyro`, `ImuAccel`, `ImuMag` of any node) is
//! added as one [`Column::Vector`] entry here: ingest, the log, the live view and the
//! data-quality table follow. The log's message for it is chosen by the protocol message
//! (`exocal_log::encode_vector` and the topic's type beside it), so a quantity the log has no
//! message for yet is that one message in `exocal.proto` and its arms there.

use exocal_dbc::spec::Kind;

use crate::MAX_JOINTS;

/// Which node sends a stream, by its role on the suit (the configuration maps joint roles to
/// node ids; the end effector is the DBC's `EndEffector` node).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Source {
    /// The node on joint `i` (0-based).
    Joint(usize),
    /// The end-effector reference node.
    EndEffector,
}

/// What a stream fills.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Column {
    /// The reading of joint `i` (0-based), rad: a column of the calibration sample.
    Angle(usize),
    /// The measured end-effector pose: a column of the calibration sample.
    Pose,
    /// A raw 3-axis IMU vector in the sensor's frame, in the unit of its message (`ImuGyro`
    /// rad/s, `ImuAccel` m/s², `ImuMag` µT): recorded and shown, not calibrated on.
    Vector,
}

impl Column {
    /// Values per sample (a pose: position and unit quaternion).
    pub const fn width(self) -> usize {
        match self {
            Column::Angle(_) => 1,
            Column::Pose => 7,
            Column::Vector => 3,
        }
    }

    /// Whether the column is part of the calibration sample (aligned onto the grid).
    pub const fn calibrates(self) -> bool {
        matches!(self, Column::Angle(_) | Column::Pose)
    }
}

/// One stream of the suit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Stream {
    /// Its name in summaries, the data-quality table and the report.
    pub name: &'static str,
    /// Who sends it.
    pub source: Source,
    /// In which message family of the protocol.
    pub message: Kind,
    /// What it fills.
    pub column: Column,
    /// The log topic it is recorded on, and the live view's channel of the same name. The
    /// joints share one topic: the log writes a sample of the arm (every joint's latest
    /// reading) as one message.
    pub topic: &'static str,
}

const fn joint(i: usize, name: &'static str) -> Stream {
    Stream {
        name,
        source: Source::Joint(i),
        message: Kind::JointState,
        column: Column::Angle(i),
        topic: JOINT_TOPIC,
    }
}

/// The log topic of the joint readings.
const JOINT_TOPIC: &str = "/joint_states";

/// Every stream a session takes in: the seven joint readings, the end-effector pose (the
/// calibration's sample), and the end-effector IMU's angular rate and magnetic field.
pub const STREAMS: [Stream; MAX_JOINTS + 3] = [
    joint(0, "Joint1"),
    joint(1, "Joint2"),
    joint(2, "Joint3"),
    joint(3, "Joint4"),
    joint(4, "Joint5"),
    joint(5, "Joint6"),
    joint(6, "Joint7"),
    Stream {
        name: "EndEffector",
        source: Source::EndEffector,
        message: Kind::EePose,
        column: Column::Pose,
        topic: "/ee_pose",
    },
    Stream {
        name: "EndEffector gyro",
        source: Source::EndEffector,
        message: Kind::ImuGyro,
        column: Column::Vector,
        topic: "/ee_gyro",
    },
    Stream {
        name: "EndEffector mag",
        source: Source::EndEffector,
        message: Kind::ImuMag,
        column: Column::Vector,
        topic: "/ee_mag",
    },
];

/// The stream of `message` from `source`, if the session takes it in.
pub fn stream_of(source: Source, message: Kind) -> Option<usize> {
    STREAMS
        .iter()
        .position(|s| s.source == source && s.message == message)
}

/// The stream of joint `i`'s reading.
pub const fn angle(i: usize) -> usize {
    i
}

/// The stream of the end-effector pose.
pub const POSE: usize = MAX_JOINTS;

/// The streams recorded as raw IMU vectors ([`Column::Vector`]), in [`STREAMS`] order.
pub fn vectors() -> impl Iterator<Item = usize> {
    (0..STREAMS.len()).filter(|&i| STREAMS[i].column == Column::Vector)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_joint_has_its_angle_stream_and_the_calibration_sample_is_complete() {
        for i in 0..MAX_JOINTS {
            assert_eq!(STREAMS[angle(i)].column, Column::Angle(i));
            assert_eq!(
                stream_of(Source::Joint(i), Kind::JointState),
                Some(angle(i))
            );
        }
        assert_eq!(STREAMS[POSE].column, Column::Pose);
        let calibrating = STREAMS.iter().filter(|s| s.column.calibrates()).count();
        assert_eq!(calibrating, MAX_JOINTS + 1);
        // No two streams share a source and message, or a name; the joints share a topic
        // (one message per sample of the arm), no other two do.
        for (i, a) in STREAMS.iter().enumerate() {
            for b in &STREAMS[i + 1..] {
                assert!(
                    (a.source, a.message) != (b.source, b.message),
                    "{a:?} {b:?}"
                );
                assert_ne!(a.name, b.name);
                let joints = matches!((a.column, b.column), (Column::Angle(_), Column::Angle(_)));
                assert_eq!(a.topic == b.topic, joints, "{a:?} {b:?}");
            }
        }
        assert!(vectors().all(|i| STREAMS[i].topic.starts_with('/')));
    }
}
