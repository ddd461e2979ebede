//! Scenarios: what the emulated suit is and does, as TOML.
//!
//! Contract: every key is optional except `name`, `seed` and `duration_s`; unknown keys are
//! errors (serde `deny_unknown_fields`), and [`Scenario::validate`] refuses values that make no
//! physical sense, naming the key. Units are in the key names. `scenarios/paper.toml` is the
//! paper's Section 4 (Table 4 arm, Table 3 ranges, Δt = 0.01 s, τ = 1 s, σ = 1).

use calib_core::{DhRow, DhTable, Discretisation, GaussMarkov, JointRanges};
use serde::{Deserialize, Serialize};
use std::path::Path;

use crate::wearer::Wearer;

const DEG: f64 = std::f64::consts::PI / 180.0;

/// A complete scenario.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scenario {
    /// Free text.
    pub name: String,
    /// Seed of everything random (motion, drift, noise, clocks, faults).
    pub seed: u64,
    /// Simulated duration, s.
    pub duration_s: f64,
    /// The true arm and its motion.
    #[serde(default)]
    pub arm: Arm,
    /// Message rates.
    #[serde(default)]
    pub rates: Rates,
    /// Joint-angle drift (Gauss-Markov).
    #[serde(default)]
    pub drift: Drift,
    /// Sensor noise.
    #[serde(default)]
    pub noise: Noise,
    /// Node clocks.
    #[serde(default)]
    pub clocks: Clocks,
    /// Faults to inject.
    #[serde(default)]
    pub faults: Faults,
    /// What the nodes' flash holds when no flash file exists yet.
    #[serde(default)]
    pub factory: Factory,
    /// How the wearer moves and follows guidance (default: the whole range, no one listening).
    #[serde(default)]
    pub wearer: Wearer,
}

/// D-H table presets.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Preset {
    /// The paper's Table 1.
    PaperNominal,
    /// The paper's Table 4.
    PaperActual,
}

impl Preset {
    /// The table.
    pub fn table(self) -> DhTable<7> {
        match self {
            Preset::PaperNominal => DhTable::paper_nominal(),
            Preset::PaperActual => DhTable::paper_actual(),
        }
    }
}

/// One D-H row in scenario units.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Row {
    /// a, m.
    pub a_m: f64,
    /// α, degrees.
    pub alpha_deg: f64,
    /// d, m.
    pub d_m: f64,
    /// θ offset, degrees.
    pub theta_offset_deg: f64,
}

/// The true arm.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Arm {
    /// Joints of the arm, 1..=7 (default 7): nodes 1..=`joints` are on it and the end
    /// effector at its end; the joint nodes past it are not on the bus.
    #[serde(default = "Arm::longest")]
    pub joints: usize,
    /// Preset table (its first `joints` rows), used unless `rows` is given.
    pub preset: Preset,
    /// Explicit rows, one per joint (override `preset`).
    pub rows: Option<Vec<Row>>,
    /// Joint ranges `[min, max]` in degrees, one per joint (default: Table 3's first).
    pub ranges_deg: Option<Vec<[f64; 2]>>,
}

impl Default for Arm {
    fn default() -> Self {
        Arm {
            joints: Arm::longest(),
            preset: Preset::PaperActual,
            rows: None,
            ranges_deg: None,
        }
    }
}

impl Arm {
    fn longest() -> usize {
        7
    }

    /// The true D-H table, padded with zero rows past `joints` (the identity link at a zero
    /// reading: the end effector is at joint `joints`'s frame).
    pub fn table(&self) -> DhTable<7> {
        let row = |i: usize| match &self.rows {
            Some(rows) => DhRow {
                a: rows[i].a_m,
                alpha: rows[i].alpha_deg * DEG,
                d: rows[i].d_m,
                theta_offset: rows[i].theta_offset_deg * DEG,
            },
            None => self.preset.table().rows[i],
        };
        let zero = DhRow {
            a: 0.0,
            alpha: 0.0,
            d: 0.0,
            theta_offset: 0.0,
        };
        DhTable {
            rows: std::array::from_fn(|i| if i < self.joints { row(i) } else { zero }),
        }
    }

