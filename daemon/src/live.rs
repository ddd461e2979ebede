//! The live view: the session served over the Foxglove WebSocket protocol (the Foxglove SDK's
//! server), so a person connects Foxglove to `ws://HOST:PORT` and watches the suit while it is
//! being calibrated.
//!
//! Contract:
//! - off unless `[live] enabled = true` (or `exocald demo --live`); it listens on
//!   `[live] listen` on a runtime of its own (one worker thread), so neither the session's loop
//!   nor a paused demo clock ever waits for a client. The view has no authentication: an
//!   address other hosts reach needs `[live] allow_remote = true` (the configuration refuses
//!   it otherwise) and is warned about at start ([`LiveView::banner`]);
//! - bounded: at most `[live] max_clients` connections at once (more get HTTP 503 and are
//!   closed), each with a send queue of [`LIVE_BACKLOG`] messages (a client that does not keep
//!   up loses its oldest messages; the SDK's server runs on an ephemeral loopback port behind
//!   the connection gate);
//! - it is an observer of the session's records ([`crate::shell::tee::Recorder`] hands it every
//!   [`Record`] the log gets) and never fails the session: a slow client misses messages;
//! - channels, with the log's schemas (`exocal-log`): `/joint_states` (every joint of the arm) and
//!   `/tf` (the arm's frames on the current table, as the exported URDF names them) and
//!   `/ee_pose` (the measured end-effector pose) and a channel per raw IMU stream (the log's
//!   topics: `/ee_gyro`, `/ee_mag`), each at most `[live] max_hz` messages per second of log time, their timestamps never
//!   stepping back (a record older than what was sent — the stream gate releases a node's
//!   frames a span at a time — updates nothing; a step back of [`CLOCK_STEP_NS`] or more is the
//!   clock stepping and starts over); `/progress` (coverage per joint, condition number),
//!   `/calibration` (the result, then the push report) and `/events`, every message;
//!   `/robot_description` (the URDF of the current table — nominal while collecting, calibrated
//!   once calibrated), with the log's schema (`exocal.RobotDescription`) as every channel;
//! - a client that subscribes to `/robot_description`, `/progress` or `/calibration` gets the
//!   latest message at once (they change rarely).

use std::net::SocketAddr;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

use tokio::io::AsyncWriteExt;
use tokio::net::{TcpListener, TcpStream};

use exocal_log::{proto, Topic};
use foxglove::websocket::{ChannelView, Client, ServerListener};
use foxglove::{ChannelBuilder, Context, PartialMetadata, RawChannel, WebSocketServerHandle};
use parking_lot::Mutex;
use prost::Message as _;

use crate::config::{Config, MAX_JOINTS};
use crate::log::records;
use crate::log::records::{arm_transforms, Observer, Record};
use exocal_log::write;

/// Messages queued per client; beyond, its oldest are dropped (the SDK's backlog).
pub const LIVE_BACKLOG: usize = 256;
/// A step back of log time at least this long is the clock stepping, not a late record.
pub const CLOCK_STEP_NS: u64 = 1_000_000_000;

/// Whether log time `log_ns` is behind `last` by less than a clock step: a late record.
fn late(last: Option<u64>, log_ns: u64) -> bool {
    last.is_some_and(|t| log_ns < t && t - log_ns < CLOCK_STEP_NS)
}

/// Whether a streaming channel last sent at `last` may send at `log_ns`: never behind `last`
/// (a late record), at most one message per `period_ns` of log time; a clock step starts
/// over. If so, `last` becomes `log_ns`.
fn due(last: &mut Option<u64>, log_ns: u64, period_ns: u64) -> bool {
    if late(*last, log_ns) || last.is_some_and(|t| log_ns >= t && log_ns - t < period_ns) {
        return false;
    }
    *last = Some(log_ns);
    true
}

/// What a connection beyond `[live] max_clients` is told (HTTP 503), before it is closed.
const BUSY: &str = "exocald: the live view has as many clients as [live] max_clients allows";

