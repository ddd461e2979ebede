//! Typed messages and the top-level [`decode`] / [`Message::encode`].
//!
//! Contract: [`decode`] accepts exactly the frames the DBC defines (standard 11-bit id, 8 data
//! bytes, a defined multiplexer value, every raw value within its DBC range or equal to the
//! signal's invalid marker, every enumerated value listed) and nothing else; [`Message::encode`]
//! produces only such frames, so `decode(encode(m)) == m` up to the signal resolution. Reserved
//! (unused) bits are written as zero and ignored on decode.
//!
//! Identifiers, layouts, ranges and the values of enumerated signals come from the generated
//! [`crate::spec`]; [`crate::spec::lookup`] and [`crate::spec::MessageSpec::check`] do the
//! validation for every message alike. What is written here by hand is what the DBC cannot say:
//! which typed field each signal is, and the types themselves.

use crate::spec::{
    ee_pose, heartbeat, imu_accel, imu_gyro, imu_mag, joint_state, lookup, stream_digest,
    stream_nonce, table_cmd, table_reply, trigger, Kind, SignalSpec, DLC,
};
use crate::table::Field;
use crate::{DecodeError, EncodeError, NodeId};

/// Joint node's fused angle and rate (`JointState_<node>`). NaN marks an invalid value.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct JointState {
    /// Sending joint node.
    pub node: NodeId,
    /// Node clock at sampling, µs, wrapping at 2^32.
    pub timestamp_us: u32,
    /// Joint angle, rad.
    pub angle: f64,
    /// Joint rate, rad/s.
    pub rate: f64,
}

/// A raw 3-axis IMU sample (`ImuGyro`/`ImuAccel`/`ImuMag`). NaN marks an invalid axis.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImuVector {
    /// Sending node.
    pub node: NodeId,
    /// x, y, z in the sensor frame (rad/s, m/s², µT).
    pub xyz: [f64; 3],
    /// Low 16 bits of the node clock at sampling, µs.
    pub timestamp_lo: u16,
}

/// One page of an end-effector pose (`EePose_EndEffector`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseFrame {
    /// Pose sequence number 0..64 shared by the four pages.
    pub seq: u8,
    /// Which part of the pose.
    pub page: PosePage,
}

/// Content of one pose page.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PosePage {
    /// Page 0: node clock at sampling (µs) and position x (m).
    TimePosX {
        /// Node clock, µs.
        timestamp_us: u32,
        /// Position x, m.
        x: f64,
    },
    /// Page 1: position y, z (m).
    PosYZ {
        /// m.
        y: f64,
        /// m.
        z: f64,
    },
    /// Page 2: quaternion w, x.
    QuatWX {
        /// Scalar part.
        w: f64,
        /// x part.
        x: f64,
    },
    /// Page 3: quaternion y, z.
    QuatYZ {
        /// y part.
        y: f64,
        /// z part.
        z: f64,
    },
}

impl PosePage {
    /// Page number (the multiplexer value).
    pub fn number(&self) -> u8 {
        use ee_pose::page::*;
        match self {
            PosePage::TimePosX { .. } => TIME_POS_X,
            PosePage::PosYZ { .. } => POS_YZ,
            PosePage::QuatWX { .. } => QUAT_WX,
            PosePage::QuatYZ { .. } => QUAT_YZ,
        }
    }
}

/// Node state reported in the heartbeat.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum NodeState {
    /// Booting, not yet sampling.
    Boot = heartbeat::state::BOOT,
    /// Sampling and sending.
    Operational = heartbeat::state::OPERATIONAL,
    /// A table transfer is open.
    Staging = heartbeat::state::STAGING,
    /// Sensor or storage fault.
    Fault = heartbeat::state::FAULT,
}

impl NodeState {
    /// Every state.
    pub const ALL: [NodeState; 4] = [
        NodeState::Boot,
        NodeState::Operational,
        NodeState::Staging,
        NodeState::Fault,
    ];

    fn from_raw(raw: i64) -> Option<NodeState> {
        NodeState::ALL.into_iter().find(|s| *s as i64 == raw)
    }
}

/// `Heartbeat_<node>`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Heartbeat {
    /// Sending node.
    pub node: NodeId,
    /// State.
    pub state: NodeState,
    /// Boots since flashing, modulo 16.
    pub boot_count: u8,
    /// CAN transmit error counter.
    pub tx_errors: u8,
    /// CAN receive error counter plus refused frames.
    pub rx_errors: u8,
    /// CRC-32 of the table held (0 when none).
    pub table_crc: u32,
    /// Firmware major version (0..16).
    pub fw_major: u8,
    /// Firmware minor version (0..16).
    pub fw_minor: u8,
}

/// A table-transfer command as named in ACK/NACK replies.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CmdCode {
    /// Open a transfer.
    Begin,
    /// One segment.
    Segment(Field),
    /// Install the staged table if its CRC matches.
    Commit,
    /// Authenticate the staged table (freshness counter and MAC) before its Commit.
    CommitAuth,
    /// Send the held table back.
    Readback,
    /// Drop the staging.
    Abort,
}

impl CmdCode {
    /// Wire value (the `Cmd` multiplexer value). Segment commands carry the field's sequence
    /// number above `SegA`'s.
    pub fn code(self) -> u8 {
        use table_cmd::cmd::*;
        match self {
            CmdCode::Begin => BEGIN,
            CmdCode::Segment(f) => SEG_A + f.seq(),
            CmdCode::Commit => COMMIT,
            CmdCode::CommitAuth => COMMIT_AUTH,
            CmdCode::Readback => READBACK,
            CmdCode::Abort => ABORT,
        }
    }