    /// Joint ranges, rad; `(0, 0)` past `joints` (those joints read 0).
    pub fn ranges(&self) -> JointRanges<7> {
        let range = |i: usize| match &self.ranges_deg {
            Some(r) => (r[i][0] * DEG, r[i][1] * DEG),
            None => JointRanges::<7>::paper().limits[i],
        };
        JointRanges {
            limits: std::array::from_fn(|i| {
                if i < self.joints {
                    range(i)
                } else {
                    (0.0, 0.0)
                }
            }),
        }
    }

    /// Whether the node of joint index `j` (0-based) is on the arm.
    pub fn has_joint(&self, j: usize) -> bool {
        j < self.joints
    }
}

/// Message rates, Hz (node-local clock).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Rates {
    /// `JointState` per joint node.
    pub joint_state_hz: f64,
    /// Each of `ImuGyro`, `ImuAccel`, `ImuMag` per node.
    pub imu_hz: f64,
    /// End-effector poses (four frames each).
    pub pose_hz: f64,
    /// `Heartbeat` per node.
    pub heartbeat_hz: f64,
}

impl Default for Rates {
    fn default() -> Self {
        Rates {
            joint_state_hz: 100.0,
            imu_hz: 100.0,
            pose_hz: 100.0,
            heartbeat_hz: 1.0,
        }
    }
}

/// Drift parameters of one joint.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JointDrift {
    /// Correlation time τ, s.
    pub tau_s: f64,
    /// σ of the paper's eq. (8) (or the stationary deviation in rad with `exact`).
    pub sigma: f64,
}

/// Discretisation of the drift process.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DriftFormula {
    /// The paper's eq. (8).
    Paper,
    /// Exact Gauss-Markov discretisation.
    Exact,
}

/// Joint-angle drift: the node reports `true angle − drift + noise`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Drift {
    /// Off switch.
    pub enabled: bool,
    /// τ for every joint, s.
    pub tau_s: f64,
    /// σ for every joint.
    pub sigma: f64,
    /// Formula.
    pub formula: DriftFormula,
    /// Seven per-joint overrides.
    pub per_joint: Option<Vec<JointDrift>>,
    /// A heading drift, °/s: the nodes on [`Drift::heading_joints`] integrate their gyro with
    /// nothing to correct its heading, so their angle gains this rate bias (its sign drawn per
    /// joint from the seed) from power-up without bound, and their rate and gyro read it.
    pub heading_deg_s: f64,
    /// The joints (numbered from 1) with the heading drift.
    pub heading_joints: Vec<u8>,
}

impl Default for Drift {
    fn default() -> Self {
        Drift {
            enabled: true,
            tau_s: 1.0,
            sigma: 1.0,
            formula: DriftFormula::Paper,
            per_joint: None,
            heading_deg_s: 0.0,
            heading_joints: Vec::new(),
        }
    }
}

impl Drift {
    /// (τ, σ) of joint `j`.
    pub fn joint(&self, j: usize) -> JointDrift {
        self.per_joint.as_ref().map_or(
            JointDrift {
                tau_s: self.tau_s,
                sigma: self.sigma,
            },
            |p| p[j],
        )
    }

    /// The process for joint `j` at sample period `dt`.
    pub fn process(&self, j: usize, dt: f64) -> GaussMarkov {
        let d = self.joint(j);
        GaussMarkov {
            dt,
            tau: d.tau_s,
            sigma: d.sigma,
            discretisation: match self.formula {
                DriftFormula::Paper => Discretisation::Paper,
                DriftFormula::Exact => Discretisation::Exact,
            },
        }
    }
}

/// White noise standard deviations and the gyro bias process.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Noise {
    /// Joint angle, rad.
    pub angle_rad: f64,
    /// Joint rate, rad/s.
    pub rate_rad_s: f64,
    /// Gyro, rad/s.
    pub gyro_rad_s: f64,
    /// Gyro bias stationary deviation, rad/s.
    pub gyro_bias_rad_s: f64,
    /// Gyro bias correlation time, s.
    pub gyro_bias_tau_s: f64,
    /// Accelerometer, m/s².
    pub accel_m_s2: f64,
    /// Magnetometer, µT.
    pub mag_ut: f64,
    /// End-effector position, m.
    pub pose_position_m: f64,
    /// End-effector rotation per axis, rad.
    pub pose_rotation_rad: f64,
}

