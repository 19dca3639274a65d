// Reads fluxcal MCAP files with Foxglove's own MCAP library (@mcap/core, what Foxglove's app uses)
// and checks what Foxglove relies on. Run by hand (Node.js 18+):
//
//   cd tools/mcap-check && npm install && node check.mjs ../../recordings/*.mcap
//
// For every file: (1) the stream reader walks every record with CRC checks; (2) if the file has a
// summary (its writer closed it), the indexed reader reads every message through the chunk and message
// indexes, again with CRCs, and its counts must equal the stream's and the Statistics record's;
// (3) every `json` channel must have a `jsonschema` schema that parses, and every message must parse
// as JSON with the schema's required keys and property types; (4) log times never go back within a
// channel. A file whose writer was killed has no summary: (1) must still read up to its last complete
// record, and the report says "no summary". Exit status 1 if any check fails.

import { open, readFile } from "node:fs/promises";
import { McapIndexedReader, McapStreamReader } from "@mcap/core";
import { FileHandleReadable } from "@mcap/nodejs";
import { loadDecompressHandlers } from "@mcap/support";

const JSON_TYPES = { number: "number", integer: "number", string: "string", boolean: "boolean", object: "object",
                     array: "object", null: "object" };

function typeOk(value, spec) {
  if (!spec || spec.type === undefined) return true;
  const types = Array.isArray(spec.type) ? spec.type : [spec.type];
  return types.some((t) => (t === "null" ? value === null
    : t === "array" ? Array.isArray(value)
    : t === "integer" ? Number.isInteger(value)
    : t === "object" ? value !== null && typeof value === "object" && !Array.isArray(value)
    : typeof value === JSON_TYPES[t]));
}

async function checkFile(path, decompressHandlers) {
  const problems = [];
  const data = new Uint8Array(await readFile(path));
  const stream = new McapStreamReader({ decompressHandlers, validateCrcs: true });
  stream.append(data);
  const schemas = new Map(), channels = new Map(), perChannel = new Map(), lastLog = new Map();
  const kinds = {};
  let footer = false, streamError = null, messages = 0;
  const decoder = new TextDecoder();
  try {
    for (let rec; (rec = stream.nextRecord()) !== undefined;) {
      kinds[rec.type] = (kinds[rec.type] ?? 0) + 1;
      if (rec.type === "Schema") schemas.set(rec.id, rec);
      else if (rec.type === "Channel") channels.set(rec.id, rec);
      else if (rec.type === "Footer") footer = true;
      else if (rec.type === "Message") {
        messages++;
        const ch = channels.get(rec.channelId);
        perChannel.set(rec.channelId, (perChannel.get(rec.channelId) ?? 0) + 1);
        const prev = lastLog.get(rec.channelId);
        if (prev !== undefined && rec.logTime < prev) problems.push(`${ch.topic}: log_time goes back at message ${messages}`);
        lastLog.set(rec.channelId, rec.logTime);
        if (ch.messageEncoding === "json") {
          const schema = schemas.get(ch.schemaId);
          let msg;
          try { msg = JSON.parse(decoder.decode(rec.data)); } catch (e) { problems.push(`${ch.topic}: message is not JSON: ${e.message}`); continue; }
          const js = schema._parsed;
          for (const key of js.required ?? []) if (!(key in msg)) problems.push(`${ch.topic}: message lacks required "${key}"`);
          for (const [key, spec] of Object.entries(js.properties ?? {})) {
            if (key in msg && !typeOk(msg[key], spec)) problems.push(`${ch.topic}: "${key}" = ${JSON.stringify(msg[key]).slice(0, 40)} is not ${JSON.stringify(spec.type)}`);
          }
        }
      }
      if (rec.type === "Channel") {
        const schema = schemas.get(rec.schemaId);
        if (rec.messageEncoding === "json") {
          if (!schema || schema.encoding !== "jsonschema") problems.push(`${rec.topic}: json channel without a jsonschema schema`);
          else {
            try { schema._parsed = JSON.parse(decoder.decode(schema.data)); }
            catch (e) { problems.push(`${rec.topic}: schema ${schema.name} is not JSON: ${e.message}`); schema._parsed = {}; }
            if (schema._parsed.type !== "object") problems.push(`${rec.topic}: schema ${schema.name} is not an object schema`);
          }
        }
      }
    }
  } catch (e) {
    streamError = e.message;
  }
  const report = { file: path, bytes: data.length, records: kinds, messages, summary: footer };
  if (streamError) report.stream_error = streamError;
  if (!footer) {
    report.note = "no summary (writer killed?): read up to the last complete record";
    if (messages === 0) problems.push("no message could be read");
  } else {
    if (streamError) problems.push(`stream reader: ${streamError}`);
    const fh = await open(path, "r");
    try {
      const reader = await McapIndexedReader.Initialize({ readable: new FileHandleReadable(fh), decompressHandlers });
      const counts = new Map();
      let n = 0;
      for await (const m of reader.readMessages({ validateCrcs: true })) {
        counts.set(m.channelId, (counts.get(m.channelId) ?? 0) + 1);
        n++;
      }
      report.indexed_messages = n;
      report.chunks = reader.chunkIndexes.length;
      report.compression = [...new Set(reader.chunkIndexes.map((c) => c.compression))];
      if (n !== messages) problems.push(`indexed reader read ${n} messages, stream reader ${messages}`);
      const stats = reader.statistics;
      if (stats && Number(stats.messageCount) !== n) problems.push(`Statistics says ${stats.messageCount} messages, read ${n}`);
      for (const [id, c] of counts) {
        if (c !== perChannel.get(id)) problems.push(`${channels.get(id).topic}: indexed ${c}, stream ${perChannel.get(id)}`);
        const sc = stats?.channelMessageCounts.get(id);
        if (sc !== undefined && Number(sc) !== c) problems.push(`${channels.get(id).topic}: Statistics ${sc}, read ${c}`);
      }
      report.metadata = reader.metadataIndexes.map((m) => m.name);
    } catch (e) {
      problems.push(`indexed reader: ${e.message}`);
    } finally {
      await fh.close();
    }
  }
  report.channels = Object.fromEntries([...channels.values()].map((c) => [c.topic,
    { encoding: c.messageEncoding, schema: schemas.get(c.schemaId)?.encoding ?? "", messages: perChannel.get(c.id) ?? 0 }]));
  report.problems = problems;
  return report;
}

const files = process.argv.slice(2);
if (files.length === 0) {
  console.error("usage: node check.mjs FILE.mcap [...]");
  process.exit(2);
}
const decompressHandlers = await loadDecompressHandlers();
let failed = 0;
for (const f of files) {
  const r = await checkFile(f, decompressHandlers);
  console.log(JSON.stringify(r, (k, v) => (typeof v === "bigint" ? Number(v) : v), 1).replace(/\n\s*/g, " "));
  if (r.problems.length) failed++;
}
console.log(failed ? `FAIL: ${failed} of ${files.length} files` : `OK: ${files.length} files`);
process.exit(failed ? 1 : 0);
