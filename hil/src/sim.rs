//! The emulated suit: true arm, nodes, sensors, clocks, faults, and the frames they produce.
//!
//! Contract: [`Suit`] is deterministic for a given scenario and seed and does no I/O besides
//! the node flash files. [`Suit::advance`] runs simulated time forward and returns the frames
//! that reach the bus by then, in bus order; [`Suit::receive`] hands a frame from the bus to the
//! nodes (table transfers). Nothing here reads a clock: time is always an argument.
//!
//! Physics: the true joint angles follow a smooth random motion inside the scenario's ranges
//! ([`Motion`], rates in closed form). A joint node on link j reports `θ_j − Δθ_j + noise` and
//! the true rate plus noise, where Δθ_j is its Gauss-Markov drift stepped once per joint sample;
//! its gyro reports the angular velocity of link j (`Σ z_{i−1} θ̇_i`) in the link frame plus a
//! slowly drifting bias and noise; its accelerometer the specific force of the link origin (the
//! second difference of its last three IMU-sample positions, so one IMU period late, plus
//! gravity along −z of the base frame); its magnetometer a fixed earth field seen from the link
//! frame. The end-effector node
//! reports `FK(true table, true angles)` plus noise as a unit quaternion with w ≥ 0.
//!
//! Motion: the scenario's `duration_s` bounds the motion. After it the suit is at rest with its
//! nodes powered: they take no more samples (no joint state, IMU or pose frames, and no injected
//! malformed or babble frames), but keep their heartbeats and answer table transfers, for as
//! long as simulated time is advanced. The frames up to `duration_s` do not depend on it.
//!
//! Clocks: each node stamps frames with `offset + (t − boot)·(1 + skew) + jumps + jitter` in
//! µs, wrapping at 2^32, and samples every `1/rate` of *its own* clock.

use crate::flash::{self, FlashImage, NodeFlash};
use crate::motion::Motion;
use crate::scenario::{Scenario, TransferBehaviour};
use crate::stream_auth::{self, Signer};
use crate::wearer::Attention;
use crate::HilError;
use calib_core::{DhTable, Discretisation, GaussMarkov, PreparedTable, Rng};
use exocal_bus::embedded_can::{ExtendedId, Frame as _, StandardId};
use exocal_bus::fault::{Fate, Faults};
use exocal_bus::Frame;
use exocal_dbc::message::{
    Command, Heartbeat, ImuVector, JointState, Message, NackReason, NodeState, Reply, TableCmd,
    TableReply,
};
use exocal_dbc::pose::Pose;
use exocal_dbc::spec;
use exocal_dbc::transfer::NodeTransfer;
use exocal_dbc::{NodeId, Table};
use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};
use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// Standard gravity, m/s².
const G: f64 = 9.80665;
/// Earth magnetic field in the base frame, µT.
const EARTH_FIELD_UT: [f64; 3] = [20.0, 0.0, -45.0];
/// Transmit latency after sampling, s.
const TX_LATENCY_S: f64 = 50e-6;
/// Reply latency after a table command, s.
const REPLY_LATENCY_S: f64 = 300e-6;
/// Firmware version the nodes report (2: protocol exocal-2, authenticated transfers).
const FW: (u8, u8) = (2, 0);

/// Identifiers the DBC leaves unused, where malformed frames with an unknown identifier are drawn
/// (a test checks the range against the generated tables).
const UNUSED_IDS: std::ops::Range<u16> = 0x300..0x580;

/// One IMU channel: value in the sensor frame, noise, full scale, message.
type ImuChannel = (Vector3<f64>, f64, f64, fn(ImuVector) -> Message);

/// The periodic samples a node takes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Kind {
    /// `JointState` (one frame).
    JointState = 0,
    /// `ImuGyro`, `ImuAccel`, `ImuMag` (three frames, one instant).
    Imu = 1,
    /// `EePose` (four frames).
    Pose = 2,
    /// `Heartbeat` (one frame).
    Heartbeat = 3,
}

impl Kind {
    /// All kinds.
    pub const ALL: [Kind; 4] = [Kind::JointState, Kind::Imu, Kind::Pose, Kind::Heartbeat];
}

/// Counters of what the emulation did.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Stats {
    /// Samples taken per node (index = node id) and kind (index = `Kind as usize`); an IMU
    /// sample is three frames, a pose sample four.
    pub samples: [[u64; 4]; 9],
    /// Frames put on the bus.
    pub frames_sent: u64,
    /// Frames lost by uniform loss or bursts (both directions).
    pub lost: u64,
    /// Extra copies sent.
    pub duplicated: u64,
    /// Frames sent with a bit of their payload flipped.
    pub corrupted: u64,
    /// Frames delayed or held back.
    pub delayed: u64,
    /// Malformed frames injected.
    pub malformed: u64,
    /// Babble frames injected.
    pub babbled: u64,
    /// NaN values injected.
    pub nans: u64,
    /// Table commands handled by a node.
    pub commands: u64,
    /// Replies produced by nodes.
    pub replies: u64,
    /// Reboots done.
    pub reboots: u64,
    /// Flash files that read as corrupt at boot.
    pub flash_corrupt: u64,
    /// Commands a keyed node refused as unauthenticated (NACK `BadMac` or `StaleCounter`).
    pub refused_unauthenticated: u64,
    /// Boots of a provisioned node that could not read its key slot or its counter record: it
    /// booted without a key, installing nothing until provisioned again (fail closed).
    pub locked: u64,
    /// `StreamNonce` frames a node did not take: unsigned, signed for another node or with
    /// another key, or not above the nonce it holds (a replay).
    pub ignored_nonces: u64,
}

#[derive(Clone, Copy, Debug)]
struct NodeClock {
    offset_us: f64,
    skew: f64,
    jitter_us: f64,
    boot_s: f64,
    jump_us: f64,
}

impl NodeClock {
    fn local_us(&self, t: f64) -> f64 {
        self.offset_us + (t - self.boot_s) * 1e6 * (1.0 + self.skew) + self.jump_us
    }
}

#[derive(Clone, Copy, Debug)]
struct Schedule {
    kind: Kind,
    next_s: f64,
    period_s: f64,
}

