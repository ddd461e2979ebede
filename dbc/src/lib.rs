//! exocal-dbc: the CAN protocol of the exocal suit.
//!
//! The contract is the file `exocal.dbc` next to this crate ([`DBC`] holds its text). This crate
//! is its typed, `no_std` codec and the table-transfer state machines:
//!
//! - [`spec`] holds the identifiers, layouts and scaling of every message, generated from the
//!   DBC at build time (`build.rs`); nothing else here restates them.
//! - [`decode`] turns an 11-bit identifier and a payload into a [`Message`], rejecting unknown
//!   identifiers, a DLC other than 8, bad multiplexer values and out-of-range raw values with a
//!   [`DecodeError`]; [`Message::encode`] is the inverse and refuses values the DBC cannot carry
//!   with an [`EncodeError`]. Raw values reserved as "invalid" in the DBC (`VAL_ … "Invalid"`)
//!   decode to `f64::NAN`, and NaN encodes to them.
//! - [`table::Table`] is one node's calibration row (D-H a, α, d, θ-offset and drift τ, σ) at
//!   1 µm / 1 µrad / 1 µs resolution with its CRC-32.
//! - [`transfer`] holds the node side ([`transfer::NodeTransfer`]) and the controller side
//!   ([`transfer::Upload`]) of the table transfer. Time is always an argument.
//! - [`auth`] authenticates transfers and triggers: AES-128-CMAC truncated to 32 bits
//!   (`cmac` + `aes`, `no_std`, so node firmware shares it) with freshness counters.
//! - [`pose::PoseAssembler`] joins the four `EePose` pages of one pose.
//!
//! Identifiers: `base | node`, node ids 1..=7 for the joints and 8 for the end-effector
//! reference node (see [`NodeId`]).
#![cfg_attr(not(any(test, feature = "std")), no_std)]
#![deny(unsafe_code)]
#![warn(missing_docs)]

pub mod auth;
pub mod frame;
mod layout;
pub mod message;
pub mod pose;
pub mod stream_auth;
pub mod table;
pub mod transfer;

pub use frame::{Frame, Received};
#[allow(clippy::approx_constant)] // the DBC's 2π bounds, 6.283185, are not `TAU`
pub mod spec {
    //! The protocol's tables, generated at build time from `exocal.dbc` by `build.rs`: a
    //! [`Kind`] and a [`MessageSpec`] static per message family (`JOINT_STATE`), a module of
    //! [`SignalSpec`] constants per family (`joint_state::ANGLE`), the named `VAL_` values
    //! (`heartbeat::state::FAULT`), [`NODE_NAMES`] and [`ALL`]. The DBC's comments are their
    //! docs. Edit the DBC, never these.
    //!
    //! The types they are made of, [`lookup`] and the signal-level codec are hand-written (see
    //! [`SignalSpec`] and [`MessageSpec::check`]).

    pub use crate::layout::{lookup, MessageSpec, MuxRole, SignalSpec};
    include!(concat!(env!("OUT_DIR"), "/spec.rs"));
}

pub use message::{
    decode, decode_frame, CmdCode, Command, Heartbeat, ImuVector, JointState, Message, NackReason,
    NodeState, PoseFrame, PosePage, Reply, StreamDigest, StreamNonce, TableCmd, TableReply,
    Trigger, TriggerCommand,
};
pub use table::{Field, Table};

/// The text of `exocal.dbc`, the protocol contract.
pub const DBC: &str = include_str!("../exocal.dbc");

/// A node on the bus: joints 1..=7, the end-effector reference node 8.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct NodeId(u8);

impl NodeId {
    /// The end-effector reference node.
    pub const END_EFFECTOR: NodeId = NodeId(8);
    /// The seven joint nodes, proximal first.
    pub const JOINTS: [NodeId; 7] = NodeId::first();
    /// Every node.
    pub const ALL: [NodeId; 8] = NodeId::first();

