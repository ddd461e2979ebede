//! Typed messages and the top-level [`decode`] / [`Message::encode`].
//!
//! Contract: [`decode`] accepts exactly the frames the DBC defines (standard 11-bit id, 8 data
//! bytes, a defined multiplexer value, every raw value within its DBC range or equal to the
//! signal's invalid marker) and nothing else; [`Message::encode`] produces only such frames, so
//! `decode(encode(m)) == m` up to the signal resolution. Reserved (unused) bits are written as
//! zero and ignored on decode.

use crate::spec::{
    s::*, MessageSpec, SignalSpec, DLC, EE_POSE, HEARTBEAT, IMU_ACCEL, IMU_GYRO, IMU_MAG,
    JOINT_STATE,
};
use crate::spec::{TABLE_CMD, TABLE_REPLY, TRIGGER};
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
        match self {
            PosePage::TimePosX { .. } => 0,
            PosePage::PosYZ { .. } => 1,
            PosePage::QuatWX { .. } => 2,
            PosePage::QuatYZ { .. } => 3,
        }
    }
}

/// Node state reported in the heartbeat.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NodeState {
    /// Booting, not yet sampling.
    Boot = 0,
    /// Sampling and sending.
    Operational = 1,
    /// A table transfer is open.
    Staging = 2,
    /// Sensor or storage fault.
    Fault = 3,
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
    /// Wire value (the `Cmd` multiplexer value).
    pub fn code(self) -> u8 {
        match self {
            CmdCode::Begin => 1,
            CmdCode::Segment(f) => 16 + f.seq(),
            CmdCode::Commit => 32,
            CmdCode::CommitAuth => 33,
            CmdCode::Readback => 48,
            CmdCode::Abort => 63,
        }
    }

    /// From a wire value.
    pub fn from_code(code: u8) -> Option<CmdCode> {
        match code {
            1 => Some(CmdCode::Begin),
            16..=21 => Field::from_seq(code - 16).map(CmdCode::Segment),
            32 => Some(CmdCode::Commit),
            33 => Some(CmdCode::CommitAuth),
            48 => Some(CmdCode::Readback),
            63 => Some(CmdCode::Abort),
            _ => None,
        }
    }
}

/// Controller → node command (`TableCmd_<node>`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Command {
    /// Open a transfer of six segments.
    Begin,
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
            Command::Begin => CmdCode::Begin,
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
pub enum NackReason {
    /// The session differs from the open transfer's.
    BadSession = 1,
    /// A segment out of sequence, or a repeat with a different value.
    OutOfOrder = 2,
    /// The staged table's CRC differs from the Commit's.
    CrcMismatch = 3,
    /// Commit before all segments were staged.
    Incomplete = 4,
    /// A value outside its range.
    OutOfRange = 5,
    /// No transfer is open.
    NotStaging = 6,
    /// Writing the table to flash failed; the old table stays.
    FlashError = 7,
    /// A table format the node does not know.
    BadFormat = 8,
    /// Readback asked of a node holding no table.
    NoTable = 9,
    /// A node holding a key got a Commit without a valid `CommitAuth`, or a `CommitAuth` whose
    /// MAC does not verify.
    BadMac = 10,
    /// A `CommitAuth` whose MAC verifies for a counter at or below the one the node stored: a
    /// replay or a stale sender.
    StaleCounter = 11,
}