struct Node {
    id: NodeId,
    clock: NodeClock,
    schedules: Vec<Schedule>,
    rng: Rng,
    drift: f64,
    gm: Option<GaussMarkov>,
    bias: [f64; 3],
    bias_gm: GaussMarkov,
    /// The heading rate bias its angle integrates (rad/s; 0 where gravity corrects it), and
    /// the joint's axis in its link's frame, which the gyro's bias reads it along.
    heading: f64,
    axis: Vector3<f64>,
    pose_seq: u8,
    /// Link origin at the last two IMU samples (time, position), for the accelerometer.
    history: [Option<(f64, Vector3<f64>)>; 2],
    up: bool,
    boot_count: u32,
    /// The stream signer, for a node holding a key (`crate::stream_auth`).
    stream: Option<Signer>,
    transfer: NodeTransfer,
    flash: NodeFlash,
    behaviour: TransferBehaviour,
    rx_errors: u32,
    tx_errors: u32,
    last_frame: Option<Frame>,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Event {
    Jump(u8, f64),
    Down(u8),
    Up(u8),
}

#[derive(Clone, Copy, Debug, PartialEq)]
struct Pending {
    t_s: f64,
    order: u64,
    frame: Frame,
}

impl Eq for Pending {}
impl PartialOrd for Pending {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Pending {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        self.t_s
            .total_cmp(&other.t_s)
            .then(self.order.cmp(&other.order))
    }
}

/// The emulated suit.
pub struct Suit {
    scenario: Scenario,
    arm: DhTable<7>,
    chain: PreparedTable<7>,
    motion: Motion,
    attention: Attention,
    nodes: Vec<Node>,
    events: Vec<(f64, Event)>,
    next_event: usize,
    babble_next: Vec<f64>,
    malformed_next: f64,
    queue: BinaryHeap<Reverse<Pending>>,
    order: u64,
    fault_rng: Rng,
    /// The wire's faults (loss, bursts, corruption, delay, reordering, duplication).
    wire: Faults,
    now_s: f64,
    flash_dir: PathBuf,
    stats: Stats,
}

fn seeded(seed: u64, stream: u64) -> Rng {
    Rng::new(seed ^ stream.wrapping_mul(0x9E37_79B9_7F4A_7C15))
}

impl Suit {
    /// Powers the suit up: reads (or factory-writes) every node's flash in `flash_dir`.
    pub fn new(scenario: Scenario, flash_dir: &Path) -> Result<Suit, HilError> {
        scenario.validate().map_err(HilError::Scenario)?;
        let arm = scenario.arm.table();
        let motion = Motion::random(&scenario.arm.ranges(), &mut seeded(scenario.seed, 1))
            .with_reach(scenario.wearer.reach)
            .with_still(scenario.wearer.still_s);
        let attention = Attention::new(scenario.wearer.clone(), seeded(scenario.seed, 5));
        let mut clock_rng = seeded(scenario.seed, 2);
        let mut heading_rng = seeded(scenario.seed, 6);
        let heading: [f64; 7] = std::array::from_fn(|j| {
            let sign = if heading_rng.uniform() < 0.5 {
                -1.0
            } else {
                1.0
            };
            let on = scenario.drift.heading_joints.contains(&(j as u8 + 1));
            if on {
                sign * scenario.drift.heading_deg_s.to_radians()
            } else {
                0.0
            }
        });
        let factory_table = scenario.factory.preset.table();
        let mut stats = Stats::default();
        let mut nodes = Vec::new();
        for id in NodeId::ALL {
            let explicit = scenario.clocks.node.iter().find(|c| c.node == id.raw());
            let offset_us = explicit
                .and_then(|c| c.offset_us)
                .unwrap_or_else(|| clock_rng.uniform() * 4294967296.0);
            let skew_ppm = explicit.and_then(|c| c.skew_ppm).unwrap_or_else(|| {
                (2.0 * clock_rng.uniform() - 1.0) * scenario.clocks.skew_ppm_max
            });
            let jitter_us = explicit
                .and_then(|c| c.jitter_us)
                .unwrap_or(scenario.clocks.jitter_us);
            let clock = NodeClock {
                offset_us,
                skew: skew_ppm * 1e-6,
                jitter_us,
                boot_s: 0.0,
                jump_us: 0.0,
            };

            let image = match flash::read(flash_dir, id) {
                Ok(image) => image,
                Err(flash::FlashError::Corrupt(..)) => {
                    stats.flash_corrupt += 1;
                    None
                }
                Err(e) => return Err(HilError::Flash(e)),
            };
            let image = match (image, id.joint_index()) {
                (Some(i), _) => Some(i),
                (None, Some(j)) => {
                    let r = factory_table.rows[j];
                    let f = &scenario.factory;
                    let table = Table::from_si(r.a, r.alpha, r.d, r.theta_offset, f.tau_s, f.sigma)
                        .map_err(|e| HilError::Factory(id, e))?;
                    Some(FlashImage {
                        boot_count: 0,
                        table,
                        counter: 0,
                    })
                }
                (None, None) => None,
            };
            let boot_count = image.map_or(0, |i| i.boot_count.wrapping_add(1));
            if let Some(i) = image {
                flash::write(flash_dir, id, &FlashImage { boot_count, ..i }).map_err(|e| {
                    HilError::Flash(flash::FlashError::Io(flash::path(flash_dir, id), e))
                })?;
            }
            let provisioning = flash::Provisioning::read(flash_dir, id);
            let mut rng = seeded(scenario.seed, 16 + u64::from(id.raw()));
            let joint_dt = 1.0 / scenario.rates.joint_state_hz;
            let gm = match id.joint_index() {
                Some(j) if scenario.drift.enabled => Some(scenario.drift.process(j, joint_dt)),
                _ => None,
            };
            let drift = gm.map_or(0.0, |g| g.initial(&mut rng));
            let bias_gm = GaussMarkov {
                dt: 1.0 / scenario.rates.imu_hz,
                tau: scenario.noise.gyro_bias_tau_s,
                sigma: scenario.noise.gyro_bias_rad_s,
                discretisation: Discretisation::Exact,
            };
            let bias = [
                bias_gm.initial(&mut rng),
                bias_gm.initial(&mut rng),
                bias_gm.initial(&mut rng),
            ];
            let mut node = Node {
                id,
                clock,
                schedules: Vec::new(),
                rng,
                drift,
                gm,
                bias,
                bias_gm,
                heading: id.joint_index().map_or(0.0, |j| heading[j]),
                axis: id.joint_index().map_or(Vector3::z(), |j| {
                    // z_{j-1} seen from link j: R_x(α_j)ᵀ ẑ.
                    let alpha = arm.rows[j].alpha;
                    Vector3::new(0.0, alpha.sin(), alpha.cos())
                }),
                pose_seq: 0,
                history: [None; 2],
                up: on_arm(&scenario, id),
                boot_count,
                stream: stream_auth::signer(
                    id,
                    provisioning.key.as_ref().ok().and_then(Option::as_ref),
                ),
                transfer: boot_transfer(id, image, provisioning, &mut stats),
                flash: NodeFlash::new(flash_dir, id, boot_count),
                behaviour: scenario.faults.transfer_behaviour(id.raw()),
                rx_errors: 0,
                tx_errors: 0,
                last_frame: None,
            };
            node.schedules = schedules(&scenario, &mut node, 0.0);
            nodes.push(node);
        }
        let mut events: Vec<(f64, Event)> = Vec::new();
        for j in &scenario.faults.clock_jumps {
            events.push((j.at_s, Event::Jump(j.node, j.jump_us)));
        }
        for r in &scenario.faults.reboots {
            events.push((r.at_s, Event::Down(r.node)));
            events.push((r.at_s + r.down_s, Event::Up(r.node)));
        }
        events.sort_by(|a, b| a.0.total_cmp(&b.0));
        let mut fault_rng = seeded(scenario.seed, 3);
        let malformed_next = if scenario.faults.malformed_hz > 0.0 {
            fault_rng.uniform() / scenario.faults.malformed_hz
        } else {
            f64::INFINITY
        };
        let babble_next = scenario.faults.babble.iter().map(|b| b.from_s).collect();
        Ok(Suit {
            chain: arm.prepare(),
            arm,
            motion,
            attention,
            nodes,
            events,
            next_event: 0,
            babble_next,
            malformed_next,
            queue: BinaryHeap::new(),
            order: 0,
            fault_rng,
            wire: Faults::new(scenario.faults.wire(), seeded(scenario.seed, 4).next_u64()),
            now_s: 0.0,
            flash_dir: flash_dir.to_path_buf(),
            stats,
            scenario,
        })
    }

    /// The scenario.
    pub fn scenario(&self) -> &Scenario {
        &self.scenario
    }

    /// The true D-H table of the arm.
    pub fn true_table(&self) -> &DhTable<7> {
        &self.arm
    }

    /// The heading rate bias each joint's angle integrates (rad/s, joint 1 first; 0 where its
    /// node corrects it): the scenario's `drift.heading_*`, with the signs drawn.
    pub fn headings(&self) -> [f64; 7] {
        let mut h = [0.0; 7];
        for n in &self.nodes {
            if let Some(j) = n.id.joint_index() {
                h[j] = n.heading;
            }
        }
        h
    }

    /// True joint angles at simulated time `t_s`.
    pub fn true_joints(&self, t_s: f64) -> [f64; 7] {
        self.motion.at(t_s)
    }

    /// The wearer is told, at the suit's time now, to move `joint` (0-based): they may follow
    /// ([`crate::wearer`]; the frames already sent are unchanged).
    pub fn heed(&mut self, joint: usize) {
        self.attention.heed(joint, self.now_s, &mut self.motion);
    }

    /// Current drift Δθ of joint `j` (0-based).
    pub fn drift(&self, j: usize) -> f64 {
        self.nodes[j].drift
    }

    /// The table node `node` holds now.
    pub fn held_table(&self, node: NodeId) -> Option<Table> {
        self.nodes[usize::from(node.raw() - 1)]
            .transfer
            .held()
            .copied()
    }

    /// Where the node flash files are.
    pub fn flash_dir(&self) -> &Path {
        &self.flash_dir
    }

    /// Counters so far.
    pub fn stats(&self) -> &Stats {
        &self.stats
    }

    /// Simulated time reached by [`Suit::advance`].
    pub fn now_s(&self) -> f64 {
        self.now_s
    }

    /// Whether the motion is over at simulated time `t` (samples at `duration_s` still count).
    fn at_rest(&self, t: f64) -> bool {
        t > self.scenario.duration_s
    }