/// The topic of the URDF.
pub const ROBOT_DESCRIPTION: &str = "/robot_description";

/// The channels a client can subscribe to.
struct Channels {
    joint_states: Arc<RawChannel>,
    tf: Arc<RawChannel>,
    ee_pose: Arc<RawChannel>,
    /// One per raw IMU stream: the stream and its channel.
    vectors: Vec<(usize, Arc<RawChannel>)>,
    progress: Arc<RawChannel>,
    calibration: Arc<RawChannel>,
    events: Arc<RawChannel>,
    robot_description: Arc<RawChannel>,
}

/// What the view keeps between records.
struct State {
    table: calib_core::DhTable<MAX_JOINTS>,
    /// Each joint's latest reading (angle, rate) and its log time, for the arm's joints.
    joints: Vec<Option<(f64, f64, u64)>>,
    /// The latest end-effector pose and its log time.
    pose: Option<(crate::log::records::Transform, u64)>,
    /// One streaming message per this much log time.
    period_ns: u64,
    last_sent_ns: Option<u64>,
    /// Log time of the last message sent on each raw IMU stream's channel, in `vectors` order.
    last_vector_ns: Vec<Option<u64>>,
    /// The latest message of the latched channels, by topic.
    latched: Vec<(&'static str, Vec<u8>)>,
}

impl State {
    fn latch(&mut self, topic: &'static str, bytes: Vec<u8>) {
        match self.latched.iter_mut().find(|(t, _)| *t == topic) {
            Some(slot) => slot.1 = bytes,
            None => self.latched.push((topic, bytes)),
        }
    }
}

struct Shared {
    channels: Channels,
    state: Mutex<State>,
}

impl Shared {
    fn channel(&self, topic: &str) -> Option<&Arc<RawChannel>> {
        let c = &self.channels;
        [&c.robot_description, &c.progress, &c.calibration]
            .into_iter()
            .find(|ch| ch.topic() == topic)
    }
}

/// Sends the latched message of a channel to a client that just subscribed to it.
struct Latch(Arc<Shared>);

impl ServerListener for Latch {
    fn on_subscribe(&self, client: Client, channel: ChannelView) {
        let Some(ch) = self.0.channel(channel.topic()) else {
            return;
        };
        let state = self.0.state.lock();
        if let Some((_, bytes)) = state.latched.iter().find(|(t, _)| *t == ch.topic()) {
            ch.log_to_sink(bytes, client.sink_id());
        }
    }
}

/// A running live view (see the module docs); dropping it stops the server.
pub struct LiveView {
    /// The server and the channels hold it weakly: it lives as long as the view.
    _context: Arc<Context>,
    shared: Arc<Shared>,
    server: Option<WebSocketServerHandle>,
    runtime: Option<tokio::runtime::Runtime>,
    /// Where clients connect (the connection gate's port).
    port: u16,
}

impl std::fmt::Debug for LiveView {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LiveView")
            .field("port", &self.port())
            .finish()
    }
}

fn channel(ctx: &Arc<Context>, topic: Topic) -> Result<Arc<RawChannel>, foxglove::FoxgloveError> {
    let s = topic.schema();
    ChannelBuilder::new(topic.name())
        .context(ctx)
        .message_encoding(exocal_log::MESSAGE_ENCODING)
        .schema(foxglove::Schema::new(s.name, s.encoding, s.data))
        .build_raw()
}

/// A URDF as the log writes it.
fn robot_description(urdf: &str) -> Vec<u8> {
    proto::RobotDescription {
        data: urdf.to_string(),
    }
    .encode_to_vec()
}