impl NackReason {
    fn from_raw(raw: i64) -> Option<NackReason> {
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
        ]
        .into_iter()
        .find(|r| *r as i64 == raw)
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
    /// before its ACK).
    Freshness {
        /// The stored counter; a CommitAuth must carry a higher one.
        counter: u32,
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
pub enum TriggerCommand {
    /// Start a calibration session.
    StartCalibration = 1,
    /// Abort the running session.
    Abort = 2,
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
}

fn node_of(spec: &MessageSpec, id: u16) -> Option<NodeId> {
    let node = (id & 0xF) as u8;
    if id & !0xF == spec.base_id && spec.nodes.contains(&node) {
        NodeId::new(node)
    } else {
        None
    }
}

fn check_node(spec: &MessageSpec, node: NodeId) -> Result<u16, EncodeError> {
    if spec.nodes.contains(&node.raw()) {
        Ok(spec.id(node.raw()))
    } else {
        Err(EncodeError::BadNode(node))
    }
}

fn get_u(spec: &SignalSpec, id: u16, d: &[u8; 8]) -> Result<i64, DecodeError> {
    spec.decode_raw(id, d)
}

/// Decodes a classic CAN frame given as an 11-bit identifier and its payload.
pub fn decode(id: u16, data: &[u8]) -> Result<Message, DecodeError> {
    let known = crate::spec::ALL.iter().any(|spec| {
        if spec.nodes.is_empty() {
            spec.base_id == id
        } else {
            node_of(spec, id).is_some()
        }
    });
    if !known {
        return Err(DecodeError::UnknownId(u32::from(id)));
    }
    let d: &[u8; 8] = data.try_into().map_err(|_| DecodeError::BadDlc {
        id,
        dlc: data.len().min(255) as u8,
    })?;
    if id == TRIGGER.base_id {
        let command = match TRIGGER_COMMAND.decode_raw(id, d)? {
            1 => TriggerCommand::StartCalibration,
            _ => TriggerCommand::Abort,
        };
        return Ok(Message::Trigger(Trigger {
            command,
            counter_lo: get_u(&TRIGGER_COUNTER_LO, id, d)? as u16,
            mac: get_u(&TRIGGER_MAC, id, d)? as u32,
        }));
    }
    if let Some(node) = node_of(&JOINT_STATE, id) {
        return Ok(Message::JointState(JointState {
            node,
            timestamp_us: get_u(&JS_TIMESTAMP, id, d)? as u32,
            angle: JS_ANGLE.decode(id, d)?,
            rate: JS_RATE.decode(id, d)?,
        }));
    }
    if node_of(&EE_POSE, id).is_some() {
        let seq = get_u(&EE_SEQ, id, d)? as u8;
        let page = match EE_PAGE.raw(d) {
            0 => PosePage::TimePosX {
                timestamp_us: get_u(&EE_TIMESTAMP, id, d)? as u32,
                x: EE_POS_X.decode(id, d)?,
            },
            1 => PosePage::PosYZ {
                y: EE_POS_Y.decode(id, d)?,
                z: EE_POS_Z.decode(id, d)?,
            },
            2 => PosePage::QuatWX {
                w: EE_QUAT_W.decode(id, d)?,
                x: EE_QUAT_X.decode(id, d)?,
            },
            _ => PosePage::QuatYZ {
                y: EE_QUAT_Y.decode(id, d)?,
                z: EE_QUAT_Z.decode(id, d)?,
            },
        };
        return Ok(Message::EePose(PoseFrame { seq, page }));
    }
    for (spec, axes, wrap) in [
        (
            &IMU_GYRO,
            &GYRO,
            Message::ImuGyro as fn(ImuVector) -> Message,
        ),
        (&IMU_ACCEL, &ACCEL, Message::ImuAccel),
        (&IMU_MAG, &MAG, Message::ImuMag),
    ] {
        if let Some(node) = node_of(spec, id) {
            let mut xyz = [0.0; 3];
            for (v, axis) in xyz.iter_mut().zip(axes.iter()) {
                *v = axis.decode(id, d)?;
            }
            return Ok(wrap(ImuVector {
                node,
                xyz,
                timestamp_lo: get_u(&IMU_TIMESTAMP_LO, id, d)? as u16,
            }));
        }
    }
    if let Some(node) = node_of(&HEARTBEAT, id) {
        let state = match get_u(&HB_STATE, id, d)? {
            0 => NodeState::Boot,
            1 => NodeState::Operational,
            2 => NodeState::Staging,
            _ => NodeState::Fault,
        };
        return Ok(Message::Heartbeat(Heartbeat {
            node,
            state,
            boot_count: get_u(&HB_BOOT_COUNT, id, d)? as u8,
            tx_errors: get_u(&HB_TX_ERRORS, id, d)? as u8,
            rx_errors: get_u(&HB_RX_ERRORS, id, d)? as u8,
            table_crc: get_u(&HB_TABLE_CRC, id, d)? as u32,
            fw_major: get_u(&HB_FW_MAJOR, id, d)? as u8,
            fw_minor: get_u(&HB_FW_MINOR, id, d)? as u8,
        }));
    }
    if let Some(node) = node_of(&TABLE_CMD, id) {
        let session = get_u(&CMD_SESSION, id, d)? as u8;
        let value = CMD.raw(d) as u8;
        let cmd = match CmdCode::from_code(value) {
            Some(CmdCode::Begin) => {
                get_u(&CMD_SEGMENT_COUNT, id, d)?;
                Command::Begin
            }
            Some(CmdCode::Segment(f)) => Command::Segment(f, get_u(&SEGMENTS[f as usize], id, d)?),
            Some(CmdCode::Commit) => Command::Commit {
                crc: get_u(&CMD_TABLE_CRC, id, d)? as u32,
            },
            Some(CmdCode::CommitAuth) => Command::CommitAuth {
                counter_lo: get_u(&CMD_COUNTER_LO, id, d)? as u16,
                mac: get_u(&CMD_COMMIT_MAC, id, d)? as u32,
            },
            Some(CmdCode::Readback) => Command::Readback {
                nonce: get_u(&CMD_NONCE, id, d)? as u32,
            },
            Some(CmdCode::Abort) => Command::Abort,
            None => return Err(DecodeError::BadMux { id, value }),
        };
        return Ok(Message::TableCmd(TableCmd { node, session, cmd }));
    }
    let node = node_of(&TABLE_REPLY, id).ok_or(DecodeError::UnknownId(u32::from(id)))?;
    let session = get_u(&REPLY_SESSION, id, d)? as u8;
    let value = REPLY.raw(d) as u8;
    let cmd_of = |spec: &SignalSpec| {
        CmdCode::from_code(spec.raw(d) as u8).ok_or(DecodeError::BadEnum {
            id,
            signal: spec.name,
        })
    };
    let reply = match value {
        0 => Reply::Ack {
            cmd: cmd_of(&ACKED_CMD)?,
            held_crc: get_u(&HELD_CRC, id, d)? as u32,
        },
        1 => Reply::Nack {
            cmd: cmd_of(&NACKED_CMD)?,
            held_crc: get_u(&NACK_HELD_CRC, id, d)? as u32,
            reason: NackReason::from_raw(get_u(&NACK_REASON, id, d)?).ok_or(
                DecodeError::BadEnum {
                    id,
                    signal: NACK_REASON.name,
                },
            )?,
        },
        2 => Reply::Freshness {
            counter: get_u(&NODE_COUNTER, id, d)? as u32,
        },
        3 => Reply::ReadbackMac {
            mac: get_u(&RB_MAC, id, d)? as u32,
        },
        16..=21 => {
            let f = Field::ALL[usize::from(value - 16)];
            Reply::Readback(f, get_u(&READBACK[f as usize], id, d)?)
        }
        _ => return Err(DecodeError::BadMux { id, value }),
    };
    Ok(Message::TableReply(TableReply {
        node,
        session,
        reply,
    }))
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
    /// The sending (or, for `TableCmd`, addressed) node; `None` for `Trigger`.
    pub fn node(&self) -> Option<NodeId> {
        match self {
            Message::JointState(m) => Some(m.node),
            Message::EePose(_) => Some(NodeId::END_EFFECTOR),
            Message::ImuGyro(m) | Message::ImuAccel(m) | Message::ImuMag(m) => Some(m.node),
            Message::Heartbeat(m) => Some(m.node),
            Message::TableCmd(m) => Some(m.node),
            Message::TableReply(m) => Some(m.node),
            Message::Trigger(_) => None,
        }
    }

    /// Encodes to `(identifier, payload, dlc)`; dlc is always 8.
    pub fn encode(&self) -> Result<(u16, [u8; 8], u8), EncodeError> {
        let mut d = [0u8; 8];
        let id = match self {
            Message::JointState(m) => {
                let id = check_node(&JOINT_STATE, m.node)?;
                JS_TIMESTAMP.encode_raw(&mut d, i64::from(m.timestamp_us))?;
                JS_ANGLE.encode(&mut d, m.angle)?;
                JS_RATE.encode(&mut d, m.rate)?;
                id
            }
            Message::EePose(m) => {
                EE_PAGE.encode_raw(&mut d, i64::from(m.page.number()))?;
                EE_SEQ.encode_raw(&mut d, i64::from(m.seq))?;
                match m.page {
                    PosePage::TimePosX { timestamp_us, x } => {
                        EE_TIMESTAMP.encode_raw(&mut d, i64::from(timestamp_us))?;
                        EE_POS_X.encode(&mut d, x)?;
                    }
                    PosePage::PosYZ { y, z } => {
                        EE_POS_Y.encode(&mut d, y)?;
                        EE_POS_Z.encode(&mut d, z)?;
                    }
                    PosePage::QuatWX { w, x } => {
                        EE_QUAT_W.encode(&mut d, w)?;
                        EE_QUAT_X.encode(&mut d, x)?;
                    }
                    PosePage::QuatYZ { y, z } => {
                        EE_QUAT_Y.encode(&mut d, y)?;
                        EE_QUAT_Z.encode(&mut d, z)?;
                    }
                }
                EE_POSE.id(NodeId::END_EFFECTOR.raw())
            }
            Message::ImuGyro(m) => encode_imu(&IMU_GYRO, &GYRO, m, &mut d)?,
            Message::ImuAccel(m) => encode_imu(&IMU_ACCEL, &ACCEL, m, &mut d)?,
            Message::ImuMag(m) => encode_imu(&IMU_MAG, &MAG, m, &mut d)?,
            Message::Heartbeat(m) => {
                let id = check_node(&HEARTBEAT, m.node)?;
                HB_STATE.encode_raw(&mut d, m.state as i64)?;
                HB_BOOT_COUNT.encode_raw(&mut d, i64::from(m.boot_count))?;
                HB_TX_ERRORS.encode_raw(&mut d, i64::from(m.tx_errors))?;
                HB_RX_ERRORS.encode_raw(&mut d, i64::from(m.rx_errors))?;
                HB_TABLE_CRC.encode_raw(&mut d, i64::from(m.table_crc))?;
                HB_FW_MAJOR.encode_raw(&mut d, i64::from(m.fw_major))?;
                HB_FW_MINOR.encode_raw(&mut d, i64::from(m.fw_minor))?;
                id
            }
            Message::TableCmd(m) => {
                let id = check_node(&TABLE_CMD, m.node)?;
                CMD.encode_raw(&mut d, i64::from(m.cmd.code().code()))?;
                CMD_SESSION.encode_raw(&mut d, i64::from(m.session))?;
                match m.cmd {
                    Command::Begin => CMD_SEGMENT_COUNT.encode_raw(&mut d, 6)?,
                    Command::Segment(f, raw) => SEGMENTS[f as usize].encode_raw(&mut d, raw)?,
                    Command::Commit { crc } => CMD_TABLE_CRC.encode_raw(&mut d, i64::from(crc))?,
                    Command::CommitAuth { counter_lo, mac } => {
                        CMD_COUNTER_LO.encode_raw(&mut d, i64::from(counter_lo))?;
                        CMD_COMMIT_MAC.encode_raw(&mut d, i64::from(mac))?;
                    }
                    Command::Readback { nonce } => {
                        CMD_NONCE.encode_raw(&mut d, i64::from(nonce))?
                    }
                    Command::Abort => {}
                }
                id
            }
            Message::TableReply(m) => {
                let id = check_node(&TABLE_REPLY, m.node)?;
                REPLY_SESSION.encode_raw(&mut d, i64::from(m.session))?;
                match m.reply {
                    Reply::Ack { cmd, held_crc } => {
                        REPLY.encode_raw(&mut d, 0)?;
                        ACKED_CMD.encode_raw(&mut d, i64::from(cmd.code()))?;
                        HELD_CRC.encode_raw(&mut d, i64::from(held_crc))?;
                    }
                    Reply::Nack {
                        cmd,
                        held_crc,
                        reason,
                    } => {
                        REPLY.encode_raw(&mut d, 1)?;
                        NACKED_CMD.encode_raw(&mut d, i64::from(cmd.code()))?;
                        NACK_HELD_CRC.encode_raw(&mut d, i64::from(held_crc))?;
                        NACK_REASON.encode_raw(&mut d, reason as i64)?;
                    }
                    Reply::Readback(f, raw) => {
                        REPLY.encode_raw(&mut d, 16 + i64::from(f.seq()))?;
                        READBACK[f as usize].encode_raw(&mut d, raw)?;
                    }
                    Reply::Freshness { counter } => {
                        REPLY.encode_raw(&mut d, 2)?;
                        NODE_COUNTER.encode_raw(&mut d, i64::from(counter))?;
                    }
                    Reply::ReadbackMac { mac } => {
                        REPLY.encode_raw(&mut d, 3)?;
                        RB_MAC.encode_raw(&mut d, i64::from(mac))?;
                    }
                }
                id
            }
            Message::Trigger(t) => {
                TRIGGER_COMMAND.encode_raw(&mut d, t.command as i64)?;
                TRIGGER_COUNTER_LO.encode_raw(&mut d, i64::from(t.counter_lo))?;
                TRIGGER_MAC.encode_raw(&mut d, i64::from(t.mac))?;
                TRIGGER.base_id
            }
        };
        Ok((id, d, DLC))
    }

    /// Encodes into any `embedded_can` frame type.
    pub fn to_frame<F: embedded_can::Frame>(&self) -> Result<F, EncodeError> {
        let (id, data, _) = self.encode()?;
        let id = embedded_can::StandardId::new(id).ok_or(EncodeError::Frame)?;
        F::new(id, &data).ok_or(EncodeError::Frame)
    }
}

fn encode_imu(
    spec: &MessageSpec,
    axes: &[SignalSpec; 3],
    m: &ImuVector,
    d: &mut [u8; 8],
) -> Result<u16, EncodeError> {
    let id = check_node(spec, m.node)?;
    for (axis, v) in axes.iter().zip(m.xyz) {
        axis.encode(d, v)?;
    }
    IMU_TIMESTAMP_LO.encode_raw(d, i64::from(m.timestamp_lo))?;
    Ok(id)
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
        (1i64..=11).prop_map(|r| NackReason::from_raw(r).unwrap())
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
    fn imu(axes: [SignalSpec; 3]) -> impl Strategy<Value = ImuVector> {
        (
            node(),
            grid(axes[0]),
            grid(axes[1]),
            grid(axes[2]),
            any::<u16>(),
        )
            .prop_map(|(node, x, y, z, timestamp_lo)| ImuVector {
                node,
                xyz: [x, y, z],
                timestamp_lo,
            })
    }

    fn message() -> impl Strategy<Value = Message> {
        let page = prop_oneof![
            (any::<u32>(), grid(EE_POS_X))
                .prop_map(|(timestamp_us, x)| PosePage::TimePosX { timestamp_us, x }),
            (grid(EE_POS_Y), grid(EE_POS_Z)).prop_map(|(y, z)| PosePage::PosYZ { y, z }),
            (grid(EE_QUAT_W), grid(EE_QUAT_X)).prop_map(|(w, x)| PosePage::QuatWX { w, x }),
            (grid(EE_QUAT_Y), grid(EE_QUAT_Z)).prop_map(|(y, z)| PosePage::QuatYZ { y, z }),
        ];
        let command = prop_oneof![
            Just(Command::Begin),
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
        ];
        let states = [
            NodeState::Boot,
            NodeState::Operational,
            NodeState::Staging,
            NodeState::Fault,
        ];
        prop_oneof![
            (joint(), any::<u32>(), grid(JS_ANGLE), grid(JS_RATE)).prop_map(
                |(node, timestamp_us, angle, rate)| Message::JointState(JointState {
                    node,
                    timestamp_us,
                    angle,
                    rate
                })
            ),
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
