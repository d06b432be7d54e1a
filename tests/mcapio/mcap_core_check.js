// Read MCAP files with @mcap/core (the TypeScript library Foxglove uses), CRCs validated,
// through the indexed reader (summary, chunk and metadata indexes) and the stream reader.
// Usage: node mcap_core_check.js FILE... (one node process for every file: its start-up
// and the libraries' load cost about 0.3 s of CPU). Prints JSON {"results": {FILE:
// {"indexed": {topic: count}, "stream": {topic: count}, "metadata": [names], "statistics":
// message count}}}, or {"missing": reason} (exit 0) when @mcap/core or fzstd cannot be
// loaded from NODE_PATH (zstd chunks need fzstd).
"use strict";
const fs = require("fs");

let core;
let fzstd;
try {
  core = require("@mcap/core");
  fzstd = require("fzstd");
} catch (err) {
  process.stdout.write(JSON.stringify({ missing: String(err && err.message).split("\n")[0] }));
  process.exit(0);
}
const { McapIndexedReader, McapStreamReader } = core;

const decompressHandlers = {
  zstd: (data, size) => fzstd.decompress(data, new Uint8Array(Number(size))),
};

async function check(path) {
  const buf = fs.readFileSync(path);
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
  return { indexed, stream, metadata, statistics: Number(reader.statistics.messageCount) };
}

async function main() {
  const results = {};
  for (const path of process.argv.slice(2)) {
    results[path] = await check(path);
  }
  process.stdout.write(JSON.stringify({ results }));
}

main().catch((err) => {
  process.stderr.write(String(err && err.stack ? err.stack : err));
  process.exit(1);
});