/// Takes clients on `listener` for the server at `inner`, at most `max` at once; the others
/// get HTTP 503 ([`BUSY`]) and are closed.
async fn gate(listener: TcpListener, inner: SocketAddr, max: usize) {
    let active = Arc::new(AtomicUsize::new(0));
    let busy: Arc<[u8]> = format!(
        "HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain\r\nConnection: close\r\n\
         Content-Length: {}\r\n\r\n{BUSY}",
        BUSY.len()
    )
    .into_bytes()
    .into();
    loop {
        let mut client = match listener.accept().await {
            Ok((client, _)) => client,
            // Out of descriptors or the like: wait instead of spinning.
            Err(_) => {
                tokio::time::sleep(std::time::Duration::from_millis(100)).await;
                continue;
            }
        };
        if active.load(Ordering::Acquire) >= max {
            let busy = busy.clone();
            tokio::spawn(async move {
                let _ = client.write_all(&busy).await;
                let _ = client.shutdown().await;
            });
            continue;
        }
        active.fetch_add(1, Ordering::AcqRel);
        let active = active.clone();
        tokio::spawn(async move {
            if let Ok(mut server) = TcpStream::connect(inner).await {
                let _ = tokio::io::copy_bidirectional(&mut client, &mut server).await;
            }
            active.fetch_sub(1, Ordering::AcqRel);
        });
    }
}

/// The padded table of an arm of `joints` rows (`None` for another count).
fn table_of(
    rows: impl Iterator<Item = calib_core::DhRow>,
    joints: usize,
) -> Option<calib_core::DhTable<MAX_JOINTS>> {
    let rows: Vec<calib_core::DhRow> = rows.collect();
    (rows.len() == joints && joints <= MAX_JOINTS).then(|| calib_core::DhTable {
        rows: std::array::from_fn(|j| {
            rows.get(j)
                .copied()
                .unwrap_or(exocal_session::arm::ZERO_ROW)
        }),
    })
}

/// Why the live view did not start: what was being done, and the error.
#[derive(Debug)]
pub struct LiveError {
    /// What was being done.
    pub what: String,
    /// The error.
    pub source: std::io::Error,
}

impl std::fmt::Display for LiveError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {}", self.what, self.source)
    }
}

impl std::error::Error for LiveError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        Some(&self.source)
    }
}

impl LiveView {
    /// The live view a session serves: started on `[live] listen` when `[live] enabled`.
    pub fn for_session(config: &Config) -> Result<Option<LiveView>, LiveError> {
        match config.live.enabled {
            true => LiveView::start(config.live.listen, config).map(Some),
            false => Ok(None),
        }
    }

    /// Starts the server on `listen` (with `config`'s `[live]` limits), the arm on `config`'s
    /// nominal table.
    pub fn start(listen: SocketAddr, config: &Config) -> Result<LiveView, LiveError> {
        let err = |e: foxglove::FoxgloveError| LiveError {
            what: format!("starting the live view on {listen}"),
            source: std::io::Error::other(e),
        };
        let listener = std::net::TcpListener::bind(listen)
            .and_then(|l| l.set_nonblocking(true).map(|()| l))
            .map_err(|source| LiveError {
                what: format!(
                    "listening on {listen} for the live view (another program on the port, \
                     e.g. another exocald? `ss -ltnp` names it; choose a free port: \
                     `exocald demo --listen 127.0.0.1:8766`, or [live] listen)"
                ),
                source,
            })?;
        let port = listener.local_addr().map_or(0, |a| a.port());
        let ctx = Context::new();
        let build = || -> Result<Channels, foxglove::FoxgloveError> {
            Ok(Channels {
                joint_states: channel(&ctx, Topic::JointStates)?,
                tf: channel(&ctx, Topic::Tf)?,
                ee_pose: channel(&ctx, Topic::EePose)?,
                vectors: (exocal_session::stream::vectors())
                    .map(|i| Ok((i, channel(&ctx, Topic::Vector(i))?)))
                    .collect::<Result<_, foxglove::FoxgloveError>>()?,
                progress: channel(&ctx, Topic::Progress)?,
                calibration: channel(&ctx, Topic::Calibration)?,
                events: channel(&ctx, Topic::Events)?,
                robot_description: channel(&ctx, Topic::RobotDescription)?,
            })
        };
        let channels = build().map_err(err)?;
        let table = config.calibration.nominal;
        let limits = config.calibration.bounds.joint_range.limits;
        let mut state = State {
            table,
            joints: vec![None; config.calibration.joints],
            pose: None,
            period_ns: (1e9 / config.live.max_hz) as u64,
            last_sent_ns: None,
            last_vector_ns: vec![None; exocal_session::stream::vectors().count()],
            latched: Vec::new(),
        };
        let nominal = records::urdf(&table, &limits, config.calibration.joints).unwrap_or_default();
        state.latch(ROBOT_DESCRIPTION, robot_description(&nominal));
        let shared = Arc::new(Shared {
            channels,
            state: Mutex::new(state),
        });
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .thread_name("exocald-live")
            .enable_all()
            .build()
            .map_err(|source| LiveError {
                what: format!("starting the live view's runtime for {listen}"),
                source,
            })?;
        let server = ctx
            .websocket_server()
            .name("exocald")
            .bind("127.0.0.1", 0)
            .message_backlog_size(LIVE_BACKLOG)
            .listener(Arc::new(Latch(shared.clone())))
            .tokio_runtime(runtime.handle());
        // Started on a thread of its own: this may run inside the session's runtime, where
        // blocking on another runtime is not allowed.
        let handle = std::thread::scope(|s| {
            s.spawn(|| runtime.block_on(server.start()))
                .join()
                .unwrap_or_else(|_| Err(foxglove::FoxgloveError::Unspecified("panicked".into())))
        })
        .map_err(err)?;
        let inner = SocketAddr::from(([127, 0, 0, 1], handle.port()));
        let max = config.live.max_clients;
        runtime.spawn(async move {
            if let Ok(listener) = TcpListener::from_std(listener) {
                gate(listener, inner, max).await;
            }
        });
        Ok(LiveView {
            _context: ctx,
            shared,
            server: Some(handle),
            runtime: Some(runtime),
            port,
        })
    }

