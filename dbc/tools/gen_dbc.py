#!/usr/bin/env python3
"""Writes dbc/exocal.dbc.

The .dbc file is the protocol contract and is committed; this script is only how its repetitive
per-node parts were written. Edit here, regenerate with `python3 dbc/tools/gen_dbc.py`, and the
crate's tests (`cargo test -p exocal-dbc`) check every Rust message and signal against the result.
"""
import os

JOINTS = [f"Joint{i}" for i in range(1, 8)]
EE = "EndEffector"
CTRL = "Controller"
NODES = JOINTS + [EE]
NODE_ID = {n: i + 1 for i, n in enumerate(NODES)}

TWO_PI = "6.283185"
out = []
comments = []
vals = []
cycle = []


def sig(name, start, length, signed, factor, offset, lo, hi, unit, rx, mux="", comment=None):
    m = f" {mux}" if mux else ""
    s = "-" if signed else "+"
    out.append(f' SG_ {name}{m} : {start}|{length}@1{s} ({factor},{offset}) [{lo}|{hi}] "{unit}" {rx}')
    return name


def msg(mid, name, tx, cmt, cyc=None):
    out.append("")
    out.append(f"BO_ {mid} {name}: 8 {tx}")
    comments.append(f'CM_ BO_ {mid} "{cmt}";')
    if cyc:
        cycle.append(f'BA_ "GenMsgCycleTime" BO_ {mid} {cyc};')


def cm(mid, signal, text):
    comments.append(f'CM_ SG_ {mid} {signal} "{text}";')


def val(mid, signal, table):
    body = " ".join(f'{k} "{v}"' for k, v in table)
    vals.append(f"VAL_ {mid} {signal} {body} ;")


# Periodic data, node -> controller.
for j in JOINTS:
    mid = 0x100 | NODE_ID[j]
    msg(mid, f"JointState_{j}", j, f"Fused joint angle of {j} (the angle it believes, drift included), sampled at Timestamp.", 10)
    sig("Timestamp", 0, 32, False, 1, 0, 0, 4294967295, "us", CTRL)
    cm(mid, "Timestamp", "Node-local microsecond clock at sampling; free-running, rolls over at 2^32 us (71.6 min), reset by a reboot.")
    sig("Angle", 32, 20, True, "1E-005", 0, -5.24287, 5.24287, "rad", CTRL)
    cm(mid, "Angle", "Joint angle theta_i as the node measures it (D-H convention, offset not applied). Raw -524288 means invalid (NaN).")
    val(mid, "Angle", [(-524288, "Invalid")])
    sig("Rate", 52, 12, True, "0.01", 0, -20.47, 20.47, "rad/s", CTRL)
    cm(mid, "Rate", "Joint angular rate. Raw -2048 means invalid (NaN).")
    val(mid, "Rate", [(-2048, "Invalid")])

mid = 0x148
msg(mid, f"EePose_{EE}", EE, "End-effector reference pose in the base frame (the lever-effect reference IMU): four pages that share Seq; page 0 carries the sampling Timestamp.", 10)
sig("Page", 0, 2, False, 1, 0, 0, 3, "", CTRL, "M")
cm(mid, "Page", "Multiplexer: which part of the pose this frame carries.")
val(mid, "Page", [(0, "TimePosX"), (1, "PosYZ"), (2, "QuatWX"), (3, "QuatYZ")])
sig("Seq", 2, 6, False, 1, 0, 0, 63, "", CTRL)
cm(mid, "Seq", "Pose sequence number (wraps at 64); the four pages of one pose share it.")
sig("Timestamp", 8, 32, False, 1, 0, 0, 4294967295, "us", CTRL, "m0")
cm(mid, "Timestamp", "Node-local microsecond clock at sampling; rolls over at 2^32 us.")
for name, start, page in [("PosX", 40, 0), ("PosY", 8, 1), ("PosZ", 32, 1)]:
    sig(name, start, 24, True, "1E-006", 0, -2, 2, "m", CTRL, f"m{page}")
    cm(mid, name, f"End-effector position {name[-1].lower()} in the base frame.")
