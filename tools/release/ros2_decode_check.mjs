// Decode every CDR message of a ros2 MCAP recording with Foxglove's own decoders
// (@foxglove/rosmsg parses the ros2msg schema, @foxglove/rosmsg2-serialization reads the CDR),
// as the Foxglove app does. Used by tools/release/ros2_decode_check.py; prints one JSON line:
// {"messages": N, "failures": N, "by_topic": {...}, "first_failures": [...]}.
//
//   NODE_PATH=DIR/node_modules node tools/release/ros2_decode_check.mjs FILE.mcap
// with DIR holding: npm install @foxglove/rosmsg @foxglove/rosmsg2-serialization @mcap/core fzstd
import { createRequire } from "node:module";
import { readFileSync } from "node:fs";
import { join } from "node:path";

const modules = process.env.NODE_PATH;
const require = createRequire(join(modules, "noop.js"));
const { McapStreamReader } = require("@mcap/core");
const { parse } = require("@foxglove/rosmsg");
const { MessageReader } = require("@foxglove/rosmsg2-serialization");
const fzstd = require("fzstd");

const reader = new McapStreamReader({
  decompressHandlers: { zstd: (buffer, size) => fzstd.decompress(buffer, new Uint8Array(Number(size))) },
});
reader.append(readFileSync(process.argv[2]));
const schemas = new Map();
const channels = new Map();
const readers = new Map();
const out = { messages: 0, failures: 0, by_topic: {}, first_failures: [] };
for (let record; (record = reader.nextRecord()); ) {
  if (record.type === "Schema") schemas.set(record.id, record);
  else if (record.type === "Channel") channels.set(record.id, record);
  else if (record.type === "Message") {
    const channel = channels.get(record.channelId);
    if (channel.messageEncoding !== "cdr") continue;
    const topic = channel.topic;
    out.by_topic[topic] ??= { messages: 0, failures: 0 };
    out.messages++;
    out.by_topic[topic].messages++;
    try {
      if (!readers.has(channel.id)) {
        const schema = schemas.get(channel.schemaId);
        const text = new TextDecoder().decode(schema.data);
        readers.set(channel.id, new MessageReader(parse(text, { ros2: true })));
      }
      const message = readers.get(channel.id).readMessage(record.data);
      if (message === undefined || message === null) throw new Error("nothing decoded");
    } catch (err) {
      out.failures++;
      out.by_topic[topic].failures++;
      if (out.first_failures.length < 5) out.first_failures.push(`${topic}: ${err}`);
    }
  }
}
console.log(JSON.stringify(out));
