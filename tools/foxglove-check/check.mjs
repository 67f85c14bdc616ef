// Reads a guard MCAP log with Foxglove's own reader (@mcap/core, the library Foxglove opens MCAP
// files with): prints one JSON line with the log's time range in UTC, its topics with their message
// counts, the first /log text and the metadata names. Exits 1 on a file it cannot read.
//
//   cd tools/foxglove-check && npm install && node check.mjs LOG.mcap
import { open } from "node:fs/promises";
import { McapIndexedReader } from "@mcap/core";
import zstd from "@foxglove/wasm-zstd";

const path = process.argv[2];
if (!path) {
  console.error("usage: node check.mjs LOG.mcap");
  process.exit(2);
}
try {
  await zstd.isLoaded;
  const handle = await open(path, "r");
  const size = BigInt((await handle.stat()).size);
  const readable = {
    size: async () => size,
    read: async (offset, length) => {
      const buffer = new Uint8Array(Number(length));
      await handle.read(buffer, 0, Number(length), Number(offset));
      return buffer;
    },
  };
  const reader = await McapIndexedReader.Initialize({
    readable,
    decompressHandlers: { zstd: (data, decompressedSize) => zstd.decompress(data, Number(decompressedSize)) },
  });
  const topics = {};
  for (const channel of reader.channelsById.values()) {
    topics[channel.topic] = Number(reader.statistics?.channelMessageCounts.get(channel.id) ?? 0n);
  }
  let firstLog = null;
  const logChannel = [...reader.channelsById.values()].find((c) => c.topic === "/log");
  for await (const message of reader.readMessages({ topics: ["/log"] })) {
    firstLog = { log_time_ns: message.logTime.toString(), bytes: message.data.length, channel: logChannel?.id };
    break;
  }
  const metadata = [];
  for await (const m of reader.readMetadata()) metadata.push(m.name);
  const start = reader.statistics.messageStartTime;
  const end = reader.statistics.messageEndTime;
  const utc = (ns) => new Date(Number(ns / 1000000n)).toISOString();
  console.log(JSON.stringify({
    start_utc: utc(start), end_utc: utc(end), start_ns: start.toString(), topics, first_log: firstLog, metadata,
  }));
  await handle.close();
} catch (error) {
  console.error(`${path}: ${error.message}`);
  process.exit(1);
}
