// Reads an MCAP file with @mcap/core's McapIndexedReader, the reader Foxglove and Lichtblick
// open files with: the summary and its chunk indexes, then every message through the message
// indexes, every chunk's CRC checked. Prints {"messages": {topic: count}, "statistics": N} on
// stdout; exits 1 naming the error if the file does not read.
//
// Usage: node tests/js/read_mcap.mjs FILE.mcap   (`cargo xtask setup` runs `npm ci` here)
import { open } from "node:fs/promises";
import { McapIndexedReader } from "@mcap/core";
import { decompress } from "fzstd";

const path = process.argv[2];
if (!path) {
  console.error("usage: read_mcap.mjs FILE.mcap");
  process.exit(64);
}
const file = await open(path, "r");
try {
  const size = BigInt((await file.stat()).size);
  const readable = {
    size: async () => size,
    read: async (offset, length) => {
      const buffer = new Uint8Array(Number(length));
      const { bytesRead } = await file.read(buffer, 0, buffer.length, Number(offset));
      if (bytesRead !== buffer.length) {
        throw new Error(`short read at ${offset}: ${bytesRead} of ${length} bytes`);
      }
      return buffer;
    },
  };
  const reader = await McapIndexedReader.Initialize({
    readable,
    decompressHandlers: {
      zstd: (data, size) => decompress(data, new Uint8Array(Number(size))),
    },
  });
  const messages = {};
  for (const channel of reader.channelsById.values()) {
    messages[channel.topic] = 0;
  }
  for await (const message of reader.readMessages({ validateCrcs: true })) {
    messages[reader.channelsById.get(message.channelId).topic] += 1;
  }
  const statistics = reader.statistics ? Number(reader.statistics.messageCount) : null;
  console.log(JSON.stringify({ messages, statistics }));
} catch (e) {
  console.error(`${path}: ${e.message}`);
  process.exitCode = 1;
} finally {
  await file.close();
}
