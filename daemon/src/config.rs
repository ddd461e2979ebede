//! The daemon's configuration: a TOML file, parsed strictly.
//!
//! Contract:
//! - every key is required and unknown keys are rejected (a typo on an unattended device must not
//!   be silently ignored);
//! - every error — syntax, unknown key, wrong type, out-of-range or inconsistent value — is a
//!   [`ConfigError`] that names the dotted key (`session.min_duration_s`, `bounds.a[2]`) and,
//!   when the key is in the file, its 1-based line;
//! - the file speaks degrees and seconds, the parsed [`Config`] speaks radians and seconds: the
//!   conversion happens once, here.
//!
//! The shipped default is `daemon/exocald.toml` ([`DEFAULT_TOML`]): the paper's Table 1 nominal
//! table, Table 2 (and our own) bounds and Table 3 joint ranges.

use std::fmt;
use std::path::{Path, PathBuf};

use calib_core::{DhRow, DhTable, JointRanges, RateBias};
use serde::Deserialize;
use toml::de::{DeTable, DeValue};
use toml_edit::{Array, DocumentMut, Item, Value};

pub use exocal_session::{Bounds, SensorSpec, Settings, ValidationRules, WindowRules, MAX_JOINTS};

/// The configuration shipped with the daemon (`daemon/exocald.toml`).
pub const DEFAULT_TOML: &str = include_str!("../exocald.toml");

/// Upper bounds of the numeric keys: beyond them a value is a typo or an attack, never a suit's
/// setting, and some would exhaust memory or overflow arithmetic downstream (`grid_hz = 1e12`
/// would ask an offline run for 480 TB). `check-config` rejects them, naming the key and its line.
pub mod limits {
    /// Longest collection window, s: what fits the unit's `MemoryMax=256M` with half of it to
    /// spare. A session's peak RSS grows linearly with its length (frames, streams and grid
    /// kept until the calibration): about 15 MiB + 0.30 MiB per second of session at
    /// `grid_hz = 100`, so 360 s is ~125 MiB (figures: docs/reliability.md, "Memory budget").
    /// A suit collects a minute or two.
    pub const MAX_DURATION_S: f64 = 360.0;
    /// The unit's memory limit (`systemd/exocald.service`), named in the refusals above.
    pub const MEMORY_MAX: &str = "MemoryMax=256M";
    /// Most points of the alignment grid (`grid_hz × max_duration_s`): the grid at 100 Hz over
    /// [`MAX_DURATION_S`], the figure the memory budget was measured at; a faster grid
    /// shortens the longest window accordingly.
    pub const MAX_GRID_POINTS: f64 = 100.0 * MAX_DURATION_S;
    /// Most grid points with `session.stop_at_expected_error`: half of [`MAX_GRID_POINTS`], as
    /// each estimate works on a copy of the collection (`exocald demo --speed 1000000` over a
    /// 180 s window: 110 MiB peak with the estimates, 67 MiB without).
    pub const MAX_GRID_POINTS_ESTIMATING: f64 = MAX_GRID_POINTS / 2.0;
    /// Fastest resampling grid, Hz: a 1 Mbit/s bus carries at most about 1 kHz per node.
    pub const MAX_GRID_HZ: f64 = 1_000.0;
    /// Longest tolerated hole in a stream, s.
    pub const MAX_GAP_S: f64 = 10.0;
    /// Largest |a|, |d| and bound on them, m: an arm, not a crane.
    pub const MAX_LENGTH_M: f64 = 10.0;
    /// Largest |angle| anywhere in the file, degrees.
    pub const MAX_ANGLE_DEG: f64 = 360.0;
    /// Largest deviation bound of alpha or the joint offset from nominal, degrees.
    pub const MAX_DEVIATION_DEG: f64 = 180.0;
    /// Largest acceptable condition number.
    pub const MAX_CONDITION_NUMBER: f64 = 1.0e12;
    /// Most push attempts after the first.
    pub const MAX_RETRIES: u32 = 100;
    /// Longest wait for a node's answer, ms (also keeps `timeout_ms * 1000` far from overflow).
    pub const MAX_TIMEOUT_MS: u64 = 60_000;
    /// Longest backoff between push attempts, ms.
    pub const MAX_BACKOFF_MS: u64 = 600_000;
    /// Largest expected-accuracy limit on position, mm (a table a metre off is no table).
    pub const MAX_EXPECTED_POSITION_ERROR_MM: f64 = 1_000.0;
    /// Largest expected-accuracy limit on rotation, mrad.
    pub const MAX_EXPECTED_ROTATION_ERROR_MRAD: f64 = 1_000.0;
    /// Largest rate bias (and rate-bias walk) of a sensor spec, °/s: a gyro after fusion that
    /// drifts by a degree a second is no sensor to calibrate with.
    pub const MAX_RATE_BIAS_DEG_S: f64 = 1.0;
    /// Longest cooldown between triggered sessions, s: a day.
    pub const MAX_COOLDOWN_S: f64 = 86_400.0;
}

/// Where and how the MCAP log is written.
#[derive(Debug, Clone, PartialEq)]
pub struct OutputConfig {
    /// Where the per-session MCAP logs go.
    pub directory: PathBuf,
    /// Longest time (s, ≤ 1) between two chunk flushes.
    pub flush_interval_s: f64,
}

/// The live view (`[live]`, optional: absent means disabled).
#[derive(Debug, Clone, PartialEq)]
pub struct LiveConfig {
    /// Serve the session over the Foxglove WebSocket protocol.
    pub enabled: bool,
    /// Address and port to listen on (loopback unless `allow_remote`).
    pub listen: std::net::SocketAddr,
    /// Whether `listen` may be an address other hosts reach (the view is unauthenticated).
    pub allow_remote: bool,
    /// Most messages per second of log time on each streaming channel.
    pub max_hz: f64,
    /// Most clients connected at once; more are refused (HTTP 503).
    pub max_clients: usize,
}

/// [`LiveConfig::max_hz`] by default: plenty to watch an arm move.
pub const LIVE_MAX_HZ: f64 = 30.0;
/// [`LiveConfig::max_clients`] by default: a person or two, and a recorder.
pub const LIVE_MAX_CLIENTS: usize = 4;
/// The most [`LiveConfig::max_clients`] may be (each client's send queue is bounded: the
/// daemon's memory grows by at most that much per client).
pub const LIVE_CLIENTS_LIMIT: usize = 32;

impl Default for LiveConfig {
    fn default() -> Self {
        LiveConfig {
            enabled: false,
            listen: std::net::SocketAddr::from(([127, 0, 0, 1], 8765)),
            allow_remote: false,
            max_hz: LIVE_MAX_HZ,
            max_clients: LIVE_MAX_CLIENTS,
        }
    }
}

/// Table push policy.
#[derive(Debug, Clone, PartialEq)]
pub struct PushPolicy {
    /// Attempts after the first one.
    pub retries: u32,
    /// Delay before the first retry (ms), doubled for each retry after it.
    pub backoff_initial_ms: u64,
    /// Longest delay between two attempts (ms).
    pub backoff_max_ms: u64,
    /// Time to wait for a node's answer before an attempt counts as failed (ms).
    pub timeout_ms: u64,
    /// `CommitAuth` before every Commit and only a MAC-verified readback counts as `New`; the
    /// serve mode's `Trigger` frames must verify too. Off only when the file says
    /// `authenticate = false`.
    pub authenticate: bool,
    /// The keys (never from the file: `exocald` loads them from its systemd credential,
    /// [`crate::keys`], the demo derives them from its seed). Empty after parsing.
    pub keys: exocal_dbc::auth::KeySet,
    /// The state directory (never from the file: `$STATE_DIRECTORY`, set by systemd's
    /// `StateDirectory=`): the nodes' verified and signed freshness counters and the trigger
    /// counter ([`crate::state`]). `None`: kept for the run only (tests, the demo).
    pub state_dir: Option<PathBuf>,
}

impl PushPolicy {
    /// Delay before retry number `retry` (1-based): exponential from `backoff_initial_ms`,
    /// capped at `backoff_max_ms`.
    pub fn backoff_ms(&self, retry: u32) -> u64 {
        let shift = retry.saturating_sub(1).min(32);
        self.backoff_initial_ms
            .saturating_mul(1u64 << shift)
            .min(self.backoff_max_ms)
    }
}

/// The serve mode's trigger rules (`exocald run`).
#[derive(Debug, Clone, PartialEq)]
pub struct TriggerRules {
    /// Least time between the starts of two triggered sessions, s.
    pub cooldown_s: f64,
}

