//! The live view: the session served over the Foxglove WebSocket protocol (the Foxglove SDK's
//! server), so a person connects Foxglove to `ws://HOST:PORT` and watches the suit while it is
//! being calibrated.
//!
//! Contract:
//! - off unless `[live] enabled = true` (or `exocald demo --live`); it listens on
//!   `[live] listen` (loopback by default) on a runtime of its own (one worker thread), so
//!   neither the session's loop nor a paused demo clock ever waits for a client;
//! - it is an observer of the session's records ([`crate::shell::tee::Recorder`] hands it every
//!   [`Record`] the log gets) and never fails the session: a slow client misses messages;
//! - channels, with the log's schemas (`exocal-log`): `/joint_states` (all seven joints) and
//!   `/tf` (the arm's frames on the current table, as the exported URDF names them) and
//!   `/ee_pose` (the measured end-effector pose) and `/ee_gyro` (the end effector's IMU rate),
//!   each at most [`LIVE_HZ`] of log time;
//!   `/progress` (coverage per joint, condition number), `/calibration` (the result, then the
//!   push report) and `/events`, every message; `/robot_description` (`std_msgs/String`, JSON:
//!   the URDF of the current table — nominal while collecting, calibrated once calibrated);
//! - a client that subscribes to `/robot_description`, `/progress` or `/calibration` gets the
//!   latest message at once (they change rarely).

use std::net::SocketAddr;
use std::sync::Arc;

use exocal_log::{proto, Topic};
use foxglove::websocket::{ChannelView, Client, ServerListener};
use foxglove::{ChannelBuilder, Context, PartialMetadata, RawChannel, WebSocketServerHandle};
use parking_lot::Mutex;
use prost::Message as _;

use crate::config::{Config, JOINTS};
use crate::log::records::{arm_transforms, Observer, Record};
use crate::log::{mcaplog, records};

/// Most messages per second of log time on the streaming channels (`/joint_states`, `/tf`,
/// `/ee_pose`): plenty to watch an arm move, a few percent of what the bus carries.
pub const LIVE_HZ: f64 = 30.0;
/// Whether a streaming channel last sent at `last` may send at `log_ns` (at most [`LIVE_HZ`] of
/// log time; a clock that stepped back sends at once); if so, `last` becomes `log_ns`.
fn due(last: &mut Option<u64>, log_ns: u64) -> bool {
    let period_ns = (1e9 / LIVE_HZ) as u64;
    if last.is_some_and(|t| log_ns < t.saturating_add(period_ns) && log_ns >= t) {
        return false;
    }
    *last = Some(log_ns);
    true
}

/// The topic of the URDF.
pub const ROBOT_DESCRIPTION: &str = "/robot_description";

/// The channels a client can subscribe to.
struct Channels {
    joint_states: Arc<RawChannel>,
    tf: Arc<RawChannel>,
    ee_pose: Arc<RawChannel>,
    ee_gyro: Arc<RawChannel>,
    progress: Arc<RawChannel>,
    calibration: Arc<RawChannel>,
    events: Arc<RawChannel>,
    robot_description: Arc<RawChannel>,
}

