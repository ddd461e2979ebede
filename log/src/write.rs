//! The per-session MCAP log.
//!
//! Contract:
//! - one file per session, zstd-compressed chunks, protobuf messages with protobuf schemas, as
//!   the `exocal-log` crate defines them (Foxglove's well-known types for joint states, poses,
//!   transforms and events; ours for raw frames and the rest): Foxglove's 3D, plot and log
//!   panels, the `mcap` crate and Python's `mcap-protobuf-support` read it without generated
//!   code;
//! - [`SessionLog::tick`] closes the open chunk and flushes it to the kernel whenever the flush
//!   interval has passed, and has it `fdatasync`ed on the log's own thread (`Syncer`): an
//!   `fdatasync` can take seconds on an SD card or a busy host, and the caller is the loop that
//!   feeds systemd's watchdog. A hard kill loses at most that interval (≤ 1 s by config) plus
//!   one sync in flight; the file stays readable by a linear scan up to its last closed chunk.
//!   A failed sync is the next tick's error;
//! - [`SessionLog::finish`] writes the summary (statistics, indexes) and footer; the daemon calls
//!   it on every exit path, SIGTERM/SIGINT included;
//! - message indexes are written, as the indexed readers need (`@mcap/core`'s, which Foxglove
//!   and Lichtblick open files with); the raw frames, most of the log, go in batches of a few
//!   milliseconds (`crate::CAN_BATCH_NS`) so that their 16 uncompressed bytes of index
//!   per message stay small, and the joint readings of one sample of the arm in one message.
//!   A batch is written when it is full or old (by log time), before the collection end and
//!   the calibration (so every frame received before them is before them in the file), and by
//!   [`SessionLog::flush`] and [`SessionLog::finish`]; not by [`SessionLog::tick`], so the same
//!   frames make the same file whatever the timing. A hard kill also loses the open batches:
//!   the last 10 ms (at most 64 frames) of each raw topic and the arm's last sample;
//! - record counts per topic are kept (frames for `/can/rx` and `/can/tx`, messages for the
//!   rest) so callers and tests can check them against the file.
//!
//! # Topics and schemas
//!
//! Defined once, in the `exocal-log` crate (re-exported here): the writer and every reader use
//! the same [`Topic`] names, schemas and record types.
//!
//! | topic | schema | what |
//! |---|---|---|
//! | `/can/rx`, `/can/tx` | `exocal.CanFrames` | every raw frame received / sent, in batches of a few milliseconds: id, flags, DLC, data, kernel and host timestamps |
//! | `/joint_states` | `foxglove.JointStates` | the decoded joint readings (`jointN`: position, velocity, as the exported URDF names the joints), one message per sample of the arm (the readings within a few milliseconds, each joint once) |
//! | `/ee_pose` | `foxglove.PoseInFrame` | each assembled end-effector reference pose, frame `base_link` |
//! | `/ee_gyro`, `/ee_mag` | `exocal.AngularRate`, `exocal.MagneticField` | the end effector's raw IMU vectors: rate (rad/s), field (µT); one topic per raw IMU stream of `exocal_session::stream::STREAMS` |
//! | `/tf` | `foxglove.FrameTransforms` | the arm's frames on the calibrated table (`base_link → link1 … linkN → tool0` for an arm of N joints, the URDF's): Foxglove's 3D panel draws the arm |
//! | `/aligned` | `exocal.AlignedSample` | samples on the common time grid, as fed to the calibration |
//! | `/progress` | `exocal.Progress` | collection progress: coverage per joint, samples, condition number |
//! | `/collection` | `exocal.CollectionEnd` | once, when collection ends: frames received in the window (a replay calibrates on exactly those), the window's end, bad-frame and drop counts |
//! | `/calibration` | `exocal.Calibration` | tables before and after, τ and σ, metrics, validation verdict; again with the push report |
//! | `/events` | `foxglove.Log` | what happened, human-readable, with a level |
//! | `/robot_description` | `exocal.RobotDescription` | the arm's URDF: the nominal table's at the start, the calibrated one's with the calibration |
//!
//! Log time is host wall-clock time in ns. Messages on a topic are numbered from 1 (the MCAP
//! `sequence`, per channel).

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufWriter, Seek, Write};
use std::path::{Path, PathBuf};

use crate::{fox, timestamp, CAN_BATCH_FRAMES, CAN_BATCH_NS, MESSAGE_ENCODING};
pub use crate::{proto, CanFrameRecord, CollectionEnd, Level, Topic};

use crate::record::{Record, Transform, BASE_FRAME};

/// zstd level of the chunks: the best size per CPU time on the demo's log (BENCHMARKS.md,
/// "Session log").
pub const ZSTD_LEVEL: u32 = 3;

/// Why the log could not be written.
#[derive(Debug)]
pub enum LogError {
    /// Writing the file failed.
    Io(std::io::Error),
    /// The MCAP writer failed.
    Mcap(mcap::McapError),
}

impl std::fmt::Display for LogError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            LogError::Io(e) => write!(f, "MCAP log I/O: {e}"),
            LogError::Mcap(e) => write!(f, "MCAP log: {e}"),
        }
    }
}