/// The validated configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct Config {
    /// The SocketCAN interface the nodes are on (`can0`; `vcan0` on a bench).
    pub interface: String,
    /// What the data path reads (`[nodes]`, `[nominal]`, `[bounds]`, `[session]`,
    /// `[validation]`): the session crate's settings.
    pub calibration: Settings,
    /// Where and how the session log is written (`[output]`).
    pub output: OutputConfig,
    /// Table push policy (`[push]`).
    pub push: PushPolicy,
    /// The live view (`[live]`).
    pub live: LiveConfig,
    /// The serve mode's trigger rules (`[trigger]`).
    pub trigger: TriggerRules,
    /// Whether an authenticated session (`[push] authenticate`) verifies the sensor streams
    /// (`exocal_session::gate`). Always on from the configuration file; off only where a
    /// test's subject is the wire's faults (the fault matrix: the gate drops every span a lost,
    /// duplicated or corrupted frame touches, so 10 % loss leaves no data).
    pub verify_streams: bool,
}

/// A configuration error: which key, on which line, what is wrong.
#[derive(Debug)]
pub enum ConfigError {
    /// The file could not be read.
    Io {
        /// The file.
        path: PathBuf,
        /// The read error.
        source: std::io::Error,
    },
    /// The text is not a valid configuration.
    Invalid {
        /// The file, when the text came from one.
        path: Option<PathBuf>,
        /// Dotted key path (`session.min_duration_s`, `bounds.a[2]`); empty for the document.
        key: String,
        /// 1-based line of the key, when it is in the file.
        line: Option<usize>,
        /// What is wrong with the value.
        message: String,
    },
}

impl ConfigError {
    /// The offending key, if the error is about one.
    pub fn key(&self) -> Option<&str> {
        match self {
            ConfigError::Invalid { key, .. } => Some(key),
            ConfigError::Io { .. } => None,
        }
    }

    /// The 1-based line of the offending key, when known.
    pub fn line(&self) -> Option<usize> {
        match self {
            ConfigError::Invalid { line, .. } => *line,
            ConfigError::Io { .. } => None,
        }
    }

    fn with_path(self, p: &Path) -> Self {
        match self {
            ConfigError::Invalid {
                key, line, message, ..
            } => ConfigError::Invalid {
                path: Some(p.to_path_buf()),
                key,
                line,
                message,
            },
            io => io,
        }
    }
}

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ConfigError::Io { path, source } => {
                write!(f, "cannot read config {}: {source}", path.display())
            }
            ConfigError::Invalid {
                path,
                key,
                line,
                message,
            } => {
                let name = path
                    .as_ref()
                    .map_or_else(|| "config".to_string(), |p| p.display().to_string());
                match line {
                    Some(l) => write!(f, "{name}:{l}: ")?,
                    None => write!(f, "{name}: ")?,
                }
                if key.is_empty() {
                    write!(f, "{message}")
                } else {
                    write!(f, "key `{key}`: {message}")
                }
            }
        }
    }
}

impl std::error::Error for ConfigError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            ConfigError::Io { source, .. } => Some(source),
            ConfigError::Invalid { .. } => None,
        }
    }
}

// ---- the file's shape -------------------------------------------------------------------------

