//! Generates the protocol tables from `exocal.dbc` into `$OUT_DIR/spec.rs`, which `src/lib.rs`
//! includes as the module `spec` (as `log/build.rs` generates the log's schema from its proto).
//!
//! A DBC message named `<Family>_<Node>`, `<Node>` one of the `BU_` nodes, is one instance of a
//! message family whose identifier is `base | node`, the node's id being its index in `BU_`
//! (Controller 0, Joint1 1, …). Every instance of a family is the same message but for the node:
//! same DLC, signals, `VAL_` tables and comments (the node's name aside). Any other name is a
//! family of one message without a node. The build fails, naming the message and signal, when
//! the DBC breaks these rules (identifiers unique too) or needs what the codec does not do:
//! extended identifiers, a DLC other than 8, big-endian signals, nested multiplexing, a switch
//! wider than 8 bits, a `[min|max]` its bits cannot hold, names that are not `CamelCase`.
//!
//! Per family it writes a `Kind` variant, a `MessageSpec` static (`JOINT_STATE`), a module of
//! `SignalSpec` constants (`joint_state::ANGLE`) and, per signal with a `VAL_` table, a module
//! of its named raw values (`heartbeat::state::OPERATIONAL`). A `VAL_` entry named `Invalid` is
//! the signal's invalid marker (NaN) instead. The DBC's comments become the doc comments.

use can_dbc::{ByteOrder, Dbc, Message, MessageId, MultiplexIndicator, NumericValue, ValueType};
use std::fmt::{self, Write as _};

/// The `VAL_` name that marks a raw value as invalid (decoded as NaN).
const INVALID: &str = "Invalid";

fn main() {
    println!("cargo:rerun-if-changed=exocal.dbc");
    let text = std::fs::read_to_string("exocal.dbc").expect("read exocal.dbc");
    let dbc =
        Dbc::try_from(text.as_str()).unwrap_or_else(|e| panic!("exocal.dbc does not parse: {e}"));
    let families = families(&dbc).unwrap_or_else(|e| panic!("exocal.dbc: {e}"));
    let nodes: Vec<&str> = dbc.nodes.iter().map(|n| n.0.as_str()).collect();
    let code = render(&nodes, &families).expect("writing to a String");
    let out = std::path::PathBuf::from(std::env::var_os("OUT_DIR").expect("OUT_DIR"));
    std::fs::write(out.join("spec.rs"), code).expect("write spec.rs");
}

/// One message family, as the generated `MessageSpec` and its signal module hold it.
struct Family {
    name: String,
    base: u16,
    /// Node ids of its instances; empty for a family without nodes.
    nodes: Vec<u8>,
    comment: String,
    signals: Vec<Signal>,
}

#[derive(PartialEq)]
struct Signal {
    spec: SignalSpec,
    comment: String,
}

/// The generated `SignalSpec`, field for field: its `Debug` output is the Rust literal.
#[derive(Debug, PartialEq)]
struct SignalSpec {
    name: String,
    start: u64,
    len: u64,
    signed: bool,
    factor: f64,
    offset: f64,
    min: f64,
    max: f64,
    unit: String,
    mux: MuxRole,
    invalid_raw: Option<i64>,
    values: Values,
}

#[derive(Clone, Copy, PartialEq)]
enum MuxRole {
    Plain,
    Switch,
    Case(u64),
}

impl fmt::Debug for MuxRole {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            MuxRole::Plain => f.write_str("MuxRole::Plain"),
            MuxRole::Switch => f.write_str("MuxRole::Switch"),
            MuxRole::Case(v) => write!(f, "MuxRole::Case({v})"),
        }
    }
}

/// The named raw values of a signal's `VAL_` table (the invalid marker aside).
#[derive(PartialEq)]
struct Values(Vec<(i64, String)>);

impl fmt::Debug for Values {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "&{:?}", self.0)
    }
}

