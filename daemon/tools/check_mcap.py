#!/usr/bin/env python3
"""Reads an exocald MCAP log with the Python `mcap` package, validating every CRC.

Usage: check_mcap.py FILE.mcap
Prints a JSON object {topic: message count} on stdout; exits non-zero (with the reason on
stderr) if the file is not a valid, finished MCAP, a CRC does not match, or a message is not
valid JSON. Setup: `python3 -m venv .venv && .venv/bin/pip install mcap zstandard`.
"""
import json
import sys

from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from mcap.records import Footer


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
    # 2. Indexed read through the summary, chunk CRCs checked again, messages decoded.
    counts = {}
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        for channel in summary.channels.values():
            counts.setdefault(channel.topic, 0)
        for _schema, channel, message in reader.iter_messages():
            json.loads(message.data)
            counts[channel.topic] += 1
        stats = summary.statistics
        if stats is not None and stats.message_count != sum(counts.values()):
            print(
                f"{path}: statistics say {stats.message_count} messages, read {sum(counts.values())}",
                file=sys.stderr,
            )
            return 1
    print(json.dumps(counts, sort_keys=True))
    return 0


if __name__ == "__main__":
    if len(sys.argv) != 2:
        print(__doc__, file=sys.stderr)
        sys.exit(64)
    sys.exit(main(sys.argv[1]))
