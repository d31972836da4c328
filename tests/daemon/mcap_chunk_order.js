// An independent MCAP reader's view of a log file: @mcap/core (the TypeScript library Foxglove uses) streams the file,
// chunk by chunk, and prints per chunk its start/end times from the chunk record and its messages' log times in
// file order, as JSON (times as strings: they are 64-bit). Used by tests/daemon/test_log_order.py.
// usage: node mcap_chunk_order.js FILE.mcap   (with NODE_PATH at the folder holding @mcap/core and lz4js)
"use strict";
const fs = require("fs");
const { McapStreamReader } = require("@mcap/core");
const lz4 = require("lz4js");

const reader = new McapStreamReader({
  includeChunks: true,
  validateCrcs: true,
  decompressHandlers: {
    lz4: (buffer, size) => Uint8Array.from(lz4.decompress(buffer, Number(size))),
  },
});
reader.append(fs.readFileSync(process.argv[2]));
const chunks = [];
const channels = {};
let outside = 0;
let current = null;
let record;
while ((record = reader.nextRecord()) !== undefined) {
  if (record.type === "Chunk") {
    current = { start: record.messageStartTime.toString(), end: record.messageEndTime.toString(), log_times: [],
                topics: [] };
    chunks.push(current);
  } else if (record.type === "Channel") {
    channels[record.id] = record.topic;
  } else if (record.type === "Message") {
    if (current === null) { outside += 1; continue; }
    current.log_times.push(record.logTime.toString());
    current.topics.push(channels[record.channelId]);
  } else if (record.type === "MessageIndex" || record.type === "Metadata" || record.type === "DataEnd") {
    current = null;
  }
}
process.stdout.write(JSON.stringify({ done: reader.done(), chunks, messages_outside_chunks: outside }));