for name, start, page in [("QuatW", 8, 2), ("QuatX", 32, 2), ("QuatY", 8, 3), ("QuatZ", 32, 3)]:
    sig(name, start, 24, True, "1E-006", 0, -1, 1, "", CTRL, f"m{page}")
    cm(mid, name, f"Orientation unit quaternion component {name[-1].lower()} (base frame to end-effector frame).")

IMU = [
    ("ImuGyro", 0x200, "0.001", "rad/s", -32.767, 32.767, "Raw gyroscope, sensor frame, bias included."),
    ("ImuAccel", 0x210, "0.002", "m/s^2", -65.534, 65.534, "Raw accelerometer (specific force), sensor frame."),
    ("ImuMag", 0x220, "0.01", "uT", -327.67, 327.67, "Raw magnetometer, sensor frame."),
]
for base_name, base, factor, unit, lo, hi, text in IMU:
    for n in NODES:
        mid = base | NODE_ID[n]
        msg(mid, f"{base_name}_{n}", n, f"{text} Node {n}.", 10)
        for axis, start in [("X", 0), ("Y", 16), ("Z", 32)]:
            sig(axis, start, 16, True, factor, 0, lo, hi, unit, CTRL)
            cm(mid, axis, f"{axis} axis. Raw -32768 means invalid (NaN).")
            val(mid, axis, [(-32768, "Invalid")])
        sig("TimestampLo", 48, 16, False, 1, 0, 0, 65535, "us", CTRL)
        cm(mid, "TimestampLo", "Low 16 bits of the node clock at sampling; the full clock is in JointState/EePose Timestamp.")

