//! The emulated node's side of the authenticated sensor streams ([`exocal_dbc::stream_auth`]):
//! a node holding a key signs the data frames it sends and sends a `StreamDigest` every
//! [`exocal_dbc::stream_auth::DIGEST_PERIOD_US`]; it takes the collection's nonce from the
//! controller's `StreamNonce_<node>` when that is signed for it and newer than the one it holds
//! (a forged or replayed one changes nothing). A node without a key sends no digests (the
//! controller, when it authenticates, then drops its frames: fail closed).

use exocal_bus::embedded_can::Frame as _;
use exocal_bus::Frame;
use exocal_dbc::auth::Key;
use exocal_dbc::message::{Message, StreamNonce};
use exocal_dbc::stream_auth::{self, covered, NonceReject};
use exocal_dbc::{spec, NodeId};

/// One node's stream signer.
#[derive(Clone)]
pub struct Signer(stream_auth::Signer);

/// The signer of a node booting with `key` in its slot (`None` without a key).
pub fn signer(node: NodeId, key: Option<&Key>) -> Option<Signer> {
    key.map(|k| {
        Signer(stream_auth::Signer::new(
            node,
            stream_auth::stream_key(k),
            0,
        ))
    })
}

impl Signer {
    /// The controller's nonce arrived: taken if signed for this node and newer.
    pub fn set_nonce(&mut self, nonce: StreamNonce, local_us: u64) -> Result<(), NonceReject> {
        self.0.set_nonce(nonce, local_us)
    }

    /// The node sends `frame`: covered if it is a data frame; the digest to send after it when
    /// the span is full.
    pub fn sign(&mut self, frame: &Frame, local_us: u64) -> Option<Frame> {
        let id = frame.raw_id() as u16;
        let data = matches!(spec::lookup(id), Some((f, Some(_))) if covered(f.kind));
        if !data || frame.is_extended() {
            return None;
        }
        self.0.add(id, frame.data(), local_us).map(digest_frame)
    }

    /// The digest frame due at `local_us`, if one is.
    pub fn due(&mut self, local_us: u64) -> Option<Frame> {
        self.0
            .due(local_us)
            .then(|| digest_frame(self.0.digest(local_us)))
    }
}

fn digest_frame(d: exocal_dbc::message::StreamDigest) -> Frame {
    Message::StreamDigest(d)
        .to_frame()
        .expect("a digest is always encodable")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scenario::Scenario;
    use crate::sim::Suit;
    use exocal_dbc::auth::KeySet;
    use exocal_dbc::stream_auth::Verifier;
    use std::collections::BTreeMap;

    #[test]
    fn keyed_nodes_sign_their_streams_under_the_controllers_nonce() {
        let dir = std::env::temp_dir().join(format!("exocal-hil-{}-stream", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let keys = KeySet::derived(5);
        crate::flash::provision(&dir, &keys).unwrap();
        let mut suit = Suit::new(Scenario::paper(), &dir).unwrap();
        let nonce = 7;
        let before = suit.advance(0.5);
        let stream_key = |n| stream_auth::stream_key(keys.node(n).unwrap());
        let frame = |n, nonce| {
            Message::StreamNonce(stream_auth::sign_nonce(&stream_key(n), n, nonce))
                .to_frame()
                .unwrap()
        };
        for n in NodeId::ALL {
            suit.receive(&frame(n, nonce), 0.5);
        }
        // Forged, for another node, replayed: ignored (the verifiers below would fail else).
        let forged = Message::StreamNonce(exocal_dbc::StreamNonce {
            node: NodeId::JOINTS[0],
            nonce: 99,
            mac: 1,
        });
        suit.receive(&forged.to_frame().unwrap(), 0.5);
        let mut misaddressed = frame(NodeId::JOINTS[1], 99);
        misaddressed = Frame::new(
            exocal_bus::embedded_can::StandardId::new(misaddressed.raw_id() as u16 - 1).unwrap(),
            misaddressed.data(),
        )
        .unwrap();
        suit.receive(&misaddressed, 0.5);
        suit.receive(&frame(NodeId::JOINTS[2], nonce - 1), 0.5);
        suit.receive(&frame(NodeId::JOINTS[3], nonce), 0.5);
        assert_eq!(suit.stats().ignored_nonces, 4);
        let mut verifiers: BTreeMap<NodeId, (Verifier, Vec<Frame>, u32)> = NodeId::ALL
            .into_iter()
            .map(|n| (n, (Verifier::new(n, stream_key(n), nonce), Vec::new(), 0)))
            .collect();
        // Before the nonce, digests verify nowhere (nonce 0).
        assert!(before
            .iter()
            .any(|f| matches!(exocal_dbc::decode_frame(f), Ok(Message::StreamDigest(_)))));
        let mut rejected = 0;
        for f in suit.advance(3.0) {
            match exocal_dbc::decode_frame(&f) {
                Ok(Message::StreamDigest(d)) => {
                    let (v, held, ok) = verifiers.get_mut(&d.node).unwrap();
                    match v.check(&d, held.iter().map(|f| (f.raw_id() as u16, f.data()))) {
                        Ok(()) => *ok += 1,
                        Err(_) => rejected += 1,
                    }
                    held.clear();
                }
                Ok(m) if covered(m.kind()) => {
                    verifiers.get_mut(&m.node().unwrap()).unwrap().1.push(f)
                }
                _ => {}
            }
        }
        // At most the span open when the nonce arrived fails, per node; then every 100 ms
        // digest of every node verifies.
        assert!(rejected <= NodeId::ALL.len(), "{rejected} rejected");
        for (node, (_, _, ok)) in verifiers {
            assert!(ok >= 20, "{node}: {ok} verified digests in 2.5 s");
        }
    }
}