    /// Nodes 1..=N.
    const fn first<const N: usize>() -> [NodeId; N] {
        let mut nodes = [NodeId(0); N];
        let mut i = 0;
        while i < N {
            nodes[i] = NodeId(i as u8 + 1);
            i += 1;
        }
        nodes
    }

    /// The node with this id, if it exists (1..=8).
    pub const fn new(id: u8) -> Option<NodeId> {
        if id >= 1 && id <= 8 {
            Some(NodeId(id))
        } else {
            None
        }
    }

    /// Joint node for the 0-based joint index (0..7).
    pub const fn joint(index: usize) -> Option<NodeId> {
        if index < 7 {
            Some(NodeId(index as u8 + 1))
        } else {
            None
        }
    }

    /// The 0-based joint index, or `None` for the end-effector node.
    pub const fn joint_index(self) -> Option<usize> {
        if self.0 <= 7 {
            Some(self.0 as usize - 1)
        } else {
            None
        }
    }

    /// The id carried in the low 4 bits of the CAN identifier.
    pub const fn raw(self) -> u8 {
        self.0
    }

    /// The DBC node name (`Joint1`, …, `EndEffector`).
    pub const fn name(self) -> &'static str {
        spec::NODE_NAMES[self.0 as usize]
    }
}

impl core::fmt::Display for NodeId {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(self.name())
    }
}

/// Why a frame could not be decoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DecodeError {
    /// No message of the DBC has this identifier (extended identifiers included).
    UnknownId(u32),
    /// A remote (RTR) frame: the protocol has none.
    Remote(u16),
    /// The payload is not 8 bytes long.
    BadDlc {
        /// Identifier.
        id: u16,
        /// Length received.
        dlc: u8,
    },
    /// The multiplexer switch has a value the DBC does not define.
    BadMux {
        /// Identifier.
        id: u16,
        /// Switch value received.
        value: u8,
    },
    /// A signal's raw value lies outside its DBC range.
    OutOfRange {
        /// Identifier.
        id: u16,
        /// Signal name.
        signal: &'static str,
    },
    /// An enumerated signal has a value its `VAL_` table does not list.
    BadEnum {
        /// Identifier.
        id: u16,
        /// Signal name.
        signal: &'static str,
    },
}

impl core::fmt::Display for DecodeError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match *self {
            DecodeError::UnknownId(id) => write!(f, "unknown CAN identifier {id:#x}"),
            DecodeError::Remote(id) => write!(f, "remote frame {id:#05x}: the protocol has none"),
            DecodeError::BadDlc { id, dlc } => {
                write!(f, "frame {id:#05x} has DLC {dlc}, expected 8")
            }
            DecodeError::BadMux { id, value } => {
                write!(f, "frame {id:#05x} has undefined multiplexer value {value}")
            }
            DecodeError::OutOfRange { id, signal } => {
                write!(f, "frame {id:#05x}: signal {signal} out of range")
            }
            DecodeError::BadEnum { id, signal } => {
                write!(f, "frame {id:#05x}: signal {signal} has an undefined value")
            }
        }
    }
}

/// Why a message could not be encoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EncodeError {
    /// The value lies outside the signal's DBC range.
    OutOfRange {
        /// Signal name.
        signal: &'static str,
    },
    /// Infinite, or NaN on a signal without an invalid marker.
    NotFinite {
        /// Signal name.
        signal: &'static str,
    },
    /// This message does not exist for this node (e.g. a joint state from the end-effector).
    BadNode(NodeId),
    /// The frame type could not be built (embedded-can refused the identifier or length).
    Frame,
}

impl core::fmt::Display for EncodeError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match *self {
            EncodeError::OutOfRange { signal } => write!(f, "signal {signal}: value out of range"),
            EncodeError::NotFinite { signal } => write!(f, "signal {signal}: value not finite"),
            EncodeError::BadNode(node) => write!(f, "message does not exist for node {node}"),
            EncodeError::Frame => f.write_str("the frame type refused the identifier or payload"),
        }
    }
}

#[cfg(feature = "std")]
impl std::error::Error for DecodeError {}
#[cfg(feature = "std")]
impl std::error::Error for EncodeError {}