# Table transfer.
TABLE = [
    ("SegA", 16, True, "m", "-1", "1", "D-H link length a_i (resolution 1 um)."),
    ("SegAlpha", 17, True, "rad", f"-{TWO_PI}", TWO_PI, "D-H link twist alpha_i (resolution 1 urad)."),
    ("SegD", 18, True, "m", "-1", "1", "D-H link offset d_i (resolution 1 um)."),
    ("SegThetaOffset", 19, True, "rad", f"-{TWO_PI}", TWO_PI, "D-H joint angle offset (resolution 1 urad)."),
    ("SegTau", 20, False, "s", "1E-006", "4294.967295", "Gauss-Markov drift correlation time tau (resolution 1 us)."),
    ("SegSigma", 21, False, "rad/s", "0", "4294.967295", "Gauss-Markov drift deviation sigma (resolution 1 urad/s)."),
]
CMDS = [(1, "Begin")] + [(code, name[3:]) for name, code, *_ in TABLE] + [(32, "Commit"), (33, "CommitAuth"), (48, "Readback"), (63, "Abort")]
CMD_VALS = [(c, n if c < 16 or c > 21 else "Seg" + n) for c, n in CMDS]
for j in JOINTS:
    mid = 0x600 | NODE_ID[j]
    msg(mid, f"TableCmd_{j}", CTRL, f"Table transfer, controller to {j}: Begin, six segments (one per table field, in order), CommitAuth (freshness counter and MAC; required by a node holding a key), Commit with the CRC-32 of the table; Readback (with a nonce) asks for the held table; Abort drops the staging.")
    sig("Cmd", 0, 8, False, 1, 0, 0, 255, "", j, "M")
    cm(mid, "Cmd", "Multiplexer: the command. Segment commands 16..21 carry their sequence number in the low bits (seq = Cmd - 16).")
    val(mid, "Cmd", CMD_VALS)
    sig("Session", 8, 8, False, 1, 0, 0, 255, "", j)
    cm(mid, "Session", "Transfer session chosen by the controller at Begin; every later frame of the transfer repeats it.")
    sig("SegmentCount", 16, 8, False, 1, 0, 6, 6, "", j, "m1")
    cm(mid, "SegmentCount", "Number of segments that follow (table format 1: always 6).")
    for name, code, signed, unit, lo, hi, text in TABLE:
        sig(name, 16, 32, signed, "1E-006", 0, lo, hi, unit, j, f"m{code}")
        cm(mid, name, text)
    sig("TableCrc", 16, 32, False, 1, 0, 0, 4294967295, "", j, "m32")
    cm(mid, "TableCrc", "CRC-32 (ISO-HDLC, as zlib.crc32) of the 24-byte table: the six segment raw values as 32-bit little-endian words in sequence order.")
    sig("CounterLo", 16, 16, False, 1, 0, 0, 65535, "", j, "m33")
    cm(mid, "CounterLo", "Low 16 bits of the freshness counter of this commit; the node takes the full counter as the smallest value above the one it stored with these low bits.")
    sig("CommitMac", 32, 32, False, 1, 0, 0, 4294967295, "", j, "m33")
    cm(mid, "CommitMac", "First 32 bits (big-endian) of AES-128-CMAC with the node's key over 'C', node id, session, full counter (u32 LE), the 24 table bytes and the CRC (u32 LE).")
    sig("Nonce", 16, 32, False, 1, 0, 0, 4294967295, "", j, "m48")
    cm(mid, "Nonce", "Chosen by the controller for this readback; the node's ReadbackMac covers it, so a recorded answer does not replay.")

    mid = 0x580 | NODE_ID[j]
    msg(mid, f"TableReply_{j}", j, f"Table transfer, {j} to controller: ACK or NACK of the last command with the CRC of the table the node now holds (installed, not staged), or one readback segment.")
    sig("Reply", 0, 8, False, 1, 0, 0, 255, "", CTRL, "M")
    cm(mid, "Reply", "Multiplexer: 0 ACK, 1 NACK, 2 freshness counter (after Begin, keyed nodes), 3 readback MAC (before the readback's ACK, keyed nodes), 16..21 readback segment (seq = Reply - 16).")
    val(mid, "Reply", [(0, "Ack"), (1, "Nack"), (2, "Freshness"), (3, "ReadbackMac")] + [(code, "Readback" + name[3:]) for name, code, *_ in TABLE])
    sig("Session", 8, 8, False, 1, 0, 0, 255, "", CTRL)
    cm(mid, "Session", "Session of the command this replies to.")
    for m in (0, 1):
        sig("AckedCmd" if m == 0 else "NackedCmd", 16, 8, False, 1, 0, 0, 255, "", CTRL, f"m{m}")
        val(mid, "AckedCmd" if m == 0 else "NackedCmd", CMD_VALS)
        sig("HeldCrc" if m == 0 else "NackHeldCrc", 24, 32, False, 1, 0, 0, 4294967295, "", CTRL, f"m{m}")
    cm(mid, "AckedCmd", "The command acknowledged.")
    cm(mid, "NackedCmd", "The command refused.")
    cm(mid, "HeldCrc", "CRC-32 of the table the node holds now (after a successful Commit: the new one).")
    cm(mid, "NackHeldCrc", "CRC-32 of the table the node holds now (unchanged by a refused command).")
    sig("NackReason", 56, 8, False, 1, 0, 1, 11, "", CTRL, "m1")
    cm(mid, "NackReason", "Why the command was refused.")
    val(mid, "NackReason", [(1, "BadSession"), (2, "OutOfOrder"), (3, "CrcMismatch"), (4, "Incomplete"), (5, "OutOfRange"), (6, "NotStaging"), (7, "FlashError"), (8, "BadFormat"), (9, "NoTable"), (10, "BadMac"), (11, "StaleCounter")])
    sig("NodeCounter", 16, 32, False, 1, 0, 0, 4294967295, "", CTRL, "m2")
    cm(mid, "NodeCounter", "The freshness counter the node stored with its table; the next CommitAuth must carry a higher one.")
    sig("RbMac", 16, 32, False, 1, 0, 0, 4294967295, "", CTRL, "m3")
    cm(mid, "RbMac", "First 32 bits (big-endian) of AES-128-CMAC with the node's key over 'R', node id, the Readback's nonce (u32 LE), the held CRC (u32 LE) and the 24 held table bytes.")
    for name, code, signed, unit, lo, hi, text in TABLE:
        sig("Rb" + name[3:], 16, 32, signed, "1E-006", 0, lo, hi, unit, CTRL, f"m{code}")
        cm(mid, "Rb" + name[3:], "Readback of the held table: " + text)

