//! Checks every Rust message and signal layout against `exocal.dbc` as parsed by `can-dbc`,
//! and that the DBC contains nothing the Rust side lacks.

use can_dbc::{ByteOrder, Comment, Dbc, MessageId, MultiplexIndicator, NumericValue, ValueType};
use exocal_dbc::spec::{MuxRole, ALL, DLC, NODE_NAMES};
use exocal_dbc::DBC;

fn num(v: &NumericValue) -> f64 {
    match *v {
        NumericValue::Uint(u) => u as f64,
        NumericValue::Int(i) => i as f64,
        NumericValue::Double(d) => d,
    }
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-12 * a.abs().max(b.abs()).max(1.0)
}

#[test]
fn every_rust_signal_matches_the_dbc_and_back() {
    let dbc = Dbc::try_from(DBC).expect("exocal.dbc parses with can-dbc");
    let nodes: Vec<&str> = dbc.nodes.iter().map(|n| n.0.as_str()).collect();
    assert_eq!(nodes, NODE_NAMES, "BU_ node list");
    let mut checked = 0;
    for spec in ALL {
        let instances: Vec<(u16, String)> = if spec.nodes.is_empty() {
            vec![(spec.base_id, spec.name.to_string())]
        } else {
            spec.nodes
                .iter()
                .map(|&n| {
                    (
                        spec.id(n),
                        format!("{}_{}", spec.name, NODE_NAMES[n as usize]),
                    )
                })
                .collect()
        };
        for (id, name) in instances {
            let msg = dbc
                .messages
                .iter()
                .find(|m| m.id == MessageId::Standard(id))
                .unwrap_or_else(|| panic!("{name} ({id:#x}) missing from the DBC"));
            assert_eq!(msg.name, name, "name of {id:#x}");
            assert_eq!(msg.size, u64::from(DLC), "{name} DLC");
            assert!(
                dbc.message_comment(msg.id).is_some_and(|c| !c.is_empty()),
                "{name} has a CM_"
            );
            assert_eq!(
                msg.signals.len(),
                spec.signals.len(),
                "{name}: signal count"
            );
            for s in spec.signals {
                let d = msg
                    .signals
                    .iter()
                    .find(|d| d.name == s.name)
                    .unwrap_or_else(|| panic!("{name}.{}", s.name));
                let what = format!("{name}.{}", s.name);
                assert_eq!(d.start_bit, u64::from(s.start), "{what} start");
                assert_eq!(d.size, u64::from(s.len), "{what} length");
                assert_eq!(d.byte_order, ByteOrder::LittleEndian, "{what} byte order");
                assert_eq!(
                    d.value_type == ValueType::Signed,
                    s.signed,
                    "{what} signedness"
                );
                assert!(
                    close(d.factor, s.factor),
                    "{what} factor {} vs {}",
                    d.factor,
                    s.factor
                );
                assert!(close(d.offset, s.offset), "{what} offset");
                assert!(
                    close(num(&d.min), s.min),
                    "{what} min {} vs {}",
                    num(&d.min),
                    s.min
                );
                assert!(
                    close(num(&d.max), s.max),
                    "{what} max {} vs {}",
                    num(&d.max),
                    s.max
                );
                assert_eq!(d.unit, s.unit, "{what} unit");
                let mux = match d.multiplexer_indicator {
                    MultiplexIndicator::Plain => MuxRole::Plain,
                    MultiplexIndicator::Multiplexor => MuxRole::Switch,
                    MultiplexIndicator::MultiplexedSignal(v) => MuxRole::Case(v as u8),
                    other => panic!("{what}: unsupported {other:?}"),
                };
                assert_eq!(mux, s.mux, "{what} multiplexing");
                let invalid = dbc
                    .value_descriptions_for_signal(msg.id, s.name)
                    .and_then(|v| v.iter().find(|v| v.description == "Invalid").map(|v| v.id));
                assert_eq!(invalid, s.invalid_raw, "{what} invalid marker in VAL_");
                assert!(
                    dbc.signal_comment(msg.id, s.name)
                        .is_some_and(|c| !c.is_empty()),
                    "{what} has a CM_"
                );
                checked += 1;
            }
        }
    }
    assert_eq!(
        dbc.messages.len(),
        ALL.iter().map(|s| s.nodes.len().max(1)).sum::<usize>(),
        "no extra messages"
    );
    assert!(checked > 300, "checked {checked} signals");
    assert!(
        dbc.comments
            .iter()
            .any(|c| matches!(c, Comment::Plain { .. })),
        "database comment"
    );
}

#[test]
fn every_id_has_its_node_in_the_low_bits_and_fits_11_bits() {
    let dbc = Dbc::try_from(DBC).unwrap();
    for m in &dbc.messages {
        let MessageId::Standard(id) = m.id else {
            panic!("{} is extended", m.name)
        };
        assert!(id < 0x800);
        if let Some(node) = m.name.split('_').nth(1) {
            let n = NODE_NAMES.iter().position(|x| *x == node).unwrap();
            assert_eq!(usize::from(id & 0xF), n, "{}", m.name);
        }
    }
}