    /// Whether babble fault `i` has a frame to come: before its own end and the motion's.
    fn babble_pending(&self, i: usize) -> bool {
        let next = self.babble_next[i];
        next < self.scenario.faults.babble[i].to_s && !self.at_rest(next)
    }

    fn next_internal_s(&self) -> f64 {
        let mut t = self.malformed_next;
        for n in self.nodes.iter().filter(|n| n.up) {
            for s in &n.schedules {
                t = t.min(s.next_s);
            }
        }
        if let Some((te, _)) = self.events.get(self.next_event) {
            t = t.min(*te);
        }
        for (i, next) in self.babble_next.iter().enumerate() {
            if self.babble_pending(i) {
                t = t.min(*next);
            }
        }
        t
    }

    /// The next simulated time at which something happens (a sample, a fault, a queued frame).
    pub fn next_event_s(&self) -> f64 {
        let q = self.queue.peek().map_or(f64::INFINITY, |p| p.0.t_s);
        self.next_internal_s().min(q)
    }

    /// Runs simulated time up to `to_s`; returns the frames that reach the bus by then, in order.
    pub fn advance(&mut self, to_s: f64) -> Vec<Frame> {
        loop {
            let t = self.next_internal_s();
            if t > to_s {
                break;
            }
            self.step(t);
        }
        self.now_s = self.now_s.max(to_s);
        let mut out = Vec::new();
        while self.queue.peek().is_some_and(|p| p.0.t_s <= to_s) {
            out.push(self.queue.pop().expect("peeked").0.frame);
        }
        self.stats.frames_sent += out.len() as u64;
        out
    }

    fn step(&mut self, t: f64) {
        if let Some(&(te, ev)) = self.events.get(self.next_event) {
            if te <= t {
                self.next_event += 1;
                self.apply(te, ev);
                return;
            }
        }
        if self.malformed_next <= t {
            if self.at_rest(t) {
                self.malformed_next = f64::INFINITY;
                return;
            }
            self.malformed(t);
            self.malformed_next =
                t - self.fault_rng.uniform().max(1e-12).ln() / self.scenario.faults.malformed_hz;
            return;
        }
        for i in 0..self.babble_next.len() {
            let b = self.scenario.faults.babble[i];
            if self.babble_next[i] <= t && self.babble_pending(i) {
                self.babble_next[i] += 1.0 / b.rate_hz;
                let node = &self.nodes[usize::from(b.node - 1)];
                if let (true, Some(f)) = (node.up, node.last_frame) {
                    self.stats.babbled += 1;
                    self.emit(t, f);
                }
                return;
            }
        }
        for n in 0..self.nodes.len() {
            if !self.nodes[n].up {
                continue;
            }
            for s in 0..self.nodes[n].schedules.len() {
                let sched = self.nodes[n].schedules[s];
                if sched.next_s <= t {
                    if sched.kind != Kind::Heartbeat && self.at_rest(t) {
                        // The motion is over: the node takes no more samples of this kind.
                        self.nodes[n].schedules[s].next_s = f64::INFINITY;
                        return;
                    }
                    self.nodes[n].schedules[s].next_s += sched.period_s;
                    self.sample(n, sched.kind, t);
                    return;
                }
            }
        }
    }

    fn apply(&mut self, t: f64, ev: Event) {
        match ev {
            Event::Jump(node, us) => self.nodes[usize::from(node - 1)].clock.jump_us += us,
            Event::Down(node) => self.nodes[usize::from(node - 1)].up = false,
            Event::Up(node) if !on_arm(&self.scenario, self.nodes[usize::from(node - 1)].id) => {}
            Event::Up(node) => {
                self.stats.reboots += 1;
                let scenario = &self.scenario;
                let n = &mut self.nodes[usize::from(node - 1)];
                n.up = true;
                n.boot_count = n.boot_count.wrapping_add(1);
                n.clock.boot_s = t;
                n.clock.jump_us = 0.0;
                n.clock.offset_us = 1000.0 * n.rng.uniform();
                n.pose_seq = 0;
                n.history = [None; 2];
                n.rx_errors = 0;
                n.tx_errors = 0;
                // RAM is gone: the table comes back from flash.
                let image = flash::read(&self.flash_dir, n.id).ok().flatten();
                if let Some(i) = image {
                    let boot_count = n.boot_count;
                    let _ = flash::write(&self.flash_dir, n.id, &FlashImage { boot_count, ..i });
                }
                let provisioning = flash::Provisioning::read(&self.flash_dir, n.id);
                // RAM is gone: the stream signer starts over, without the collection's nonce.
                n.stream = stream_auth::signer(
                    n.id,
                    provisioning.key.as_ref().ok().and_then(Option::as_ref),
                );
                n.transfer = boot_transfer(n.id, image, provisioning, &mut self.stats);
                n.flash = NodeFlash::new(&self.flash_dir, n.id, n.boot_count);
                n.schedules = schedules(scenario, n, t);
            }
        }
    }

    fn stamp(&mut self, n: usize, t: f64) -> u32 {
        let node = &mut self.nodes[n];
        let jitter = gauss(&mut node.rng, node.clock.jitter_us);
        (node.clock.local_us(t) + jitter).rem_euclid(4294967296.0) as u64 as u32
    }