    /// From a wire value.
    pub fn from_code(code: u8) -> Option<CmdCode> {
        use table_cmd::cmd::*;
        match code {
            BEGIN => Some(CmdCode::Begin),
            SEG_A..=SEG_SIGMA => Field::from_seq(code - SEG_A).map(CmdCode::Segment),
            COMMIT => Some(CmdCode::Commit),
            COMMIT_AUTH => Some(CmdCode::CommitAuth),
            READBACK => Some(CmdCode::Readback),
            ABORT => Some(CmdCode::Abort),
            _ => None,
        }
    }
}

/// Controller → node command (`TableCmd_<node>`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Command {
    /// Open a transfer of six segments; a keyed node answers with its counter and a MAC over
    /// `nonce` ([`Reply::Freshness`], [`Reply::FreshnessMac`]).
    Begin {
        /// Chosen by the controller, covered by the node's [`Reply::FreshnessMac`].
        nonce: u32,
    },
    /// One table field, raw units (see [`crate::Table`]).
    Segment(Field, i64),
    /// Install the staged table if its CRC-32 equals `crc` (and, on a node holding a key, the
    /// staged table was authenticated by a valid `CommitAuth`).
    Commit {
        /// CRC-32 of the table the controller sent.
        crc: u32,
    },
    /// Authenticates the staged table: the MAC covers node, session, the full freshness
    /// counter, the table and its CRC ([`crate::auth::commit_mac`]).
    CommitAuth {
        /// Low 16 bits of the freshness counter.
        counter_lo: u16,
        /// The truncated AES-128-CMAC.
        mac: u32,
    },
    /// Ask for the held table; a node holding a key answers with a MAC over `nonce`.
    Readback {
        /// Chosen by the controller, covered by the node's [`Reply::ReadbackMac`].
        nonce: u32,
    },
    /// Drop the staging.
    Abort,
}

impl Command {
    /// The code used to name this command in replies.
    pub fn code(&self) -> CmdCode {
        match *self {
            Command::Begin { .. } => CmdCode::Begin,
            Command::Segment(f, _) => CmdCode::Segment(f),
            Command::Commit { .. } => CmdCode::Commit,
            Command::CommitAuth { .. } => CmdCode::CommitAuth,
            Command::Readback { .. } => CmdCode::Readback,
            Command::Abort => CmdCode::Abort,
        }
    }
}

/// A `TableCmd_<node>` frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TableCmd {
    /// Addressed joint node.
    pub node: NodeId,
    /// Transfer session.
    pub session: u8,
    /// The command.
    pub cmd: Command,
}

/// Why a node refused a command.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum NackReason {
    /// The session differs from the open transfer's.
    BadSession = table_reply::nack_reason::BAD_SESSION,
    /// A segment out of sequence, or a repeat with a different value.
    OutOfOrder = table_reply::nack_reason::OUT_OF_ORDER,
    /// The staged table's CRC differs from the Commit's.
    CrcMismatch = table_reply::nack_reason::CRC_MISMATCH,
    /// Commit before all segments were staged.
    Incomplete = table_reply::nack_reason::INCOMPLETE,
    /// A value outside its range.
    OutOfRange = table_reply::nack_reason::OUT_OF_RANGE,
    /// No transfer is open.
    NotStaging = table_reply::nack_reason::NOT_STAGING,
    /// Writing the table to flash failed; the old table stays.
    FlashError = table_reply::nack_reason::FLASH_ERROR,
    /// A table format the node does not know.
    BadFormat = table_reply::nack_reason::BAD_FORMAT,
    /// Readback asked of a node holding no table.
    NoTable = table_reply::nack_reason::NO_TABLE,
    /// A node holding a key got a Commit without a valid `CommitAuth`, or a `CommitAuth` whose
    /// MAC does not verify.
    BadMac = table_reply::nack_reason::BAD_MAC,
    /// A `CommitAuth` whose MAC verifies for a counter at or below the one the node stored: a
    /// replay or a stale sender.
    StaleCounter = table_reply::nack_reason::STALE_COUNTER,
    /// A node without a key (never provisioned, or its key or counter unreadable) installs
    /// nothing: it refuses every transfer until it is provisioned.
    NoKey = table_reply::nack_reason::NO_KEY,
}

impl NackReason {
    /// Every reason.
    pub const ALL: [NackReason; 12] = {
        use NackReason::*;
        [
            BadSession,
            OutOfOrder,
            CrcMismatch,
            Incomplete,
            OutOfRange,
            NotStaging,
            FlashError,
            BadFormat,
            NoTable,
            BadMac,
            StaleCounter,
            NoKey,
        ]
    };

    fn from_raw(raw: i64) -> Option<NackReason> {
        NackReason::ALL.into_iter().find(|r| *r as i64 == raw)
    }
}

