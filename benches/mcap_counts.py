#!/usr/bin/env python3
"""Prints `topic=count` for every channel of an MCAP file (from its summary, CRC-checked by the
reader), one line: `MCAP topic1=n1 topic2=n2 ...`. Used by `benches/ingest.sh` on the daemon's
session log."""

import sys

from mcap.reader import make_reader


def main():
    if len(sys.argv) != 2:
        sys.exit("usage: mcap_counts.py FILE.mcap")
    with open(sys.argv[1], "rb") as f:
        summary = make_reader(f).get_summary()
    if summary is None or summary.statistics is None:
        sys.exit(f"mcap_counts.py: {sys.argv[1]} has no summary (not finished?)")
    counts = summary.statistics.channel_message_counts
    parts = [f"{summary.channels[cid].topic}={n}" for cid, n in sorted(counts.items())]
    print("MCAP " + " ".join(parts))


if __name__ == "__main__":
    main()