for n in NODES:
    mid = 0x700 | NODE_ID[n]
    msg(mid, f"Heartbeat_{n}", n, f"Heartbeat of {n}.", 1000)
    sig("State", 0, 4, False, 1, 0, 0, 3, "", CTRL)
    val(mid, "State", [(0, "Boot"), (1, "Operational"), (2, "Staging"), (3, "Fault")])
    cm(mid, "State", "Node state; Staging while a table transfer is open.")
    sig("BootCount", 4, 4, False, 1, 0, 0, 15, "", CTRL)
    cm(mid, "BootCount", "Boots since flashing, modulo 16: a change means the node rebooted (clock and counters reset).")
    sig("TxErrors", 8, 8, False, 1, 0, 0, 255, "", CTRL)
    cm(mid, "TxErrors", "CAN transmit error counter (TEC), saturating at 255.")
    sig("RxErrors", 16, 8, False, 1, 0, 0, 255, "", CTRL)
    cm(mid, "RxErrors", "CAN receive error counter (REC) plus refused frames, saturating at 255.")
    sig("TableCrc", 24, 32, False, 1, 0, 0, 4294967295, "", CTRL)
    cm(mid, "TableCrc", "CRC-32 of the table the node holds (0 on the end-effector node, which holds none).")
    sig("FwMajor", 56, 4, False, 1, 0, 0, 15, "", CTRL)
    sig("FwMinor", 60, 4, False, 1, 0, 0, 15, "", CTRL)
    cm(mid, "FwMajor", "Firmware version, major.")
    cm(mid, "FwMinor", "Firmware version, minor.")

mid = 0x020
msg(mid, "Trigger", "Vector__XXX", "Operator request to the controller (a button or a bench tool), authenticated with the trigger key.")
sig("Command", 0, 8, False, 1, 0, 1, 2, "", CTRL)
val(mid, "Command", [(1, "StartCalibration"), (2, "Abort")])
cm(mid, "Command", "What the operator asks for.")
sig("CounterLo", 16, 16, False, 1, 0, 0, 65535, "", CTRL)
cm(mid, "CounterLo", "Low 16 bits of the sender's freshness counter; the controller takes the smallest value above the last one it accepted with these low bits.")
sig("Mac", 32, 32, False, 1, 0, 0, 4294967295, "", CTRL)
cm(mid, "Mac", "First 32 bits (big-endian) of AES-128-CMAC with the trigger key over 'T', Command and the full counter (u32 LE).")

header = f"""VERSION "exocal-2"


NS_ :
	CM_
	BA_DEF_
	BA_
	VAL_
	BA_DEF_DEF_

BS_:

BU_: {CTRL} {' '.join(NODES)}
"""
node_cm = [f'CM_ BU_ {CTRL} "The suit controller running exocald; sends table transfers.";']
node_cm += [f'CM_ BU_ {j} "Joint node {j[-1]}: 9-DoF IMU and fused joint angle; node id {NODE_ID[j]}.";' for j in JOINTS]
node_cm.append(f'CM_ BU_ {EE} "End-effector reference node (lever-effect IMU); node id 8.";')
db_cm = ['CM_ "exocal suit CAN protocol. Classic CAN, 11-bit identifiers, every frame DLC 8, little-endian (Intel) signals. Identifier = function base | node id (Joint1..Joint7 = 1..7, EndEffector = 8): JointState 0x100, EePose 0x140, ImuGyro 0x200, ImuAccel 0x210, ImuMag 0x220, TableReply 0x580, TableCmd 0x600, Heartbeat 0x700; Trigger 0x020.";']
attrs = [
    'BA_DEF_ BO_ "GenMsgCycleTime" INT 0 65535;',
    'BA_DEF_DEF_ "GenMsgCycleTime" 0;',
]
text = header + "\n".join(out) + "\n\n" + "\n".join(db_cm + node_cm + comments) + "\n" + "\n".join(attrs + cycle) + "\n" + "\n".join(vals) + "\n"
path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "exocal.dbc")
with open(path, "w", newline="\n") as f:
    f.write(text)