    /// The port it listens on.
    pub fn port(&self) -> u16 {
        self.port
    }

    /// The line that says where to connect, with a warning where other hosts can.
    pub fn banner(&self, config: &Config) -> String {
        let ip = config.live.listen.ip();
        let mut line = format!("live view: connect Foxglove to ws://{ip}:{}", self.port);
        if !ip.is_loopback() {
            line.push_str(
                " — WARNING: reachable from other hosts (allow_remote), with no authentication",
            );
        }
        line
    }
}

impl Observer for LiveView {
    /// Publishes what `record` (at log time `log_ns`) shows (see the module docs).
    fn observe(&self, log_ns: u64, record: &Record<'_>) {
        let c = &self.shared.channels;
        let at = PartialMetadata::with_log_time(log_ns);
        let mut state = self.shared.state.lock();
        match *record {
            Record::Joint { joint, angle, rate } => {
                if let Some(slot) = state.joints.get_mut(joint.wrapping_sub(1)) {
                    if !late(slot.map(|s| s.2), log_ns) {
                        *slot = Some((angle, rate, log_ns));
                    }
                }
                self.stream(&mut state, log_ns);
            }
            Record::EePose(pose) => {
                if !late(state.pose.map(|p| p.1), log_ns) {
                    state.pose = Some((*pose, log_ns));
                }
                self.stream(&mut state, log_ns);
            }
            Record::Vector {
                stream,
                node_timestamp_lo_us,
                xyz,
            } => {
                let Some(k) = c.vectors.iter().position(|(i, _)| *i == stream) else {
                    return;
                };
                let period = state.period_ns;
                if !due(&mut state.last_vector_ns[k], log_ns, period) {
                    return;
                }
                let mut bytes = Vec::new();
                exocal_log::encode_vector(stream, node_timestamp_lo_us, xyz, &mut bytes);
                c.vectors[k].1.log_with_meta(&bytes, at);
            }
            Record::Progress(p) => {
                let bytes = write::progress(p).encode_to_vec();
                c.progress.log_with_meta(&bytes, at);
                state.latch(Topic::Progress.name(), bytes);
            }
            Record::Calibration(cal) => {
                let bytes = cal.encode_to_vec();
                c.calibration.log_with_meta(&bytes, at);
                state.latch(Topic::Calibration.name(), bytes);
                self.calibrated(&mut state, cal);
            }
            Record::Event { level, message } => {
                let bytes = write::log_message(log_ns, level, message).encode_to_vec();
                c.events.log_with_meta(&bytes, at);
            }
            Record::RobotDescription(urdf) => {
                let bytes = robot_description(urdf);
                c.robot_description.log_with_meta(&bytes, at);
                state.latch(ROBOT_DESCRIPTION, bytes);
            }
            Record::Frame { .. }
            | Record::Arm(_)
            | Record::Aligned { .. }
            | Record::CollectionEnd(_) => {}
        }
    }
}