/// Groups the DBC's messages into families, checking the rules of the module docs.
fn families(dbc: &Dbc) -> Result<Vec<Family>, String> {
    let nodes: Vec<&str> = dbc.nodes.iter().map(|n| n.0.as_str()).collect();
    let mut families: Vec<Family> = Vec::new();
    for m in &dbc.messages {
        let MessageId::Standard(id) = m.id else {
            return Err(format!("{}: extended identifier", m.name));
        };
        if id >= 0x800 || m.size != 8 {
            return Err(format!("{}: not 11 bits and 8 bytes", m.name));
        }
        if dbc.messages.iter().filter(|other| other.id == m.id).count() > 1 {
            return Err(format!("{}: identifier {id:#x} not unique", m.name));
        }
        let by_node = m.name.rsplit_once('_').and_then(|(family, node)| {
            Some((family, nodes.iter().position(|n| *n == node)? as u8, node))
        });
        let (name, base, node) = match by_node {
            Some((family, node, node_name)) if u16::from(node) == id & 0xF => {
                (family, id & !0xF, Some((node, node_name)))
            }
            Some((_, node, _)) => return Err(format!("{}: node id {node} not in its id", m.name)),
            None => (m.name.as_str(), id, None),
        };
        ident(name)?;
        // The comments with the node's name in place of `<node>`.
        let generic = |text: &str| match node {
            Some((_, node_name)) => text.replace(node_name, "`<node>`"),
            None => text.to_string(),
        };
        let mut signals = Vec::new();
        for s in &m.signals {
            let spec = signal(dbc, m, s).map_err(|e| format!("{}.{}: {e}", m.name, s.name))?;
            let comment = generic(dbc.signal_comment(m.id, &s.name).unwrap_or(""));
            signals.push(Signal { spec, comment });
        }
        let switches = signals
            .iter()
            .filter(|s| s.spec.mux == MuxRole::Switch)
            .count();
        let cases = signals
            .iter()
            .any(|s| matches!(s.spec.mux, MuxRole::Case(_)));
        if switches > 1 || (cases && switches == 0) {
            return Err(format!("{}: one multiplexer switch expected", m.name));
        }
        let comment = generic(dbc.message_comment(m.id).unwrap_or(""));
        match families.iter_mut().find(|f| f.name == name) {
            None => families.push(Family {
                name: name.to_string(),
                base,
                nodes: node.map(|(n, _)| n).into_iter().collect(),
                comment,
                signals,
            }),
            Some(f) if f.base != base || f.nodes.is_empty() != node.is_none() => {
                return Err(format!("{}: identifier differs from {}'s", m.name, f.name))
            }
            Some(f) if f.comment != comment || f.signals != signals => {
                return Err(format!(
                    "{}: differs from {}'s other messages beyond the node name \
                     (layout, VAL_ or comments)",
                    m.name, f.name
                ))
            }
            Some(f) => f.nodes.extend(node.map(|(n, _)| n)),
        }
    }
    Ok(families)
}

fn signal(dbc: &Dbc, m: &Message, s: &can_dbc::Signal) -> Result<SignalSpec, String> {
    ident(&s.name)?;
    if s.byte_order != ByteOrder::LittleEndian {
        return Err("big-endian signals are not supported".into());
    }
    if s.size == 0 || s.start_bit + s.size > 64 {
        return Err("does not fit 8 bytes".into());
    }
    let signed = s.value_type == ValueType::Signed;
    let mux = match s.multiplexer_indicator {
        MultiplexIndicator::Plain => MuxRole::Plain,
        MultiplexIndicator::Multiplexor if s.size <= 8 && !signed => MuxRole::Switch,
        MultiplexIndicator::MultiplexedSignal(v) if v <= 255 => MuxRole::Case(v),
        other => return Err(format!("unsupported multiplexing {other:?}")),
    };
    let num = |v: NumericValue| match v {
        NumericValue::Uint(u) => u as f64,
        NumericValue::Int(i) => i as f64,
        NumericValue::Double(d) => d,
    };
    let (min, max) = (num(s.min), num(s.max));
    if !(s.factor.is_finite() && s.factor != 0.0 && s.offset.is_finite() && min <= max) {
        return Err("factor, offset or [min|max] unusable".into());
    }
    // The raw range the codec derives (`SignalSpec::raw_bounds`) must fit the bits.
    let (bit_lo, bit_hi) = if signed {
        (-(1i128 << (s.size - 1)), (1i128 << (s.size - 1)) - 1)
    } else {
        (0, (1i128 << s.size) - 1)
    };
    let fits = |raw: i128| raw >= bit_lo && raw <= bit_hi;
    let raw = |phys: f64| ((phys - s.offset) / s.factor).round() as i128;
    if !fits(raw(min)) || !fits(raw(max)) {
        return Err(format!("[{min}|{max}] needs more than {} bits", s.size));
    }
    let mut invalid_raw = None;
    let mut values = Vec::new();
    for v in dbc
        .value_descriptions_for_signal(m.id, &s.name)
        .unwrap_or(&[])
    {
        if !fits(i128::from(v.id)) {
            return Err(format!("VAL_ {} does not fit {} bits", v.id, s.size));
        }
        if v.description == INVALID {
            invalid_raw = Some(v.id);
        } else {
            ident(&v.description)?;
            values.push((v.id, v.description.clone()));
        }
    }
    Ok(SignalSpec {
        name: s.name.clone(),
        start: s.start_bit,
        len: s.size,
        signed,
        factor: s.factor,
        offset: s.offset,
        min,
        max,
        unit: s.unit.clone(),
        mux,
        invalid_raw,
        values: Values(values),
    })
}

