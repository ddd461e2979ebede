//! The session's observers, fed once: [`Recorder`] hands every [`Record`] a session makes to
//! its MCAP log ([`SessionLog`]) and to its other [`Observer`]s (the live view, when enabled;
//! in a demo, the emulated wearer's ear).
//!
//! Contract: the log's errors are the session's ([`Recorder::record`] returns them); the live
//! view never fails a session.

use std::io::{BufWriter, Write};

use exocal_log::{proto, CanFrameRecord, CollectionEnd, Level};

use crate::log::records::{Link, Observer, Record, Transform};
use exocal_log::write::{Counts, LogError, SessionLog};
use exocal_session::align::AlignedSample;
use exocal_session::ingest::Reading;
use exocal_session::stream::{Column, STREAMS};
use exocal_session::window::Progress;

/// The session's observers: its log and the others. The methods are the records a session
/// writes (see [`Record`]).
pub struct Recorder<'a, W: Write + std::io::Seek = BufWriter<std::fs::File>> {
    log: SessionLog<W>,
    observers: &'a [&'a dyn Observer],
}

impl<'a, W: Write + std::io::Seek> Recorder<'a, W> {
    /// A recorder writing to `log` and handing every record to `observers` too.
    pub fn new(log: SessionLog<W>, observers: &'a [&'a dyn Observer]) -> Self {
        Recorder { log, observers }
    }

    /// Hands `record` at log time `log_ns` to every observer.
    pub fn record(&mut self, log_ns: u64, record: Record<'_>) -> Result<(), LogError> {
        for o in self.observers {
            o.observe(log_ns, &record);
        }
        self.log.write_record(log_ns, &record)
    }

    /// Records the raw frame `frame`, sent or received (`sent`), at its host time.
    pub fn can_frame(&mut self, sent: bool, frame: &CanFrameRecord) -> Result<(), LogError> {
        self.record(frame.host_ns, Record::Frame { sent, frame })
    }

    /// Records a sample of stream `stream` (an index of `exocal_session::stream::STREAMS`) on
    /// the stream's topic: a joint reading in the arm's sample on `/joint_states`, a pose on
    /// `/ee_pose`, a raw IMU vector on its own (`/ee_gyro`, `/ee_mag`).
    pub fn sample(
        &mut self,
        log_ns: u64,
        stream: usize,
        node_timestamp_us: u32,
        reading: Reading,
    ) -> Result<(), LogError> {
        let Some(s) = STREAMS.get(stream) else {
            return Ok(());
        };
        match (s.column, reading) {
            (Column::Angle(joint), Reading::Angle { angle, rate }) => {
                self.joint_state(log_ns, joint + 1, angle, rate)
            }
            (Column::Pose, Reading::Pose(p)) => {
                let pose = Transform {
                    translation: p.position,
                    rotation_wxyz: p.quat,
                };
                self.ee_pose(log_ns, &pose)
            }
            (Column::Vector, Reading::Vector(xyz)) => self.record(
                log_ns,
                Record::Vector {
                    stream,
                    node_timestamp_lo_us: node_timestamp_us,
                    xyz,
                },
            ),
            _ => Ok(()),
        }
    }

    /// Records joint `joint`'s (1-based) reading: angle (rad) and rate (rad/s).
    pub fn joint_state(
        &mut self,
        log_ns: u64,
        joint: usize,
        angle: f64,
        rate: f64,
    ) -> Result<(), LogError> {
        self.record(log_ns, Record::Joint { joint, angle, rate })
    }

    /// Records a measured end-effector pose.
    pub fn ee_pose(&mut self, log_ns: u64, pose: &Transform) -> Result<(), LogError> {
        self.record(log_ns, Record::EePose(pose))
    }

    /// Records the arm's frames ([`crate::log::records::arm_transforms`]).
    pub fn arm_transforms(&mut self, log_ns: u64, links: &[Link]) -> Result<(), LogError> {
        self.record(log_ns, Record::Arm(links))
    }

    /// Records a sample on the common grid, of an arm of `joints` joints.
    pub fn aligned(
        &mut self,
        log_ns: u64,
        sample: &AlignedSample,
        joints: usize,
    ) -> Result<(), LogError> {
        self.record(log_ns, Record::Aligned { sample, joints })
    }

    /// Records a snapshot of the collection's progress.
    pub fn progress(&mut self, log_ns: u64, progress: &Progress) -> Result<(), LogError> {
        self.record(log_ns, Record::Progress(progress))
    }

    /// Records the end of the collection window, at the window's end.
    pub fn collection_end(&mut self, end: &CollectionEnd) -> Result<(), LogError> {
        self.record(end.window_end_ns, Record::CollectionEnd(end))
    }

    /// Records the calibration result (and, once pushed, the push report).
    pub fn calibration(
        &mut self,
        log_ns: u64,
        calibration: &proto::Calibration,
    ) -> Result<(), LogError> {
        self.record(log_ns, Record::Calibration(calibration))
    }

    /// Records the arm's URDF ([`crate::log::records::urdf`]).
    pub fn robot_description(&mut self, log_ns: u64, urdf: &str) -> Result<(), LogError> {
        self.record(log_ns, Record::RobotDescription(urdf))
    }

    /// Records a human-readable event.
    pub fn event(&mut self, log_ns: u64, level: Level, message: &str) -> Result<(), LogError> {
        self.record(log_ns, Record::Event { level, message })
    }

    /// See [`SessionLog::tick`].
    pub fn tick(&mut self, now_ns: u64) -> Result<bool, LogError> {
        self.log.tick(now_ns)
    }

    /// Messages written to the log so far, per topic.
    pub fn counts(&self) -> Counts {
        self.log.counts()
    }

    /// Finishes the log (see [`SessionLog::finish`]).
    pub fn finish(self) -> Result<Counts, LogError> {
        self.log.finish()
    }
}
