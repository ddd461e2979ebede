#!/usr/bin/env python3
"""Reads an exocald MCAP log with the Python `mcap` package, validating every CRC and decoding
every message with the protobuf schemas the file carries (`mcap-protobuf-support`: no generated
code, the same way Foxglove reads it).

Usage: check_mcap.py FILE.mcap
Prints a JSON object on stdout: {"counts": {topic: record count}, "messages": {topic: message
count}, "samples": {...}} (records: the frames of /can/rx and /can/tx, which are written in
batches, one per message elsewhere) where
samples are decoded values the Rust test compares with what it wrote (the first /can/rx frame,
the first joint state, the first aligned sample, the collection end, the calibration's condition
number); exits non-zero (with the reason on stderr) if the file is not a valid, finished MCAP, a
CRC does not match, or a message does not decode. Setup: `pip install -r tests/requirements.txt`.
"""
import json
import sys

from mcap.reader import make_reader
from mcap.records import Footer
from mcap.stream_reader import StreamReader
from mcap_protobuf.decoder import DecoderFactory


def main(path: str) -> int:
    # 1. Linear scan of every record, chunk and data-section CRCs checked.
    footer_seen = False
    with open(path, "rb") as f:
        for record in StreamReader(f, skip_magic=False, validate_crcs=True).records:
            if isinstance(record, Footer):
                footer_seen = True
    if not footer_seen:
        print(f"{path}: no footer (file not finished)", file=sys.stderr)
        return 1
    # 2. Indexed read through the summary, chunk CRCs checked again, every message decoded
    #    with its channel's protobuf schema.
    counts = {}
    messages = {}
    samples = {}
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        for channel in summary.channels.values():
            counts.setdefault(channel.topic, 0)
            messages.setdefault(channel.topic, 0)
            if channel.message_encoding != "protobuf":
                print(f"{path}: {channel.topic} is {channel.message_encoding}", file=sys.stderr)
                return 1
        for schema, channel, message, proto in reader.iter_decoded_messages():
            messages[channel.topic] += 1
            # A batch of raw frames (times relative to base_ns), or one (logs written before
            # the batches); one record per message elsewhere.
            if schema.name == "exocal.CanFrames":
                frames = [
                    {
                        "id": f.id,
                        "flags": f.flags & 3,
                        "dlc": f.dlc,
                        "data": list(f.data),
                        "host_ns": proto.base_ns + f.host_offset_ns,
                        "kernel_ns": proto.base_ns + f.host_offset_ns + f.kernel_offset_ns
                        if f.flags & 4
                        else 0,
                    }
                    for f in proto.frames
                ]
            elif schema.name == "exocal.CanFrame":
                frames = [
                    {
                        "id": proto.id,
                        "flags": proto.flags,
                        "dlc": proto.dlc,
                        "data": list(proto.data),
                        "host_ns": proto.host_ns,
                        "kernel_ns": proto.kernel_ns,
                    }
                ]
            else:
                frames = [None]
            counts[channel.topic] += len(frames)
            if messages[channel.topic] != 1 and channel.topic != "/calibration":
                continue
            if channel.topic == "/can/rx":
                samples["can_rx"] = frames[0]
            elif channel.topic == "/joint_states":
                j = proto.joints[0]
                samples["joint_state"] = {
                    "name": j.name,
                    "position": j.position,
                    "velocity": j.velocity,
                    # foxglove's timestamps are google.protobuf.Timestamp
                    "sec": proto.timestamp.seconds,
                    "nsec": proto.timestamp.nanos,
                }
            elif channel.topic == "/aligned":
                samples["aligned"] = {"t": proto.t, "joints": list(proto.joints)}
            elif channel.topic == "/collection":
                samples["collection_frames"] = proto.frames
            elif channel.topic == "/calibration":
                samples["condition_number"] = proto.condition_number
            elif channel.topic == "/events":
                samples["event"] = {"level": proto.level, "message": proto.message}
        stats = summary.statistics
        if stats is not None and stats.message_count != sum(messages.values()):
            print(
                f"{path}: statistics say {stats.message_count} messages, read {sum(messages.values())}",
                file=sys.stderr,
            )
            return 1
    print(json.dumps({"counts": counts, "messages": messages, "samples": samples}, sort_keys=True))
    return 0


if __name__ == "__main__":
    if len(sys.argv) != 2:
        print(__doc__, file=sys.stderr)
        sys.exit(64)
    sys.exit(main(sys.argv[1]))
