#!/usr/bin/env python3
"""Reads back a daemon session log (MCAP) with the python `mcap` reader, for `benches/ingest.sh`.

    mcap_counts.py FILE.mcap            one line `MCAP topic1=n1 topic2=n2 ...` (from the summary)
    mcap_counts.py --events FILE.mcap   one line `EVENT <log_time_ns> <message>` per /events message
"""

import sys

from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory


def counts(path):
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    if summary is None or summary.statistics is None:
        sys.exit(f"mcap_counts.py: {path} has no summary (not finished?)")
    stats = summary.statistics.channel_message_counts
    parts = [f"{summary.channels[cid].topic}={n}" for cid, n in sorted(stats.items())]
    print("MCAP " + " ".join(parts))


def events(path):
    # foxglove.Log messages, decoded with the protobuf schema the file carries.
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _schema, _channel, message, log in reader.iter_decoded_messages(topics=["/events"]):
            print(f"EVENT {message.log_time} {' '.join(log.message.split())}")


def main():
    args = sys.argv[1:]
    if len(args) == 2 and args[0] == "--events":
        events(args[1])
    elif len(args) == 1:
        counts(args[0])
    else:
        sys.exit(__doc__)


if __name__ == "__main__":
    main()