/// Node → controller reply content.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Reply {
    /// The command was accepted; `held_crc` is the CRC of the table the node holds now.
    Ack {
        /// The command accepted.
        cmd: CmdCode,
        /// CRC-32 of the installed table.
        held_crc: u32,
    },
    /// The command was refused; the installed table is unchanged.
    Nack {
        /// The command refused.
        cmd: CmdCode,
        /// CRC-32 of the installed table.
        held_crc: u32,
        /// Why.
        reason: NackReason,
    },
    /// One field of the held table, raw units.
    Readback(Field, i64),
    /// The freshness counter the node stored with its table (a keyed node's answer to Begin,
    /// before [`Reply::FreshnessMac`] and the ACK).
    Freshness {
        /// The stored counter; a CommitAuth must carry a higher one.
        counter: u32,
    },
    /// The MAC of a keyed node's answer to Begin: over node, session, the Begin's nonce, the
    /// counter and the held CRC ([`crate::auth::freshness_mac`]), so the counter the controller
    /// signs above cannot be forged.
    FreshnessMac {
        /// The truncated AES-128-CMAC.
        mac: u32,
    },
    /// The MAC of a keyed node's readback (after the six fields, before the ACK): over node,
    /// nonce, held CRC and table ([`crate::auth::readback_mac`]).
    ReadbackMac {
        /// The truncated AES-128-CMAC.
        mac: u32,
    },
}

/// A `TableReply_<node>` frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TableReply {
    /// Replying joint node.
    pub node: NodeId,
    /// Session of the command replied to.
    pub session: u8,
    /// The reply.
    pub reply: Reply,
}

/// What an operator asks for (`Trigger.Command`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum TriggerCommand {
    /// Start a calibration session.
    StartCalibration = trigger::command::START_CALIBRATION,
    /// Abort the running session.
    Abort = trigger::command::ABORT,
}

impl TriggerCommand {
    /// Every command.
    pub const ALL: [TriggerCommand; 2] = [TriggerCommand::StartCalibration, TriggerCommand::Abort];

    fn from_raw(raw: i64) -> Option<TriggerCommand> {
        TriggerCommand::ALL.into_iter().find(|c| *c as i64 == raw)
    }
}

/// Operator request (`Trigger`), authenticated with the trigger key
/// ([`crate::auth::trigger_mac`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Trigger {
    /// What is asked.
    pub command: TriggerCommand,
    /// Low 16 bits of the sender's freshness counter.
    pub counter_lo: u16,
    /// The truncated AES-128-CMAC.
    pub mac: u32,
}

/// A `StreamDigest_<node>` frame: authenticates the data frames the node sent since its
/// previous digest ([`crate::stream_auth`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StreamDigest {
    /// Sending node.
    pub node: NodeId,
    /// Low 16 bits of the digest sequence number.
    pub seq_lo: u16,
    /// Data frames covered.
    pub count: u8,
    /// The AES-128-CMAC truncated to 40 bits.
    pub mac: u64,
}

/// `StreamNonce_<node>`: the controller's nonce for one node's stream digests of a collection,
/// signed for that node ([`crate::stream_auth::sign_nonce`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StreamNonce {
    /// The node it is for.
    pub node: NodeId,
    /// The nonce (never 0: a node's signer starts under 0, which nothing signs).
    pub nonce: u32,
    /// The first 32 bits of the CMAC over it.
    pub mac: u32,
}

/// Any message of the protocol.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Message {
    /// `JointState_<node>`.
    JointState(JointState),
    /// `EePose_EndEffector` page.
    EePose(PoseFrame),
    /// `ImuGyro_<node>` (rad/s).
    ImuGyro(ImuVector),
    /// `ImuAccel_<node>` (m/s²).
    ImuAccel(ImuVector),
    /// `ImuMag_<node>` (µT).
    ImuMag(ImuVector),
    /// `Heartbeat_<node>`.
    Heartbeat(Heartbeat),
    /// `TableCmd_<node>`.
    TableCmd(TableCmd),
    /// `TableReply_<node>`.
    TableReply(TableReply),
    /// `Trigger`.
    Trigger(Trigger),
    /// `StreamDigest_<node>`.
    StreamDigest(StreamDigest),
    /// `StreamNonce`.
    StreamNonce(StreamNonce),
}