impl LiveView {
    /// The streaming channels, at most one message per `period_ns` of log time.
    fn stream(&self, state: &mut State, log_ns: u64) {
        let mut last = state.last_sent_ns;
        if !due(&mut last, log_ns, state.period_ns) {
            return;
        }
        let Some(q) = state
            .joints
            .iter()
            .map(|j| j.map(|(angle, ..)| angle))
            .collect::<Option<Vec<f64>>>()
        else {
            return;
        };
        state.last_sent_ns = last;
        let c = &self.shared.channels;
        let at = PartialMetadata::with_log_time(log_ns);
        let readings: Vec<(usize, f64, f64)> = state
            .joints
            .iter()
            .enumerate()
            .filter_map(|(i, j)| j.map(|(a, r, _)| (i + 1, a, r)))
            .collect();
        c.joint_states
            .log_with_meta(&write::joint_states(log_ns, &readings).encode_to_vec(), at);
        let q: [f64; MAX_JOINTS] = std::array::from_fn(|i| q.get(i).copied().unwrap_or(0.0));
        let links = arm_transforms(&state.table, &q, state.joints.len());
        c.tf.log_with_meta(&write::frame_transforms(log_ns, &links).encode_to_vec(), at);
        if let Some((pose, _)) = state.pose {
            c.ee_pose
                .log_with_meta(&write::pose_in_frame(log_ns, &pose).encode_to_vec(), at);
        }
    }

    /// A calibrated table: the arm is drawn on it from now on (its URDF comes as the session's
    /// [`Record::RobotDescription`], stamped with the calibration's log time).
    fn calibrated(&self, state: &mut State, cal: &proto::Calibration) {
        let rows = cal.after.iter().map(|r| calib_core::DhRow {
            a: r.a,
            alpha: r.alpha,
            d: r.d,
            theta_offset: r.theta_offset,
        });
        if let Some(table) = table_of(rows, state.joints.len()) {
            state.table = table;
        }
    }
}

impl Drop for LiveView {
    fn drop(&mut self) {
        if let Some(server) = self.server.take() {
            // Closes every connection; the server's tasks end with the runtime.
            drop(server.stop());
        }
        if let Some(runtime) = self.runtime.take() {
            runtime.shutdown_background();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// At most one message per period of log time; a late record (behind what was sent by
    /// less than a clock step) never sends, so timestamps never step back; a clock step starts
    /// over.
    #[test]
    fn a_streaming_channel_sends_at_its_rate_and_never_steps_back() {
        let period = 33_333_333;
        let mut last = None;
        let ms = 1_000_000u64;
        let sent: Vec<u64> = (0..100u64)
            .map(|k| 10_000 * ms + 5 * ms * k)
            .filter(|&t| due(&mut last, t, period))
            .collect();
        assert!(sent.windows(2).all(|w| w[1] - w[0] >= period), "{sent:?}");
        assert_eq!(sent.len(), 15); // 0.5 s at one per 35 ms (the first 5-ms step past 33.3)
        let at = last.unwrap();
        assert!(!due(&mut last, at - 100 * ms, period), "a late record");
        assert_eq!(last, Some(at));
        assert!(
            due(&mut last, at - 2 * CLOCK_STEP_NS, period),
            "a clock step"
        );
        assert!(late(Some(at), at - 1) && !late(Some(at), at) && !late(None, 0));
    }
}