/// What the view keeps between records.
struct State {
    table: calib_core::DhTable<JOINTS>,
    joints: [Option<(f64, f64)>; JOINTS],
    pose: Option<crate::log::records::Transform>,
    last_sent_ns: Option<u64>,
    /// Log time of the last `/ee_gyro` message sent.
    last_rate_ns: Option<u64>,
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

/// A URDF as a `std_msgs/String` JSON message.
fn robot_description(urdf: &str) -> Vec<u8> {
    serde_json::to_vec(&serde_json::json!({ "data": urdf })).unwrap_or_default()
}

fn table_of(rows: impl Iterator<Item = calib_core::DhRow>) -> Option<calib_core::DhTable<JOINTS>> {
    let rows: Vec<calib_core::DhRow> = rows.collect();
    Some(calib_core::DhTable {
        rows: rows.try_into().ok()?,
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
    /// Starts the server on `listen`, the arm on `config`'s nominal table.
    pub fn start(listen: SocketAddr, config: &Config) -> Result<LiveView, LiveError> {
        let err = |e: foxglove::FoxgloveError| LiveError {
            what: format!("starting the live view on {listen}"),
            source: std::io::Error::other(e),
        };
        let ctx = Context::new();
        let build = || -> Result<Channels, foxglove::FoxgloveError> {
            Ok(Channels {
                joint_states: channel(&ctx, Topic::JointStates)?,
                tf: channel(&ctx, Topic::Tf)?,
                ee_pose: channel(&ctx, Topic::EePose)?,
                ee_gyro: channel(&ctx, Topic::EeGyro)?,
                progress: channel(&ctx, Topic::Progress)?,
                calibration: channel(&ctx, Topic::Calibration)?,
                events: channel(&ctx, Topic::Events)?,
                robot_description: ChannelBuilder::new(ROBOT_DESCRIPTION)
                    .context(&ctx)
                    .message_encoding("json")
                    .schema(foxglove::Schema::new(
                        "std_msgs/String",
                        "jsonschema",
                        br#"{"type":"object","properties":{"data":{"type":"string"}}}"#.as_slice(),
                    ))
                    .build_raw()?,
            })
        };
        let channels = build().map_err(err)?;
        let table = config.calibration.nominal;
        let limits = config.calibration.bounds.joint_range.limits;
        let mut state = State {
            table,
            joints: [None; JOINTS],
            pose: None,
            last_sent_ns: None,
            last_rate_ns: None,
            latched: Vec::new(),
        };
        let nominal = records::urdf(&table, &limits).unwrap_or_default();
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
            .bind(listen.ip().to_string(), listen.port())
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
        Ok(LiveView {
            _context: ctx,
            shared,
            server: Some(handle),
            runtime: Some(runtime),
        })
    }

    /// The port it listens on.
    pub fn port(&self) -> u16 {
        self.server.as_ref().map_or(0, WebSocketServerHandle::port)
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
                    *slot = Some((angle, rate));
                }
                self.stream(&mut state, log_ns);
            }
            Record::EePose(pose) => {
                state.pose = Some(*pose);
                self.stream(&mut state, log_ns);
            }
            Record::Rate {
                stream,
                node_timestamp_lo_us,
                xyz,
            } => {
                if !due(&mut state.last_rate_ns, log_ns) {
                    return;
                }
                let bytes =
                    mcaplog::angular_rate(stream, node_timestamp_lo_us, xyz).encode_to_vec();
                c.ee_gyro.log_with_meta(&bytes, at);
            }
            Record::Progress(p) => {
                let bytes = mcaplog::progress(p).encode_to_vec();
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
                let bytes = mcaplog::log_message(log_ns, level, message).encode_to_vec();
                c.events.log_with_meta(&bytes, at);
            }
            Record::RobotDescription(urdf) => {
                let bytes = robot_description(urdf);
                c.robot_description.log_with_meta(&bytes, at);
                state.latch(ROBOT_DESCRIPTION, bytes);
            }
            Record::Frame { .. }
            | Record::Arm(_)
            | Record::Aligned(_)
            | Record::CollectionEnd(_) => {}
        }
    }
}

impl LiveView {
    /// The streaming channels, at most [`LIVE_HZ`] of log time.
    fn stream(&self, state: &mut State, log_ns: u64) {
        let mut last = state.last_sent_ns;
        if !due(&mut last, log_ns) {
            return;
        }
        let Some(q) = state
            .joints
            .iter()
            .map(|j| j.map(|(angle, _)| angle))
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
            .filter_map(|(i, j)| j.map(|(a, r)| (i + 1, a, r)))
            .collect();
        c.joint_states.log_with_meta(
            &mcaplog::joint_states(log_ns, &readings).encode_to_vec(),
            at,
        );
        let q: [f64; JOINTS] = std::array::from_fn(|i| q[i]);
        let links = arm_transforms(&state.table, &q);
        c.tf.log_with_meta(
            &mcaplog::frame_transforms(log_ns, &links).encode_to_vec(),
            at,
        );
        if let Some(pose) = state.pose {
            c.ee_pose
                .log_with_meta(&mcaplog::pose_in_frame(log_ns, &pose).encode_to_vec(), at);
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
        if let Some(table) = table_of(rows) {
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
