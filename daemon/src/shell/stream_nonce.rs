//! The controller's side of stream authentication: the nonces it sends the nodes.
//!
//! Contract:
//! - [`StreamNonces::open`] gives the session its stream gate (which holds each node's frames
//!   until its digest verifies) when the streams are to be authenticated and a node has a key;
//! - [`StreamNonces::next`] picks a nonce above every one sent before, also across restarts
//!   ([`crate::state::next_stream_nonce`]), gives it to the gate, and returns the
//!   `StreamNonce_<node>` frame, signed for it, for every keyed node: at the collection's start
//!   and again whenever the session wants one (a node rebooted and lost its nonce). The caller
//!   sends and logs them.

use exocal_bus::Frame;
use exocal_dbc::{stream_auth, Message, NodeId};
use exocal_session::gate::StreamGate;
use exocal_session::Session;

use crate::config::PushPolicy;
use crate::exit::DaemonError;

/// The stream nonces of one session (see the module docs).
pub struct StreamNonces<'a> {
    policy: &'a PushPolicy,
    /// The last nonce sent (0: none yet).
    last: u32,
}

impl<'a> StreamNonces<'a> {
    /// No nonce sent yet, under `policy` (its keys and state directory).
    pub fn new(policy: &'a PushPolicy) -> Self {
        StreamNonces { policy, last: 0 }
    }

    /// Authenticates `session`'s streams if `on` and a node has a key; whether it did. The
    /// gate's nonce is set with the first one sent.
    pub fn open(&self, on: bool, session: &mut Session) -> bool {
        let keys = &self.policy.keys;
        let keyed = NodeId::ALL.into_iter().any(|n| keys.node(n).is_some());
        if on && keyed {
            session.authenticate(StreamGate::new(keys, 0));
        }
        on && keyed
    }

    /// The next nonce's frames, one per keyed node (none when the streams are not
    /// authenticated); the nonce is `session`'s gate's from now on.
    pub fn next(&mut self, session: &mut Session) -> Result<Vec<(NodeId, Frame)>, DaemonError> {
        if session.gate().is_none() {
            return Ok(Vec::new());
        }
        let state_dir = self.policy.state_dir.as_deref();
        let now = std::time::SystemTime::now();
        let nonce = crate::state::next_stream_nonce(state_dir, self.last, now)?;
        self.last = nonce;
        session.renonce(nonce);
        let keyed = NodeId::ALL
            .into_iter()
            .filter_map(|n| Some((n, self.policy.keys.node(n)?)));
        keyed
            .map(|(node, key)| {
                let signed = stream_auth::sign_nonce(&stream_auth::stream_key(key), node, nonce);
                let frame = Message::StreamNonce(signed).to_frame();
                let frame = frame.map_err(|e| DaemonError::Internal {
                    what: "encoding the stream nonce".into(),
                    source: e.to_string().into(),
                })?;
                Ok((node, frame))
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use exocal_dbc::auth::Key;
    use exocal_dbc::stream_auth::Signer;

    fn policy(keyed: &[NodeId]) -> PushPolicy {
        let mut policy = crate::config::Config::default_config().push;
        policy.keys = Default::default();
        for (i, &node) in keyed.iter().enumerate() {
            policy
                .keys
                .set_node(node, Some(Key::new([i as u8 + 1; 16])));
        }
        policy.state_dir = None;
        policy
    }

    fn session() -> Session {
        Session::new(&exocal_session::Settings::suit_default())
    }

    #[test]
    fn without_authentication_or_keys_no_gate_and_no_frames() {
        let keyed = policy(&[NodeId::JOINTS[0]]);
        let mut s = session();
        let mut nonces = StreamNonces::new(&keyed);
        assert!(!nonces.open(false, &mut s), "authentication off");
        assert!(s.gate().is_none());
        assert!(nonces.next(&mut s).unwrap().is_empty());
        let unkeyed = policy(&[]);
        assert!(!StreamNonces::new(&unkeyed).open(true, &mut s), "no keys");
        assert!(s.gate().is_none());
    }

    #[test]
    fn each_keyed_node_gets_a_rising_nonce_signed_with_its_own_key() {
        let keyed = [NodeId::JOINTS[0], NodeId::JOINTS[3], NodeId::END_EFFECTOR];
        let policy = policy(&keyed);
        let mut s = session();
        let mut nonces = StreamNonces::new(&policy);
        assert!(nonces.open(true, &mut s));
        assert!(s.gate().is_some());
        let mut last = 0;
        for _ in 0..3 {
            let frames = nonces.next(&mut s).unwrap();
            let nodes: Vec<NodeId> = frames.iter().map(|f| f.0).collect();
            assert_eq!(
                nodes, keyed,
                "one frame per keyed node, none for the others"
            );
            for (node, frame) in frames {
                let Ok(Message::StreamNonce(n)) = exocal_dbc::decode_frame(&frame) else {
                    panic!("{node}: not a StreamNonce frame");
                };
                assert!(n.nonce > last, "{} after {last}", n.nonce);
                // The node takes it with its own stream key, and would refuse another node's.
                let key = stream_auth::stream_key(policy.keys.node(node).unwrap());
                let mut signer = Signer::new(node, key, 0);
                assert_eq!(signer.set_nonce(n, 0), Ok(()), "{node}");
                let other = stream_auth::stream_key(&Key::new([0xee; 16]));
                assert!(Signer::new(node, other, 0).set_nonce(n, 0).is_err());
            }
            last = nonces.last;
        }
    }
}