impl std::error::Error for LogError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            LogError::Io(e) => Some(e),
            LogError::Mcap(e) => Some(e),
        }
    }
}

impl From<std::io::Error> for LogError {
    fn from(e: std::io::Error) -> Self {
        LogError::Io(e)
    }
}

impl From<mcap::McapError> for LogError {
    fn from(e: mcap::McapError) -> Self {
        LogError::Mcap(e)
    }
}

fn v3(p: [f64; 3]) -> fox::Vector3 {
    fox::Vector3 {
        x: p[0],
        y: p[1],
        z: p[2],
    }
}

fn quat(q: [f64; 4]) -> fox::Quaternion {
    fox::Quaternion {
        w: q[0],
        x: q[1],
        y: q[2],
        z: q[3],
    }
}

/// The name of joint `joint` (1-based), as the exported URDF names it.
pub fn joint_name(joint: usize) -> String {
    format!("joint{joint}")
}

/// `foxglove.JointStates` of one joint reading.
pub fn joint_states(log_ns: u64, joints: &[(usize, f64, f64)]) -> fox::JointStates {
    fox::JointStates {
        timestamp: Some(timestamp(log_ns)),
        joints: joints
            .iter()
            .map(|&(j, angle, rate)| fox::JointState {
                name: joint_name(j),
                position: Some(angle),
                velocity: Some(rate),
                ..Default::default()
            })
            .collect(),
    }
}

/// `foxglove.PoseInFrame` of an end-effector pose in the base frame.
pub fn pose_in_frame(log_ns: u64, pose: &Transform) -> fox::PoseInFrame {
    fox::PoseInFrame {
        timestamp: Some(timestamp(log_ns)),
        frame_id: BASE_FRAME.to_string(),
        pose: Some(fox::Pose {
            position: Some(v3(pose.translation)),
            orientation: Some(quat(pose.rotation_wxyz)),
        }),
    }
}

/// `foxglove.FrameTransforms` of the arm's frames.
pub fn frame_transforms(log_ns: u64, links: &[crate::record::Link]) -> fox::FrameTransforms {
    fox::FrameTransforms {
        transforms: links
            .iter()
            .map(|l| fox::FrameTransform {
                timestamp: Some(timestamp(log_ns)),
                parent_frame_id: l.parent.clone(),
                child_frame_id: l.child.clone(),
                translation: Some(v3(l.transform.translation)),
                rotation: Some(quat(l.transform.rotation_wxyz)),
            })
            .collect(),
    }
}

/// `exocal.Progress`.
pub fn progress(p: &exocal_session::window::Progress) -> proto::Progress {
    proto::Progress {
        elapsed_s: p.elapsed_s,
        samples: p.samples,
        coverage: p.coverage.to_vec(),
        condition_number: p.condition_number,
        readiness: p.readiness,
        expected_position_mm: p.expected.map(|e| e.position_mm),
        expected_rotation_mrad: p.expected.map(|e| e.rotation_mrad),
        guidance: p.guidance.clone().unwrap_or_default(),
    }
}

/// `foxglove.Log` of an event.
pub fn log_message(log_ns: u64, level: Level, message: &str) -> fox::Log {
    fox::Log {
        timestamp: Some(timestamp(log_ns)),
        level: fox::LogLevel::from(level) as i32,
        message: message.to_string(),
        name: "exocald".to_string(),
        file: String::new(),
        line: 0,
    }
}

/// `exocal.AlignedSample` of an arm of `joints` joints.
pub fn aligned_sample(
    s: &exocal_session::align::AlignedSample,
    joints: usize,
) -> proto::AlignedSample {
    proto::AlignedSample {
        t: s.t,
        joints: s.joints[..joints.min(s.joints.len())].to_vec(),
        position: s.pose.position.to_vec(),
        orientation_wxyz: s.pose.orientation.to_vec(),
        unseen_s: s.unseen_s,
    }
}

/// Records written per topic (frames on `/can/rx` and `/can/tx`, messages elsewhere).
pub type Counts = BTreeMap<Topic, u64>;

/// An open session log.
pub struct SessionLog<W: Write + Seek> {
    writer: mcap::Writer<W>,
    channels: [u16; Topic::ALL.len()],
    counts: [u64; Topic::ALL.len()],
    sequences: [u32; Topic::ALL.len()],
    flush_interval_ns: u64,
    last_flush_ns: Option<u64>,
    sync: Option<Syncer>,
    buffer: Vec<u8>,
    /// The raw frames not written yet, `/can/rx`'s and `/can/tx`'s, each with its first
    /// frame's log time.
    batches: [(u64, Vec<CanFrameRecord>); 2],
    /// The joint readings of the arm's sample not written yet (joint, angle, rate), with the
    /// first one's log time.
    sample: (u64, Vec<(usize, f64, f64)>),
}

