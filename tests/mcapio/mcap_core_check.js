// Read an MCAP file with @mcap/core (the TypeScript library Foxglove uses), CRCs validated,
// through the indexed reader (summary, chunk and metadata indexes) and the stream reader.
// Prints JSON: {"indexed": {topic: count}, "stream": {topic: count}, "metadata": [names],
// "statistics": message count}. Needs @mcap/core and fzstd on NODE_PATH (zstd chunks).
"use strict";
const fs = require("fs");
const { McapIndexedReader, McapStreamReader } = require("@mcap/core");
const fzstd = require("fzstd");

const decompressHandlers = {
  zstd: (data, size) => fzstd.decompress(data, new Uint8Array(Number(size))),
};

async function main() {
  const buf = fs.readFileSync(process.argv[2]);
  const readable = {
    size: async () => BigInt(buf.length),
    read: async (offset, size) => buf.subarray(Number(offset), Number(offset + size)),
  };
  const reader = await McapIndexedReader.Initialize({ readable, decompressHandlers });
  const indexed = {};
  for await (const message of reader.readMessages({ validateCrcs: true })) {
    const topic = reader.channelsById.get(message.channelId).topic;
    indexed[topic] = (indexed[topic] || 0) + 1;
  }
  const metadata = [];
  for await (const record of reader.readMetadata()) {
    metadata.push(record.name);
  }
  const stream = {};
  const channels = new Map();
  const streamReader = new McapStreamReader({ decompressHandlers, validateCrcs: true });
  streamReader.append(buf);
  let record;
  while ((record = streamReader.nextRecord()) !== undefined) {
    if (record.type === "Channel") channels.set(record.id, record.topic);
    if (record.type === "Message") {
      const topic = channels.get(record.channelId);
      stream[topic] = (stream[topic] || 0) + 1;
    }
  }
  if (!streamReader.done()) throw new Error("stream reader did not reach the end magic");
  process.stdout.write(
    JSON.stringify({
      indexed,
      stream,
      metadata,
      statistics: Number(reader.statistics.messageCount),
    }),
  );
}

main().catch((err) => {
  process.stderr.write(String(err && err.stack ? err.stack : err));
  process.exit(1);
});