    fn sample(&mut self, n: usize, kind: Kind, t: f64) {
        let id = self.nodes[n].id;
        self.stats.samples[usize::from(id.raw())][kind as usize] += 1;
        let link = id.joint_index().unwrap_or(6);
        let noise = self.scenario.noise;
        let nan_p = self.scenario.faults.nan;
        let messages: Vec<Message> = match kind {
            Kind::JointState => {
                let (q, qd) = self.motion.joint(link, t);
                let node = &mut self.nodes[n];
                if let Some(gm) = node.gm {
                    node.drift = gm.step(node.drift, &mut node.rng);
                }
                // The heading integrates from power-up; the rate is the node's gyro about the axis.
                let mut angle =
                    q - node.drift + node.heading * t + gauss(&mut node.rng, noise.angle_rad);
                let rate = qd + node.heading + gauss(&mut node.rng, noise.rate_rad_s);
                if nan_p > 0.0 && self.fault_rng.uniform() < nan_p {
                    angle = f64::NAN;
                    self.stats.nans += 1;
                }
                let timestamp_us = self.stamp(n, t);
                vec![Message::JointState(JointState {
                    node: id,
                    timestamp_us,
                    angle,
                    rate,
                })]
            }
            Kind::Imu => {
                let mut q = [0.0; 7];
                let mut qd = [0.0; 7];
                for j in 0..=link {
                    (q[j], qd[j]) = self.motion.joint(j, t);
                }
                let frames = self.chain.frames(&q, link + 1);
                let (r, p) = (frames[link].r, frames[link].p);
                // Gyro: angular velocity of the link, Σ z_{i-1} q̇_i, seen from the link frame.
                let mut w = Vector3::zeros();
                let mut z = Vector3::z();
                for j in 0..=link {
                    w += z * qd[j];
                    z = frames[j].r.column(2).into_owned();
                }
                let node = &mut self.nodes[n];
                // Accelerometer: second difference over this node's last three IMU samples.
                let a = match node.history {
                    [Some((t1, p1)), Some((t2, p2))] => {
                        2.0 * ((p - p1) / (t - t1) - (p1 - p2) / (t1 - t2)) / (t - t2)
                    }
                    _ => Vector3::zeros(),
                };
                node.history = [Some((t, p)), node.history[0]];
                for b in node.bias.iter_mut() {
                    *b = node.bias_gm.step(*b, &mut node.rng);
                }
                // Along the joint's axis, a heading node's gyro bias is its heading.
                let mut bias = Vector3::from(node.bias);
                if node.heading != 0.0 {
                    bias += node.axis * (node.heading - bias.dot(&node.axis));
                }
                let channels: [ImuChannel; 3] = [
                    (
                        r.transpose() * w + bias,
                        noise.gyro_rad_s,
                        32.767,
                        Message::ImuGyro,
                    ),
                    (
                        r.transpose() * (a + Vector3::new(0.0, 0.0, G)),
                        noise.accel_m_s2,
                        65.534,
                        Message::ImuAccel,
                    ),
                    (
                        r.transpose() * Vector3::from(EARTH_FIELD_UT),
                        noise.mag_ut,
                        327.67,
                        Message::ImuMag,
                    ),
                ];
                let timestamp_lo = self.stamp(n, t) as u16;
                let mut out = Vec::with_capacity(3);
                for (mut v, sd, max, wrap) in channels {
                    let node = &mut self.nodes[n];
                    for x in v.iter_mut() {
                        // Sensors saturate at their full scale.
                        *x = (*x + gauss(&mut node.rng, sd)).clamp(-max, max);
                    }
                    let mut xyz = [v.x, v.y, v.z];
                    if nan_p > 0.0 && self.fault_rng.uniform() < nan_p {
                        xyz[0] = f64::NAN;
                        self.stats.nans += 1;
                    }
                    out.push(wrap(ImuVector {
                        node: id,
                        xyz,
                        timestamp_lo,
                    }));
                }
                out
            }
            Kind::Pose => {
                let q = self.motion.at(t);
                let mut pose = self.chain.frames(&q, 7)[6];
                let node = &mut self.nodes[n];
                let (sp, sr) = (noise.pose_position_m, noise.pose_rotation_rad);
                if sp > 0.0 {
                    pose.p += Vector3::new(
                        sp * node.rng.normal(),
                        sp * node.rng.normal(),
                        sp * node.rng.normal(),
                    );
                }
                if sr > 0.0 {
                    let w = Vector3::new(
                        sr * node.rng.normal(),
                        sr * node.rng.normal(),
                        sr * node.rng.normal(),
                    );
                    pose.r *= Rotation3::new(w).into_inner();
                }
                let mut quat = quaternion(&pose.r);
                if quat[0] < 0.0 {
                    quat = quat.map(|c| -c);
                }
                let seq = node.pose_seq;
                node.pose_seq = (node.pose_seq + 1) % 64;
                let timestamp_us = self.stamp(n, t);
                let pose = Pose {
                    seq,
                    timestamp_us,
                    position: [pose.p.x, pose.p.y, pose.p.z],
                    quat,
                };
                pose.pages().map(Message::EePose).to_vec()
            }
            Kind::Heartbeat => {
                let node = &self.nodes[n];
                let local = ((t - node.clock.boot_s) * 1e6) as u64;
                let state = if node.transfer.is_staging(local) {
                    NodeState::Staging
                } else {
                    NodeState::Operational
                };
                vec![Message::Heartbeat(Heartbeat {
                    node: id,
                    state,
                    boot_count: (node.boot_count % 16) as u8,
                    tx_errors: node.tx_errors.min(255) as u8,
                    rx_errors: node.rx_errors.min(255) as u8,
                    table_crc: node.transfer.held_crc(),
                    fw_major: FW.0,
                    fw_minor: FW.1,
                })]
            }
        };
        let local_us = self.nodes[n].local_us(t);
        for m in messages {
            match m.to_frame::<Frame>() {
                Ok(f) => {
                    self.nodes[n].last_frame = Some(f);
                    self.emit(t + TX_LATENCY_S, f);
                    let full = self.nodes[n]
                        .stream
                        .as_mut()
                        .and_then(|s| s.sign(&f, local_us));
                    if let Some(digest) = full {
                        self.emit(t + TX_LATENCY_S, digest);
                    }
                }
                // A value the DBC cannot carry: the firmware drops the sample and counts it.
                Err(_) => self.nodes[n].tx_errors += 1,
            }
        }
        if let Some(digest) = self.nodes[n].stream.as_mut().and_then(|s| s.due(local_us)) {
            self.emit(t + TX_LATENCY_S, digest);
        }
    }

    fn malformed(&mut self, t: f64) {
        self.stats.malformed += 1;
        let r = &mut self.fault_rng;
        let pick = (r.uniform() * 3.0) as u32;
        let byte = (r.next_u64() & 0xFF) as u8;
        let frame = match pick {
            0 => {
                // A JointState identifier with a short payload.
                let nodes = spec::JOINT_STATE.nodes;
                let node = nodes[(r.uniform() * nodes.len() as f64) as usize];
                let len = (r.uniform() * 8.0) as usize;
                Frame::new(
                    StandardId::new(spec::JOINT_STATE.id(node)).expect("11 bits"),
                    &[byte; 8][..len],
                )
            }
            1 => {
                // An identifier the DBC does not define.
                let width = f64::from(UNUSED_IDS.end - UNUSED_IDS.start);
                let id = UNUSED_IDS.start + (r.uniform() * width) as u16;
                Frame::new(StandardId::new(id).expect("11 bits"), &[byte; 8])
            }
            _ => {
                let id = (r.next_u64() as u32) & 0x1FFF_FFFF;
                Frame::new(ExtendedId::new(id).expect("29 bits"), &[byte; 8])
            }
        };
        self.emit(t, frame.expect("valid frame"));
    }

    /// Puts a frame on the (faulty) wire at `t`: its fate is drawn by the bus's [`Faults`] (in
    /// simulated time), then a bus stall holds it back.
    fn emit(&mut self, t: f64, frame: Frame) {
        let Fate::Deliver { frame, at, again } = self.wire.fate(Duration::from_secs_f64(t), frame)
        else {
            self.sync_wire_stats();
            return;
        };
        self.sync_wire_stats();
        let stall = |at: f64| {
            self.scenario
                .faults
                .bus_stalls
                .iter()
                .filter(|s| (s.from_s..s.to_s).contains(&t))
                .fold(at, |at, s| at.max((t + s.late_ms * 1e-3).min(s.to_s)))
        };
        let (at, again) = (
            stall(at.as_secs_f64()),
            again.map(|a| stall(a.as_secs_f64())),
        );
        self.push(at, frame);
        if let Some(again) = again {
            self.push(again, frame);
        }
    }

    /// Copies the wire's counters into the suit's.
    fn sync_wire_stats(&mut self) {
        let w = self.wire.stats();
        self.stats.lost = w.dropped;
        self.stats.duplicated = w.duplicated;
        self.stats.delayed = w.delayed;
        self.stats.corrupted = w.corrupted;
    }

    fn push(&mut self, t_s: f64, frame: Frame) {
        self.order += 1;
        self.queue.push(Reverse(Pending {
            t_s,
            order: self.order,
            frame,
        }));
    }

    /// A frame from the bus reaches the nodes at simulated time `t_s`. Table commands are
    /// handled (subject to loss, the node being up, and its transfer behaviour); everything else
    /// is ignored, as node firmware would.
    pub fn receive(&mut self, frame: &Frame, t_s: f64) {
        if frame.is_extended() {
            return;
        }
        if let Ok(Message::StreamNonce(nonce)) = exocal_dbc::decode_frame(frame) {
            // Only the addressed node, up and keyed, takes it, and only if it is signed for it
            // and newer (exocal_dbc::stream_auth).
            let taken = self
                .nodes
                .iter_mut()
                .find(|n| n.up && n.id == nonce.node)
                .and_then(|node| {
                    let local_us = node.local_us(t_s);
                    node.stream.as_mut().map(|s| s.set_nonce(nonce, local_us))
                });
            if !matches!(taken, Some(Ok(()))) {
                self.stats.ignored_nonces += 1;
            }
            return;
        }
        // A table command addresses a joint node: index n of `self.nodes`.
        let n = match spec::lookup(frame.raw_id() as u16) {
            Some((family, Some(node))) if family.kind == spec::Kind::TableCmd => node.joint_index(),
            _ => None,
        };
        let Some(n) = n else { return };
        if !self.nodes[n].up {
            return;
        }
        let lost = self.wire.lost();
        self.sync_wire_stats();
        if lost {
            return;
        }
        let cmd: TableCmd = match exocal_dbc::decode_frame(frame) {
            Ok(Message::TableCmd(c)) => c,
            _ => {
                self.nodes[n].rx_errors += 1;
                return;
            }
        };
        self.stats.commands += 1;
        let node = &mut self.nodes[n];
        let local = node.local_us(t_s);
        let replies: Vec<TableReply> = match node.behaviour {
            TransferBehaviour::Silent => Vec::new(),
            TransferBehaviour::Nack => vec![TableReply {
                node: node.id,
                session: cmd.session,
                reply: Reply::Nack {
                    cmd: cmd.cmd.code(),
                    held_crc: node.transfer.held_crc(),
                    reason: NackReason::FlashError,
                },
            }],
            TransferBehaviour::Normal => node
                .transfer
                .handle(&cmd, local, &mut node.flash)
                .into_iter()
                .collect(),
        };
        if matches!(cmd.cmd, Command::Begin { .. } | Command::Segment(..)) && replies.is_empty() {
            node.rx_errors += 1;
        }
        let unauthenticated = |r: &TableReply| {
            matches!(
                r.reply,
                Reply::Nack {
                    reason: NackReason::BadMac | NackReason::StaleCounter,
                    ..
                }
            )
        };
        self.stats.refused_unauthenticated +=
            replies.iter().filter(|r| unauthenticated(r)).count() as u64;
        for (i, r) in replies.into_iter().enumerate() {
            self.stats.replies += 1;
            let frame = Message::TableReply(r)
                .to_frame::<Frame>()
                .expect("replies are always encodable");
            self.emit(t_s + REPLY_LATENCY_S + i as f64 * 20e-6, frame);
        }
    }
}

impl Node {
    /// Microseconds since the node booted (its firmware's monotonic time).
    fn local_us(&self, t_s: f64) -> u64 {
        ((t_s - self.clock.boot_s).max(0.0) * 1e6) as u64
    }
}

/// A node's transfer state machine as it boots from its flash `image`, key slot and counter
/// record ([`flash::Provisioning::boot`]); a provisioned node that boots without its key is
/// counted in `stats.locked`.
fn boot_transfer(
    id: NodeId,
    image: Option<FlashImage>,
    provisioning: flash::Provisioning,
    stats: &mut Stats,
) -> NodeTransfer {
    let provisioned = provisioning.provisioned();
    let transfer = provisioning.boot(id, image.as_ref());
    if provisioned && !transfer.is_keyed() {
        stats.locked += 1;
    }
    transfer
}

/// A normal draw of deviation `sd`; no draw at all when `sd` is 0 (cheaper, and switching a
/// noise off leaves the other random streams as they were).
fn gauss(rng: &mut Rng, sd: f64) -> f64 {
    if sd > 0.0 {
        sd * rng.normal()
    } else {
        0.0
    }
}

fn quaternion(r: &Matrix3<f64>) -> [f64; 4] {
    // FK products are orthonormal to rounding: no re-orthonormalisation needed.
    let q = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(*r));
    [q.w, q.i, q.j, q.k]
}

