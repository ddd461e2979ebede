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

use serde::Deserialize;
use toml::de::{DeTable, DeValue};

/// Number of joints (and of D-H rows) of the exoskeleton.
pub const JOINTS: usize = 7;

/// The configuration shipped with the daemon (`daemon/exocald.toml`).
pub const DEFAULT_TOML: &str = include_str!("../exocald.toml");

/// One row of a D-H table, SI units (metres, radians).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DhRow {
    /// Link length a_i (m).
    pub a: f64,
    /// Link twist α_i (rad).
    pub alpha: f64,
    /// Link offset d_i (m).
    pub d: f64,
    /// Joint angle offset added to the measured angle θ_i (rad).
    pub offset: f64,
}

/// A closed interval `[min, max]`, `min < max`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Interval {
    pub min: f64,
    pub max: f64,
}

impl Interval {
    /// Whether `x` lies in the interval (bounds included).
    pub fn contains(&self, x: f64) -> bool {
        self.min <= x && x <= self.max
    }

    /// `max - min`.
    pub fn width(&self) -> f64 {
        self.max - self.min
    }
}

/// Anatomical bounds a table must respect to be pushed.
#[derive(Debug, Clone, PartialEq)]
pub struct Bounds {
    /// Allowed a_i (m).
    pub a: [Interval; JOINTS],
    /// Allowed d_i (m).
    pub d: [Interval; JOINTS],
    /// Largest |α_i − nominal α_i| (rad).
    pub alpha_deviation: f64,
    /// Largest |offset_i − nominal offset_i| (rad).
    pub offset_deviation: f64,
    /// Anatomical rotation range of each joint (rad).
    pub joint_range: [Interval; JOINTS],
}

/// Collection window rules.
#[derive(Debug, Clone, PartialEq)]
pub struct SessionRules {
    pub min_duration_s: f64,
    pub max_duration_s: f64,
    /// Fraction (0, 1] of each joint's range the motion must visit.
    pub excitation_required: f64,
    pub min_samples: usize,
    pub grid_hz: f64,
    pub max_gap_s: f64,
}

/// What a calibration must satisfy to be pushed.
#[derive(Debug, Clone, PartialEq)]
pub struct ValidationRules {
    pub max_condition_number: f64,
    /// Fraction (0, 1) of the session, at its end, kept out of the fit.
    pub holdout_fraction: f64,
    /// Required relative drop (0, 1] of held-out pose error versus the nominal table.
    pub min_improvement: f64,
}

/// Where and how the MCAP log is written.
#[derive(Debug, Clone, PartialEq)]
pub struct OutputConfig {
    pub directory: PathBuf,
    /// Longest time (s, ≤ 1) between two chunk flushes.
    pub flush_interval_s: f64,
}

/// Table push policy.
#[derive(Debug, Clone, PartialEq)]
pub struct PushPolicy {
    /// Attempts after the first one.
    pub retries: u32,
    pub backoff_initial_ms: u64,
    pub backoff_max_ms: u64,
    pub timeout_ms: u64,
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

/// The validated configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct Config {
    pub interface: String,
    /// CAN node id of the node on joint `i + 1`.
    pub joint_nodes: [u8; JOINTS],
    pub nominal: [DhRow; JOINTS],
    pub bounds: Bounds,
    pub session: SessionRules,
    pub validation: ValidationRules,
    pub output: OutputConfig,
    pub push: PushPolicy,
}

