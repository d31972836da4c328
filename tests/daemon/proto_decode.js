// Decodes protobuf payloads with protobufjs from the shipped .proto files (daemon/log_format/proto/), independently of
// the Python protobuf runtime and of the descriptors stored in the logs. Used by tests/daemon/test_proto_files.py.
// usage: node proto_decode.js PROTO_DIR < [{"file": "roadlog/ImuSample.proto", "type": "roadlog.ImuSample",
//                                          "data": BASE64}, ...]      prints the decoded objects as JSON
"use strict";
const fs = require("fs");
const path = require("path");
const protobuf = require("protobufjs");

const protoDir = process.argv[2];
const requests = JSON.parse(fs.readFileSync(0, "utf8"));
const out = requests.map(({ file, type, data }) => {
  const root = new protobuf.Root();
  root.resolvePath = (origin, target) =>
    target.startsWith("google/protobuf/") ? target : path.join(protoDir, target);
  root.loadSync(file, { keepCase: true });
  const message = root.lookupType(type);
  const decoded = message.decode(Buffer.from(data, "base64"));
  return message.toObject(decoded, { longs: String, bytes: String, enums: String, defaults: true });
});
process.stdout.write(JSON.stringify(out));
