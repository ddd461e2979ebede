//! The session-log messages the suites check, decoded with the log's one schema
//! (`exocal-log`) into JSON values: CAN frames as `{"id", "data"}`, a `/calibration` message as
//! `{}` or, once pushed, `{"nodes": [{"node", "new_crc", "holds", "authenticated"}]}`.

use prost::Message;
use serde_json::{json, Value};

/// `data` of a message on `topic` as JSON, for the topics above; `None` for other topics.
/// Panics naming the topic when a message does not decode.
pub fn log_message_json(topic: &str, encoding: &str, data: &[u8]) -> Option<Value> {
    match topic {
        "/can/rx" | "/can/tx" => {
            let f = exocal_log::decode_can_frame(encoding, data)
                .unwrap_or_else(|e| panic!("{topic}: {e}"));
            Some(json!({ "id": f.id, "data": f.data }))
        }
        "/calibration" => {
            let c = exocal_log::proto::Calibration::decode(data)
                .unwrap_or_else(|e| panic!("{topic}: {e}"));
            if c.push.is_empty() {
                return Some(json!({}));
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
            Some(json!({ "nodes": nodes }))
        }
        _ => None,
    }
}