/// The generated source.
fn render(nodes: &[&str], families: &[Family]) -> Result<String, fmt::Error> {
    let mut out = String::new();
    let o = &mut out;
    writeln!(
        o,
        "// Generated by dbc/build.rs from exocal.dbc: edit the DBC, not this file.\n"
    )?;
    doc(
        o,
        "",
        "The message families of `exocal.dbc`, one per [`MessageSpec`].",
    )?;
    writeln!(
        o,
        "#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]\npub enum Kind {{"
    )?;
    for f in families {
        doc(o, "    ", &format!("{}.", title(f)))?;
        writeln!(o, "    {},", f.name)?;
    }
    writeln!(o, "}}\n\nimpl Kind {{")?;
    doc(o, "    ", "The family's layout.")?;
    writeln!(
        o,
        "    pub const fn spec(self) -> &'static MessageSpec {{\n        match self {{"
    )?;
    for f in families {
        writeln!(o, "            Kind::{} => &{},", f.name, upper(&f.name))?;
    }
    writeln!(o, "        }}\n    }}\n}}\n")?;
    doc(o, "", "DBC node names (`BU_`) by node id.")?;
    writeln!(
        o,
        "pub const NODE_NAMES: [&str; {}] = {nodes:?};\n",
        nodes.len()
    )?;
    doc(o, "", "Every frame is 8 bytes.")?;
    writeln!(o, "pub const DLC: u8 = 8;\n")?;

    for f in families {
        let module = snake(&f.name);
        let id = if f.nodes.is_empty() {
            format!("identifier `{:#05x}`", f.base)
        } else {
            let nodes: Vec<String> = f.nodes.iter().map(u8::to_string).collect();
            format!(
                "identifier `{:#05x} | node`, nodes {}",
                f.base,
                nodes.join(", ")
            )
        };
        doc(o, "", &format!("{} ({id}): {}", title(f), f.comment))?;
        let signals: Vec<String> = f
            .signals
            .iter()
            .map(|s| format!("{module}::{}", upper(&s.spec.name)))
            .collect();
        writeln!(
            o,
            "pub static {}: MessageSpec = MessageSpec {{ kind: Kind::{}, name: {:?}, \
             base_id: {:#05x}, nodes: &{:?}, signals: &[{}] }};\n",
            upper(&f.name),
            f.name,
            f.name,
            f.base,
            f.nodes,
            signals.join(", ")
        )?;
        doc(o, "", &format!("The signals of {}.", title(f)))?;
        writeln!(
            o,
            "pub mod {module} {{\n    use super::{{MuxRole, SignalSpec}};"
        )?;
        for s in &f.signals {
            signal_const(o, s)?;
        }
        writeln!(o, "}}\n")?;
    }
    doc(o, "", "Every message family, in DBC order.")?;
    let all: Vec<String> = families
        .iter()
        .map(|f| format!("&{}", upper(&f.name)))
        .collect();
    writeln!(
        o,
        "pub static ALL: [&MessageSpec; {}] = [{}];",
        all.len(),
        all.join(", ")
    )?;
    Ok(out)
}

