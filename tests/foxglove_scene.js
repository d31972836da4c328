// What Foxglove's 3D panel gets from a log, read as Foxglove reads it: @mcap/core streams the file, and each message
// of a foxglove.* channel is decoded with protobufjs from the schema stored in the log (its FileDescriptorSet), not
// from our code. Prints, as JSON, per topic the fields the 3D panel uses: transforms (parent, child, timestamp,
// translation), point clouds (frame_id, timestamp, point count), images and poses (frame_id, timestamp, position).
// Times are strings of nanoseconds (64-bit). Used by tests/test_foxglove_scene.py.
// usage: node foxglove_scene.js FILE.mcap   (NODE_PATH at the folder holding @mcap/core, lz4js and protobufjs)
"use strict";
const fs = require("fs");
const { McapStreamReader } = require("@mcap/core");
const lz4 = require("lz4js");
const protobuf = require("protobufjs");
const descriptor = require("protobufjs/ext/descriptor");

const reader = new McapStreamReader({
  validateCrcs: true,
  decompressHandlers: { lz4: (buffer, size) => Uint8Array.from(lz4.decompress(buffer, Number(size))) },
});
reader.append(fs.readFileSync(process.argv[2]));

const schemas = {};
const decoders = {}; // schema id -> its protobufjs type, built from the schema's own FileDescriptorSet
const channels = {};
const out = {};
const ns = (stamp) => (BigInt(stamp.sec ?? stamp.seconds ?? 0) * 1000000000n + BigInt(stamp.nsec ?? stamp.nanos ?? 0))
  .toString();
const vec = (v) => [v.x, v.y, v.z];

function summary(schemaName, m) {
  switch (schemaName) {
    case "foxglove.FrameTransform":
      return { parent: m.parent_frame_id, child: m.child_frame_id, t: ns(m.timestamp), translation: vec(m.translation) };
    case "foxglove.FrameTransforms":
      return { transforms: m.transforms.map((tf) => summary("foxglove.FrameTransform", tf)) };
    case "foxglove.PointCloud":
      return { frame_id: m.frame_id, t: ns(m.timestamp), points: m.data.length / m.point_stride,
               fields: m.fields.map((f) => f.name) };
    case "foxglove.PoseInFrame":
      return { frame_id: m.frame_id, t: ns(m.timestamp), position: vec(m.pose.position) };
    case "foxglove.CompressedImage":
    case "foxglove.RawImage":
      return { frame_id: m.frame_id, t: ns(m.timestamp) };
    default:
      return null;
  }
}

let record;
while ((record = reader.nextRecord()) !== undefined) {
  if (record.type === "Schema") {
    schemas[record.id] = record;
  } else if (record.type === "Channel") {
    channels[record.id] = record;
  } else if (record.type === "Message") {
    const channel = channels[record.channelId];
    const schema = schemas[channel.schemaId];
    if (!schema.name.startsWith("foxglove.")) continue;
    if (!decoders[schema.id]) {
      const set = descriptor.FileDescriptorSet.decode(schema.data);
      decoders[schema.id] = protobuf.Root.fromDescriptor(set).lookupType(schema.name);
    }
    const type = decoders[schema.id];
    const m = type.toObject(type.decode(record.data), { longs: String, defaults: true });
    const s = summary(schema.name, m);
    if (s === null) continue;
    s.log_time = record.logTime.toString();
    (out[channel.topic] ??= { schema: schema.name, messages: [] }).messages.push(s);
  }
}
process.stdout.write(JSON.stringify({ done: reader.done(), topics: out }));