impl Default for Noise {
    fn default() -> Self {
        Noise {
            angle_rad: 1e-4,
            rate_rad_s: 1e-3,
            gyro_rad_s: 2e-3,
            gyro_bias_rad_s: 5e-3,
            gyro_bias_tau_s: 100.0,
            accel_m_s2: 0.02,
            mag_ut: 0.3,
            pose_position_m: 1e-4,
            pose_rotation_rad: 2e-4,
        }
    }
}

/// One node's clock, explicitly.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NodeClockSpec {
    /// Node id 1..=8.
    pub node: u8,
    /// Clock reading at simulated time 0, µs (u32 range; rolls over at 2^32).
    pub offset_us: Option<f64>,
    /// Rate error, ppm.
    pub skew_ppm: Option<f64>,
    /// Timestamp jitter (std dev), µs.
    pub jitter_us: Option<f64>,
}

/// Node clocks. Unlisted nodes draw offset uniform in `[0, 2^32)` µs and skew uniform in
/// `±skew_ppm_max`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Clocks {
    /// Bound of the random skew, ppm.
    pub skew_ppm_max: f64,
    /// Default timestamp jitter, µs.
    pub jitter_us: f64,
    /// Explicit clocks.
    pub node: Vec<NodeClockSpec>,
}

impl Default for Clocks {
    fn default() -> Self {
        Clocks {
            skew_ppm_max: 50.0,
            jitter_us: 20.0,
            node: Vec::new(),
        }
    }
}

/// A clock jump.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ClockJump {
    /// Node id.
    pub node: u8,
    /// When, simulated s.
    pub at_s: f64,
    /// By how much, µs (may be negative).
    pub jump_us: f64,
}

/// A node reboot: silent for `down_s`, then clock from ~0, counters reset, table from flash.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Reboot {
    /// Node id.
    pub node: u8,
    /// When, simulated s.
    pub at_s: f64,
    /// Silent time, s.
    #[serde(default = "default_down_s")]
    pub down_s: f64,
}

fn default_down_s() -> f64 {
    0.2
}

/// A babbling node: repeats its last frame at `rate_hz` during `[from_s, to_s)`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Babble {
    /// Node id.
    pub node: u8,
    /// Start, simulated s.
    pub from_s: f64,
    /// End, simulated s.
    pub to_s: f64,
    /// Frames per second.
    pub rate_hz: f64,
}

/// The bus (or the receiver, or the sender) stalls: every frame put on the wire during
/// `[from_s, to_s)`, by any node, arrives `late_ms` later, but no later than `to_s`, when the
/// backlog goes out at once. The nodes' clocks run on: their timestamps are those of the
/// samples.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BusStall {
    /// Start, simulated s.
    pub from_s: f64,
    /// End, simulated s.
    pub to_s: f64,
    /// How late the frames arrive, ms.
    pub late_ms: f64,
}

/// How a node treats table transfers.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TransferBehaviour {
    /// Runs the real state machine.
    #[default]
    Normal,
    /// Refuses every command (NACK, reason FlashError).
    Nack,
    /// Never answers.
    Silent,
}

/// A node's transfer behaviour.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransferFault {
    /// Node id.
    pub node: u8,
    /// Behaviour.
    pub behaviour: TransferBehaviour,
}

