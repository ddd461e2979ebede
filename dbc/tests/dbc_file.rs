//! The codec against `exocal.dbc` as `can-dbc` reads it, with frames packed here bit by bit
//! (not by the crate's codec): every message, every multiplexer value and every enumerated value
//! the DBC defines decodes and re-encodes to the same bytes; every signal refuses, by name, the
//! raw values outside its range and its `VAL_` table; every identifier the DBC does not define is
//! unknown. Also the DBC's own conventions (node id in the low bits, comments everywhere).
//!
//! That the generated tables hold what the DBC says is checked against an independent parser,
//! cantools, in `tests/cantools.rs`.

use can_dbc::{Comment, Dbc, Message, MessageId, MultiplexIndicator, NumericValue, ValueType};
use exocal_dbc::spec::NODE_NAMES;
use exocal_dbc::{decode, DecodeError, DBC};

/// One signal as this test reads the DBC.
struct Sig {
    name: String,
    start: u64,
    len: u64,
    /// Switch, plain (`None`) or the switch value it needs.
    case: Option<Option<i64>>,
    /// Raw range from `[min|max]`.
    lo: i64,
    hi: i64,
    /// Raw range of the bits.
    bit_lo: i64,
    bit_hi: i64,
    invalid: Option<i64>,
    values: Vec<i64>,
}

fn signals(dbc: &Dbc, m: &Message) -> Vec<Sig> {
    m.signals
        .iter()
        .map(|s| {
            let num = |v: NumericValue| match v {
                NumericValue::Uint(u) => u as f64,
                NumericValue::Int(i) => i as f64,
                NumericValue::Double(d) => d,
            };
            let raw = |v| ((num(v) - s.offset) / s.factor).round() as i64;
            let signed = s.value_type == ValueType::Signed;
            let (bit_lo, bit_hi) = if signed {
                (-(1i64 << (s.size - 1)), (1i64 << (s.size - 1)) - 1)
            } else {
                (0, ((1u64 << s.size) - 1) as i64)
            };
            let vals = dbc
                .value_descriptions_for_signal(m.id, &s.name)
                .unwrap_or(&[]);
            Sig {
                name: s.name.clone(),
                start: s.start_bit,
                len: s.size,
                case: match s.multiplexer_indicator {
                    MultiplexIndicator::Multiplexor => None,
                    MultiplexIndicator::Plain => Some(None),
                    MultiplexIndicator::MultiplexedSignal(v) => Some(Some(v as i64)),
                    other => panic!("{}.{}: {other:?}", m.name, s.name),
                },
                lo: raw(s.min),
                hi: raw(s.max),
                bit_lo,
                bit_hi,
                invalid: vals
                    .iter()
                    .find(|v| v.description == "Invalid")
                    .map(|v| v.id),
                values: vals
                    .iter()
                    .filter(|v| v.description != "Invalid")
                    .map(|v| v.id)
                    .collect(),
            }
        })
        .collect()
}

/// Writes `raw` into the little-endian payload word.
fn put(word: &mut u64, s: &Sig, raw: i64) {
    let mask = if s.len == 64 {
        u64::MAX
    } else {
        (1 << s.len) - 1
    };
    *word = (*word & !(mask << s.start)) | ((raw as u64 & mask) << s.start);
}

fn id_of(m: &Message) -> u16 {
    match m.id {
        MessageId::Standard(id) => id,
        MessageId::Extended(_) => panic!("{} is extended", m.name),
    }
}

/// Every switch value of a message (`[None]` without a switch).
fn switch_values(sigs: &[Sig]) -> Vec<Option<i64>> {
    match sigs.iter().find(|s| s.case.is_none()) {
        None => vec![None],
        Some(s) if s.values.is_empty() => (s.lo..=s.hi).map(Some).collect(),
        Some(s) => s.values.iter().copied().map(Some).collect(),
    }
}

/// Does a frame with this switch value carry `s` (the switch itself excluded)?
fn carried(s: &Sig, switch: Option<i64>) -> bool {
    matches!(s.case, Some(None)) || s.case == Some(switch) && switch.is_some()
}

/// A deterministic stream of u64 (splitmix64).
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `lo..=hi`.
    fn range(&mut self, lo: i64, hi: i64) -> i64 {
        lo + (self.next() % ((hi - lo) as u64 + 1)) as i64
    }
}

/// A valid frame of `m` with this switch value: sample `k` of each carried signal (edges first,
/// then the invalid marker, then uniform; enumerated signals cycle through their values).
fn frame(sigs: &[Sig], switch: Option<i64>, k: usize, rng: &mut Rng) -> u64 {
    let mut word = 0;
    for s in sigs {
        let raw = if s.case.is_none() {
            switch.unwrap()
        } else if !carried(s, switch) {
            continue;
        } else if !s.values.is_empty() {
            s.values[k % s.values.len()]
        } else {
            match (k, s.invalid) {
                (0, _) => s.lo,
                (1, _) => s.hi,
                (2, Some(marker)) => marker,
                _ => rng.range(s.lo, s.hi),
            }
        };
        put(&mut word, s, raw);
    }
    word
}