/// `fdatasync`s a log file on a thread of its own, on request: requests made while one waits
/// are one sync (it starts after them). The first error is kept for the next request.
struct Syncer {
    file: File,
    requests: Option<std::sync::mpsc::SyncSender<()>>,
    error: std::sync::Arc<std::sync::Mutex<Option<std::io::Error>>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Syncer {
    fn new(file: File) -> std::io::Result<Syncer> {
        let (requests, rx) = std::sync::mpsc::sync_channel::<()>(1);
        let error: std::sync::Arc<std::sync::Mutex<Option<std::io::Error>>> =
            std::sync::Arc::default();
        let (f, e) = (file.try_clone()?, std::sync::Arc::clone(&error));
        let thread = std::thread::Builder::new()
            .name("exocald-log-sync".into())
            .spawn(move || {
                while rx.recv().is_ok() {
                    if let Err(err) = f.sync_data() {
                        let mut slot = e.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
                        slot.get_or_insert(err);
                    }
                }
            })?;
        Ok(Syncer {
            file,
            requests: Some(requests),
            error,
            thread: Some(thread),
        })
    }

    /// The first sync error since the last call, if any.
    fn failed(&self) -> Option<std::io::Error> {
        self.error
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .take()
    }

    /// Asks for a sync of what was written so far; returns an earlier sync's error.
    fn request(&self) -> std::io::Result<()> {
        if let Some(e) = self.failed() {
            return Err(e);
        }
        if let Some(tx) = &self.requests {
            // Full: a sync is already waiting to start, and will cover this request too.
            let _ = tx.try_send(());
        }
        Ok(())
    }

    /// Waits for the thread to end, then syncs everything (data and metadata) here.
    fn finish(mut self) -> std::io::Result<()> {
        self.stop();
        if let Some(e) = self.failed() {
            return Err(e);
        }
        self.file.sync_all()
    }

    fn stop(&mut self) {
        self.requests = None;
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for Syncer {
    fn drop(&mut self) {
        self.stop();
    }
}

/// The file name of a session started at `start_ns` (ns since the epoch, UTC).
pub fn session_file_name(start_ns: u64) -> String {
    let ((y, m, d), (h, min, s)) = utc(start_ns);
    format!("exocal-{y:04}{m:02}{d:02}T{h:02}{min:02}{s:02}Z.mcap")
}

/// `2026-11-29 04:05:06 UTC` for a time in ns since the Unix epoch (the report's header).
pub fn utc_time(ns: u64) -> String {
    let ((y, m, d), (h, min, s)) = utc(ns);
    format!("{y:04}-{m:02}-{d:02} {h:02}:{min:02}:{s:02} UTC")
}

/// (year, month, day), (hour, minute, second) of a time in ns since the Unix epoch.
fn utc(ns: u64) -> ((i64, u32, u32), (i64, i64, i64)) {
    let secs = (ns / 1_000_000_000) as i64;
    let (days, rem) = (secs.div_euclid(86_400), secs.rem_euclid(86_400));
    (
        civil_from_days(days),
        (rem / 3600, rem % 3600 / 60, rem % 60),
    )
}

/// Days since 1970-01-01 to (year, month, day), proleptic Gregorian (H. Hinnant's algorithm).
fn civil_from_days(z: i64) -> (i64, u32, u32) {
    let z = z + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = (doy - (153 * mp + 2) / 5 + 1) as u32;
    let m = if mp < 10 { mp + 3 } else { mp - 9 } as u32;
    (yoe + era * 400 + i64::from(m <= 2), m, d)
}

impl SessionLog<BufWriter<File>> {
    /// Creates `dir` if needed and a new log file in it named after `start_ns`; refuses to
    /// overwrite an existing file (a suffix `-1`, `-2`, … is added instead).
    pub fn create_in(
        dir: &Path,
        start_ns: u64,
        flush_interval_ns: u64,
    ) -> Result<(PathBuf, Self), LogError> {
        std::fs::create_dir_all(dir)?;
        let base = session_file_name(start_ns);
        let stem = base.trim_end_matches(".mcap");
        let mut n = 0u32;
        let (path, file) = loop {
            let name = if n == 0 {
                base.clone()
            } else {
                format!("{stem}-{n}.mcap")
            };
            let path = dir.join(name);
            match std::fs::OpenOptions::new()
                .write(true)
                .create_new(true)
                .open(&path)
            {
                Ok(f) => break (path, f),
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists && n < 1000 => n += 1,
                Err(e) => return Err(e.into()),
            }
        };
        let sync = Syncer::new(file.try_clone()?)?;
        let mut log = SessionLog::new(BufWriter::new(file), flush_interval_ns)?;
        log.sync = Some(sync);
        Ok((path, log))
    }
}

impl<W: Write + Seek> SessionLog<W> {
    /// Starts a log on `w`: header, schemas and every channel are written at once, so a
    /// session's file always lists every topic, even an empty one.
    pub fn new(w: W, flush_interval_ns: u64) -> Result<Self, LogError> {
        let options = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .compression_level(ZSTD_LEVEL)
            // One thread: zstd's worker pool (the crate's default, one per physical CPU) locks a
            // mutex on every record written and wakes threads for a few hundred kB a second.
            .compression_threads(0)
            // Message indexes: Foxglove's indexed reader needs them (16 uncompressed bytes per
            // message: the raw frames go in batches).
            .emit_message_indexes(true)
            .profile("")
            .library(concat!("exocald ", env!("CARGO_PKG_VERSION")))
            // Chunks close on time (tick) or at this size, whichever first.
            .chunk_size(Some(1 << 20));
        let mut writer = mcap::Writer::with_options(w, options)?;
        let mut channels = [0u16; Topic::ALL.len()];
        for (slot, topic) in channels.iter_mut().zip(Topic::ALL) {
            let schema = topic.schema();
            let schema_id = writer.add_schema(schema.name, schema.encoding, &schema.data)?;
            *slot =
                writer.add_channel(schema_id, topic.name(), MESSAGE_ENCODING, &BTreeMap::new())?;
        }
        Ok(SessionLog {
            writer,
            channels,
            counts: [0; Topic::ALL.len()],
            sequences: [0; Topic::ALL.len()],
            flush_interval_ns: flush_interval_ns.max(1),
            last_flush_ns: None,
            sync: None,
            buffer: Vec::with_capacity(512),
            batches: Default::default(),
            sample: (0, Vec::with_capacity(8)),
        })
    }

    /// Writes one message on `topic` at log time `log_ns`.
    pub fn write<M: prost::Message>(
        &mut self,
        topic: Topic,
        log_ns: u64,
        message: &M,
    ) -> Result<(), LogError> {
        self.put(topic, log_ns, message)?;
        self.counts[topic.index()] += 1;
        Ok(())
    }

    /// Writes one message on `topic` at log time `log_ns`, uncounted.
    fn put<M: prost::Message>(
        &mut self,
        topic: Topic,
        log_ns: u64,
        message: &M,
    ) -> Result<(), LogError> {
        let mut buffer = std::mem::take(&mut self.buffer);
        buffer.clear();
        message
            .encode(&mut buffer)
            .expect("a Vec grows to fit any message");
        let written = self.put_encoded(topic, log_ns, &buffer);
        self.buffer = buffer;
        written
    }

    /// Writes one encoded message on `topic` at log time `log_ns`, uncounted.
    fn put_encoded(&mut self, topic: Topic, log_ns: u64, data: &[u8]) -> Result<(), LogError> {
        let i = topic.index();
        self.sequences[i] = self.sequences[i].wrapping_add(1);
        let header = mcap::records::MessageHeader {
            channel_id: self.channels[i],
            sequence: self.sequences[i],
            log_time: log_ns,
            publish_time: log_ns,
        };
        self.writer.write_to_known_channel(&header, data)?;
        Ok(())
    }

    /// Adds a raw frame to its topic's batch, writing the batch first if it is old and after if
    /// it is full.
    fn batch(&mut self, sent: bool, log_ns: u64, frame: &CanFrameRecord) -> Result<(), LogError> {
        let (topic, b) = if sent {
            (Topic::CanTx, 1)
        } else {
            (Topic::CanRx, 0)
        };
        let (first, batch) = &self.batches[b];
        if !batch.is_empty() && log_ns.saturating_sub(*first) >= CAN_BATCH_NS {
            self.write_batch(b)?;
        }
        let (first, batch) = &mut self.batches[b];
        if batch.is_empty() {
            *first = log_ns;
        }
        batch.push(frame.clone());
        self.counts[topic.index()] += 1;
        if batch.len() >= CAN_BATCH_FRAMES {
            self.write_batch(b)?;
        }
        Ok(())
    }

    /// Writes batch `b` (0: `/can/rx`, 1: `/can/tx`) if it holds any frame.
    fn write_batch(&mut self, b: usize) -> Result<(), LogError> {
        if self.batches[b].1.is_empty() {
            return Ok(());
        }
        let message = crate::can_batch(&self.batches[b].1);
        let first = self.batches[b].0;
        self.batches[b].1.clear();
        let topic = if b == 1 { Topic::CanTx } else { Topic::CanRx };
        self.put(topic, first, &message)
    }

    /// Writes every batch that holds a frame, and the arm's sample.
    fn write_batches(&mut self) -> Result<(), LogError> {
        self.write_batch(0)?;
        self.write_batch(1)?;
        self.write_sample()
    }

    /// Adds a joint reading to the arm's sample, writing the sample first if it already has
    /// this joint or is old: one `/joint_states` message per sample of the arm, as Foxglove's
    /// panels take it.
    fn joint(&mut self, log_ns: u64, reading: (usize, f64, f64)) -> Result<(), LogError> {
        let (first, joints) = &self.sample;
        if !joints.is_empty()
            && (joints.iter().any(|j| j.0 == reading.0)
                || log_ns.saturating_sub(*first) >= CAN_BATCH_NS)
        {
            self.write_sample()?;
        }
        if self.sample.1.is_empty() {
            self.sample.0 = log_ns;
        }
        self.sample.1.push(reading);
        Ok(())
    }

    /// Writes the arm's sample if it holds a reading.
    fn write_sample(&mut self) -> Result<(), LogError> {
        if self.sample.1.is_empty() {
            return Ok(());
        }
        let message = joint_states(self.sample.0, &self.sample.1);
        self.sample.1.clear();
        self.write(Topic::JointStates, self.sample.0, &message)
    }

    /// Writes `record` (see [`Record`]) at log time `log_ns`.
    pub fn write_record(&mut self, log_ns: u64, record: &Record<'_>) -> Result<(), LogError> {
        match *record {
            Record::Frame { sent, frame } => self.batch(sent, log_ns, frame),
            Record::Joint { joint, angle, rate } => self.joint(log_ns, (joint, angle, rate)),
            Record::EePose(pose) => self.write(Topic::EePose, log_ns, &pose_in_frame(log_ns, pose)),
            Record::Vector {
                stream,
                node_timestamp_lo_us,
                xyz,
            } => {
                let mut buffer = std::mem::take(&mut self.buffer);
                crate::encode_vector(stream, node_timestamp_lo_us, xyz, &mut buffer);
                let written = self.put_encoded(Topic::Vector(stream), log_ns, &buffer);
                self.buffer = buffer;
                written?;
                self.counts[Topic::Vector(stream).index()] += 1;
                Ok(())
            }
            Record::Arm(links) => self.write(Topic::Tf, log_ns, &frame_transforms(log_ns, links)),
            Record::Aligned { sample, joints } => {
                self.write(Topic::Aligned, log_ns, &aligned_sample(sample, joints))
            }
            Record::Progress(p) => self.write(Topic::Progress, log_ns, &progress(p)),
            // Every frame before these records in time is before them in the file.
            Record::CollectionEnd(end) => {
                self.write_batches()?;
                self.write(Topic::Collection, log_ns, end)
            }
            Record::Calibration(c) => {
                self.write_batches()?;
                self.write(Topic::Calibration, log_ns, c)
            }
            Record::RobotDescription(urdf) => self.write(
                Topic::RobotDescription,
                log_ns,
                &proto::RobotDescription {
                    data: urdf.to_string(),
                },
            ),
            Record::Event { level, message } => {
                self.write(Topic::Events, log_ns, &log_message(log_ns, level, message))
            }
        }
    }

    /// Closes the open chunk and syncs the file if `flush_interval` has passed since the last
    /// flush. `now_ns` is any monotonic clock; returns whether it flushed.
    pub fn tick(&mut self, now_ns: u64) -> Result<bool, LogError> {
        let due = match self.last_flush_ns {
            None => {
                self.last_flush_ns = Some(now_ns);
                false
            }
            Some(last) => now_ns.saturating_sub(last) >= self.flush_interval_ns,
        };
        if due {
            self.close_chunk()?;
            self.last_flush_ns = Some(now_ns);
        }
        Ok(due)
    }

    /// Writes the open batches, closes the open chunk, flushes it to the kernel and has it
    /// synced (on the log's sync thread; an earlier sync's error is returned here).
    pub fn flush(&mut self) -> Result<(), LogError> {
        self.write_batches()?;
        self.close_chunk()
    }

    /// [`SessionLog::flush`] without the open batches: what [`SessionLog::tick`] does, so that
    /// where the batches close depends on the frames alone, not on when ticks come (the same
    /// frames make the same file).
    fn close_chunk(&mut self) -> Result<(), LogError> {
        self.writer.flush()?;
        if let Some(s) = &self.sync {
            s.request()?;
        }
        Ok(())
    }

    /// Records written so far, per topic (an arm's sample not written yet included).
    pub fn counts(&self) -> Counts {
        let pending = |t: Topic| u64::from(t == Topic::JointStates && !self.sample.1.is_empty());
        Topic::ALL
            .iter()
            .map(|&t| (t, self.counts[t.index()] + pending(t)))
            .collect()
    }

    /// Writes the summary and footer; returns the counts.
    pub fn finish(mut self) -> Result<Counts, LogError> {
        self.write_batches()?;
        self.writer.finish()?;
        if let Some(s) = self.sync.take() {
            s.finish()?;
        }
        Ok(self.counts())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::record::Link;
    use exocal_session::align::{AlignedSample, Pose};
    use prost::Message as _;
    use std::io::Cursor;

    fn links(p: Transform, n: usize) -> Vec<Link> {
        (0..n)
            .map(|i| Link {
                parent: if i == 0 {
                    "base_link".into()
                } else {
                    format!("link{i}")
                },
                child: format!("link{}", i + 1),
                transform: p,
            })
            .collect()
    }

    fn progress_of(elapsed_s: f64) -> exocal_session::window::Progress {
        exocal_session::window::Progress {
            elapsed_s,
            samples: 3,
            coverage: vec![0.5; 7],
            condition_number: None,
            expected: None,
            guidance: Some(vec![1.0, 0.9, 0.9, 0.9, 0.9, 0.9, 0.4]),
            readiness: 0.1,
            target: None,
        }
    }

    fn sample(t: f64) -> AlignedSample {
        AlignedSample {
            t,
            joints: [t, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6],
            rates: [0.0; 7],
            pose: Pose {
                position: [0.1, 0.2, t],
                orientation: [1.0, 0.0, 0.0, 0.0],
            },
            unseen_s: 0.0,
        }
    }

    /// Writes a small session with known counts per topic.
    fn write_session<W: Write + Seek>(log: &mut SessionLog<W>) -> BTreeMap<&'static str, u64> {
        let t0 = 1_700_000_000_000_000_000u64;
        for k in 0..250u64 {
            let ns = t0 + k * 10_000_000;
            let frame = CanFrameRecord {
                id: 0x101 + (k % 7) as u32,
                extended: false,
                remote: false,
                dlc: 8,
                data: vec![k as u8; 8],
                host_ns: ns,
                kernel_ns: Some(ns - 1000),
            };
            log.write_record(
                ns,
                &Record::Frame {
                    sent: false,
                    frame: &frame,
                },
            )
            .unwrap();
            let joint = Record::Joint {
                joint: (k % 7) as usize + 1,
                angle: 0.5,
                rate: -0.1,
            };
            log.write_record(ns, &joint).unwrap();
            if k % 10 == 0 {
                for stream in exocal_session::stream::vectors() {
                    let imu = Record::Vector {
                        stream,
                        node_timestamp_lo_us: (k * 10_000 % 65_536) as u32,
                        xyz: [0.1, -0.2, 0.3],
                    };
                    log.write_record(ns, &imu).unwrap();
                }
            }
            if k % 5 == 0 {
                let p = Transform {
                    translation: [0.3, 0.1, 0.0],
                    rotation_wxyz: [1.0, 0.0, 0.0, 0.0],
                };
                log.write_record(ns, &Record::EePose(&p)).unwrap();
                log.write_record(ns, &Record::Arm(&links(p, 8))).unwrap();
                log.write_record(
                    ns,
                    &Record::Aligned {
                        sample: &sample(k as f64 * 0.01),
                        joints: 7,
                    },
                )
                .unwrap();
            }
            log.tick(k * 10_000_000).unwrap();
        }
        let sent = CanFrameRecord {
            id: 0x301,
            extended: false,
            remote: false,
            dlc: 8,
            data: vec![1; 8],
            host_ns: t0,
            kernel_ns: None,
        };
        log.write_record(
            t0,
            &Record::Frame {
                sent: true,
                frame: &sent,
            },
        )
        .unwrap();
        log.write_record(t0, &Record::Progress(&progress_of(1.0)))
            .unwrap();
        let end = CollectionEnd {
            frames: 250,
            window_end_ns: t0,
            unknown: 0,
            malformed: 0,
            invalid_angles: 0,
            dropped: 0,
            stream: None,
        };
        log.write_record(t0, &Record::CollectionEnd(&end)).unwrap();
        let calibration = proto::Calibration {
            condition_number: 22.4,
            ..Default::default()
        };
        log.write_record(t0, &Record::Calibration(&calibration))
            .unwrap();
        log.write_record(t0, &Record::RobotDescription("<robot name=\"r\"/>"))
            .unwrap();
        for (level, message) in [
            (Level::Info, "session started"),
            (Level::Warning, "node 3: 2 malformed frames"),
        ] {
            log.write_record(t0, &Record::Event { level, message })
                .unwrap();
        }
        BTreeMap::from([
            ("/can/rx", 250),
            ("/can/tx", 1),
            ("/joint_states", 250),
            ("/ee_pose", 50),
            ("/ee_gyro", 25),
            ("/ee_mag", 25),
            ("/tf", 50),
            ("/aligned", 50),
            ("/progress", 1),
            ("/collection", 1),
            ("/robot_description", 1),
            ("/calibration", 1),
            ("/events", 2),
        ])
    }

    /// Decodes a message of `topic` as the schema says, panicking if it does not; the records
    /// it holds (frames of a batch on `/can/*`, else 1).
    fn decode_any(topic: &str, data: &[u8]) -> u64 {
        match Topic::from_name(topic).unwrap() {
            Topic::CanRx | Topic::CanTx => {
                let frames =
                    crate::decode_can_frames("exocal.CanFrames", "protobuf", data).unwrap();
                assert!(!frames.is_empty(), "an empty batch on {topic}");
                return frames.len() as u64;
            }
            Topic::JointStates => drop(fox::JointStates::decode(data).unwrap()),
            Topic::EePose => drop(fox::PoseInFrame::decode(data).unwrap()),
            Topic::Vector(i) => match exocal_session::stream::STREAMS[i].message {
                exocal_dbc::spec::Kind::ImuMag => drop(proto::MagneticField::decode(data).unwrap()),
                _ => drop(proto::AngularRate::decode(data).unwrap()),
            },
            Topic::Tf => drop(fox::FrameTransforms::decode(data).unwrap()),
            Topic::Aligned => drop(proto::AlignedSample::decode(data).unwrap()),
            Topic::Progress => drop(proto::Progress::decode(data).unwrap()),
            Topic::Collection => drop(proto::CollectionEnd::decode(data).unwrap()),
            Topic::Calibration => drop(proto::Calibration::decode(data).unwrap()),
            Topic::Events => drop(fox::Log::decode(data).unwrap()),
            Topic::RobotDescription => drop(proto::RobotDescription::decode(data).unwrap()),
        }
        1
    }

    /// Records per topic (frames on `/can/*`), every message decoded as its topic's type.
    fn read_counts(bytes: &[u8]) -> BTreeMap<String, u64> {
        let mut counts = BTreeMap::new();
        for m in mcap::MessageStream::new(bytes).unwrap() {
            let m = m.unwrap();
            *counts.entry(m.channel.topic.clone()).or_insert(0) +=
                decode_any(&m.channel.topic, &m.data);
        }
        counts
    }

    /// The sync runs on the log's thread and its error reaches the next request: `fsync` of
    /// `/dev/null` fails (EINVAL) as a full disk or a dying SD card would.
    #[test]
    fn a_failed_sync_is_the_next_flush_error_and_never_blocks_the_caller() {
        let syncer = Syncer::new(File::open("/dev/null").unwrap()).unwrap();
        assert!(syncer.request().is_ok(), "the first request only asks");
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
        let err = loop {
            std::thread::sleep(std::time::Duration::from_millis(5));
            if let Err(e) = syncer.request() {
                break e;
            }
            assert!(
                std::time::Instant::now() < deadline,
                "the sync thread never ran"
            );
        };
        assert_eq!(err.raw_os_error(), Some(22), "EINVAL: {err}");
        // A good file: requests coalesce, finish syncs everything and ends the thread.
        let path = std::env::temp_dir().join(format!("exocald-sync-{}", std::process::id()));
        let good = Syncer::new(File::create(&path).unwrap()).unwrap();
        for _ in 0..100 {
            good.request().unwrap();
        }
        good.finish().unwrap();
        std::fs::remove_file(&path).unwrap();
    }

    #[test]
    fn a_session_reads_back_with_every_channel_and_the_right_counts() {
        let mut log = SessionLog::new(Cursor::new(Vec::new()), 500_000_000).unwrap();
        let expected = write_session(&mut log);
        let counts = log.counts();
        let bytes = {
            let SessionLog { mut writer, .. } = log;
            writer.finish().unwrap();
            writer.into_inner().into_inner()
        };
        let got = read_counts(&bytes);
        let expected: BTreeMap<String, u64> = expected
            .into_iter()
            .map(|(k, v)| (k.to_string(), v))
            .collect();
        assert_eq!(got, expected);
        for (t, n) in counts {
            assert_eq!(expected[t.name()], n);
        }
        // The summary lists every channel with its schema and its count.
        let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
        assert_eq!(summary.channels.len(), Topic::ALL.len());
        let stats = summary.stats.unwrap();
        assert_eq!(stats.message_count, expected.values().sum::<u64>());
        for ch in summary.channels.values() {
            let schema = ch.schema.as_ref().unwrap();
            let topic = Topic::from_name(&ch.topic).unwrap();
            assert_eq!(schema.name, topic.message_type());
            assert_eq!(schema.encoding, "protobuf");
            assert_eq!(ch.message_encoding, "protobuf");
        }
        // ~250 messages at 10 ms over 2.5 s with a 0.5 s flush: several chunks, all zstd.
        assert!(
            summary.chunk_indexes.len() >= 4,
            "{}",
            summary.chunk_indexes.len()
        );
        assert!(summary
            .chunk_indexes
            .iter()
            .all(|c| c.compression == "zstd"));
    }

    #[test]
    fn foxglove_messages_have_the_well_known_shape() {
        let mut log = SessionLog::new(Cursor::new(Vec::new()), 1).unwrap();
        let p = Transform {
            translation: [1.0, 2.0, 3.0],
            rotation_wxyz: [0.5, 0.5, 0.5, 0.5],
        };
        log.write_record(1_500_000_123, &Record::EePose(&p))
            .unwrap();
        log.write_record(7, &Record::Arm(&links(p, 2))).unwrap();
        let joint = Record::Joint {
            joint: 3,
            angle: 0.25,
            rate: 1.5,
        };
        log.write_record(5, &joint).unwrap();
        // The arm's sample is written when the next begins, or here.
        log.write_batches().unwrap();
        let bytes = {
            let SessionLog { mut writer, .. } = log;
            writer.finish().unwrap();
            writer.into_inner().into_inner()
        };
        let msgs: Vec<_> = mcap::MessageStream::new(&bytes)
            .unwrap()
            .map(|m| m.unwrap())
            .collect();
        assert_eq!(
            msgs[0].channel.schema.as_ref().unwrap().name,
            "foxglove.PoseInFrame"
        );
        let pose = fox::PoseInFrame::decode(&msgs[0].data[..]).unwrap();
        let t = pose.timestamp.unwrap();
        assert_eq!((t.sec(), t.nsec()), (1, 500_000_123));
        assert_eq!(pose.frame_id, "base_link");
        let inner = pose.pose.unwrap();
        assert_eq!(inner.orientation.unwrap().w, 0.5);
        assert_eq!(inner.position.unwrap().z, 3.0);
        let tf = fox::FrameTransforms::decode(&msgs[1].data[..]).unwrap();
        assert_eq!(tf.transforms[0].parent_frame_id, "base_link");
        assert_eq!(tf.transforms[0].child_frame_id, "link1");
        assert_eq!(tf.transforms[1].parent_frame_id, "link1");
        assert_eq!(tf.transforms[1].child_frame_id, "link2");
        let js = fox::JointStates::decode(&msgs[2].data[..]).unwrap();
        assert_eq!(js.joints[0].name, "joint3");
        assert_eq!(js.joints[0].position, Some(0.25));
        assert_eq!(js.joints[0].velocity, Some(1.5));
        assert_eq!(msgs[2].sequence, 1, "numbered per topic");
    }

    #[test]
    fn tick_flushes_on_the_interval_only() {
        let mut log = SessionLog::new(Cursor::new(Vec::new()), 1_000).unwrap();
        assert!(!log.tick(10).unwrap()); // first tick starts the clock
        assert!(!log.tick(500).unwrap());
        assert!(log.tick(1_010).unwrap());
        assert!(!log.tick(1_500).unwrap());
        assert!(log.tick(2_100).unwrap());
    }

    #[test]
    fn a_killed_file_reads_back_up_to_its_last_flush() {
        let dir = std::env::temp_dir().join(format!("exocald-mcap-{}", std::process::id()));
        let t0 = 1_700_000_000_000_000_000u64;
        let (path, mut log) = SessionLog::create_in(&dir, t0, 100).unwrap();
        assert!(path
            .file_name()
            .unwrap()
            .to_str()
            .unwrap()
            .starts_with("exocal-20231114T2213"));
        let event = |message| Record::Event {
            level: Level::Info,
            message,
        };
        for k in 0..100u64 {
            log.write_record(t0 + k, &event("flushed")).unwrap();
        }
        log.tick(0).unwrap();
        assert!(log.tick(200).unwrap());
        for k in 0..10u64 {
            log.write_record(t0 + 1000 + k, &event("not flushed"))
                .unwrap();
        }
        // Simulate kill -9: forget the writer without finishing (no Drop runs).
        std::mem::forget(log);
        let bytes = std::fs::read(&path).unwrap();
        let mut ok = 0;
        for m in mcap::MessageStream::new(&bytes).unwrap() {
            match m {
                Ok(m) => {
                    let v = fox::Log::decode(&m.data[..]).unwrap();
                    assert_eq!(v.message, "flushed");
                    ok += 1;
                }
                Err(_) => break,
            }
        }
        assert_eq!(ok, 100);
        // A second log in the same second gets its own file.
        let (path2, log2) = SessionLog::create_in(&dir, t0, 100).unwrap();
        assert_ne!(path, path2);
        log2.finish().unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// Cross-check with another implementation: Python's `mcap`, every CRC validated, every
    /// message decoded by `mcap-protobuf-support` from the schemas in the file alone.
    /// Run: `EXOCAL_PYTHON=<venv>/bin/python cargo test -p exocal-log -- --ignored python`.
    #[test]
    #[ignore = "needs the project venv (EXOCAL_PYTHON): `cargo xtask test` runs it"]
    fn python_mcap_reader_validates_crcs_and_decodes_the_samples() {
        let python = std::env::var("EXOCAL_PYTHON").unwrap_or_else(|_| "python3".into());
        let dir = std::env::temp_dir().join(format!("exocald-py-{}", std::process::id()));
        let t0 = 1_700_000_000_000_000_000u64;
        let (path, mut log) = SessionLog::create_in(&dir, t0, 500_000_000).unwrap();
        let expected = write_session(&mut log);
        log.finish().unwrap();
        // The daemon's tool (its README documents it for users), run on what this crate wrote.
        let script = concat!(env!("CARGO_MANIFEST_DIR"), "/../daemon/tools/check_mcap.py");
        let out = std::process::Command::new(&python)
            .arg(script)
            .arg(&path)
            .output()
            .unwrap_or_else(|e| panic!("cannot run {python}: {e}"));
        assert!(
            out.status.success(),
            "python mcap reader failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let got: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        let counts: BTreeMap<String, u64> = serde_json::from_value(got["counts"].clone()).unwrap();
        let expected: BTreeMap<String, u64> = expected
            .into_iter()
            .map(|(k, v)| (k.to_string(), v))
            .collect();
        assert_eq!(counts, expected);
        // The same samples as written (see `write_session`).
        let s = &got["samples"];
        assert_eq!(
            s["can_rx"],
            serde_json::json!({"id": 0x101, "flags": 0, "dlc": 8, "data": [0, 0, 0, 0, 0, 0, 0, 0],
                "kernel_ns": t0 - 1000, "host_ns": t0})
        );
        assert_eq!(
            s["joint_state"],
            serde_json::json!({"name": "joint1", "position": 0.5, "velocity": -0.1,
                "sec": 1_700_000_000u64, "nsec": 0})
        );
        assert_eq!(
            s["aligned"],
            serde_json::json!({"t": 0.0, "joints": [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6]})
        );
        assert_eq!(s["collection_frames"], 250);
        assert_eq!(s["condition_number"], 22.4);
        assert_eq!(
            s["event"],
            serde_json::json!({"level": 2, "message": "session started"})
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn file_names_are_utc_dates() {
        assert_eq!(session_file_name(0), "exocal-19700101T000000Z.mcap");
        // 2024-02-29 12:34:56 UTC
        assert_eq!(
            session_file_name(1_709_210_096_000_000_000),
            "exocal-20240229T123456Z.mcap"
        );
        assert_eq!(
            utc_time(1_709_210_096_000_000_000),
            "2024-02-29 12:34:56 UTC"
        );
    }
}
