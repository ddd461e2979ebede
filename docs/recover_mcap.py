#!/usr/bin/env python3
"""Recovers an exocald MCAP log left by a killed daemon (no summary, no footer).

Usage: python3 docs/recover_mcap.py KILLED.mcap RECOVERED.mcap
Needs `pip install mcap zstandard`. Scans the file linearly (it never seeks to the missing
footer), copies every schema, channel and message of each complete chunk, and stops at the
first truncated or corrupt record; writes a complete file with summary and footer and prints
how many messages it kept and the log time of the last one.
"""
import sys

from mcap.reader import NonSeekingReader
from mcap.writer import CompressionType, Writer


def recover(src, dst):
    kept, last = 0, None
    with open(src, "rb") as f, open(dst, "wb") as out:
        w = Writer(out, compression=CompressionType.ZSTD)
        w.start(profile="", library="exocald recover_mcap.py")
        schemas, channels = {}, {}
        try:
            reader = NonSeekingReader(f, validate_crcs=True)
            for schema, channel, message in reader.iter_messages(log_time_order=False):
                if schema is not None and schema.id not in schemas:
                    schemas[schema.id] = w.register_schema(schema.name, schema.encoding, schema.data)
                if channel.id not in channels:
                    channels[channel.id] = w.register_channel(
                        channel.topic, channel.message_encoding,
                        schemas.get(channel.schema_id, 0), channel.metadata)
                w.add_message(channels[channel.id], message.log_time, message.data,
                              message.publish_time, message.sequence)
                kept += 1
                last = message.log_time if last is None else max(last, message.log_time)
        except Exception as e:  # noqa: BLE001 - any error here is the truncated tail
            print(f"stopped at the truncated tail: {type(e).__name__}: {e}", file=sys.stderr)
        w.finish()
    return kept, last


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    kept, last = recover(sys.argv[1], sys.argv[2])
    print(f"{kept} messages recovered; last log time {last} ns")