#[test]
fn every_message_switch_and_enumerated_value_decodes_and_re_encodes_identically() {
    let dbc = Dbc::try_from(DBC).expect("exocal.dbc parses with can-dbc");
    let mut rng = Rng(7);
    let mut frames = 0;
    for m in &dbc.messages {
        let (id, sigs) = (id_of(m), signals(&dbc, m));
        for switch in switch_values(&sigs) {
            for k in 0..40 {
                let data = frame(&sigs, switch, k, &mut rng).to_le_bytes();
                let msg = decode(id, &data)
                    .unwrap_or_else(|e| panic!("{} (switch {switch:?}) {data:02x?}: {e}", m.name));
                assert_eq!(
                    msg.encode(),
                    Ok((id, data, 8)),
                    "{} (switch {switch:?}) as {msg:?}",
                    m.name
                );
                frames += 1;
            }
        }
    }
    // 47 messages, 6 of them with 10 or 11 switch values.
    assert!(frames > 4000, "{frames} frames");
}

#[test]
fn every_signal_refuses_what_its_range_and_val_table_exclude_by_name() {
    let dbc = Dbc::try_from(DBC).unwrap();
    let mut rng = Rng(11);
    let mut refused = 0;
    for m in &dbc.messages {
        let (id, sigs) = (id_of(m), signals(&dbc, m));
        for switch in switch_values(&sigs) {
            let valid = frame(&sigs, switch, 3, &mut rng);
            for s in sigs
                .iter()
                .filter(|s| s.case.is_none() || carried(s, switch))
            {
                let outside = [s.lo - 1, s.hi + 1]
                    .into_iter()
                    .filter(|r| (s.bit_lo..=s.bit_hi).contains(r) && Some(*r) != s.invalid);
                // The first raw value in range that an enumerated signal's VAL_ table lacks.
                let unlisted = if s.values.is_empty() {
                    None
                } else {
                    (s.lo..=s.hi).find(|r| !s.values.contains(r))
                };
                for raw in outside.chain(unlisted) {
                    let mut word = valid;
                    put(&mut word, s, raw);
                    let got = decode(id, &word.to_le_bytes());
                    let in_range = (s.lo..=s.hi).contains(&raw);
                    let named = |i: u16, signal: &str| i == id && signal == s.name;
                    let right = match got {
                        Err(DecodeError::OutOfRange { id: i, signal }) => {
                            !in_range && named(i, signal)
                        }
                        Err(DecodeError::BadMux { id: i, value }) => {
                            in_range && s.case.is_none() && i == id && i64::from(value) == raw
                        }
                        Err(DecodeError::BadEnum { id: i, signal }) => {
                            in_range && s.case.is_some() && named(i, signal)
                        }
                        _ => false,
                    };
                    assert!(
                        right,
                        "{}.{} raw {raw} (switch {switch:?}): {got:?}",
                        m.name, s.name
                    );
                    refused += 1;
                }
            }
        }
    }
    assert!(refused > 100, "{refused} refusals");
}

#[test]
fn every_identifier_the_dbc_does_not_define_is_unknown_and_every_one_it_does_needs_8_bytes() {
    let dbc = Dbc::try_from(DBC).unwrap();
    let defined: Vec<u16> = dbc.messages.iter().map(id_of).collect();
    for id in 0..0x800u16 {
        if defined.contains(&id) {
            assert_eq!(
                decode(id, &[0; 7]),
                Err(DecodeError::BadDlc { id, dlc: 7 }),
                "{id:#x}"
            );
        } else {
            assert_eq!(
                decode(id, &[0; 8]),
                Err(DecodeError::UnknownId(u32::from(id)))
            );
        }
    }
}

#[test]
fn every_id_has_its_node_in_the_low_bits_and_fits_11_bits() {
    let dbc = Dbc::try_from(DBC).unwrap();
    let nodes: Vec<&str> = dbc.nodes.iter().map(|n| n.0.as_str()).collect();
    assert_eq!(nodes, NODE_NAMES, "BU_ node list");
    for m in &dbc.messages {
        let id = id_of(m);
        assert!(id < 0x800);
        if let Some(node) = m.name.split('_').nth(1) {
            let n = NODE_NAMES.iter().position(|x| *x == node).unwrap();
            assert_eq!(usize::from(id & 0xF), n, "{}", m.name);
        }
    }
}

#[test]
fn every_message_and_signal_is_commented() {
    let dbc = Dbc::try_from(DBC).unwrap();
    for m in &dbc.messages {
        assert!(
            dbc.message_comment(m.id).is_some_and(|c| !c.is_empty()),
            "{} has a CM_",
            m.name
        );
        for s in &m.signals {
            assert!(
                dbc.signal_comment(m.id, &s.name)
                    .is_some_and(|c| !c.is_empty()),
                "{}.{} has a CM_",
                m.name,
                s.name
            );
        }
    }
    assert!(
        dbc.comments
            .iter()
            .any(|c| matches!(c, Comment::Plain { .. })),
        "database comment"
    );
}
