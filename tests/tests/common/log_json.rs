//! The session-log messages the suites check, decoded with the log's one schema
//! (`exocal-log`) into JSON values: CAN frames as `{"id", "data"}` (a message on `/can/*` is a
//! batch of them), a `/calibration` message as `{}` or, once pushed,
//! `{"nodes": [{"node", "new_crc", "holds", "authenticated"}]}`.

use prost::Message;
use serde_json::{json, Value};

/// The records of a message on `topic` (its channel's schema named `schema`) as JSON, for the
/// topics above (every frame of a batch); empty for other topics. Panics naming the topic when
/// a message does not decode.
pub fn log_message_json(topic: &str, schema: &str, encoding: &str, data: &[u8]) -> Vec<Value> {
    match topic {
        "/can/rx" | "/can/tx" => exocal_log::decode_can_frames(schema, encoding, data)
            .unwrap_or_else(|e| panic!("{topic}: {e}"))
            .into_iter()
            .map(|f| json!({ "id": f.id, "data": f.data }))
            .collect(),
        "/calibration" => {
            let c = exocal_log::proto::Calibration::decode(data)
                .unwrap_or_else(|e| panic!("{topic}: {e}"));
            if c.push.is_empty() {
                return vec![json!({})];
            }
            let nodes: Vec<Value> = c
                .push
                .iter()
                .map(|n| {
                    json!({
                        "node": n.node,
                        "new_crc": n.new_crc,
                        "holds": n.holds,
                        "authenticated": n.authenticated,
                    })
                })
                .collect();
            vec![json!({ "nodes": nodes })]
        }
        _ => Vec::new(),
    }
}