type Pair = [f64; 2];

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawConfig {
    can: RawCan,
    nodes: RawNodes,
    nominal: RawNominal,
    bounds: RawBounds,
    session: RawSession,
    validation: RawValidation,
    output: RawOutput,
    push: RawPush,
    live: Option<RawLive>,
    trigger: RawTrigger,
    sensors: Option<RawSensors>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSensors {
    #[serde(default)]
    rate_bias_deg_s: f64,
    #[serde(default)]
    rate_bias_walk_deg_s_per_sqrt_s: f64,
    #[serde(default)]
    unaided_joints: Vec<i64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCan {
    interface: String,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawNodes {
    joints: Vec<u8>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawNominal {
    a: Vec<f64>,
    alpha_deg: Vec<f64>,
    d: Vec<f64>,
    offset_deg: Vec<f64>,
}

/// `[nominal]`'s rows checked against the arm's length, padded.
struct RawNominalRows {
    a: [f64; MAX_JOINTS],
    alpha_deg: [f64; MAX_JOINTS],
    d: [f64; MAX_JOINTS],
    offset_deg: [f64; MAX_JOINTS],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawBounds {
    a: Vec<Pair>,
    d: Vec<Pair>,
    alpha_deviation_deg: f64,
    offset_deviation_deg: f64,
    joint_range_deg: Vec<Pair>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSession {
    min_duration_s: f64,
    max_duration_s: f64,
    excitation_required: f64,
    min_samples: usize,
    grid_hz: f64,
    max_gap_s: f64,
    #[serde(default)]
    stop_at_expected_error: Option<[f64; 2]>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawValidation {
    max_condition_number: f64,
    holdout_fraction: f64,
    max_expected_position_error_mm: f64,
    max_expected_rotation_error_mrad: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawOutput {
    directory: PathBuf,
    flush_interval_s: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawLive {
    enabled: bool,
    listen: String,
    #[serde(default)]
    allow_remote: bool,
    max_hz: Option<f64>,
    max_clients: Option<u64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawPush {
    retries: u32,
    backoff_initial_ms: u64,
    backoff_max_ms: u64,
    timeout_ms: u64,
    authenticate: bool,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawTrigger {
    cooldown_s: f64,
}

// ---- parsing ----------------------------------------------------------------------------------

impl Config {
    /// The configured joint nodes' ids (the ones the DBC knows), joint 1 first.
    pub fn joint_node_ids(&self) -> Vec<exocal_dbc::NodeId> {
        let joints = self.calibration.joints.min(MAX_JOINTS);
        self.calibration.joint_nodes[..joints]
            .iter()
            .filter_map(|&n| exocal_dbc::NodeId::new(n))
            .collect()
    }

    /// Reads and validates the configuration file at `path`.
    pub fn load(path: &Path) -> Result<Config, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Config::parse(&text).map_err(|e| e.with_path(path))
    }

    /// The shipped default configuration.
    pub fn default_config() -> Config {
        Config::parse(DEFAULT_TOML).expect("the shipped exocald.toml is valid (tested)")
    }

    /// Parses and validates configuration text.
    pub fn parse(text: &str) -> Result<Config, ConfigError> {
        let de = toml::Deserializer::parse(text).map_err(|e| toml_error(text, "", &e))?;
        let raw: RawConfig = serde_path_to_error::deserialize(de).map_err(|e| {
            let path = e.path().to_string();
            toml_error(text, &path, e.inner())
        })?;
        Checker { text }.build(raw)
    }
}

/// Turns a toml/serde error into a [`ConfigError`] naming the key and its line.
fn toml_error(text: &str, path: &str, e: &toml::de::Error) -> ConfigError {
    let message = e.message().trim().to_string();
    let mut key = if path == "." {
        String::new()
    } else {
        path.to_string()
    };
    // serde reports an unknown field at its parent's path: name the field itself.
    if let Some(rest) = message.strip_prefix("unknown field `") {
        if let Some(field) = rest.split('`').next() {
            let named = key == field || key.ends_with(&format!(".{field}"));
            key = if named {
                key
            } else if key.is_empty() {
                field.to_string()
            } else {
                format!("{key}.{field}")
            };
        }
    }
    let line = e
        .span()
        .map(|s| line_of(text, s.start))
        .or_else(|| key_line(text, &key));
    ConfigError::Invalid {
        path: None,
        key,
        line,
        message,
    }
}

/// 1-based line of byte offset `at`.
fn line_of(text: &str, at: usize) -> usize {
    text.as_bytes()[..at.min(text.len())]
        .iter()
        .filter(|&&b| b == b'\n')
        .count()
        + 1
}

/// 1-based line where the dotted key path (`bounds.a[2]`) is written, if it is in the text.
fn key_line(text: &str, key: &str) -> Option<usize> {
    if key.is_empty() {
        return None;
    }
    let doc = DeTable::parse(text).ok()?;
    let mut table = doc.get_ref();
    let mut span = None;
    let mut value: Option<&DeValue> = None;
    for segment in key.split('.') {
        let (name, indices) = match segment.find('[') {
            Some(i) => (&segment[..i], &segment[i..]),
            None => (segment, ""),
        };
        if let Some(v) = value {
            table = match v {
                DeValue::Table(t) => t,
                _ => return span.map(|s: std::ops::Range<usize>| line_of(text, s.start)),
            };
        }
        let (k, v) = table.iter().find(|(k, _)| k.get_ref() == name)?;
        span = Some(k.span());
        let mut current = v;
        for index in indices
            .split(['[', ']'])
            .filter(|s| !s.is_empty())
            .filter_map(|s| s.parse::<usize>().ok())
        {
            match current.get_ref() {
                DeValue::Array(items) if index < items.len() => {
                    current = &items[index];
                    span = Some(current.span());
                }
                _ => break,
            }
        }
        value = Some(current.get_ref());
    }
    span.map(|s| line_of(text, s.start))
}

/// Semantic checks, with access to the text to find lines.
struct Checker<'t> {
    text: &'t str,
}

impl Checker<'_> {
    fn err(&self, key: impl Into<String>, message: impl Into<String>) -> ConfigError {
        let key = key.into();
        ConfigError::Invalid {
            path: None,
            line: key_line(self.text, &key),
            key,
            message: message.into(),
        }
    }

    fn finite(&self, key: &str, x: f64) -> Result<f64, ConfigError> {
        if x.is_finite() {
            Ok(x)
        } else {
            Err(self.err(key, format!("must be a finite number, got {x}")))
        }
    }

    fn positive(&self, key: &str, x: f64) -> Result<f64, ConfigError> {
        if self.finite(key, x)? > 0.0 {
            Ok(x)
        } else {
            Err(self.err(key, format!("must be > 0, got {x}")))
        }
    }

    /// `0 < x <= max`.
    fn positive_at_most(&self, key: &str, x: f64, max: f64) -> Result<f64, ConfigError> {
        if self.positive(key, x)? <= max {
            Ok(x)
        } else {
            Err(self.err(key, format!("{x} is above the limit {max}")))
        }
    }

    /// `0 <= x <= max`.
    fn non_negative_at_most(&self, key: &str, x: f64, max: f64) -> Result<f64, ConfigError> {
        match self.finite(key, x)? {
            x if x < 0.0 => Err(self.err(key, format!("must be ≥ 0, got {x}"))),
            x if x > max => Err(self.err(key, format!("{x} is above the limit {max}"))),
            x => Ok(x),
        }
    }

    /// A set of joints, numbered from 1, each once.
    fn joint_set(
        &self,
        key: &str,
        list: &[i64],
        joints: usize,
    ) -> Result<[bool; MAX_JOINTS], ConfigError> {
        let mut set = [false; MAX_JOINTS];
        for &j in list {
            let i = usize::try_from(j)
                .ok()
                .filter(|i| (1..=joints).contains(i))
                .ok_or_else(|| {
                    self.err(
                        key,
                        format!("joint {j}: the arm's joints are numbered 1 to {joints}"),
                    )
                })?;
            if std::mem::replace(&mut set[i - 1], true) {
                return Err(self.err(key, format!("joint {j} is listed twice")));
            }
        }
        Ok(set)
    }

    /// `|x| <= max`.
    fn magnitude_at_most(&self, key: &str, x: f64, max: f64) -> Result<f64, ConfigError> {
        if self.finite(key, x)?.abs() <= max {
            Ok(x)
        } else {
            Err(self.err(key, format!("{x} is outside the limit ±{max}")))
        }
    }

    /// `x <= max` for an integer key.
    fn count_at_most<T: PartialOrd + fmt::Display>(
        &self,
        key: &str,
        x: T,
        max: T,
    ) -> Result<T, ConfigError> {
        if x <= max {
            Ok(x)
        } else {
            Err(self.err(key, format!("{x} is above the limit {max}")))
        }
    }

    /// `lo < x <= hi` (`lo_open`) or `lo <= x <= hi`.
    fn fraction(&self, key: &str, x: f64, hi_inclusive: bool) -> Result<f64, ConfigError> {
        let ok = self.finite(key, x)? > 0.0 && (x < 1.0 || (hi_inclusive && x == 1.0));
        if ok {
            Ok(x)
        } else {
            let hi = if hi_inclusive { "1]" } else { "1)" };
            Err(self.err(key, format!("must be in (0, {hi}, got {x}")))
        }
    }

    /// A per-joint array of the arm's `joints` rows, padded with zeros ([`exocal_session::arm`]).
    fn rows<T: Copy + Default>(
        &self,
        key: &str,
        values: &[T],
        joints: usize,
    ) -> Result<[T; MAX_JOINTS], ConfigError> {
        if values.len() != joints {
            return Err(self.err(
                key,
                format!(
                    "{} rows for an arm of {joints} joints (nodes.joints lists {joints})",
                    values.len()
                ),
            ));
        }
        Ok(std::array::from_fn(|j| {
            values.get(j).copied().unwrap_or_default()
        }))
    }

    fn intervals(
        &self,
        key: &str,
        pairs: &[Pair],
        joints: usize,
        scale: f64,
        limit: f64,
    ) -> Result<[(f64, f64); MAX_JOINTS], ConfigError> {
        let pairs = self.rows(key, pairs, joints)?;
        let mut out = [(0.0, 0.0); MAX_JOINTS];
        for (i, [lo, hi]) in pairs.iter().copied().enumerate().take(joints) {
            let k = format!("{key}[{i}]");
            self.magnitude_at_most(&k, lo, limit)?;
            self.magnitude_at_most(&k, hi, limit)?;
            if lo >= hi {
                return Err(self.err(k, format!("min {lo} must be below max {hi}")));
            }
            out[i] = (lo * scale, hi * scale);
        }
        Ok(out)
    }

    fn build(&self, raw: RawConfig) -> Result<Config, ConfigError> {
        use limits::*;
        let deg = std::f64::consts::PI / 180.0;

        let interface = raw.can.interface;
        // Linux IFNAMSIZ is 16 including the NUL.
        if interface.is_empty()
            || interface.len() > 15
            || interface
                .chars()
                .any(|c| c.is_whitespace() || c == '/' || c == ':')
        {
            return Err(self.err(
                "can.interface",
                format!("`{interface}` is not a network interface name (1-15 chars, no '/', ':' or spaces)"),
            ));
        }

        let joints = raw.nodes.joints.len();
        if !(1..=MAX_JOINTS).contains(&joints) {
            return Err(self.err(
                "nodes.joints",
                format!("{joints} joints: an arm has 1 to {MAX_JOINTS}"),
            ));
        }
        let joint_nodes: [u8; MAX_JOINTS] = self.rows("nodes.joints", &raw.nodes.joints, joints)?;
        for (i, &id) in raw.nodes.joints.iter().enumerate() {
            if !(1..=MAX_JOINTS as u8).contains(&id) {
                return Err(self.err(
                    format!("nodes.joints[{i}]"),
                    format!("node id {id}: the DBC's joint nodes are 1..=7"),
                ));
            }
            if joint_nodes[..i].contains(&id) {
                return Err(self.err(
                    format!("nodes.joints[{i}]"),
                    format!("node id {id} is used twice"),
                ));
            }
        }

        let n = &raw.nominal;
        let n = RawNominalRows {
            a: self.rows("nominal.a", &n.a, joints)?,
            alpha_deg: self.rows("nominal.alpha_deg", &n.alpha_deg, joints)?,
            d: self.rows("nominal.d", &n.d, joints)?,
            offset_deg: self.rows("nominal.offset_deg", &n.offset_deg, joints)?,
        };
        let mut nominal = DhTable {
            rows: [exocal_session::arm::ZERO_ROW; MAX_JOINTS],
        };
        for (i, row) in nominal.rows.iter_mut().enumerate().take(joints) {
            *row = DhRow {
                a: self.finite(&format!("nominal.a[{i}]"), n.a[i])?,
                alpha: self.magnitude_at_most(
                    &format!("nominal.alpha_deg[{i}]"),
                    n.alpha_deg[i],
                    MAX_ANGLE_DEG,
                )? * deg,
                d: self.finite(&format!("nominal.d[{i}]"), n.d[i])?,
                theta_offset: self.magnitude_at_most(
                    &format!("nominal.offset_deg[{i}]"),
                    n.offset_deg[i],
                    MAX_ANGLE_DEG,
                )? * deg,
            };
        }

        let b = &raw.bounds;
        let bounds = Bounds {
            a: self.intervals("bounds.a", &b.a, joints, 1.0, MAX_LENGTH_M)?,
            d: self.intervals("bounds.d", &b.d, joints, 1.0, MAX_LENGTH_M)?,
            alpha_deviation: self.positive_at_most(
                "bounds.alpha_deviation_deg",
                b.alpha_deviation_deg,
                MAX_DEVIATION_DEG,
            )? * deg,
            offset_deviation: self.positive_at_most(
                "bounds.offset_deviation_deg",
                b.offset_deviation_deg,
                MAX_DEVIATION_DEG,
            )? * deg,
            joint_range: JointRanges {
                limits: self.intervals(
                    "bounds.joint_range_deg",
                    &b.joint_range_deg,
                    joints,
                    deg,
                    MAX_ANGLE_DEG,
                )?,
            },
        };
        let within = |x: f64, (min, max): (f64, f64)| (min..=max).contains(&x);
        for (i, row) in nominal.rows.iter().enumerate().take(joints) {
            if !within(row.a, bounds.a[i]) {
                return Err(self.err(
                    format!("nominal.a[{i}]"),
                    format!("{} is outside bounds.a[{i}]", row.a),
                ));
            }
            if !within(row.d, bounds.d[i]) {
                return Err(self.err(
                    format!("nominal.d[{i}]"),
                    format!("{} is outside bounds.d[{i}]", row.d),
                ));
            }
        }

        let s = &raw.session;
        let session = WindowRules {
            min_duration_s: self.positive_at_most(
                "session.min_duration_s",
                s.min_duration_s,
                MAX_DURATION_S,
            )?,
            max_duration_s: self.positive("session.max_duration_s", s.max_duration_s)?,
            excitation_required: self.fraction(
                "session.excitation_required",
                s.excitation_required,
                true,
            )?,
            min_samples: s.min_samples,
            grid_hz: self.positive_at_most("session.grid_hz", s.grid_hz, MAX_GRID_HZ)?,
            max_gap_s: self.positive_at_most("session.max_gap_s", s.max_gap_s, MAX_GAP_S)?,
            stop_at_expected_error: match s.stop_at_expected_error {
                None => None,
                Some([mm, mrad]) => Some((
                    self.positive_at_most(
                        "session.stop_at_expected_error[0]",
                        mm,
                        MAX_EXPECTED_POSITION_ERROR_MM,
                    )?,
                    self.positive_at_most(
                        "session.stop_at_expected_error[1]",
                        mrad,
                        MAX_EXPECTED_ROTATION_ERROR_MRAD,
                    )?,
                )),
            },
        };
        if session.max_duration_s > MAX_DURATION_S {
            return Err(self.err(
                "session.max_duration_s",
                format!(
                    "{} s is above the limit {MAX_DURATION_S} s: a session's memory grows with \
                     its length (about 0.3 MiB a second), and a longer one would not fit the \
                     unit's {MEMORY_MAX} with margin",
                    session.max_duration_s
                ),
            ));
        }
        let (limit, why) = match session.stop_at_expected_error {
            Some(_) => (
                MAX_GRID_POINTS_ESTIMATING,
                " with session.stop_at_expected_error (each estimate copies the collection)",
            ),
            None => (MAX_GRID_POINTS, ""),
        };
        if session.grid_hz * session.max_duration_s > limit {
            return Err(self.err(
                "session.max_duration_s",
                format!(
                    "{} s at session.grid_hz = {} Hz is {:.0} grid points, above the limit \
                     {limit:.0}{why}: a session that long would not fit the unit's \
                     {MEMORY_MAX} with margin; shorten it or slow the grid",
                    session.max_duration_s,
                    session.grid_hz,
                    session.grid_hz * session.max_duration_s
                ),
            ));
        }
        if session.max_duration_s < session.min_duration_s {
            return Err(self.err(
                "session.max_duration_s",
                format!(
                    "{} is below session.min_duration_s = {}",
                    session.max_duration_s, session.min_duration_s
                ),
            ));
        }
        if session.min_samples == 0 {
            return Err(self.err("session.min_samples", "must be at least 1"));
        }
        // The grid holds at most grid_hz × max_duration_s samples: more can never be collected.
        let reachable = session.grid_hz * session.max_duration_s;
        if session.min_samples as f64 > reachable {
            return Err(self.err(
                "session.min_samples",
                format!(
                    "{} can never be collected: at most session.grid_hz × session.max_duration_s \
                     = {reachable:.0} samples",
                    session.min_samples
                ),
            ));
        }
        if session.max_gap_s * session.grid_hz < 1.0 {
            return Err(self.err(
                "session.max_gap_s",
                format!(
                    "{} s is shorter than one grid period (1/{} s): every sample would be a gap",
                    session.max_gap_s, session.grid_hz
                ),
            ));
        }

        let v = &raw.validation;
        let validation = ValidationRules {
            max_condition_number: self.positive_at_most(
                "validation.max_condition_number",
                v.max_condition_number,
                MAX_CONDITION_NUMBER,
            )?,
            holdout_fraction: self.fraction(
                "validation.holdout_fraction",
                v.holdout_fraction,
                false,
            )?,
            max_expected_position_error_mm: self.positive_at_most(
                "validation.max_expected_position_error_mm",
                v.max_expected_position_error_mm,
                MAX_EXPECTED_POSITION_ERROR_MM,
            )?,
            max_expected_rotation_error_mrad: self.positive_at_most(
                "validation.max_expected_rotation_error_mrad",
                v.max_expected_rotation_error_mrad,
                MAX_EXPECTED_ROTATION_ERROR_MRAD,
            )?,
        };
        if validation.max_condition_number < 1.0 {
            return Err(self.err(
                "validation.max_condition_number",
                "a condition number is at least 1",
            ));
        }

        let o = raw.output;
        if o.directory.as_os_str().is_empty() {
            return Err(self.err("output.directory", "must not be empty"));
        }
        let flush = self.positive("output.flush_interval_s", o.flush_interval_s)?;
        if flush > 1.0 {
            return Err(self.err(
                "output.flush_interval_s",
                format!("{flush} s: must be at most 1 s (a hard kill may lose only that much)"),
            ));
        }
        let output = OutputConfig {
            directory: o.directory,
            flush_interval_s: flush,
        };

        let p = raw.push;
        let push = PushPolicy {
            retries: self.count_at_most("push.retries", p.retries, MAX_RETRIES)?,
            backoff_initial_ms: self.count_at_most(
                "push.backoff_initial_ms",
                p.backoff_initial_ms,
                MAX_BACKOFF_MS,
            )?,
            backoff_max_ms: self.count_at_most(
                "push.backoff_max_ms",
                p.backoff_max_ms,
                MAX_BACKOFF_MS,
            )?,
            timeout_ms: self.count_at_most("push.timeout_ms", p.timeout_ms, MAX_TIMEOUT_MS)?,
            authenticate: p.authenticate,
            keys: exocal_dbc::auth::KeySet::default(),
            state_dir: None,
        };
        if push.backoff_initial_ms == 0 {
            return Err(self.err("push.backoff_initial_ms", "must be at least 1"));
        }
        if push.backoff_max_ms < push.backoff_initial_ms {
            return Err(self.err(
                "push.backoff_max_ms",
                format!(
                    "{} is below push.backoff_initial_ms = {}",
                    push.backoff_max_ms, push.backoff_initial_ms
                ),
            ));
        }
        if push.timeout_ms == 0 {
            return Err(self.err("push.timeout_ms", "must be at least 1"));
        }

        let live = match raw.live {
            None => LiveConfig::default(),
            Some(l) => {
                let listen: std::net::SocketAddr = l.listen.parse().map_err(|_| {
                    self.err(
                        "live.listen",
                        format!(
                            "{:?} is not an address and port (e.g. \"127.0.0.1:8765\")",
                            l.listen
                        ),
                    )
                })?;
                if !listen.ip().is_loopback() && !l.allow_remote {
                    return Err(self.err(
                        "live.listen",
                        format!(
                            "{listen} is reachable from other hosts and the live view has no \
                             authentication: listen on loopback (127.0.0.1), or set \
                             allow_remote = true in [live] to serve it anyway"
                        ),
                    ));
                }
                let max_clients = l.max_clients.unwrap_or(LIVE_MAX_CLIENTS as u64);
                if max_clients == 0 || max_clients > LIVE_CLIENTS_LIMIT as u64 {
                    return Err(self.err(
                        "live.max_clients",
                        format!("must be 1 to {LIVE_CLIENTS_LIMIT}, got {max_clients}"),
                    ));
                }
                LiveConfig {
                    enabled: l.enabled,
                    listen,
                    allow_remote: l.allow_remote,
                    max_hz: self.positive_at_most(
                        "live.max_hz",
                        l.max_hz.unwrap_or(LIVE_MAX_HZ),
                        1000.0,
                    )?,
                    max_clients: max_clients as usize,
                }
            }
        };
        let sensors = match raw.sensors {
            None => SensorSpec::default(),
            Some(r) => SensorSpec {
                rate_bias: RateBias {
                    ramp: self
                        .non_negative_at_most(
                            "sensors.rate_bias_deg_s",
                            r.rate_bias_deg_s,
                            MAX_RATE_BIAS_DEG_S,
                        )?
                        .to_radians(),
                    walk: self
                        .non_negative_at_most(
                            "sensors.rate_bias_walk_deg_s_per_sqrt_s",
                            r.rate_bias_walk_deg_s_per_sqrt_s,
                            MAX_RATE_BIAS_DEG_S,
                        )?
                        .to_radians(),
                },
                unaided: self.joint_set("sensors.unaided_joints", &r.unaided_joints, joints)?,
            },
        };
        let trigger = TriggerRules {
            cooldown_s: self.positive_at_most(
                "trigger.cooldown_s",
                raw.trigger.cooldown_s,
                MAX_COOLDOWN_S,
            )?,
        };

        Ok(Config {
            interface,
            calibration: Settings {
                joints,
                joint_nodes,
                nominal,
                bounds,
                window: session,
                validation,
                sensors,
            },
            output,
            push,
            live,
            trigger,
            verify_streams: true,
        })
    }
}

// ---- writing ----------------------------------------------------------------------------------

/// Why a configuration with a calibrated table cannot be written.
#[derive(Debug, Clone, PartialEq)]
pub enum ExportError {
    /// The base configuration is not valid TOML (the parser's message).
    BaseToml(String),
    /// The base configuration has no `[nominal]` table.
    NoNominal,
    /// A parameter is not finite (`d3`, …).
    NotFinite(String),
}

impl fmt::Display for ExportError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ExportError::BaseToml(e) => write!(f, "the base configuration is not TOML: {e}"),
            ExportError::NoNominal => write!(f, "the base configuration has no [nominal] table"),
            ExportError::NotFinite(p) => write!(f, "parameter {p} is not finite"),
        }
    }
}

impl std::error::Error for ExportError {}

/// The comment [`with_nominal`] puts above the calibrated table.
pub const CALIBRATED_NOTE: &str =
    "# The suit's calibrated table (standard D-H parameters), written by \
     `exocald offline --export-toml`: this suit's own, not the paper's Table 1.\n";

/// `base` (a configuration text: the one the daemon ran with, or its shipped default) with its
/// `[nominal]` table replaced by `table`: only the four `[nominal]` arrays are rewritten
/// (lengths in metres, angles in degrees, as the file speaks), every other key, comment and
/// layout kept, except the comment above the table's first key: it described the table that
/// was there (the shipped file's says "The paper's Table 1"), so it becomes [`CALIBRATED_NOTE`].
/// The result is a complete configuration whose nominal table is the calibrated one (`exocald
/// offline --export-toml`). `rows` are the arm's, joint 1 first.
pub fn with_nominal(base: &str, rows: &[DhRow]) -> Result<String, ExportError> {
    for (i, r) in rows.iter().enumerate() {
        let values = [
            ("a", r.a),
            ("alpha", r.alpha),
            ("d", r.d),
            ("offset", r.theta_offset),
        ];
        if let Some((name, _)) = values.iter().find(|(_, v)| !v.is_finite()) {
            return Err(ExportError::NotFinite(format!("{name}{}", i + 1)));
        }
    }
    let mut doc: DocumentMut = base
        .parse()
        .map_err(|e: toml_edit::TomlError| ExportError::BaseToml(e.to_string()))?;
    let nominal = doc
        .get_mut("nominal")
        .and_then(Item::as_table_like_mut)
        .ok_or(ExportError::NoNominal)?;
    type Column = (&'static str, fn(&calib_core::DhRow) -> f64);
    let columns: [Column; 4] = [
        ("a", |r| r.a),
        ("alpha_deg", |r| r.alpha.to_degrees()),
        ("d", |r| r.d),
        ("offset_deg", |r| r.theta_offset.to_degrees()),
    ];
    for (key, get) in columns {
        let values: Array = rows.iter().map(get).collect();
        match nominal.get_mut(key).and_then(Item::as_value_mut) {
            // Keep the key's decoration (comments, spacing) and replace the value.
            Some(old) => {
                let decor = old.decor().clone();
                *old = Value::Array(values);
                *old.decor_mut() = decor;
            }
            None => {
                nominal.insert(key, Item::Value(Value::Array(values)));
            }
        }
    }
    let first = nominal.iter().next().map(|(k, _)| k.to_string());
    if let Some(mut key) = first.and_then(|k| nominal.key_mut(&k)) {
        key.leaf_decor_mut().set_prefix(CALIBRATED_NOTE);
    }
    Ok(doc.to_string())
}

impl Config {
    /// The configuration as a TOML file in the file's own units (degrees, seconds, metres),
    /// the sections and keys in the order of [`DEFAULT_TOML`], without comments: what
    /// `check-config` prints, and what [`Config::parse`] reads back to the same configuration.
    pub fn to_toml(&self) -> String {
        use std::fmt::Write as _;
        // Radians back to the file's degrees, rounded to 1e-9 degrees so that a value written as
        // 90.0 prints as 90 and not as 90.00000000000001.
        let deg = |r: f64| ((r / (std::f64::consts::PI / 180.0)) * 1e9).round() / 1e9;
        let list = |v: &mut dyn Iterator<Item = String>| v.collect::<Vec<_>>().join(", ");
        let num = |x: f64| format!("{x:?}");
        let joints = self.calibration.joints.min(MAX_JOINTS);
        let pairs = |v: &[(f64, f64); MAX_JOINTS], scale: &dyn Fn(f64) -> f64| {
            list(
                &mut v[..joints]
                    .iter()
                    .map(|&(min, max)| format!("[{}, {}]", num(scale(min)), num(scale(max)))),
            )
        };
        let text = |s: &str| toml::Value::String(s.to_string()).to_string();
        let n = &self.calibration.nominal.rows[..joints];
        let b = &self.calibration.bounds;
        let s = &self.calibration.window;
        let v = &self.calibration.validation;
        let p = &self.push;
        let mut out = String::new();
        let w = &mut out;
        // Writing into a String cannot fail.
        let _ = writeln!(w, "[can]\ninterface = {}\n", text(&self.interface));
        let _ = writeln!(
            w,
            "[nodes]\njoints = [{}]\n",
            list(
                &mut self.calibration.joint_nodes[..joints]
                    .iter()
                    .map(|j| j.to_string())
            )
        );
        let _ = writeln!(
            w,
            "[nominal]\na = [{}]\nalpha_deg = [{}]\nd = [{}]\noffset_deg = [{}]\n",
            list(&mut n.iter().map(|r| num(r.a))),
            list(&mut n.iter().map(|r| num(deg(r.alpha)))),
            list(&mut n.iter().map(|r| num(r.d))),
            list(&mut n.iter().map(|r| num(deg(r.theta_offset)))),
        );
        let _ = writeln!(
            w,
            "[bounds]\na = [{}]\nd = [{}]\nalpha_deviation_deg = {}\noffset_deviation_deg = {}\n\
             joint_range_deg = [{}]\n",
            pairs(&b.a, &|x| x),
            pairs(&b.d, &|x| x),
            num(deg(b.alpha_deviation)),
            num(deg(b.offset_deviation)),
            pairs(&b.joint_range.limits, &deg),
        );
        let _ = writeln!(
            w,
            "[session]\nmin_duration_s = {}\nmax_duration_s = {}\nexcitation_required = {}\n\
             min_samples = {}\ngrid_hz = {}\nmax_gap_s = {}\n",
            num(s.min_duration_s),
            num(s.max_duration_s),
            num(s.excitation_required),
            s.min_samples,
            num(s.grid_hz),
            num(s.max_gap_s),
        );
        if let Some((mm, mrad)) = s.stop_at_expected_error {
            let _ = writeln!(w, "stop_at_expected_error = [{}, {}]\n", num(mm), num(mrad));
        }
        let _ = writeln!(
            w,
            "[validation]\nmax_condition_number = {}\nholdout_fraction = {}\n\
             max_expected_position_error_mm = {}\nmax_expected_rotation_error_mrad = {}\n",
            num(v.max_condition_number),
            num(v.holdout_fraction),
            num(v.max_expected_position_error_mm),
            num(v.max_expected_rotation_error_mrad),
        );
        let _ = writeln!(
            w,
            "[output]\ndirectory = {}\nflush_interval_s = {}\n",
            text(&self.output.directory.to_string_lossy()),
            num(self.output.flush_interval_s),
        );
        let _ = writeln!(
            w,
            "[push]\nretries = {}\nbackoff_initial_ms = {}\nbackoff_max_ms = {}\ntimeout_ms = {}\n\
             authenticate = {}\n",
            p.retries, p.backoff_initial_ms, p.backoff_max_ms, p.timeout_ms, p.authenticate,
        );
        let _ = writeln!(
            w,
            "[live]\nenabled = {}\nlisten = {}\nallow_remote = {}\nmax_hz = {}\nmax_clients = {}\n",
            self.live.enabled,
            text(&self.live.listen.to_string()),
            self.live.allow_remote,
            num(self.live.max_hz),
            self.live.max_clients,
        );
        let _ = write!(
            w,
            "[trigger]\ncooldown_s = {}\n",
            num(self.trigger.cooldown_s)
        );
        let rb = self.calibration.sensors.rate_bias;
        let unaided = exocal_session::rules::joint_list(&self.calibration.sensors.unaided);
        if !rb.is_none() || !unaided.is_empty() {
            let _ = write!(
                w,
                "\n[sensors]\nrate_bias_deg_s = {}\nrate_bias_walk_deg_s_per_sqrt_s = {}\nunaided_joints = [{}]\n",
                num(deg(rb.ramp)),
                num(deg(rb.walk)),
                unaided
            );
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shipped_file_is_the_session_crates_suit_default() {
        // exocal_session::Settings::suit_default() states the shipped values for tests and
        // examples that need a suit without a file: they must not drift apart.
        let shipped = Config::default_config().calibration;
        let code = Settings::suit_default();
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-12 * a.abs().max(1.0);
        for (a, b) in shipped.nominal.rows.iter().zip(&code.nominal.rows) {
            assert!(close(a.a, b.a) && close(a.d, b.d), "{a:?} vs {b:?}");
            assert!(close(a.alpha, b.alpha) && close(a.theta_offset, b.theta_offset));
        }
        let limits = |s: &Settings| s.bounds.joint_range.limits;
        for (a, b) in limits(&shipped).iter().zip(&limits(&code)) {
            assert!(close(a.0, b.0) && close(a.1, b.1), "{a:?} vs {b:?}");
        }
        assert!(close(
            shipped.bounds.alpha_deviation,
            code.bounds.alpha_deviation
        ));
        assert!(close(
            shipped.bounds.offset_deviation,
            code.bounds.offset_deviation
        ));
        assert_eq!(
            (shipped.bounds.a, shipped.bounds.d, shipped.joint_nodes),
            (code.bounds.a, code.bounds.d, code.joint_nodes)
        );
        assert_eq!(shipped.window, code.window);
        assert_eq!(shipped.validation, code.validation);
        assert_eq!(shipped.sensors, code.sensors);
    }

    #[test]
    fn a_sensor_spec_is_optional_read_in_degrees_and_written_back() {
        let with = format!(
            "{DEFAULT_TOML}\n[sensors]\nrate_bias_deg_s = 0.02\nrate_bias_walk_deg_s_per_sqrt_s = 0.001\n"
        );
        let c = Config::parse(&with).unwrap();
        let rb = c.calibration.sensors.rate_bias;
        assert!((rb.ramp - 0.02f64.to_radians()).abs() < 1e-15, "{rb:?}");
        assert!((rb.walk - 0.001f64.to_radians()).abs() < 1e-15);
        assert_eq!(Config::parse(&c.to_toml()).unwrap(), c);
        let bad = with.replace("rate_bias_deg_s = 0.02", "rate_bias_deg_s = -1");
        let e = Config::parse(&bad).unwrap_err();
        assert_eq!(e.key(), Some("sensors.rate_bias_deg_s"), "{e}");
        assert!(e.line().is_some(), "{e}");
    }

    #[test]
    fn unaided_joints_are_read_written_back_and_checked() {
        let with = format!("{DEFAULT_TOML}\n[sensors]\nunaided_joints = [1, 3, 5]\n");
        let c = Config::parse(&with).unwrap();
        let s = c.calibration.sensors;
        assert_eq!(s.unaided, [true, false, true, false, true, false, false]);
        assert!(s.rate_bias.is_none());
        assert_eq!(Config::parse(&c.to_toml()).unwrap(), c);
        for (list, says) in [
            ("[0]", "numbered 1 to 7"),
            ("[8]", "numbered 1 to 7"),
            ("[2, 2]", "twice"),
        ] {
            let bad = with.replace("[1, 3, 5]", list);
            let e = Config::parse(&bad).unwrap_err();
            assert_eq!(e.key(), Some("sensors.unaided_joints"), "{e}");
            assert!(e.to_string().contains(says), "{e}");
        }
    }
    use calib_core::ParamKind;

    #[test]
    fn config_export_replaces_only_the_nominal_arrays() {
        let base = "# head\n[can]\ninterface = \"can0\" # keep me\n\n[nominal]\n# rows\na = [1.0]\nalpha_deg = [0.0] # twist\nd = [0.0]\noffset_deg = [0.0]\n\n[push]\nretries = 3\n";
        let t = DhTable::<MAX_JOINTS>::paper_actual();
        let out = with_nominal(base, &t.rows).unwrap();
        assert!(out.contains("interface = \"can0\" # keep me"), "{out}");
        // The comment on the table that was there is replaced (it would mislabel the calibrated
        // table, e.g. as "The paper's Table 1"); the others are kept.
        assert!(
            !out.contains("# rows") && out.contains(CALIBRATED_NOTE),
            "{out}"
        );
        assert!(out.contains("# twist"));
        assert!(out.contains("retries = 3"));
        let doc: toml_edit::DocumentMut = out.parse().unwrap();
        let read = |k: &str| -> Vec<f64> {
            doc["nominal"][k]
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_float().unwrap())
                .collect()
        };
        assert_eq!(read("a"), t.rows.map(|r| r.a).to_vec());
        assert_eq!(read("d"), t.rows.map(|r| r.d).to_vec());
        for (deg, r) in read("alpha_deg").iter().zip(&t.rows) {
            assert!((deg.to_radians() - r.alpha).abs() < 1e-15);
        }
        for (deg, r) in read("offset_deg").iter().zip(&t.rows) {
            assert!((deg.to_radians() - r.theta_offset).abs() < 1e-15);
        }
    }

    #[test]
    fn config_export_errors_name_the_problem() {
        let t = DhTable::<MAX_JOINTS>::paper_actual();
        assert!(matches!(
            with_nominal("a = [", &t.rows),
            Err(ExportError::BaseToml(_))
        ));
        assert_eq!(
            with_nominal("[can]\nx = 1\n", &t.rows),
            Err(ExportError::NoNominal)
        );
        let mut bad = t;
        bad.rows[2].d = f64::NAN;
        assert_eq!(
            with_nominal("[nominal]\n", &bad.rows),
            Err(ExportError::NotFinite("d3".into()))
        );
    }

    /// The default text with `from` replaced by `to` (which must occur exactly once).
    fn edited(from: &str, to: &str) -> String {
        edited_in(DEFAULT_TOML, from, to)
    }

    fn edited_in(text: &str, from: &str, to: &str) -> String {
        assert_eq!(text.matches(from).count(), 1, "`{from}` not unique");
        text.replace(from, to)
    }

    fn line_containing(text: &str, needle: &str) -> usize {
        text.lines().position(|l| l.contains(needle)).unwrap() + 1
    }

    fn invalid(text: &str) -> (String, Option<usize>, String) {
        match Config::parse(text) {
            Err(ConfigError::Invalid {
                key, line, message, ..
            }) => (key, line, message),
            other => panic!("expected an invalid config, got {other:?}"),
        }
    }

    #[test]
    fn the_shipped_default_is_valid_and_is_table_1() {
        let c = Config::parse(DEFAULT_TOML).unwrap();
        assert_eq!(c.interface, "can0");
        assert_eq!(c.calibration.joint_nodes, [1, 2, 3, 4, 5, 6, 7]);
        let a: Vec<f64> = c.calibration.nominal.rows.iter().map(|r| r.a).collect();
        assert_eq!(a, [0.04, 0.04, 0.431, 0.244, 0.0, 0.0, 0.0]);
        assert!((c.calibration.nominal.rows[0].alpha + std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        assert!(
            (c.calibration.nominal.rows[1].theta_offset - std::f64::consts::FRAC_PI_2).abs()
                < 1e-12
        );
        assert_eq!(c.calibration.bounds.a[2], (0.377, 0.485));
        assert!((c.calibration.bounds.joint_range.limits[4].0 + 20f64.to_radians()).abs() < 1e-12);
        // The table bounds: a and d as configured, α and the offset around nominal.
        let t = c
            .calibration
            .bounds
            .table(&c.calibration.nominal, c.calibration.joints);
        assert_eq!(t.limits[ParamKind::A as usize][2], Some((0.377, 0.485)));
        let (lo, hi) = t.limits[ParamKind::Alpha as usize][0].unwrap();
        assert!((0.5 * (lo + hi) - c.calibration.nominal.rows[0].alpha).abs() < 1e-12);
        assert!((0.5 * (hi - lo) - c.calibration.bounds.alpha_deviation).abs() < 1e-12);
        assert_eq!(c.push.retries, 3);
        assert_eq!(Config::default_config(), c);
    }

    #[test]
    fn to_toml_speaks_degrees_and_reads_back_to_the_same_configuration() {
        let edits = [
            ("alpha_deviation_deg = 10.0", "alpha_deviation_deg = 7.25"),
            ("interface = \"can0\"", "interface = \"vcan0\""),
            (
                "max_condition_number = 1.0e4",
                "max_condition_number = 2.5e11",
            ),
            ("d          = [0.0,", "d          = [1.0e-7,"),
            (
                "directory = \"/var/lib/exocald\"",
                "directory = 'C:\\odd \"dir\"'",
            ),
            (
                "stop_at_expected_error = [2.0, 6.0]",
                "stop_at_expected_error = [2.5, 7.0]",
            ),
        ];
        let mut text = DEFAULT_TOML.to_string();
        for (from, to) in edits {
            text = edited_in(&text, from, to);
        }
        for source in [DEFAULT_TOML, text.as_str()] {
            let c = Config::parse(source).unwrap();
            let written = c.to_toml();
            assert_eq!(Config::parse(&written).unwrap(), c, "{written}");
            assert_eq!(Config::parse(&written).unwrap().to_toml(), written);
        }
        let shown = Config::default_config().to_toml();
        assert!(
            shown.contains("alpha_deg = [-90.0, 90.0, 90.0, -90.0, 90.0, 90.0, 90.0]"),
            "{shown}"
        );
        assert!(
            shown.contains("joint_range_deg = [[-90.0, 90.0], [-120.0, 30.0]"),
            "{shown}"
        );
        assert!(shown.contains("offset_deviation_deg = 15.0"), "{shown}");
    }

    #[test]
    fn stop_when_good_enough_is_on_by_default_off_when_commented_out_and_checked() {
        assert_eq!(
            Config::default_config()
                .calibration
                .window
                .stop_at_expected_error,
            Some((2.0, 6.0))
        );
        let off = edited(
            "stop_at_expected_error = [2.0, 6.0]",
            "# stop_at_expected_error = [2.0, 6.0]",
        );
        assert_eq!(
            Config::parse(&off)
                .unwrap()
                .calibration
                .window
                .stop_at_expected_error,
            None
        );
        let bad = edited(
            "stop_at_expected_error = [2.0, 6.0]",
            "stop_at_expected_error = [2.0, -6.0]",
        );
        let (key, line, _) = invalid(&bad);
        assert_eq!(key, "session.stop_at_expected_error[1]");
        assert_eq!(
            line,
            Some(line_containing(&bad, "stop_at_expected_error ="))
        );
    }

    #[test]
    fn an_unknown_key_is_named_with_its_line() {
        let text = edited("grid_hz = 100.0", "grid_hz = 100.0\ngrid_hertz = 50.0");
        let (key, line, message) = invalid(&text);
        assert_eq!(key, "session.grid_hertz");
        assert_eq!(line, Some(line_containing(&text, "grid_hertz")));
        assert!(message.contains("unknown field"), "{message}");
    }

    #[test]
    fn an_unknown_section_is_named() {
        let text = format!("{DEFAULT_TOML}\n[extra]\nx = 1\n");
        let (key, line, _) = invalid(&text);
        assert_eq!(key, "extra");
        assert_eq!(line, Some(line_containing(&text, "[extra]")));
    }

    /// The live view has no authentication, so an address other hosts
    /// reach needs `allow_remote`; its client limit is bounded.
    #[test]
    fn a_live_view_for_other_hosts_needs_allow_remote() {
        let live = |extra: &str| {
            let text = DEFAULT_TOML.replace(
                "listen = \"127.0.0.1:8765\"\n",
                &format!("listen = \"0.0.0.0:8765\"\n{extra}"),
            );
            Config::parse(&text)
        };
        let allowed = DEFAULT_TOML.replace("allow_remote = false", "allow_remote = true");
        let e = Config::parse(&allowed.replace("127.0.0.1:8765", "0.0.0.0:8765"));
        assert!(e.is_ok(), "{e:?}");
        let e = live("").unwrap_err().to_string();
        assert!(
            e.contains("live.listen") && e.contains("allow_remote"),
            "{e}"
        );
        let e = Config::parse(&DEFAULT_TOML.replace("max_clients = 4", "max_clients = 0"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("live.max_clients"), "{e}");
        let c = Config::parse(DEFAULT_TOML).unwrap();
        assert_eq!(
            (c.live.max_hz, c.live.max_clients),
            (LIVE_MAX_HZ, LIVE_MAX_CLIENTS)
        );
    }

    #[test]
    fn a_missing_key_is_named() {
        let text = edited("retries = 3\n", "");
        let (key, _, message) = invalid(&text);
        assert!(key == "push" || key == "push.retries", "{key}");
        assert!(message.contains("retries"), "{message}");
    }

    #[test]
    fn a_wrong_type_is_named_with_its_line() {
        let text = edited("min_duration_s = 20.0", "min_duration_s = \"sixty\"");
        let (key, line, _) = invalid(&text);
        assert_eq!(key, "session.min_duration_s");
        assert_eq!(line, Some(line_containing(&text, "min_duration_s =")));
    }

    #[test]
    fn a_short_array_is_named() {
        let text = edited(
            "d          = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]",
            "d          = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]",
        );
        let (key, line, message) = invalid(&text);
        assert_eq!(key, "nominal.d");
        assert_eq!(line, Some(line_containing(&text, "d          = [")));
        assert!(
            message.contains("6 rows for an arm of 7 joints"),
            "{message}"
        );
    }

    #[test]
    fn a_syntax_error_has_a_line() {
        let text = edited("retries = 3", "retries = = 3");
        let (_, line, _) = invalid(&text);
        assert_eq!(line, Some(line_containing(&text, "retries = =")));
    }

    #[test]
    fn inverted_durations_are_rejected() {
        let text = edited("max_duration_s = 180.0", "max_duration_s = 10.0");
        let (key, line, message) = invalid(&text);
        assert_eq!(key, "session.max_duration_s");
        assert_eq!(line, Some(line_containing(&text, "max_duration_s =")));
        assert!(message.contains("below"), "{message}");
    }

    #[test]
    fn an_inverted_interval_names_its_index() {
        let text = edited("[0.377, 0.485]", "[0.485, 0.377]");
        let (key, line, _) = invalid(&text);
        assert_eq!(key, "bounds.a[2]");
        assert_eq!(line, Some(line_containing(&text, "[0.485, 0.377]")));
    }

    #[test]
    fn an_arm_of_fewer_joints_is_its_rows_and_every_row_count_is_checked() {
        let mut c = Config::default_config();
        c.calibration = c.calibration.first(4);
        let text = c.to_toml();
        assert!(text.contains("[nodes]\njoints = [1, 2, 3, 4]\n"), "{text}");
        assert!(text.contains("a = [0.04, 0.04, 0.431, 0.244]\n"), "{text}");
        let back = Config::parse(&text).unwrap_or_else(|e| panic!("{e}\n{text}"));
        assert_eq!(back, c);
        assert_eq!(back.calibration.joints, 4);
        assert!(back.calibration.nominal.rows[4..]
            .iter()
            .all(|r| *r == exocal_session::arm::ZERO_ROW));
        // Every per-joint key must have one row per node.
        for (from, to, key) in [
            (
                "a = [0.04, 0.04, 0.431, 0.244]",
                "a = [0.04, 0.04, 0.431]",
                "nominal.a",
            ),
            (
                "offset_deg = [0.0, 90.0, 0.0, 0.0]",
                "offset_deg = [0.0, 90.0, 0.0, 0.0, 0.0]",
                "nominal.offset_deg",
            ),
            (
                "joint_range_deg = [[-90.0, 90.0], ",
                "joint_range_deg = [",
                "bounds.joint_range_deg",
            ),
        ] {
            let (k, _, message) = invalid(&edited_in(&text, from, to));
            assert_eq!(k, key, "{message}");
            assert!(message.contains("for an arm of 4 joints"), "{message}");
        }
        let (k, _, message) = invalid(&edited_in(&text, "joints = [1, 2, 3, 4]", "joints = []"));
        assert_eq!(k, "nodes.joints");
        assert!(message.contains("1 to 7"), "{message}");
        let unaided = format!("{text}\n[sensors]\nunaided_joints = [5]\n");
        let (k, _, message) = invalid(&unaided);
        assert_eq!(k, "sensors.unaided_joints");
        assert!(message.contains("numbered 1 to 4"), "{message}");
    }

    #[test]
    fn a_nominal_outside_bounds_is_rejected() {
        let text = edited(
            "a          = [0.04, 0.04, 0.431",
            "a          = [0.04, 0.04, 0.631",
        );
        let (key, _, message) = invalid(&text);
        assert_eq!(key, "nominal.a[2]");
        assert!(message.contains("outside"), "{message}");
    }

    #[test]
    fn fractions_must_be_fractions() {
        for (from, to, key) in [
            (
                "excitation_required = 0.5",
                "excitation_required = 1.5",
                "session.excitation_required",
            ),
            (
                "holdout_fraction = 0.2",
                "holdout_fraction = 1.0",
                "validation.holdout_fraction",
            ),
        ] {
            let (k, line, _) = invalid(&edited(from, to));
            assert_eq!(k, key);
            assert!(line.is_some());
        }
    }

    #[test]
    fn non_finite_and_non_positive_values_are_rejected() {
        let (key, _, _) = invalid(&edited("grid_hz = 100.0", "grid_hz = nan"));
        assert_eq!(key, "session.grid_hz");
        let (key, _, _) = invalid(&edited("grid_hz = 100.0", "grid_hz = -100.0"));
        assert_eq!(key, "session.grid_hz");
        let (key, _, _) = invalid(&edited("max_gap_s = 0.05", "max_gap_s = 0.001"));
        assert_eq!(key, "session.max_gap_s");
        let (key, _, _) = invalid(&edited(
            "max_expected_position_error_mm = 3.0",
            "max_expected_position_error_mm = 0.0",
        ));
        assert_eq!(key, "validation.max_expected_position_error_mm");
        let (key, _, _) = invalid(&edited(
            "max_expected_rotation_error_mrad = 10.0",
            "max_expected_rotation_error_mrad = inf",
        ));
        assert_eq!(key, "validation.max_expected_rotation_error_mrad");
    }

    #[test]
    fn node_ids_must_be_distinct_and_in_range() {
        let (key, _, m) = invalid(&edited(
            "joints = [1, 2, 3, 4, 5, 6, 7]",
            "joints = [1, 2, 3, 4, 5, 6, 6]",
        ));
        assert_eq!(key, "nodes.joints[6]");
        assert!(m.contains("twice"));
        let (key, _, _) = invalid(&edited(
            "joints = [1, 2, 3, 4, 5, 6, 7]",
            "joints = [0, 2, 3, 4, 5, 6, 7]",
        ));
        assert_eq!(key, "nodes.joints[0]");
        let (key, _, _) = invalid(&edited(
            "joints = [1, 2, 3, 4, 5, 6, 7]",
            "joints = [1, 2, 3, 4, 5, 6, 8]",
        ));
        assert_eq!(key, "nodes.joints[6]");
        let (key, _, _) = invalid(&edited(
            "joints = [1, 2, 3, 4, 5, 6, 7]",
            "joints = [1, 2, 3, 4, 5, 6, 300]",
        ));
        assert_eq!(key, "nodes.joints[6]");
    }

    #[test]
    fn interface_names_are_checked() {
        let (key, line, _) = invalid(&edited(
            "interface = \"can0\"",
            "interface = \"a-name-far-too-long\"",
        ));
        assert_eq!(key, "can.interface");
        assert!(line.is_some());
    }

    #[test]
    fn flush_interval_is_at_most_a_second() {
        let (key, _, _) = invalid(&edited("flush_interval_s = 0.5", "flush_interval_s = 2.0"));
        assert_eq!(key, "output.flush_interval_s");
    }

    #[test]
    fn push_backoff_is_checked_and_capped() {
        let (key, _, _) = invalid(&edited("backoff_max_ms = 2000", "backoff_max_ms = 50"));
        assert_eq!(key, "push.backoff_max_ms");
        let p = Config::default_config().push;
        assert_eq!(
            [1, 2, 3, 4, 5, 6, 60].map(|r| p.backoff_ms(r)),
            [100, 200, 400, 800, 1600, 2000, 2000]
        );
    }

    /// A window longer than the memory budget allows (1,800 s needs about 511 MiB, twice
    /// `MemoryMax=256M`) is refused, naming the key, the limit and why; so is one
    /// within it whose faster grid holds more points than the budget was measured at.
    #[test]
    fn a_session_longer_than_the_memory_budget_is_refused() {
        let text = edited("max_duration_s = 180.0", "max_duration_s = 1800.0");
        let (key, line, message) = invalid(&text);
        assert_eq!(key, "session.max_duration_s");
        assert_eq!(line, Some(line_containing(&text, "max_duration_s =")));
        assert!(
            message.contains("1800 s is above the limit 360 s")
                && message.contains("MemoryMax=256M"),
            "{message}"
        );
        let text = edited("grid_hz = 100.0", "grid_hz = 500.0");
        let (key, _, message) = invalid(&text);
        assert_eq!(key, "session.max_duration_s");
        assert!(
            message.contains(
                "180 s at session.grid_hz = 500 Hz is 90000 grid points, above the limit 18000 \
                 with session.stop_at_expected_error"
            ),
            "{message}"
        );
        // Stopping when good enough, the estimates' copies halve the budget: 360 s is refused
        // with it and accepted without it.
        let (key, _, message) =
            invalid(&edited("max_duration_s = 180.0", "max_duration_s = 360.0"));
        assert_eq!(key, "session.max_duration_s");
        assert!(message.contains("above the limit 18000"), "{message}");
        let fixed = edited(
            "stop_at_expected_error = [2.0, 6.0]",
            "# stop_at_expected_error = [2.0, 6.0]",
        );
        let text = edited_in(&fixed, "grid_hz = 100.0", "grid_hz = 500.0");
        let (_, _, message) = invalid(&text);
        assert!(
            message.contains(
                "180 s at session.grid_hz = 500 Hz is 90000 grid points, above the limit 36000:"
            ),
            "{message}"
        );
        // At the limit, and a faster grid over a shorter window, are accepted.
        let at = edited_in(&fixed, "max_duration_s = 180.0", "max_duration_s = 360.0");
        assert_eq!(
            Config::parse(&at)
                .unwrap()
                .calibration
                .window
                .max_duration_s,
            360.0
        );
        let fast = edited_in(
            &edited("grid_hz = 100.0", "grid_hz = 500.0"),
            "max_duration_s = 180.0",
            "max_duration_s = 36.0",
        );
        assert!(Config::parse(&fast).is_ok());
    }

    /// Every numeric key has an upper bound: just past it, the key is named with its line.
    #[test]
    fn every_numeric_key_has_an_upper_bound() {
        let cases = [
            (
                "min_duration_s = 20.0",
                "min_duration_s = 90000.0",
                "session.min_duration_s",
            ),
            (
                "max_duration_s = 180.0",
                "max_duration_s = 361.0",
                "session.max_duration_s",
            ),
            ("grid_hz = 100.0", "grid_hz = 1e12", "session.grid_hz"),
            ("max_gap_s = 0.05", "max_gap_s = 11.0", "session.max_gap_s"),
            (
                "min_samples = 1000",
                "min_samples = 18001",
                "session.min_samples",
            ),
            (
                "max_condition_number = 1.0e4",
                "max_condition_number = 1.0e13",
                "validation.max_condition_number",
            ),
            ("retries = 3", "retries = 4294967295", "push.retries"),
            (
                "timeout_ms = 500",
                "timeout_ms = 9223372036854775807",
                "push.timeout_ms",
            ),
            (
                "backoff_max_ms = 2000",
                "backoff_max_ms = 600001",
                "push.backoff_max_ms",
            ),
            (
                "backoff_initial_ms = 100",
                "backoff_initial_ms = 600001",
                "push.backoff_initial_ms",
            ),
            (
                "alpha_deviation_deg = 10.0",
                "alpha_deviation_deg = 181.0",
                "bounds.alpha_deviation_deg",
            ),
            (
                "offset_deviation_deg = 15.0",
                "offset_deviation_deg = 1e300",
                "bounds.offset_deviation_deg",
            ),
            (
                "joint_range_deg = [[-90.0, 90.0],",
                "joint_range_deg = [[-90.0, 361.0],",
                "bounds.joint_range_deg[0]",
            ),
            (
                "max_expected_position_error_mm = 3.0",
                "max_expected_position_error_mm = 1e9",
                "validation.max_expected_position_error_mm",
            ),
            (
                "max_expected_rotation_error_mrad = 10.0",
                "max_expected_rotation_error_mrad = 1000.5",
                "validation.max_expected_rotation_error_mrad",
            ),
            (
                "cooldown_s = 300.0",
                "cooldown_s = 1e30",
                "trigger.cooldown_s",
            ),
            (
                "a          = [0.04, 0.04, 0.431",
                "a          = [1e300, 0.04, 0.431",
                "nominal.a[0]",
            ),
            (
                "flush_interval_s = 0.5",
                "flush_interval_s = 1e20",
                "output.flush_interval_s",
            ),
            (
                "joints = [1, 2, 3, 4, 5, 6, 7]",
                "joints = [1, 2, 3, 4, 5, 6, 200]",
                "nodes.joints[6]",
            ),
        ];
        for (from, to, want) in cases {
            let text = edited(from, to);
            let (key, line, message) = invalid(&text);
            assert_eq!(key, want, "{to}: {message}");
            assert!(
                [
                    "limit",
                    "never",
                    "outside bounds",
                    "at most 1 s",
                    "joint nodes are"
                ]
                .iter()
                .any(|m| message.contains(m)),
                "{message}"
            );
            let needle = to.split(" = ").next().unwrap();
            assert_eq!(
                line,
                Some(line_containing(&text, &format!("{needle} ="))),
                "{to}"
            );
        }
        // At the limits themselves the file is valid (the fastest grid over a window short
        // enough for the memory budget).
        let at = edited("grid_hz = 100.0", "grid_hz = 1000.0");
        let at = at.replace("max_duration_s = 180.0", "max_duration_s = 18.0");
        let at = at.replace("min_duration_s = 20.0", "min_duration_s = 15.0");
        let at = at.replace("retries = 3", "retries = 100");
        let at = at.replace("timeout_ms = 500", "timeout_ms = 60000");
        assert!(Config::parse(&at).is_ok());
    }

    #[test]
    fn display_names_file_line_and_key() {
        let dir = std::env::temp_dir().join(format!("exocald-config-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("bad.toml");
        let text = edited("grid_hz = 100.0", "grid_hz = 100.0\ngrid_hertz = 50.0");
        std::fs::write(&path, &text).unwrap();
        let e = Config::load(&path).unwrap_err();
        let shown = e.to_string();
        let line = line_containing(&text, "grid_hertz");
        assert!(
            shown.starts_with(&format!(
                "{}:{line}: key `session.grid_hertz`",
                path.display()
            )),
            "{shown}"
        );
        std::fs::remove_dir_all(&dir).unwrap();
        let missing = Config::load(&dir.join("none.toml")).unwrap_err();
        assert!(matches!(missing, ConfigError::Io { .. }));
        assert!(missing.to_string().contains("none.toml"));
    }
}