/// The signals of an IMU family: the x, y, z axes and the low timestamp.
type ImuSignals = [&'static SignalSpec; 4];
const GYRO: ImuSignals = [
    &imu_gyro::X,
    &imu_gyro::Y,
    &imu_gyro::Z,
    &imu_gyro::TIMESTAMP_LO,
];
const ACCEL: ImuSignals = [
    &imu_accel::X,
    &imu_accel::Y,
    &imu_accel::Z,
    &imu_accel::TIMESTAMP_LO,
];
const MAG: ImuSignals = [
    &imu_mag::X,
    &imu_mag::Y,
    &imu_mag::Z,
    &imu_mag::TIMESTAMP_LO,
];

/// Decodes a classic CAN frame given as an 11-bit identifier and its payload.
pub fn decode(id: u16, data: &[u8]) -> Result<Message, DecodeError> {
    let (spec, node) = lookup(id).ok_or(DecodeError::UnknownId(u32::from(id)))?;
    let d: &[u8; 8] = data.try_into().map_err(|_| DecodeError::BadDlc {
        id,
        dlc: data.len().min(255) as u8,
    })?;
    spec.check(id, d)?;
    // Every signal this frame carries now holds a value the DBC allows, which fits the field
    // it is cast to below; the errors left are a DBC value this code does not know.
    let raw = |s: &SignalSpec| s.raw(d);
    let phys = |s: &SignalSpec| s.value(d);
    let node = node.ok_or(DecodeError::UnknownId(u32::from(id)));
    let bad_enum = |s: &SignalSpec| DecodeError::BadEnum { id, signal: s.name };
    let imu = |[x, y, z, ts]: ImuSignals| -> Result<ImuVector, DecodeError> {
        Ok(ImuVector {
            node: node?,
            xyz: [phys(x), phys(y), phys(z)],
            timestamp_lo: raw(ts) as u16,
        })
    };
    Ok(match spec.kind {
        Kind::JointState => Message::JointState(JointState {
            node: node?,
            timestamp_us: raw(&joint_state::TIMESTAMP) as u32,
            angle: phys(&joint_state::ANGLE),
            rate: phys(&joint_state::RATE),
        }),
        Kind::EePose => {
            use ee_pose::*;
            let page = match raw(&PAGE) as u8 {
                page::TIME_POS_X => PosePage::TimePosX {
                    timestamp_us: raw(&TIMESTAMP) as u32,
                    x: phys(&POS_X),
                },
                page::POS_YZ => PosePage::PosYZ {
                    y: phys(&POS_Y),
                    z: phys(&POS_Z),
                },
                page::QUAT_WX => PosePage::QuatWX {
                    w: phys(&QUAT_W),
                    x: phys(&QUAT_X),
                },
                page::QUAT_YZ => PosePage::QuatYZ {
                    y: phys(&QUAT_Y),
                    z: phys(&QUAT_Z),
                },
                value => return Err(DecodeError::BadMux { id, value }),
            };
            Message::EePose(PoseFrame {
                seq: raw(&SEQ) as u8,
                page,
            })
        }
        Kind::ImuGyro => Message::ImuGyro(imu(GYRO)?),
        Kind::ImuAccel => Message::ImuAccel(imu(ACCEL)?),
        Kind::ImuMag => Message::ImuMag(imu(MAG)?),
        Kind::Heartbeat => {
            use heartbeat::*;
            Message::Heartbeat(Heartbeat {
                node: node?,
                state: NodeState::from_raw(raw(&STATE)).ok_or(bad_enum(&STATE))?,
                boot_count: raw(&BOOT_COUNT) as u8,
                tx_errors: raw(&TX_ERRORS) as u8,
                rx_errors: raw(&RX_ERRORS) as u8,
                table_crc: raw(&TABLE_CRC) as u32,
                fw_major: raw(&FW_MAJOR) as u8,
                fw_minor: raw(&FW_MINOR) as u8,
            })
        }
        Kind::TableCmd => {
            use table_cmd::*;
            let value = raw(&CMD) as u8;
            let cmd = match CmdCode::from_code(value).ok_or(DecodeError::BadMux { id, value })? {
                CmdCode::Begin => Command::Begin {
                    nonce: raw(&BEGIN_NONCE) as u32,
                },
                CmdCode::Segment(f) => Command::Segment(f, raw(f.segment())),
                CmdCode::Commit => Command::Commit {
                    crc: raw(&TABLE_CRC) as u32,
                },
                CmdCode::CommitAuth => Command::CommitAuth {
                    counter_lo: raw(&COUNTER_LO) as u16,
                    mac: raw(&COMMIT_MAC) as u32,
                },
                CmdCode::Readback => Command::Readback {
                    nonce: raw(&NONCE) as u32,
                },
                CmdCode::Abort => Command::Abort,
            };
            Message::TableCmd(TableCmd {
                node: node?,
                session: raw(&SESSION) as u8,
                cmd,
            })
        }
        Kind::TableReply => {
            use table_reply::*;
            let cmd_of = |s: &SignalSpec| CmdCode::from_code(raw(s) as u8).ok_or(bad_enum(s));
            let reply = match raw(&REPLY) as u8 {
                reply::ACK => Reply::Ack {
                    cmd: cmd_of(&ACKED_CMD)?,
                    held_crc: raw(&HELD_CRC) as u32,
                },
                reply::NACK => Reply::Nack {
                    cmd: cmd_of(&NACKED_CMD)?,
                    held_crc: raw(&NACK_HELD_CRC) as u32,
                    reason: NackReason::from_raw(raw(&NACK_REASON))
                        .ok_or(bad_enum(&NACK_REASON))?,
                },
                reply::FRESHNESS => Reply::Freshness {
                    counter: raw(&NODE_COUNTER) as u32,
                },
                reply::READBACK_MAC => Reply::ReadbackMac {
                    mac: raw(&RB_MAC) as u32,
                },
                reply::FRESHNESS_MAC => Reply::FreshnessMac {
                    mac: raw(&FRESH_MAC) as u32,
                },
                value @ reply::READBACK_A..=reply::READBACK_SIGMA => {
                    let f = Field::from_seq(value - reply::READBACK_A)
                        .ok_or(DecodeError::BadMux { id, value })?;
                    Reply::Readback(f, raw(f.readback()))
                }
                value => return Err(DecodeError::BadMux { id, value }),
            };
            Message::TableReply(TableReply {
                node: node?,
                session: raw(&SESSION) as u8,
                reply,
            })
        }
        Kind::Trigger => {
            use trigger::*;
            Message::Trigger(Trigger {
                command: TriggerCommand::from_raw(raw(&COMMAND)).ok_or(bad_enum(&COMMAND))?,
                counter_lo: raw(&COUNTER_LO) as u16,
                mac: raw(&MAC) as u32,
            })
        }
        Kind::StreamDigest => {
            use stream_digest::*;
            Message::StreamDigest(StreamDigest {
                node: node?,
                seq_lo: raw(&SEQ) as u16,
                count: raw(&COUNT) as u8,
                mac: raw(&MAC) as u64,
            })
        }
        Kind::StreamNonce => Message::StreamNonce(StreamNonce {
            node: node?,
            nonce: raw(&stream_nonce::NONCE) as u32,
            mac: raw(&stream_nonce::MAC) as u32,
        }),
    })
}

/// Decodes an `embedded_can` frame: extended identifiers are unknown, remote frames refused.
pub fn decode_frame<F: embedded_can::Frame>(frame: &F) -> Result<Message, DecodeError> {
    let id = match frame.id() {
        embedded_can::Id::Standard(id) => id.as_raw(),
        embedded_can::Id::Extended(id) => return Err(DecodeError::UnknownId(id.as_raw())),
    };
    if frame.is_remote_frame() {
        return Err(DecodeError::Remote(id));
    }
    decode(id, frame.data())
}

impl Message {
    /// The sending (or, for `TableCmd` and `StreamNonce`, addressed) node; `None` for `Trigger`.
    pub fn node(&self) -> Option<NodeId> {
        match self {
            Message::JointState(m) => Some(m.node),
            Message::EePose(_) => Some(NodeId::END_EFFECTOR),
            Message::ImuGyro(m) | Message::ImuAccel(m) | Message::ImuMag(m) => Some(m.node),
            Message::Heartbeat(m) => Some(m.node),
            Message::TableCmd(m) => Some(m.node),
            Message::TableReply(m) => Some(m.node),
            Message::StreamDigest(m) => Some(m.node),
            Message::StreamNonce(m) => Some(m.node),
            Message::Trigger(_) => None,
        }
    }

    /// The message family.
    pub fn kind(&self) -> Kind {
        match self {
            Message::JointState(_) => Kind::JointState,
            Message::EePose(_) => Kind::EePose,
            Message::ImuGyro(_) => Kind::ImuGyro,
            Message::ImuAccel(_) => Kind::ImuAccel,
            Message::ImuMag(_) => Kind::ImuMag,
            Message::Heartbeat(_) => Kind::Heartbeat,
            Message::TableCmd(_) => Kind::TableCmd,
            Message::TableReply(_) => Kind::TableReply,
            Message::Trigger(_) => Kind::Trigger,
            Message::StreamDigest(_) => Kind::StreamDigest,
            Message::StreamNonce(_) => Kind::StreamNonce,
        }
    }

    /// Encodes to `(identifier, payload, dlc)`; dlc is always 8.
    pub fn encode(&self) -> Result<(u16, [u8; 8], u8), EncodeError> {
        let spec = self.kind().spec();
        let id = match self.node() {
            Some(node) => spec.id_for(node)?,
            None => spec.base_id,
        };
        let mut d = [0u8; 8];
        let d = &mut d;
        let imu = |m: &ImuVector, [x, y, z, ts]: ImuSignals, d: &mut [u8; 8]| {
            for (axis, v) in [x, y, z].into_iter().zip(m.xyz) {
                axis.encode(d, v)?;
            }
            ts.encode_raw(d, i64::from(m.timestamp_lo))
        };
        match self {
            Message::JointState(m) => {
                use joint_state::*;
                TIMESTAMP.encode_raw(d, i64::from(m.timestamp_us))?;
                ANGLE.encode(d, m.angle)?;
                RATE.encode(d, m.rate)?;
            }
            Message::EePose(m) => {
                use ee_pose::*;
                PAGE.encode_raw(d, i64::from(m.page.number()))?;
                SEQ.encode_raw(d, i64::from(m.seq))?;
                match m.page {
                    PosePage::TimePosX { timestamp_us, x } => {
                        TIMESTAMP.encode_raw(d, i64::from(timestamp_us))?;
                        POS_X.encode(d, x)?;
                    }
                    PosePage::PosYZ { y, z } => {
                        POS_Y.encode(d, y)?;
                        POS_Z.encode(d, z)?;
                    }
                    PosePage::QuatWX { w, x } => {
                        QUAT_W.encode(d, w)?;
                        QUAT_X.encode(d, x)?;
                    }
                    PosePage::QuatYZ { y, z } => {
                        QUAT_Y.encode(d, y)?;
                        QUAT_Z.encode(d, z)?;
                    }
                }
            }
            Message::ImuGyro(m) => imu(m, GYRO, d)?,
            Message::ImuAccel(m) => imu(m, ACCEL, d)?,
            Message::ImuMag(m) => imu(m, MAG, d)?,
            Message::Heartbeat(m) => {
                use heartbeat::*;
                STATE.encode_raw(d, m.state as i64)?;
                BOOT_COUNT.encode_raw(d, i64::from(m.boot_count))?;
                TX_ERRORS.encode_raw(d, i64::from(m.tx_errors))?;
                RX_ERRORS.encode_raw(d, i64::from(m.rx_errors))?;
                TABLE_CRC.encode_raw(d, i64::from(m.table_crc))?;
                FW_MAJOR.encode_raw(d, i64::from(m.fw_major))?;
                FW_MINOR.encode_raw(d, i64::from(m.fw_minor))?;
            }
            Message::TableCmd(m) => {
                use table_cmd::*;
                CMD.encode_raw(d, i64::from(m.cmd.code().code()))?;
                SESSION.encode_raw(d, i64::from(m.session))?;
                match m.cmd {
                    Command::Begin { nonce } => {
                        SEGMENT_COUNT.encode_raw(d, Field::ALL.len() as i64)?;
                        BEGIN_NONCE.encode_raw(d, i64::from(nonce))?;
                    }
                    Command::Segment(f, raw) => f.segment().encode_raw(d, raw)?,
                    Command::Commit { crc } => TABLE_CRC.encode_raw(d, i64::from(crc))?,
                    Command::CommitAuth { counter_lo, mac } => {
                        COUNTER_LO.encode_raw(d, i64::from(counter_lo))?;
                        COMMIT_MAC.encode_raw(d, i64::from(mac))?;
                    }
                    Command::Readback { nonce } => NONCE.encode_raw(d, i64::from(nonce))?,
                    Command::Abort => {}
                }
            }
            Message::TableReply(m) => {
                use table_reply::*;
                SESSION.encode_raw(d, i64::from(m.session))?;
                let switch = match m.reply {
                    Reply::Ack { cmd, held_crc } => {
                        ACKED_CMD.encode_raw(d, i64::from(cmd.code()))?;
                        HELD_CRC.encode_raw(d, i64::from(held_crc))?;
                        reply::ACK
                    }
                    Reply::Nack {
                        cmd,
                        held_crc,
                        reason,
                    } => {
                        NACKED_CMD.encode_raw(d, i64::from(cmd.code()))?;
                        NACK_HELD_CRC.encode_raw(d, i64::from(held_crc))?;
                        NACK_REASON.encode_raw(d, reason as i64)?;
                        reply::NACK
                    }
                    Reply::Readback(f, raw) => {
                        f.readback().encode_raw(d, raw)?;
                        reply::READBACK_A + f.seq()
                    }
                    Reply::Freshness { counter } => {
                        NODE_COUNTER.encode_raw(d, i64::from(counter))?;
                        reply::FRESHNESS
                    }
                    Reply::ReadbackMac { mac } => {
                        RB_MAC.encode_raw(d, i64::from(mac))?;
                        reply::READBACK_MAC
                    }
                    Reply::FreshnessMac { mac } => {
                        FRESH_MAC.encode_raw(d, i64::from(mac))?;
                        reply::FRESHNESS_MAC
                    }
                };
                REPLY.encode_raw(d, i64::from(switch))?;
            }
            Message::Trigger(t) => {
                use trigger::*;
                COMMAND.encode_raw(d, t.command as i64)?;
                COUNTER_LO.encode_raw(d, i64::from(t.counter_lo))?;
                MAC.encode_raw(d, i64::from(t.mac))?;
            }
            Message::StreamDigest(m) => {
                use stream_digest::*;
                SEQ.encode_raw(d, i64::from(m.seq_lo))?;
                COUNT.encode_raw(d, i64::from(m.count))?;
                MAC.encode_raw(d, m.mac as i64)?;
            }
            Message::StreamNonce(m) => {
                stream_nonce::NONCE.encode_raw(d, i64::from(m.nonce))?;
                stream_nonce::MAC.encode_raw(d, i64::from(m.mac))?;
            }
        }
        Ok((id, *d, DLC))
    }

    /// Encodes into any `embedded_can` frame type.
    pub fn to_frame<F: embedded_can::Frame>(&self) -> Result<F, EncodeError> {
        let (id, data, _) = self.encode()?;
        let id = embedded_can::StandardId::new(id).ok_or(EncodeError::Frame)?;
        F::new(id, &data).ok_or(EncodeError::Frame)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn node() -> impl Strategy<Value = NodeId> {
        (1u8..=8).prop_map(|n| NodeId::new(n).unwrap())
    }
    fn joint() -> impl Strategy<Value = NodeId> {
        (1u8..=7).prop_map(|n| NodeId::new(n).unwrap())
    }
    fn field() -> impl Strategy<Value = Field> {
        (0u8..6).prop_map(|s| Field::from_seq(s).unwrap())
    }
    fn field_raw() -> impl Strategy<Value = (Field, i64)> {
        field().prop_flat_map(|f| {
            let (lo, hi) = f.raw_bounds();
            (Just(f), lo..=hi)
        })
    }
    fn cmd_code() -> impl Strategy<Value = CmdCode> {
        prop_oneof![
            Just(CmdCode::Begin),
            field().prop_map(CmdCode::Segment),
            Just(CmdCode::Commit),
            Just(CmdCode::CommitAuth),
            Just(CmdCode::Readback),
            Just(CmdCode::Abort)
        ]
    }
    fn reason() -> impl Strategy<Value = NackReason> {
        prop::sample::select(&NackReason::ALL[..])
    }
    /// Any value on the signal's grid, or (for signals with a marker) NaN.
    fn grid(spec: SignalSpec) -> impl Strategy<Value = f64> {
        let (lo, hi) = spec.raw_bounds();
        let on_grid = (lo..=hi).prop_map(move |r| r as f64 * spec.factor);
        if spec.invalid_raw.is_some() {
            prop_oneof![9 => on_grid, 1 => Just(f64::NAN)].boxed()
        } else {
            on_grid.boxed()
        }
    }
    fn imu([x, y, z, _]: ImuSignals) -> impl Strategy<Value = ImuVector> {
        (node(), grid(*x), grid(*y), grid(*z), any::<u16>()).prop_map(
            |(node, x, y, z, timestamp_lo)| ImuVector {
                node,
                xyz: [x, y, z],
                timestamp_lo,
            },
        )
    }

    fn message() -> impl Strategy<Value = Message> {
        let page = prop_oneof![
            (any::<u32>(), grid(ee_pose::POS_X))
                .prop_map(|(timestamp_us, x)| PosePage::TimePosX { timestamp_us, x }),
            (grid(ee_pose::POS_Y), grid(ee_pose::POS_Z))
                .prop_map(|(y, z)| PosePage::PosYZ { y, z }),
            (grid(ee_pose::QUAT_W), grid(ee_pose::QUAT_X))
                .prop_map(|(w, x)| PosePage::QuatWX { w, x }),
            (grid(ee_pose::QUAT_Y), grid(ee_pose::QUAT_Z))
                .prop_map(|(y, z)| PosePage::QuatYZ { y, z }),
        ];
        let command = prop_oneof![
            any::<u32>().prop_map(|nonce| Command::Begin { nonce }),
            field_raw().prop_map(|(f, r)| Command::Segment(f, r)),
            any::<u32>().prop_map(|crc| Command::Commit { crc }),
            (any::<u16>(), any::<u32>())
                .prop_map(|(counter_lo, mac)| Command::CommitAuth { counter_lo, mac }),
            any::<u32>().prop_map(|nonce| Command::Readback { nonce }),
            Just(Command::Abort),
        ];
        let reply = prop_oneof![
            (cmd_code(), any::<u32>()).prop_map(|(cmd, held_crc)| Reply::Ack { cmd, held_crc }),
            (cmd_code(), any::<u32>(), reason()).prop_map(|(cmd, held_crc, reason)| Reply::Nack {
                cmd,
                held_crc,
                reason
            }),
            field_raw().prop_map(|(f, r)| Reply::Readback(f, r)),
            any::<u32>().prop_map(|counter| Reply::Freshness { counter }),
            any::<u32>().prop_map(|mac| Reply::ReadbackMac { mac }),
            any::<u32>().prop_map(|mac| Reply::FreshnessMac { mac }),
        ];
        let states = NodeState::ALL;
        prop_oneof![
            (
                joint(),
                any::<u32>(),
                grid(joint_state::ANGLE),
                grid(joint_state::RATE)
            )
                .prop_map(|(node, timestamp_us, angle, rate)| Message::JointState(
                    JointState {
                        node,
                        timestamp_us,
                        angle,
                        rate
                    }
                )),
            (0u8..64, page).prop_map(|(seq, page)| Message::EePose(PoseFrame { seq, page })),
            imu(GYRO).prop_map(Message::ImuGyro),
            imu(ACCEL).prop_map(Message::ImuAccel),
            imu(MAG).prop_map(Message::ImuMag),
            (
                node(),
                0usize..4,
                0u8..16,
                any::<u8>(),
                any::<u8>(),
                any::<u32>(),
                0u8..16,
                0u8..16
            )
                .prop_map(
                    move |(
                        node,
                        s,
                        boot_count,
                        tx_errors,
                        rx_errors,
                        table_crc,
                        fw_major,
                        fw_minor,
                    )| {
                        Message::Heartbeat(Heartbeat {
                            node,
                            state: states[s],
                            boot_count,
                            tx_errors,
                            rx_errors,
                            table_crc,
                            fw_major,
                            fw_minor,
                        })
                    }
                ),
            (joint(), any::<u8>(), command).prop_map(|(node, session, cmd)| Message::TableCmd(
                TableCmd { node, session, cmd }
            )),
            (joint(), any::<u8>(), reply).prop_map(|(node, session, reply)| Message::TableReply(
                TableReply {
                    node,
                    session,
                    reply
                }
            )),
            (
                prop_oneof![
                    Just(TriggerCommand::StartCalibration),
                    Just(TriggerCommand::Abort)
                ],
                any::<u16>(),
                any::<u32>()
            )
                .prop_map(|(command, counter_lo, mac)| Message::Trigger(Trigger {
                    command,
                    counter_lo,
                    mac
                })),
            (node(), any::<u16>(), any::<u8>(), 0u64..1 << 40).prop_map(
                |(node, seq_lo, count, mac)| Message::StreamDigest(StreamDigest {
                    node,
                    seq_lo,
                    count,
                    mac
                })
            ),
            (node(), 1u32.., any::<u32>()).prop_map(|(node, nonce, mac)| Message::StreamNonce(
                StreamNonce { node, nonce, mac }
            )),
        ]
    }

    /// Bitwise equality on floats so that NaN == NaN, and grid values compare after one rounding.
    fn same(a: &Message, b: &Message) -> bool {
        format!("{a:?}") == format!("{b:?}")
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(4000))]

        #[test]
        fn every_message_round_trips(m in message()) {
            let (id, data, dlc) = m.encode().unwrap();
            prop_assert_eq!(dlc, 8);
            let back = decode(id, &data).unwrap();
            prop_assert!(same(&m, &back), "{:?} -> {:?}", m, back);
            // Re-encoding gives the same bytes.
            prop_assert_eq!(back.encode().unwrap(), (id, data, dlc));
        }

        #[test]
        fn decode_never_panics_and_accepted_frames_re_encode_identically(id in 0u16..0x800, data in any::<[u8; 8]>()) {
            if let Ok(m) = decode(id, &data) {
                let (id2, data2, _) = m.encode().unwrap();
                prop_assert_eq!(id2, id);
                // Reserved bits may differ; decoding the re-encoded frame gives the same message.
                prop_assert!(same(&decode(id2, &data2).unwrap(), &m));
            }
        }

        #[test]
        fn wrong_length_is_bad_dlc(m in message(), len in 0usize..8) {
            let (id, data, _) = m.encode().unwrap();
            prop_assert_eq!(decode(id, &data[..len]), Err(DecodeError::BadDlc { id, dlc: len as u8 }));
        }
    }

    #[test]
    fn typed_errors_for_malformed_frames() {
        assert_eq!(
            decode(0x108, &[0; 8]),
            Err(DecodeError::UnknownId(0x108)),
            "no JointState for node 8"
        );
        assert_eq!(decode(0x7FF, &[0; 8]), Err(DecodeError::UnknownId(0x7FF)));
        assert_eq!(
            decode(0x101, &[0; 9]),
            Err(DecodeError::BadDlc { id: 0x101, dlc: 9 })
        );
        let mut cmd = [0u8; 8];
        cmd[0] = 2;
        assert_eq!(
            decode(0x601, &cmd),
            Err(DecodeError::BadMux {
                id: 0x601,
                value: 2
            })
        );
        cmd[0] = 1; // Begin with SegmentCount 0
        assert_eq!(
            decode(0x601, &cmd),
            Err(DecodeError::OutOfRange {
                id: 0x601,
                signal: "SegmentCount"
            })
        );
        let mut reply = [0u8; 8];
        reply[0] = 1;
        reply[2] = 16; // NACK of segment 0 with reason 0
        assert_eq!(
            decode(0x581, &reply),
            Err(DecodeError::OutOfRange {
                id: 0x581,
                signal: "NackReason"
            })
        );
        let mut ack = [0u8; 8];
        ack[2] = 2; // ACK of command 2, which does not exist
        assert_eq!(
            decode(0x581, &ack),
            Err(DecodeError::BadEnum {
                id: 0x581,
                signal: "AckedCmd"
            })
        );
        let mut hb = [0u8; 8];
        hb[0] = 4; // state 4
        assert_eq!(
            decode(0x701, &hb),
            Err(DecodeError::OutOfRange {
                id: 0x701,
                signal: "State"
            })
        );
        let mut tau = [0u8; 8];
        tau[0] = 20; // SegTau = 0 is below its 1 µs minimum
        assert_eq!(
            decode(0x601, &tau),
            Err(DecodeError::OutOfRange {
                id: 0x601,
                signal: "SegTau"
            })
        );
    }

    #[test]
    fn encode_refuses_values_and_nodes_the_dbc_cannot_carry() {
        let js = |node, angle| {
            Message::JointState(JointState {
                node,
                timestamp_us: 0,
                angle,
                rate: 0.0,
            })
        };
        assert_eq!(
            js(NodeId::END_EFFECTOR, 0.0).encode(),
            Err(EncodeError::BadNode(NodeId::END_EFFECTOR))
        );
        assert_eq!(
            js(NodeId::JOINTS[0], 6.0).encode(),
            Err(EncodeError::OutOfRange { signal: "Angle" })
        );
        let pose = Message::EePose(PoseFrame {
            seq: 64,
            page: PosePage::PosYZ { y: 0.0, z: 0.0 },
        });
        assert_eq!(
            pose.encode(),
            Err(EncodeError::OutOfRange { signal: "Seq" })
        );
        let seg = TableCmd {
            node: NodeId::JOINTS[0],
            session: 0,
            cmd: Command::Segment(Field::Tau, 0),
        };
        assert_eq!(
            Message::TableCmd(seg).encode(),
            Err(EncodeError::OutOfRange { signal: "SegTau" })
        );
        let q = Message::EePose(PoseFrame {
            seq: 0,
            page: PosePage::QuatWX {
                w: f64::NAN,
                x: 0.0,
            },
        });
        assert_eq!(q.encode(), Err(EncodeError::NotFinite { signal: "QuatW" }));
    }

    #[test]
    fn frame_helpers_reject_extended_and_remote() {
        #[derive(Debug)]
        struct F(embedded_can::Id, [u8; 8], bool);
        impl embedded_can::Frame for F {
            fn new(id: impl Into<embedded_can::Id>, data: &[u8]) -> Option<Self> {
                Some(F(id.into(), data.try_into().ok()?, false))
            }
            fn new_remote(id: impl Into<embedded_can::Id>, _dlc: usize) -> Option<Self> {
                Some(F(id.into(), [0; 8], true))
            }
            fn is_extended(&self) -> bool {
                matches!(self.0, embedded_can::Id::Extended(_))
            }
            fn is_remote_frame(&self) -> bool {
                self.2
            }
            fn id(&self) -> embedded_can::Id {
                self.0
            }
            fn dlc(&self) -> usize {
                8
            }
            fn data(&self) -> &[u8] {
                &self.1
            }
        }
        let m = Message::Trigger(Trigger {
            command: TriggerCommand::StartCalibration,
            counter_lo: 7,
            mac: 0xdead_beef,
        });
        let f: F = m.to_frame().unwrap();
        assert_eq!(decode_frame(&f), Ok(m));
        let ext = F(
            embedded_can::ExtendedId::new(0x101).unwrap().into(),
            [0; 8],
            false,
        );
        assert_eq!(decode_frame(&ext), Err(DecodeError::UnknownId(0x101)));
        let rtr = F(
            embedded_can::StandardId::new(0x101).unwrap().into(),
            [0; 8],
            true,
        );
        assert_eq!(decode_frame(&rtr), Err(DecodeError::Remote(0x101)));
    }
}
