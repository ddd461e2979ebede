#!/usr/bin/env python3
"""Decodes a `candump -L` log with cantools against a DBC, strictly.

Usage: check_candump.py <dbc> <log>
Prints one JSON object: {"frames": N, "unknown": U, "undecodable": D, "counts": {message: n}}
and exits 1 if any frame has an identifier the DBC lacks or fails to decode (wrong length,
multiplexer value without a definition, ...), 0 otherwise.
"""
import json
import sys

import cantools

db = cantools.database.load_file(sys.argv[1])
counts = {}
unknown = undecodable = frames = 0
errors = []
for line in open(sys.argv[2]):
    line = line.strip()
    if not line:
        continue
    # (1436509052.249713) vcan0 101#0011223344556677
    _, _, frame = line.split()
    ident, data = frame.split("#")
    frames += 1
    if len(ident) > 3:
        unknown += 1
        errors.append(f"extended id {ident}")
        continue
    try:
        msg = db.get_message_by_frame_id(int(ident, 16))
    except KeyError:
        unknown += 1
        errors.append(f"unknown id {ident}")
        continue
    try:
        payload = bytes.fromhex(data)
        if len(payload) != msg.length:
            raise ValueError(f"length {len(payload)} != {msg.length}")
        msg.decode(payload, decode_choices=True, allow_truncated=False)
    except Exception as e:  # noqa: BLE001 - every failure counts as undecodable
        undecodable += 1
        errors.append(f"{msg.name} {data}: {e}")
        continue
    counts[msg.name] = counts.get(msg.name, 0) + 1
print(json.dumps({"frames": frames, "unknown": unknown, "undecodable": undecodable, "counts": counts, "errors": errors[:20]}))
sys.exit(1 if unknown or undecodable or frames == 0 else 0)