/// A `SignalSpec` constant, documented with the DBC comment and its layout, and the module of
/// its named values.
fn signal_const(o: &mut String, s: &Signal) -> fmt::Result {
    let spec = &s.spec;
    let mut about = format!(
        "Bits {}..{}, {}, factor {:?}, offset {:?}, from {:?} to {:?}",
        spec.start,
        spec.start + spec.len,
        if spec.signed { "signed" } else { "unsigned" },
        spec.factor,
        spec.offset,
        spec.min,
        spec.max,
    );
    if !spec.unit.is_empty() {
        write!(about, " {}", spec.unit)?;
    }
    match spec.mux {
        MuxRole::Plain => {}
        MuxRole::Switch => about.push_str("; the multiplexer switch"),
        MuxRole::Case(v) => write!(about, "; only when the switch is {v}")?,
    }
    if let Some(raw) = spec.invalid_raw {
        write!(about, "; raw {raw} is invalid (NaN)")?;
    }
    let comment = match s.comment.as_str() {
        "" => format!("`{}`.", spec.name),
        text => text.to_string(),
    };
    doc(o, "    ", &format!("{comment}\n\n{about}."))?;
    writeln!(
        o,
        "    pub const {}: SignalSpec = {spec:?};",
        upper(&spec.name)
    )?;
    if !spec.values.0.is_empty() {
        let bits = [8, 16, 32, 64]
            .into_iter()
            .find(|b| spec.len <= *b)
            .unwrap_or(64);
        let ty = format!("{}{bits}", if spec.signed { 'i' } else { 'u' });
        doc(
            o,
            "    ",
            &format!("The named raw values of `{}` (`VAL_`).", spec.name),
        )?;
        writeln!(o, "    pub mod {} {{", snake(&spec.name))?;
        for (raw, name) in &spec.values.0 {
            doc(o, "        ", &format!("`{name}`."))?;
            writeln!(o, "        pub const {}: {ty} = {raw};", upper(name))?;
        }
        writeln!(o, "    }}")?;
    }
    Ok(())
}

/// `JointState_<node>` or `Trigger`, for the docs.
fn title(f: &Family) -> String {
    if f.nodes.is_empty() {
        format!("`{}`", f.name)
    } else {
        format!("`{}_<node>`", f.name)
    }
}

/// Refuses a name that is not a `CamelCase` identifier.
fn ident(name: &str) -> Result<(), String> {
    let mut chars = name.chars();
    if chars.next().is_some_and(|c| c.is_ascii_uppercase())
        && chars.all(|c| c.is_ascii_alphanumeric())
    {
        Ok(())
    } else {
        Err(format!("`{name}` is not a CamelCase identifier"))
    }
}

/// `CamelCase` → `snake_case` (`PosYZ` → `pos_yz`, `TimestampLo` → `timestamp_lo`).
fn snake(name: &str) -> String {
    let chars: Vec<char> = name.chars().collect();
    let mut out = String::new();
    for (i, &c) in chars.iter().enumerate() {
        let prev = if i > 0 { chars[i - 1] } else { ' ' };
        let next_lower = chars.get(i + 1).is_some_and(|n| n.is_ascii_lowercase());
        if c.is_ascii_uppercase()
            && (prev.is_ascii_lowercase()
                || prev.is_ascii_digit()
                || (prev.is_ascii_uppercase() && next_lower))
        {
            out.push('_');
        }
        out.push(c.to_ascii_lowercase());
    }
    out
}

/// `CamelCase` → `UPPER_SNAKE_CASE`.
fn upper(name: &str) -> String {
    snake(name).to_uppercase()
}

/// `text` as `#[doc]` attributes (escaped as Rust strings), one per line.
fn doc(o: &mut String, indent: &str, text: &str) -> fmt::Result {
    for line in text.lines() {
        writeln!(o, "{indent}#[doc = {:?}]", format!(" {line}"))?;
    }
    Ok(())
}
