"""MCAP files written by another implementation (python `mcap`), in every variant its writer has,
and cut short: the conformance set `daemon/tests/mcap_conformance.rs` gives `exocald recover`
and `exocald offline` (issue 47, item 6).

    python mcap_variants.py write OUTDIR              # the files and OUTDIR/manifest.json
    python mcap_variants.py check OUTDIR RECOVERED    # per file, as JSON: what python's stream
        # reader salvages from OUTDIR/F (every record before the cut) and what its indexed
        # reader finds in RECOVERED/F (exocald recover's output), as counts of messages,
        # attachments and metadata records

Variants: chunked or not; zstd, lz4 or no compression; with or without chunk and message
indexes; with or without the summary's statistics and offsets; each with two schemas, three
channels, messages on all of them, an attachment and a metadata record. Each complete file is
also written cut short at a quarter, half and three quarters of its length, and missing its
last 9 bytes (the footer's magic).
"""

import io
import json
import os
import sys

from mcap.reader import make_reader
from mcap.records import Attachment, Message, Metadata
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, IndexType, Writer

MESSAGES_PER_CHANNEL = 40


def write(out_dir):
    os.makedirs(out_dir, exist_ok=True)
    manifest = {}
    for compression in (CompressionType.NONE, CompressionType.ZSTD, CompressionType.LZ4):
        for chunked in (True, False):
            if not chunked and compression != CompressionType.NONE:
                continue  # compression is of chunks
            for indexed in (True, False):
                for summary in (True, False):
                    name = "{}-{}-{}-{}".format(
                        compression.name.lower(),
                        "chunked" if chunked else "unchunked",
                        "indexed" if indexed else "unindexed",
                        "summary" if summary else "nosummary",
                    )
                    buf = io.BytesIO()
                    w = Writer(
                        buf,
                        chunk_size=4096,
                        compression=compression,
                        index_types=IndexType.ALL if indexed else IndexType.NONE,
                        use_chunking=chunked,
                        use_statistics=summary,
                        use_summary_offsets=summary,
                        repeat_channels=summary,
                        repeat_schemas=summary,
                    )
                    w.start(profile="", library="conformance")
                    pose = w.register_schema(name="test.Pose", encoding="jsonschema", data=b"{}")
                    text = w.register_schema(name="test.Text", encoding="jsonschema", data=b"{}")
                    channels = [
                        w.register_channel(topic="/pose", message_encoding="json", schema_id=pose),
                        w.register_channel(topic="/text", message_encoding="json", schema_id=text),
                        w.register_channel(
                            topic="/raw", message_encoding="json", schema_id=text, metadata={"k": "v"}
                        ),
                    ]
                    messages = 0
                    for k in range(MESSAGES_PER_CHANNEL):
                        for c in channels:
                            data = json.dumps({"k": k, "pad": "x" * (k % 17)}).encode()
                            w.add_message(c, log_time=1_000_000 * k + c, publish_time=1_000_000 * k, data=data, sequence=k)
                            messages += 1
                        if k == MESSAGES_PER_CHANNEL // 2:
                            w.add_attachment(
                                log_time=1_000_000 * k, create_time=0, name="calib.urdf",
                                media_type="application/xml", data=b"<robot name='r'/>",
                            )
                            w.add_metadata(name="session", data={"suit": "test", "seed": "7"})
                    w.finish()
                    data = buf.getvalue()
                    with open(os.path.join(out_dir, name + ".mcap"), "wb") as f:
                        f.write(data)
                    manifest[name] = {"messages": messages, "attachments": 1, "metadata": 1, "complete": True}
                    for label, end in (("q1", len(data) // 4), ("q2", len(data) // 2),
                                       ("q3", 3 * len(data) // 4), ("nomagic", len(data) - 9)):
                        cut = name + "-cut-" + label
                        with open(os.path.join(out_dir, cut + ".mcap"), "wb") as f:
                            f.write(data[:end])
                        manifest[cut] = {"messages": messages, "attachments": 1, "metadata": 1, "complete": False}
    with open(os.path.join(out_dir, "manifest.json"), "w") as f:
        json.dump(manifest, f, indent=1, sort_keys=True)


def indexed(path):
    """Counts by the indexed (seeking) reader: needs a whole file with its summary."""
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        return {
            "messages": sum(1 for _ in reader.iter_messages()),
            "attachments": sum(1 for _ in reader.iter_attachments()),
            "metadata": sum(1 for _ in reader.iter_metadata()),
        }


def salvage(path):
    """Counts of the records python's stream reader yields before the file stops making sense."""
    n = {"messages": 0, "attachments": 0, "metadata": 0}
    with open(path, "rb") as f:
        try:
            for r in StreamReader(f, validate_crcs=True).records:
                if isinstance(r, Message):
                    n["messages"] += 1
                elif isinstance(r, Attachment):
                    n["attachments"] += 1
                elif isinstance(r, Metadata):
                    n["metadata"] += 1
        except Exception:  # the cut: everything before it is what there is to salvage
            pass
    return n


def check(out_dir, recovered_dir):
    result = {}
    for name in sorted(json.load(open(os.path.join(out_dir, "manifest.json")))):
        f = name + ".mcap"
        result[name] = {
            "salvaged": salvage(os.path.join(out_dir, f)),
            "recovered": indexed(os.path.join(recovered_dir, f)),
        }
    print(json.dumps(result))


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "write":
        write(sys.argv[2])
    elif len(sys.argv) == 4 and sys.argv[1] == "check":
        check(sys.argv[2], sys.argv[3])
    else:
        sys.exit(__doc__)