/// Seeded faults. Probabilities are per frame.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Faults {
    /// Uniform loss probability (both directions).
    pub loss: f64,
    /// Probability per frame that a loss burst starts.
    pub burst_start: f64,
    /// Frames lost per burst.
    pub burst_len: u32,
    /// Duplication probability.
    pub duplicate: f64,
    /// Probability that one bit of a frame's payload is flipped on the wire.
    pub corrupt: f64,
    /// Probability that a frame is held back up to `reorder_max_ms`, landing after later ones.
    pub reorder: f64,
    /// Bound of the reorder hold-back, ms.
    pub reorder_max_ms: f64,
    /// Probability that a frame is delayed by `delay_ms`.
    pub delay: f64,
    /// Delay, ms.
    pub delay_ms: f64,
    /// Probability that a sampled value is NaN (sent as the DBC's invalid marker).
    pub nan: f64,
    /// Malformed frames per second (bad DLC, unknown ids, extended ids).
    pub malformed_hz: f64,
    /// Clock jumps.
    pub clock_jumps: Vec<ClockJump>,
    /// Reboots.
    pub reboots: Vec<Reboot>,
    /// Babbling nodes.
    pub babble: Vec<Babble>,
    /// Stalls of the whole bus.
    pub bus_stalls: Vec<BusStall>,
    /// Transfer behaviours.
    pub transfer: Vec<TransferFault>,
}

impl Faults {
    /// The wire's part (loss, bursts, corruption, delay, reordering, duplication), as the bus's
    /// fault injector takes it; the suit draws every frame's fate from it.
    pub fn wire(&self) -> exocal_bus::FaultConfig {
        let ms = |v: f64| std::time::Duration::from_secs_f64(v.max(0.0) * 1e-3);
        exocal_bus::FaultConfig {
            drop: self.loss,
            burst_start: self.burst_start,
            burst_len: self.burst_len,
            corrupt: self.corrupt,
            delay: self.delay,
            delay_by: ms(self.delay_ms),
            reorder: self.reorder,
            reorder_max: ms(self.reorder_max_ms),
            duplicate: self.duplicate,
            fail_sends_after: None,
        }
    }

    /// Behaviour of `node`.
    pub fn transfer_behaviour(&self, node: u8) -> TransferBehaviour {
        self.transfer
            .iter()
            .find(|t| t.node == node)
            .map_or(TransferBehaviour::Normal, |t| t.behaviour)
    }
}

/// Factory flash content.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Factory {
    /// Table the nodes are flashed with (default: the nominal Table 1).
    pub preset: Preset,
    /// Drift τ written with it, s.
    pub tau_s: f64,
    /// Drift σ written with it.
    pub sigma: f64,
}

impl Default for Factory {
    fn default() -> Self {
        Factory {
            preset: Preset::PaperNominal,
            tau_s: 1.0,
            sigma: 1.0,
        }
    }
}

/// Why a scenario was refused.
#[derive(Debug)]
pub enum ScenarioError {
    /// The file could not be read.
    Io(std::path::PathBuf, std::io::Error),
    /// TOML syntax, unknown key or wrong type (the message names key and line).
    Toml(toml::de::Error),
    /// A value out of its domain.
    Invalid {
        /// Dotted key.
        key: String,
        /// What is wrong.
        why: String,
    },
}

impl std::fmt::Display for ScenarioError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ScenarioError::Io(p, e) => write!(f, "cannot read scenario {}: {e}", p.display()),
            ScenarioError::Toml(e) => write!(f, "bad scenario: {e}"),
            ScenarioError::Invalid { key, why } => write!(f, "bad scenario: `{key}` {why}"),
        }
    }
}

impl std::error::Error for ScenarioError {}

fn invalid(key: impl Into<String>, why: impl Into<String>) -> ScenarioError {
    ScenarioError::Invalid {
        key: key.into(),
        why: why.into(),
    }
}

/// The paper scenario shipped with the crate.
pub const PAPER_TOML: &str = include_str!("../scenarios/paper.toml");

impl Scenario {
    /// The paper's Section 4 (`scenarios/paper.toml`).
    pub fn paper() -> Scenario {
        Scenario::from_toml(PAPER_TOML).expect("the shipped paper scenario is valid")
    }

    /// Parses and validates TOML text.
    pub fn from_toml(text: &str) -> Result<Scenario, ScenarioError> {
        let s: Scenario = toml::from_str(text).map_err(ScenarioError::Toml)?;
        s.validate()?;
        Ok(s)
    }

    /// Reads, parses and validates a file.
    pub fn load(path: &Path) -> Result<Scenario, ScenarioError> {
        let text =
            std::fs::read_to_string(path).map_err(|e| ScenarioError::Io(path.to_path_buf(), e))?;
        Scenario::from_toml(&text)
    }