/// A configuration error: which key, on which line, what is wrong.
#[derive(Debug)]
pub enum ConfigError {
    /// The file could not be read.
    Io {
        path: PathBuf,
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
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCan {
    interface: String,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawNodes {
    joints: [u8; JOINTS],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawNominal {
    a: [f64; JOINTS],
    alpha_deg: [f64; JOINTS],
    d: [f64; JOINTS],
    offset_deg: [f64; JOINTS],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawBounds {
    a: [Pair; JOINTS],
    d: [Pair; JOINTS],
    alpha_deviation_deg: f64,
    offset_deviation_deg: f64,
    joint_range_deg: [Pair; JOINTS],
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
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawValidation {
    max_condition_number: f64,
    holdout_fraction: f64,
    min_improvement: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawOutput {
    directory: PathBuf,
    flush_interval_s: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawPush {
    retries: u32,
    backoff_initial_ms: u64,
    backoff_max_ms: u64,
    timeout_ms: u64,
}

// ---- parsing ----------------------------------------------------------------------------------

impl Config {
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

    fn intervals(
        &self,
        key: &str,
        pairs: &[Pair; JOINTS],
        scale: f64,
    ) -> Result<[Interval; JOINTS], ConfigError> {
        let mut out = [Interval { min: 0.0, max: 0.0 }; JOINTS];
        for (i, [lo, hi]) in pairs.iter().copied().enumerate() {
            let k = format!("{key}[{i}]");
            self.finite(&k, lo)?;
            self.finite(&k, hi)?;
            if lo >= hi {
                return Err(self.err(k, format!("min {lo} must be below max {hi}")));
            }
            out[i] = Interval {
                min: lo * scale,
                max: hi * scale,
            };
        }
        Ok(out)
    }

    fn build(&self, raw: RawConfig) -> Result<Config, ConfigError> {
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

        let joint_nodes = raw.nodes.joints;
        for (i, &id) in joint_nodes.iter().enumerate() {
            if !(1..=JOINTS as u8).contains(&id) {
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
        let mut nominal = [DhRow {
            a: 0.0,
            alpha: 0.0,
            d: 0.0,
            offset: 0.0,
        }; JOINTS];
        for (i, row) in nominal.iter_mut().enumerate() {
            *row = DhRow {
                a: self.finite(&format!("nominal.a[{i}]"), n.a[i])?,
                alpha: self.finite(&format!("nominal.alpha_deg[{i}]"), n.alpha_deg[i])? * deg,
                d: self.finite(&format!("nominal.d[{i}]"), n.d[i])?,
                offset: self.finite(&format!("nominal.offset_deg[{i}]"), n.offset_deg[i])? * deg,
            };
        }

        let b = &raw.bounds;
        let bounds = Bounds {
            a: self.intervals("bounds.a", &b.a, 1.0)?,
            d: self.intervals("bounds.d", &b.d, 1.0)?,
            alpha_deviation: self.positive("bounds.alpha_deviation_deg", b.alpha_deviation_deg)?
                * deg,
            offset_deviation: self
                .positive("bounds.offset_deviation_deg", b.offset_deviation_deg)?
                * deg,
            joint_range: self.intervals("bounds.joint_range_deg", &b.joint_range_deg, deg)?,
        };
        for (i, row) in nominal.iter().enumerate() {
            if !bounds.a[i].contains(row.a) {
                return Err(self.err(
                    format!("nominal.a[{i}]"),
                    format!("{} is outside bounds.a[{i}]", row.a),
                ));
            }
            if !bounds.d[i].contains(row.d) {
                return Err(self.err(
                    format!("nominal.d[{i}]"),
                    format!("{} is outside bounds.d[{i}]", row.d),
                ));
            }
        }

        let s = &raw.session;
        let session = SessionRules {
            min_duration_s: self.positive("session.min_duration_s", s.min_duration_s)?,
            max_duration_s: self.positive("session.max_duration_s", s.max_duration_s)?,
            excitation_required: self.fraction(
                "session.excitation_required",
                s.excitation_required,
                true,
            )?,
            min_samples: s.min_samples,
            grid_hz: self.positive("session.grid_hz", s.grid_hz)?,
            max_gap_s: self.positive("session.max_gap_s", s.max_gap_s)?,
        };
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
            max_condition_number: self
                .positive("validation.max_condition_number", v.max_condition_number)?,
            holdout_fraction: self.fraction(
                "validation.holdout_fraction",
                v.holdout_fraction,
                false,
            )?,
            min_improvement: self.fraction(
                "validation.min_improvement",
                v.min_improvement,
                true,
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
        if p.backoff_initial_ms == 0 {
            return Err(self.err("push.backoff_initial_ms", "must be at least 1"));
        }
        if p.backoff_max_ms < p.backoff_initial_ms {
            return Err(self.err(
                "push.backoff_max_ms",
                format!(
                    "{} is below push.backoff_initial_ms = {}",
                    p.backoff_max_ms, p.backoff_initial_ms
                ),
            ));
        }
        if p.timeout_ms == 0 {
            return Err(self.err("push.timeout_ms", "must be at least 1"));
        }
        let push = PushPolicy {
            retries: p.retries,
            backoff_initial_ms: p.backoff_initial_ms,
            backoff_max_ms: p.backoff_max_ms,
            timeout_ms: p.timeout_ms,
        };

        Ok(Config {
            interface,
            joint_nodes,
            nominal,
            bounds,
            session,
            validation,
            output,
            push,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The default text with `from` replaced by `to` (which must occur exactly once).
    fn edited(from: &str, to: &str) -> String {
        assert_eq!(DEFAULT_TOML.matches(from).count(), 1, "`{from}` not unique");
        DEFAULT_TOML.replace(from, to)
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
        assert_eq!(c.joint_nodes, [1, 2, 3, 4, 5, 6, 7]);
        let a: Vec<f64> = c.nominal.iter().map(|r| r.a).collect();
        assert_eq!(a, [0.04, 0.04, 0.431, 0.244, 0.0, 0.0, 0.0]);
        assert!((c.nominal[0].alpha + std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        assert!((c.nominal[1].offset - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        assert_eq!(
            c.bounds.a[2],
            Interval {
                min: 0.377,
                max: 0.485
            }
        );
        assert!((c.bounds.joint_range[4].min + 20f64.to_radians()).abs() < 1e-12);
        assert_eq!(c.push.retries, 3);
        assert_eq!(Config::default_config(), c);
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

    #[test]
    fn a_missing_key_is_named() {
        let text = edited("retries = 3\n", "");
        let (key, _, message) = invalid(&text);
        assert!(key == "push" || key == "push.retries", "{key}");
        assert!(message.contains("retries"), "{message}");
    }

    #[test]
    fn a_wrong_type_is_named_with_its_line() {
        let text = edited("min_duration_s = 60.0", "min_duration_s = \"sixty\"");
        let (key, line, _) = invalid(&text);
        assert_eq!(key, "session.min_duration_s");
        assert_eq!(line, Some(line_containing(&text, "min_duration_s =")));
    }

    #[test]
    fn a_short_array_is_named() {
        let text = edited(
            "joints = [1, 2, 3, 4, 5, 6, 7]",
            "joints = [1, 2, 3, 4, 5, 6]",
        );
        let (key, line, message) = invalid(&text);
        assert_eq!(key, "nodes.joints");
        assert_eq!(line, Some(line_containing(&text, "joints = [")));
        assert!(message.contains("length"), "{message}");
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
            (
                "min_improvement = 0.5",
                "min_improvement = 0.0",
                "validation.min_improvement",
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