/// Whether node `id` is on the emulated arm: the end effector, and the joint nodes of its
/// `arm.joints` joints (the others are not on the bus).
fn on_arm(scenario: &Scenario, id: NodeId) -> bool {
    id.joint_index().is_none_or(|j| scenario.arm.has_joint(j))
}

fn schedules(scenario: &Scenario, node: &mut Node, boot_s: f64) -> Vec<Schedule> {
    if !on_arm(scenario, node.id) {
        return Vec::new();
    }
    let r = scenario.rates;
    let kinds: &[(Kind, f64)] = if node.id.joint_index().is_some() {
        &[
            (Kind::JointState, r.joint_state_hz),
            (Kind::Imu, r.imu_hz),
            (Kind::Heartbeat, r.heartbeat_hz),
        ]
    } else {
        &[
            (Kind::Imu, r.imu_hz),
            (Kind::Pose, r.pose_hz),
            (Kind::Heartbeat, r.heartbeat_hz),
        ]
    };
    kinds
        .iter()
        .map(|&(kind, hz)| {
            // The node's timer ticks every 1/hz of its own clock.
            let period_s = 1.0 / (hz * (1.0 + node.clock.skew));
            Schedule {
                kind,
                next_s: boot_s + period_s * node.rng.uniform(),
                period_s,
            }
        })
        .collect()
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use exocal_dbc::pose::PoseAssembler;
    use exocal_dbc::{decode_frame, PoseFrame};
    use std::collections::BTreeMap;

    pub(crate) fn temp_dir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("exocal-hil-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    /// A scenario with ideal clocks (offset 0, no skew, no jitter) so that timestamps are the
    /// simulated sample times.
    fn ideal(mut s: Scenario) -> Scenario {
        s.clocks.skew_ppm_max = 0.0;
        s.clocks.jitter_us = 0.0;
        s.clocks.node = (1..=8)
            .map(|node| crate::scenario::NodeClockSpec {
                node,
                offset_us: Some(0.0),
                skew_ppm: Some(0.0),
                jitter_us: Some(0.0),
            })
            .collect();
        s
    }

    fn counts(frames: &[Frame]) -> BTreeMap<u32, u64> {
        let mut c = BTreeMap::new();
        for f in frames {
            *c.entry(f.raw_id()).or_default() += 1;
        }
        c
    }

    #[test]
    fn unused_ids_are_unused() {
        assert!(UNUSED_IDS.clone().all(|id| spec::lookup(id).is_none()));
    }

    #[test]
    fn paper_scenario_sends_every_message_at_its_rate_and_all_decode() {
        let dir = temp_dir("rates");
        let mut suit = Suit::new(Scenario::paper(), &dir).unwrap();
        let frames = suit.advance(10.0);
        for f in &frames {
            decode_frame(f).unwrap_or_else(|e| panic!("{f:?}: {e}"));
        }
        let c = counts(&frames);
        let near = |message: &spec::MessageSpec, node: NodeId, want: f64, tol: f64| {
            let id = message.id(node.raw());
            let got = c.get(&u32::from(id)).copied().unwrap_or(0) as f64;
            assert!(
                (got - want).abs() <= tol,
                "{id:#x}: {got} frames, want {want}"
            );
        };
        for j in NodeId::JOINTS {
            near(&spec::JOINT_STATE, j, 1000.0, 2.0);
        }
        for n in NodeId::ALL {
            near(&spec::IMU_GYRO, n, 1000.0, 2.0);
            near(&spec::IMU_ACCEL, n, 1000.0, 2.0);
            near(&spec::IMU_MAG, n, 1000.0, 2.0);
            near(&spec::HEARTBEAT, n, 10.0, 1.0);
        }
        near(&spec::EE_POSE, NodeId::END_EFFECTOR, 4000.0, 8.0);
        assert_eq!(c.len(), 7 + 3 * 8 + 8 + 1, "no other identifiers");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn an_arm_of_four_joints_is_four_joint_nodes_and_the_end_effector_at_its_end() {
        let dir = temp_dir("four");
        let mut s = ideal(Scenario::paper());
        s.arm.joints = 4;
        let mut suit = Suit::new(s, &dir).unwrap();
        let frames = suit.advance(5.0);
        let senders: std::collections::BTreeSet<u8> = (frames.iter())
            .filter_map(|f| decode_frame(f).unwrap().node().map(NodeId::raw))
            .collect();
        assert_eq!(
            senders,
            [1, 2, 3, 4, 8].into(),
            "only the arm's nodes are on the bus"
        );
        let arm: calib_core::DhTable<4> = DhTable::<7>::paper_actual().first();
        let mut poses = PoseAssembler::new();
        let mut checked = 0;
        for f in &frames {
            if let Message::EePose(p) = decode_frame(f).unwrap() {
                if let Some(pose) = poses.push(PoseFrame { ..p }) {
                    let pose = pose.unwrap();
                    let q = suit.true_joints(f64::from(pose.timestamp_us) * 1e-6);
                    assert!(q[4..].iter().all(|&q| q == 0.0), "{q:?}");
                    let fk = arm.fk(&[q[0], q[1], q[2], q[3]]);
                    for k in 0..3 {
                        assert!(
                            (pose.position[k] - fk.p[k]).abs() <= 3e-6,
                            "{pose:?} vs {fk:?}"
                        );
                    }
                    checked += 1;
                }
            }
        }
        assert!(checked > 400, "{checked}");
        let mut bad = Scenario::paper();
        bad.arm.joints = 8;
        assert!(bad
            .validate()
            .unwrap_err()
            .to_string()
            .contains("arm.joints"));
        let mut rows = Scenario::paper();
        rows.arm.joints = 4;
        rows.arm.ranges_deg = Some(vec![[-10.0, 10.0]; 7]);
        let e = rows.validate().unwrap_err().to_string();
        assert!(e.contains("needs 4 ranges"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn the_same_seed_gives_the_same_frames() {
        let (d1, d2, d3) = (temp_dir("seed1"), temp_dir("seed2"), temp_dir("seed3"));
        let a = Suit::new(Scenario::paper(), &d1).unwrap().advance(2.0);
        let b = Suit::new(Scenario::paper(), &d2).unwrap().advance(2.0);
        let mut other = Scenario::paper();
        other.seed += 1;
        let c = Suit::new(other, &d3).unwrap().advance(2.0);
        assert_eq!(a, b);
        assert_ne!(a, c);
        for d in [d1, d2, d3] {
            let _ = std::fs::remove_dir_all(d);
        }
    }

    #[test]
    fn joint_angles_are_truth_minus_drift_and_pose_is_fk_of_truth() {
        for drift in [false, true] {
            let dir = temp_dir(&format!("truth{drift}"));
            let mut s = ideal(Scenario::paper());
            s.drift.enabled = drift;
            let mut suit = Suit::new(s, &dir).unwrap();
            let frames = suit.advance(20.0);
            let (mut sum2, mut n) = (0.0, 0.0);
            let mut poses = PoseAssembler::new();
            let mut pose_checked = 0;
            for f in &frames {
                match decode_frame(f).unwrap() {
                    Message::JointState(js) => {
                        let t = f64::from(js.timestamp_us) * 1e-6;
                        let j = js.node.joint_index().unwrap();
                        let e = js.angle - suit.true_joints(t)[j];
                        sum2 += e * e;
                        n += 1.0;
                        if !drift {
                            assert!(e.abs() <= 1e-5, "1e-5 rad and 1 µs resolution only: {e}");
                        }
                    }
                    Message::EePose(p) => {
                        if let Some(pose) = poses.push(PoseFrame { ..p }) {
                            let pose = pose.unwrap();
                            let t = f64::from(pose.timestamp_us) * 1e-6;
                            let fk = suit.true_table().fk(&suit.true_joints(t));
                            for k in 0..3 {
                                // 1 µm wire resolution plus the 1 µs timestamp resolution.
                                assert!(
                                    (pose.position[k] - fk.p[k]).abs() <= 3e-6,
                                    "{pose:?} vs {fk:?}"
                                );
                            }
                            let q = quaternion(&fk.r);
                            let dot: f64 = (0..4).map(|k| q[k] * pose.quat[k]).sum();
                            // Components are rounded to 1e-6 on the wire.
                            assert!(dot.abs() > 1.0 - 1e-5, "{q:?} vs {:?}", pose.quat);
                            pose_checked += 1;
                        }
                    }
                    _ => {}
                }
            }
            assert!(pose_checked > 1900, "{pose_checked}");
            let rms = (sum2 / n).sqrt();
            if drift {
                // Paper drift: stationary deviation √(Δt²σ²(1−φ)/(1−φ²)) ≈ 0.0071 rad.
                let gm = GaussMarkov::paper();
                let want = gm.stationary_variance().sqrt();
                assert!((rms / want - 1.0).abs() < 0.25, "rms {rms} vs {want}");
            }
            let _ = std::fs::remove_dir_all(&dir);
        }
    }

    #[test]
    fn imu_channels_are_physically_consistent() {
        let dir = temp_dir("imu");
        let mut s = Scenario::paper();
        s.noise.accel_m_s2 = 0.0;
        s.noise.mag_ut = 0.0;
        let mut suit = Suit::new(s, &dir).unwrap();
        let (mut acc, mut na) = (0.0, 0.0);
        let field = Vector3::from(EARTH_FIELD_UT).norm();
        for f in suit.advance(5.0) {
            match decode_frame(&f).unwrap() {
                Message::ImuAccel(v) => {
                    acc += Vector3::from(v.xyz).norm();
                    na += 1.0;
                }
                Message::ImuMag(v) => {
                    assert!((Vector3::from(v.xyz).norm() - field).abs() < 0.03, "{v:?}")
                }
                _ => {}
            }
        }
        // Slow arm motion: the specific force is dominated by gravity.
        assert!((acc / na - G).abs() < 0.5, "mean |f| = {}", acc / na);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn node_clocks_roll_over_and_reboots_reset_clock_and_count_boots() {
        let dir = temp_dir("reboot");
        let mut s = Scenario::paper();
        s.faults.reboots.push(crate::scenario::Reboot {
            node: 3,
            at_s: 5.0,
            down_s: 0.5,
        });
        let mut suit = Suit::new(s, &dir).unwrap();
        let frames = suit.advance(20.0);
        let mut j7: Vec<u32> = Vec::new();
        let mut j3: Vec<u32> = Vec::new();
        let mut boots = Vec::new();
        for f in &frames {
            match decode_frame(f).unwrap() {
                Message::JointState(js) if js.node.raw() == 7 => j7.push(js.timestamp_us),
                Message::JointState(js) if js.node.raw() == 3 => j3.push(js.timestamp_us),
                Message::Heartbeat(h) if h.node.raw() == 3 => boots.push(h.boot_count),
                _ => {}
            }
        }
        let wraps = j7.windows(2).filter(|w| w[1] < w[0]).count();
        assert_eq!(wraps, 1, "node 7 rolls over once at ~17 s");
        let resets: Vec<usize> = (1..j3.len()).filter(|&i| j3[i] < j3[i - 1]).collect();
        assert_eq!(resets.len(), 1);
        assert!(
            j3[resets[0]] < 20_000,
            "clock restarts near 0: {}",
            j3[resets[0]]
        );
        assert!(
            (1949..=1952).contains(&j3.len()),
            "0.5 s silent: {}",
            j3.len()
        );
        assert_eq!(boots.first().map(|b| (b + 1) % 16), boots.last().copied());
        assert_eq!(suit.stats().reboots, 1);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn after_the_motion_nodes_send_only_heartbeats_and_take_a_table_with_readback() {
        use exocal_dbc::transfer::{RetryPolicy, Upload};
        let dir = temp_dir("rest");
        let mut s = Scenario::paper();
        s.duration_s = 3.0;
        s.faults.malformed_hz = 20.0;
        s.faults.babble.push(crate::scenario::Babble {
            node: 2,
            from_s: 1.0,
            to_s: 10.0,
            rate_hz: 100.0,
        });
        // Up to its end, the motion is that of a longer scenario, faults included (keyed alike:
        // the same stream digests).
        let keys = exocal_dbc::auth::KeySet::derived(8);
        let mut long = s.clone();
        long.duration_s = 100.0;
        let long_dir = temp_dir("rest-long");
        flash::provision(&long_dir, &keys).unwrap();
        let moving = Suit::new(long, &long_dir).unwrap().advance(3.0);
        flash::provision(&dir, &keys).unwrap();
        let mut suit = Suit::new(s, &dir).unwrap();
        assert_eq!(suit.advance(3.0), moving);
        // The last samples are on the wire 50 µs after they are taken.
        suit.advance(3.001);
        let samples = suit.stats().samples;
        // At rest: heartbeats only, from every node at its rate (1 Hz in this scenario), but for
        // the digest closing each node's last span of motion (every node is keyed), which goes
        // out with a heartbeat once a digest period has passed.
        let (digests, rest): (Vec<Frame>, Vec<Frame>) = suit
            .advance(13.001)
            .into_iter()
            .partition(|f| matches!(decode_frame(f), Ok(Message::StreamDigest(_))));
        assert_eq!(
            counts(&digests),
            NodeId::ALL
                .map(|n| (u32::from(spec::STREAM_DIGEST.id(n.raw())), 1))
                .into_iter()
                .collect(),
        );
        let c = counts(&rest);
        assert_eq!(
            c.keys().copied().collect::<Vec<_>>(),
            NodeId::ALL
                .map(|n| u32::from(spec::HEARTBEAT.id(n.raw())))
                .to_vec(),
            "{c:?}"
        );
        assert!(c.values().all(|n| (9..=11).contains(n)), "{c:?}");
        for (before, after) in samples.iter().zip(&suit.stats().samples) {
            assert_eq!(before[..3], after[..3]);
        }
        // A table pushed at rest is installed, read back, and announced by the heartbeats.
        let node = NodeId::JOINTS[2];
        let table = Table::from_si(0.0301, -1.5, 0.0299, 0.01, 1.2, 0.9).unwrap();
        let policy = RetryPolicy {
            timeout_us: 500_000,
            max_attempts: 4,
            max_restarts: 2,
        };
        let key = keys.node(node).unwrap().clone();
        let mut up = Upload::authenticated(node, 9, table, policy, key);
        let mut t = 13.001;
        while up.outcome().is_none() && t < 40.0 {
            if let Some(cmd) = up.poll((t * 1e6) as u64) {
                suit.receive(&Message::TableCmd(cmd).to_frame::<Frame>().unwrap(), t);
            }
            t += 1e-3;
            for f in suit.advance(t) {
                if let Ok(Message::TableReply(r)) = decode_frame(&f) {
                    up.on_reply(&r);
                }
            }
        }
        assert_eq!(up.outcome(), Some(Ok(table.crc())));
        assert_eq!(
            flash::read(&dir, node).unwrap().map(|i| i.table),
            Some(table)
        );
        let later = suit.advance(t + 2.0);
        let crcs: Vec<u32> = later
            .iter()
            .filter_map(|f| match decode_frame(f) {
                Ok(Message::Heartbeat(h)) if h.node == node => Some(h.table_crc),
                _ => None,
            })
            .collect();
        assert!(!crcs.is_empty() && crcs.iter().all(|&c| c == table.crc()));
        assert!(later
            .iter()
            .all(|f| matches!(decode_frame(f), Ok(Message::Heartbeat(_)))));
        for d in [dir, long_dir] {
            let _ = std::fs::remove_dir_all(d);
        }
    }

    #[test]
    fn injected_faults_show_on_the_wire() {
        let dir = temp_dir("faults");
        let mut s = Scenario::paper();
        s.faults.malformed_hz = 50.0;
        s.faults.nan = 0.01;
        s.faults.loss = 0.05;
        s.faults.duplicate = 0.01;
        s.faults.babble.push(crate::scenario::Babble {
            node: 2,
            from_s: 1.0,
            to_s: 2.0,
            rate_hz: 2000.0,
        });
        let clean = Suit::new(Scenario::paper(), &temp_dir("clean"))
            .unwrap()
            .advance(10.0)
            .len() as f64;
        let mut suit = Suit::new(s, &dir).unwrap();
        let frames = suit.advance(10.0);
        let st = suit.stats().clone();
        let bad = frames.iter().filter(|f| decode_frame(*f).is_err()).count() as u64;
        assert!(
            bad > 350 && bad <= st.malformed,
            "{bad} undecodable of {} malformed",
            st.malformed
        );
        let nans = frames
            .iter()
            .filter(|f| match decode_frame(*f) {
                Ok(Message::JointState(j)) => j.angle.is_nan(),
                Ok(Message::ImuGyro(v) | Message::ImuAccel(v) | Message::ImuMag(v)) => {
                    v.xyz[0].is_nan()
                }
                _ => false,
            })
            .count() as f64;
        assert!(
            (nans / st.nans as f64) > 0.9,
            "{nans} NaN frames of {} injected",
            st.nans
        );
        assert!(st.babbled > 1900 && st.duplicated > 0);
        let want =
            clean + st.babbled as f64 + st.malformed as f64 + st.duplicated as f64 - st.lost as f64;
        assert!(
            (frames.len() as f64 - want).abs() < 0.01 * want,
            "{} vs {want}",
            frames.len()
        );
        let lost_ratio = st.lost as f64 / (frames.len() as f64 + st.lost as f64);
        assert!((lost_ratio - 0.05).abs() < 0.01, "{lost_ratio}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_bus_stall_holds_every_frame_back_then_lets_the_backlog_out() {
        let key = |frames: &[Frame]| {
            let mut k: Vec<(u32, Vec<u8>)> = frames
                .iter()
                .map(|f| (f.raw_id(), f.data().to_vec()))
                .collect();
            k.sort();
            k
        };
        let clean = Suit::new(Scenario::paper(), &temp_dir("stall-clean"))
            .unwrap()
            .advance(6.0);
        let mut s = Scenario::paper();
        s.faults.bus_stalls.push(crate::scenario::BusStall {
            from_s: 5.0,
            to_s: 6.0,
            late_ms: 300.0,
        });
        let dir = temp_dir("stall");
        let mut suit = Suit::new(s, &dir).unwrap();
        let mut frames = suit.advance(5.0);
        // Nothing reaches the bus for 300 ms; by the end of the stall, everything has.
        assert!(suit.advance(5.299).is_empty());
        let first_late = suit.advance(5.301);
        assert!(!first_late.is_empty());
        frames.extend(first_late);
        frames.extend(suit.advance(6.0));
        assert_eq!(key(&frames), key(&clean));
        for d in [dir, temp_dir("stall-clean")] {
            let _ = std::fs::remove_dir_all(d);
        }
    }

    #[test]
    fn delays_and_reordering_change_the_order_not_the_content() {
        let dir = temp_dir("reorder");
        let mut s = Scenario::paper();
        s.faults.reorder = 0.2;
        s.faults.reorder_max_ms = 30.0;
        s.faults.delay = 0.01;
        s.faults.delay_ms = 50.0;
        let mut suit = Suit::new(s, &dir).unwrap();
        let frames = suit.advance(5.0);
        let mut last = BTreeMap::new();
        let mut out_of_order = 0;
        for f in &frames {
            if let Ok(Message::JointState(js)) = decode_frame(f) {
                if let Some(prev) = last.insert(js.node, js.timestamp_us) {
                    out_of_order += usize::from(js.timestamp_us < prev);
                }
            }
        }
        assert!(out_of_order > 100, "{out_of_order}");
        let _ = std::fs::remove_dir_all(&dir);
    }
    /// What [`exchange`] saw: the outcome, every command sent, every reply, the time reached.
    type Exchanged = (
        Option<Result<u32, exocal_dbc::transfer::UploadError>>,
        Vec<TableCmd>,
        Vec<Reply>,
        f64,
    );

    /// Drives `up` against `suit` from simulated time `t` until it has an outcome; returns the
    /// outcome, every command sent, every reply seen and the time reached.
    fn exchange(suit: &mut Suit, up: &mut exocal_dbc::transfer::Upload, mut t: f64) -> Exchanged {
        let (mut sent, mut replies) = (Vec::new(), Vec::new());
        let end = t + 60.0;
        while up.outcome().is_none() && t < end {
            if let Some(cmd) = up.poll((t * 1e6) as u64) {
                sent.push(cmd);
                suit.receive(&Message::TableCmd(cmd).to_frame::<Frame>().unwrap(), t);
            }
            t += 1e-3;
            for f in suit.advance(t) {
                if let Ok(Message::TableReply(r)) = decode_frame(&f) {
                    replies.push(r.reply);
                    up.on_reply(&r);
                }
            }
        }
        (up.outcome(), sent, replies, t)
    }

    /// Sends `cmds` to `suit` at `t`, a millisecond apart; returns the replies and the time.
    fn replay(suit: &mut Suit, cmds: &[TableCmd], mut t: f64) -> (Vec<Reply>, f64) {
        let mut replies = Vec::new();
        for c in cmds {
            suit.receive(&Message::TableCmd(*c).to_frame::<Frame>().unwrap(), t);
            t += 1e-3;
            replies.extend(
                suit.advance(t)
                    .iter()
                    .filter_map(|f| match decode_frame(f) {
                        Ok(Message::TableReply(r)) => Some(r.reply),
                        _ => None,
                    }),
            );
        }
        (replies, t)
    }

    fn at_rest(seconds: f64) -> Scenario {
        let mut s = Scenario::paper();
        s.duration_s = seconds;
        s
    }

    fn rest_policy() -> exocal_dbc::transfer::RetryPolicy {
        exocal_dbc::transfer::RetryPolicy {
            timeout_us: 100_000,
            max_attempts: 4,
            max_restarts: 2,
        }
    }

    /// A provisioned node that reboots and cannot read its key slot (or its
    /// counter record, or finds its key slot gone) boots without a key and installs nothing
    /// (NACK `NoKey`), instead of accepting unauthenticated tables.
    #[test]
    fn a_node_that_cannot_read_its_key_or_counter_at_a_reboot_installs_nothing() {
        use exocal_dbc::transfer::{Upload, UploadError};
        let node = NodeId::JOINTS[2];
        let keys = exocal_dbc::auth::KeySet::derived(34);
        let key = keys.node(node).unwrap().clone();
        let table = Table::from_si(0.0301, -1.5, 0.0299, 0.01, 1.2, 0.9).unwrap();
        type Damage = fn(&Path, NodeId);
        let damages: [(&str, Damage); 3] = [
            ("key slot unreadable", |d, n| {
                std::fs::write(flash::key_path(d, n), [1u8, 2, 3]).unwrap()
            }),
            ("counter record corrupt", |d, n| {
                let p = flash::counter_path(d, n);
                let mut b = std::fs::read(&p).unwrap();
                b[9] ^= 0x40;
                std::fs::write(p, b).unwrap()
            }),
            ("key slot gone", |d, n| {
                std::fs::remove_file(flash::key_path(d, n)).unwrap()
            }),
        ];
        for (what, damage) in damages {
            let dir = temp_dir(&format!("locked-{}", what.replace(' ', "-")));
            flash::provision(&dir, &keys).unwrap();
            let mut s = at_rest(1.0);
            s.faults.reboots.push(crate::scenario::Reboot {
                node: node.raw(),
                at_s: 2.0,
                down_s: 0.5,
            });
            let mut suit = Suit::new(s, &dir).unwrap();
            suit.advance(2.2);
            damage(&dir, node);
            suit.advance(3.0);
            assert_eq!(suit.stats().locked, 1, "{what}");
            let factory = flash::read(&dir, node).unwrap().unwrap();
            let mut up = Upload::authenticated(node, 1, table, rest_policy(), key.clone());
            let (outcome, _, replies, t) = exchange(&mut suit, &mut up, 3.0);
            assert_eq!(
                outcome,
                Some(Err(UploadError::Nacked(
                    exocal_dbc::CmdCode::Begin,
                    NackReason::NoKey
                ))),
                "{what}: {replies:?}"
            );
            // Nor does a plain transfer, with the right CRC, install anything.
            let mut plain = Upload::new(node, 2, table, rest_policy());
            let (outcome, ..) = exchange(&mut suit, &mut plain, t);
            assert!(
                matches!(
                    outcome,
                    Some(Err(UploadError::Nacked(_, NackReason::NoKey)))
                ),
                "{what}: {outcome:?}"
            );
            assert_eq!(flash::read(&dir, node).unwrap().unwrap(), factory, "{what}");
            let _ = std::fs::remove_dir_all(&dir);
        }
    }

    /// The freshness counter survives a corrupt table image. A genuine
    /// authenticated push installs a table (counter 1); the image is then corrupted and the
    /// suit powered up again (the node finds no table and is given its factory one, counter 0
    /// in the image); the recorded genuine transfer, replayed, is refused as stale: its counter
    /// comes back from the record kept apart.
    #[test]
    fn a_corrupt_table_image_keeps_the_counter_and_a_recorded_transfer_stays_stale() {
        use exocal_dbc::transfer::Upload;
        let dir = temp_dir("corrupt-image");
        let node = NodeId::JOINTS[4];
        let keys = exocal_dbc::auth::KeySet::derived(35);
        flash::provision(&dir, &keys).unwrap();
        let table = Table::from_si(0.0301, -1.5, 0.0299, 0.01, 1.2, 0.9).unwrap();
        let mut suit = Suit::new(at_rest(1.0), &dir).unwrap();
        suit.advance(1.5);
        let key = keys.node(node).unwrap().clone();
        let mut up = Upload::authenticated(node, 7, table, rest_policy(), key);
        let (outcome, sent, _, _) = exchange(&mut suit, &mut up, 1.5);
        assert_eq!(outcome, Some(Ok(table.crc())));
        assert_eq!(flash::read_counter(&dir, node).unwrap(), Some(1));
        drop(suit);
        let p = flash::path(&dir, node);
        let mut image = std::fs::read(&p).unwrap();
        image[20] ^= 0x01;
        std::fs::write(&p, image).unwrap();
        let mut suit = Suit::new(at_rest(1.0), &dir).unwrap();
        assert_eq!(suit.stats().flash_corrupt, 1);
        suit.advance(1.5);
        let factory = flash::read(&dir, node).unwrap().unwrap();
        assert_ne!(factory.table, table);
        let transfer: Vec<TableCmd> = sent
            .into_iter()
            .filter(|c| c.cmd.code() != exocal_dbc::CmdCode::Readback)
            .collect();
        let (replies, _) = replay(&mut suit, &transfer, 1.5);
        assert!(
            replies.iter().any(|r| matches!(
                r,
                Reply::Nack {
                    reason: NackReason::StaleCounter,
                    ..
                }
            )),
            "{replies:?}"
        );
        assert_eq!(flash::read(&dir, node).unwrap().unwrap(), factory);
        assert_eq!(flash::read_counter(&dir, node).unwrap(), Some(1));
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// Restarting `exocal-hil` re-provisions the nodes. Were provisioning to write an
    /// unreadable counter record back as the image's counter, a flipped bit in the record and
    /// a lost image would take a node's counter from 2 to 0 under the same key, and every
    /// recorded `CommitAuth` would install again (any earlier table). So the node stays locked:
    /// provisioning names it and leaves it alone, it boots keyless, the recorded transfer
    /// installs nothing. A new key unlocks it, and the old transfer does not verify under it.
    #[test]
    fn a_corrupt_counter_record_keeps_the_node_locked_until_a_new_key() {
        use exocal_dbc::transfer::Upload;
        let dir = temp_dir("corrupt-counter");
        let node = NodeId::JOINTS[1];
        let keys = exocal_dbc::auth::KeySet::derived(48);
        flash::provision(&dir, &keys).unwrap();
        let old = Table::from_si(0.0301, -1.5, 0.0299, 0.01, 1.2, 0.9).unwrap();
        let new = Table::from_si(0.0302, -1.5, 0.0298, 0.02, 1.2, 0.9).unwrap();
        let mut suit = Suit::new(at_rest(1.0), &dir).unwrap();
        suit.advance(1.5);
        let key = keys.node(node).unwrap().clone();
        let mut up = Upload::authenticated(node, 7, old, rest_policy(), key.clone());
        let (outcome, sent, _, t) = exchange(&mut suit, &mut up, 1.5);
        assert_eq!(outcome, Some(Ok(old.crc())));
        let mut up = Upload::authenticated(node, 8, new, rest_policy(), key);
        let (outcome, ..) = exchange(&mut suit, &mut up, t);
        assert_eq!(outcome, Some(Ok(new.crc())));
        assert_eq!(flash::read_counter(&dir, node).unwrap(), Some(2));
        drop(suit);
        // One bit of the counter record flips, the table image is lost; exocal-hil restarts
        // (it provisions from its key file at every start).
        let p = flash::counter_path(&dir, node);
        let mut record = std::fs::read(&p).unwrap();
        record[8] ^= 0x02;
        std::fs::write(&p, record).unwrap();
        std::fs::remove_file(flash::path(&dir, node)).unwrap();
        let done = flash::provision(&dir, &keys).unwrap();
        assert_eq!(done.keyed.len(), NodeId::ALL.len() - 1);
        assert_eq!(done.locked.len(), 1);
        assert_eq!(done.locked[0].0, node);
        assert!(
            done.locked[0].1.contains("CRC mismatch"),
            "{:?}",
            done.locked
        );
        let mut suit = Suit::new(at_rest(1.0), &dir).unwrap();
        suit.advance(1.5);
        assert_eq!(suit.stats().locked, 1);
        let factory = flash::read(&dir, node).unwrap().unwrap();
        assert_ne!(factory.table, old);
        let transfer: Vec<TableCmd> = sent
            .into_iter()
            .filter(|c| c.cmd.code() != exocal_dbc::CmdCode::Readback)
            .collect();
        let (replies, _) = replay(&mut suit, &transfer, 1.5);
        assert!(
            replies.iter().any(|r| matches!(
                r,
                Reply::Nack {
                    reason: NackReason::NoKey,
                    ..
                }
            )),
            "{replies:?}"
        );
        assert_eq!(flash::read(&dir, node).unwrap().unwrap(), factory);
        drop(suit);
        // Provisioned with the same keys again: still locked. With a new key: keyed, and the
        // recorded transfer (the old key's MAC) still installs nothing.
        assert_eq!(flash::provision(&dir, &keys).unwrap().locked.len(), 1);
        let rekeyed = exocal_dbc::auth::KeySet::derived(49);
        let done = flash::provision(&dir, &rekeyed).unwrap();
        assert!(
            done.locked.is_empty() && done.keyed.contains(&node),
            "{done:?}"
        );
        let mut suit = Suit::new(at_rest(1.0), &dir).unwrap();
        suit.advance(1.5);
        assert_eq!(suit.stats().locked, 0);
        let (replies, _) = replay(&mut suit, &transfer, 1.5);
        assert!(
            !replies.iter().any(|r| matches!(
                r,
                Reply::Ack {
                    cmd: exocal_dbc::CmdCode::Commit,
                    ..
                }
            )),
            "{replies:?}"
        );
        let held = flash::read(&dir, node).unwrap().unwrap();
        assert_eq!((held.table, held.counter), (factory.table, factory.counter));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