    /// Checks every value, naming the first bad key.
    pub fn validate(&self) -> Result<(), ScenarioError> {
        let pos = |key: &str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(invalid(key, format!("must be a positive number, got {v}")))
            }
        };
        let nonneg = |key: &str, v: f64| {
            if v.is_finite() && v >= 0.0 {
                Ok(())
            } else {
                Err(invalid(key, format!("must be finite and ≥ 0, got {v}")))
            }
        };
        let prob = |key: &str, v: f64| {
            if (0.0..=1.0).contains(&v) {
                Ok(())
            } else {
                Err(invalid(
                    key,
                    format!("must be a probability in [0, 1], got {v}"),
                ))
            }
        };
        let node = |key: &str, n: u8| {
            if (1..=8).contains(&n) {
                Ok(())
            } else {
                Err(invalid(key, format!("must be a node id 1..=8, got {n}")))
            }
        };
        pos("duration_s", self.duration_s)?;
        let w = &self.wearer;
        for (j, &r) in w.reach.iter().enumerate() {
            if !(r > 0.0 && r <= 1.0) {
                return Err(invalid(
                    format!("wearer.reach[{j}]"),
                    format!("must be in (0, 1], got {r}"),
                ));
            }
        }
        prob("wearer.compliance", w.compliance)?;
        nonneg("wearer.reaction_s", w.reaction_s)?;
        if !(w.follow_s.is_finite() && w.follow_s >= 2.0 * crate::wearer::RAMP_S) {
            return Err(invalid(
                "wearer.follow_s",
                format!(
                    "must be finite and at least {} s, got {}",
                    2.0 * crate::wearer::RAMP_S,
                    w.follow_s
                ),
            ));
        }
        for (k, v) in [
            ("rates.joint_state_hz", self.rates.joint_state_hz),
            ("rates.imu_hz", self.rates.imu_hz),
            ("rates.pose_hz", self.rates.pose_hz),
            ("rates.heartbeat_hz", self.rates.heartbeat_hz),
        ] {
            pos(k, v)?;
            if v > 1000.0 {
                return Err(invalid(k, format!("must be at most 1000 Hz, got {v}")));
            }
        }
        let joints = self.arm.joints;
        if !(1..=7).contains(&joints) {
            return Err(invalid(
                "arm.joints",
                format!("an arm has 1 to 7 joints, got {joints}"),
            ));
        }
        if let Some(rows) = &self.arm.rows {
            if rows.len() != joints {
                return Err(invalid(
                    "arm.rows",
                    format!("needs {joints} rows (arm.joints), got {}", rows.len()),
                ));
            }
            for (i, r) in rows.iter().enumerate() {
                for (k, v) in [
                    ("a_m", r.a_m),
                    ("alpha_deg", r.alpha_deg),
                    ("d_m", r.d_m),
                    ("theta_offset_deg", r.theta_offset_deg),
                ] {
                    if !v.is_finite() {
                        return Err(invalid(format!("arm.rows[{i}].{k}"), "must be finite"));
                    }
                }
            }
        }
        if let Some(r) = &self.arm.ranges_deg {
            if r.len() != joints {
                return Err(invalid(
                    "arm.ranges_deg",
                    format!("needs {joints} ranges (arm.joints), got {}", r.len()),
                ));
            }
            for (i, [lo, hi]) in r.iter().enumerate() {
                if !(lo.is_finite()
                    && hi.is_finite()
                    && lo < hi
                    && lo.abs() <= 300.0
                    && hi.abs() <= 300.0)
                {
                    return Err(invalid(
                        format!("arm.ranges_deg[{i}]"),
                        "must be [min, max] with min < max within ±300°",
                    ));
                }
            }
        }
        if let Some(p) = &self.drift.per_joint {
            if p.len() != 7 {
                return Err(invalid(
                    "drift.per_joint",
                    format!("needs 7 entries, got {}", p.len()),
                ));
            }
        }
        if !(self.drift.heading_deg_s.is_finite() && self.drift.heading_deg_s.abs() <= 1.0) {
            return Err(invalid(
                "drift.heading_deg_s",
                format!("must be within ±1 °/s, got {}", self.drift.heading_deg_s),
            ));
        }
        if let Some(j) = self
            .drift
            .heading_joints
            .iter()
            .find(|&&j| !(1..=7).contains(&j))
        {
            return Err(invalid(
                "drift.heading_joints",
                format!("joint {j}: joints are numbered 1 to 7"),
            ));
        }
        for j in 0..7 {
            let d = self.drift.joint(j);
            pos("drift.tau_s", d.tau_s)?;
            nonneg("drift.sigma", d.sigma)?;
        }
        let n = &self.noise;
        for (k, v) in [
            ("noise.angle_rad", n.angle_rad),
            ("noise.rate_rad_s", n.rate_rad_s),
            ("noise.gyro_rad_s", n.gyro_rad_s),
            ("noise.gyro_bias_rad_s", n.gyro_bias_rad_s),
            ("noise.accel_m_s2", n.accel_m_s2),
            ("noise.mag_ut", n.mag_ut),
            ("noise.pose_position_m", n.pose_position_m),
            ("noise.pose_rotation_rad", n.pose_rotation_rad),
        ] {
            nonneg(k, v)?;
        }
        pos("noise.gyro_bias_tau_s", n.gyro_bias_tau_s)?;
        nonneg("clocks.skew_ppm_max", self.clocks.skew_ppm_max)?;
        nonneg("clocks.jitter_us", self.clocks.jitter_us)?;
        for c in &self.clocks.node {
            node("clocks.node.node", c.node)?;
            if let Some(o) = c.offset_us {
                if !(0.0..4294967296.0).contains(&o) {
                    return Err(invalid("clocks.node.offset_us", "must be in [0, 2^32) µs"));
                }
            }
            if c.skew_ppm
                .is_some_and(|s| !s.is_finite() || s.abs() > 10_000.0)
            {
                return Err(invalid("clocks.node.skew_ppm", "must be within ±10000 ppm"));
            }
            if let Some(j) = c.jitter_us {
                nonneg("clocks.node.jitter_us", j)?;
            }
        }
        let f = &self.faults;
        for (k, v) in [
            ("faults.loss", f.loss),
            ("faults.burst_start", f.burst_start),
            ("faults.duplicate", f.duplicate),
            ("faults.corrupt", f.corrupt),
            ("faults.reorder", f.reorder),
            ("faults.delay", f.delay),
            ("faults.nan", f.nan),
        ] {
            prob(k, v)?;
        }
        nonneg("faults.reorder_max_ms", f.reorder_max_ms)?;
        nonneg("faults.delay_ms", f.delay_ms)?;
        nonneg("faults.malformed_hz", f.malformed_hz)?;
        for j in &f.clock_jumps {
            node("faults.clock_jumps.node", j.node)?;
            nonneg("faults.clock_jumps.at_s", j.at_s)?;
            if !j.jump_us.is_finite() {
                return Err(invalid("faults.clock_jumps.jump_us", "must be finite"));
            }
        }
        for r in &f.reboots {
            node("faults.reboots.node", r.node)?;
            nonneg("faults.reboots.at_s", r.at_s)?;
            nonneg("faults.reboots.down_s", r.down_s)?;
        }
        for b in &f.bus_stalls {
            nonneg("faults.bus_stalls.from_s", b.from_s)?;
            nonneg("faults.bus_stalls.late_ms", b.late_ms)?;
            if b.to_s.partial_cmp(&b.from_s) != Some(std::cmp::Ordering::Greater)
                || !b.to_s.is_finite()
            {
                return Err(invalid(
                    "faults.bus_stalls.to_s",
                    "must be finite and after from_s",
                ));
            }
        }
        for b in &f.babble {
            node("faults.babble.node", b.node)?;
            nonneg("faults.babble.from_s", b.from_s)?;
            pos("faults.babble.rate_hz", b.rate_hz)?;
            if b.to_s.partial_cmp(&b.from_s) != Some(std::cmp::Ordering::Greater) {
                return Err(invalid("faults.babble.to_s", "must be after from_s"));
            }
        }
        for t in &f.transfer {
            node("faults.transfer.node", t.node)?;
        }
        pos("factory.tau_s", self.factory.tau_s)?;
        nonneg("factory.sigma", self.factory.sigma)?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_wearer_is_read_and_checked() {
        let base = PAPER_TOML;
        let s = Scenario::from_toml(&format!(
            "{base}\n[wearer]\nreach = [1, 1, 1, 1, 1, 1, 0.3]\ncompliance = 0.7\n"
        ))
        .unwrap();
        assert_eq!(s.wearer.reach[6], 0.3);
        assert_eq!((s.wearer.compliance, s.wearer.follow_s), (0.7, 10.0));
        assert_eq!(Scenario::paper().wearer, Wearer::default());
        for (bad, key) in [
            ("reach = [1, 1, 1, 1, 1, 1, 0]", "wearer.reach[6]"),
            ("compliance = 1.5", "wearer.compliance"),
            ("follow_s = 1", "wearer.follow_s"),
        ] {
            match Scenario::from_toml(&format!("{base}\n[wearer]\n{bad}\n")) {
                Err(ScenarioError::Invalid { key: k, .. }) => assert_eq!(k, key),
                other => panic!("{bad}: {other:?}"),
            }
        }
    }

    #[test]
    fn paper_scenario_loads_and_is_section_4() {
        let s = Scenario::paper();
        assert_eq!(s.arm.table(), DhTable::paper_actual());
        assert_eq!(s.arm.ranges(), JointRanges::paper());
        assert_eq!(s.drift.process(0, 0.01), GaussMarkov::paper());
        assert_eq!(s.rates.joint_state_hz, 100.0);
    }

    #[test]
    fn unknown_keys_are_errors_naming_key_and_line() {
        let text = "name = \"x\"\nseed = 1\nduration_s = 1\n[rates]\njoint_hz = 5\n";
        let e = Scenario::from_toml(text).unwrap_err().to_string();
        assert!(e.contains("joint_hz") && e.contains("line 5"), "{e}");
    }

    #[test]
    fn bad_values_name_the_key() {
        let base = "name = \"x\"\nseed = 1\nduration_s = 1\n";
        for (extra, key) in [
            ("[rates]\nimu_hz = 2000\n", "rates.imu_hz"),
            ("[faults]\nloss = 1.5\n", "faults.loss"),
            (
                "[[faults.reboots]]\nnode = 9\nat_s = 1\n",
                "faults.reboots.node",
            ),
            (
                "[arm]\npreset = \"paper_actual\"\nranges_deg = [[0, 1]]\n",
                "arm.ranges_deg",
            ),
            (
                "[[faults.bus_stalls]]\nfrom_s = 2\nto_s = 1\nlate_ms = 10\n",
                "faults.bus_stalls.to_s",
            ),
            (
                "[[faults.bus_stalls]]\nfrom_s = 1\nto_s = 2\nlate_ms = -1\n",
                "faults.bus_stalls.late_ms",
            ),
        ] {
            let e = Scenario::from_toml(&format!("{base}{extra}"))
                .unwrap_err()
                .to_string();
            assert!(e.contains(key), "{extra}: {e}");
        }
        let e = Scenario::from_toml("name = \"x\"\nseed = 1\nduration_s = -1\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("duration_s"), "{e}");
    }

    #[test]
    fn explicit_rows_override_the_preset() {
        let mut rows = String::new();
        for i in 0..7 {
            rows.push_str(&format!(
                "{{ a_m = 0.1, alpha_deg = 90, d_m = 0.0{i}, theta_offset_deg = 0 }},"
            ));
        }
        let s = Scenario::from_toml(&format!(
            "name = \"x\"\nseed = 1\nduration_s = 1\n[arm]\npreset = \"paper_nominal\"\nrows = [{rows}]\n"
        ))
        .unwrap();
        let t = s.arm.table();
        assert_eq!(t.rows[3].d, 0.03);
        assert!((t.rows[0].alpha - std::f64::consts::FRAC_PI_2).abs() < 1e-15);
    }
}
