// Puts MediaPipe's pose_landmarker_lite.task together from the two models the
// legacy @mediapipe/pose package ships, for @mediapipe/tasks-vision's
// PoseLandmarker, which ships no model (build.mjs, at `npm ci`; nothing is
// downloaded). A .task is a zip of pose_detector.tflite and
// pose_landmarks_detector.tflite. The legacy models are the same networks but
// lack the TFLite metadata the tasks graphs read their input's normalization
// from (they refuse a float input without it), so each gets a ModelMetadata
// with one input tensor and its NormalizationOptions: the detector takes
// [-1, 1] (mean 127.5, std 127.5), the landmark model [0, 1] (mean 0, std 255),
// as the legacy graphs' ImageToTensorCalculator ranges say. Each model is read
// back before it is zipped.
import { readFileSync } from "node:fs";
import { join } from "node:path";

// The .task bytes from the installed @mediapipe/pose at POSE (its folder).
export function poseLandmarkerLiteTask(pose) {
  // The detector is hidden in the package's Emscripten file package: its loader
  // lists each file's start and end offsets in the .data file.
  const loader = readFileSync(join(pose, "pose_solution_packed_assets_loader.js"), "utf8");
  const entry = /"filename": *"[^"]*\/pose_detection\.tflite", *"start": *(\d+), *"end": *(\d+)/.exec(loader);
  if (!entry) throw new Error("pose_detection.tflite is not in @mediapipe/pose's packed assets");
  const detector = readFileSync(join(pose, "pose_solution_packed_assets.data")).subarray(Number(entry[1]), Number(entry[2]));
  const landmarks = readFileSync(join(pose, "pose_landmark_lite.tflite"));
  return storedZip([
    ["pose_detector.tflite", withInputNormalization(detector, 127.5, 127.5)],
    ["pose_landmarks_detector.tflite", withInputNormalization(landmarks, 0, 255)],
  ]);
}

// ---- flatbuffers, front to back -------------------------------------------------------------
// A flatbuffer's references (uoffset) only point forward. Nodes: ["table", [field...]] (a field
// is null, { u8 }, { u32 } or a node it references), ["vec", [node...]] (a vector of references),
// ["bytes", Buffer] (its data 16-aligned), ["f32", [number...]], ["str", string] and
// ["at", position] (an object already in the buffer that follows, as `base + position`).
// Writes NODE (the root) after a root offset and the 4-byte IDENTIFIER; returns the bytes and
// the references to "at" nodes left to patch once the following buffer's base is known.
function writeForward(node, identifier) {
  let out = Buffer.alloc(4096), len = 8;
  const ats = [];
  const room = (n) => {
    if (len + n <= out.length) return;
    const more = Buffer.alloc(Math.max(2 * out.length, len + n));
    out.copy(more, 0, 0, len);
    out = more;
  };
  const align = (a) => { room(a); len = Math.ceil(len / a) * a; };
  const u32 = (v) => { room(4); out.writeUInt32LE(v >>> 0, len); len += 4; };
  // Children after their parents; `slots` holds [slot position, node] to patch.
  const children = (slots) => {
    for (const [slot, child] of slots) {
      if (child[0] === "at") ats.push([slot, child[1]]);
      else out.writeUInt32LE(place(child) - slot, slot);
    }
  };
  function place(n) {
    const [kind, v] = n;
    if (kind === "table") {
      align(4);
      const vt = len, vtSize = 4 + 2 * v.length;
      room(vtSize + 4 + 4 * v.length);
      len += vtSize;
      align(4);
      const table = len;
      out.writeUInt16LE(vtSize, vt);
      out.writeUInt16LE(4 + 4 * v.length, vt + 2);
      out.writeInt32LE(table - vt, table);
      len += 4;
      const slots = [];
      v.forEach((f, i) => {
        out.writeUInt16LE(f == null ? 0 : len - table, vt + 4 + 2 * i);
        if (f == null) { len += 4; return; }
        if ("u8" in f) out.writeUInt8(f.u8, len);
        else if ("u32" in f) out.writeUInt32LE(f.u32, len);
        else slots.push([len, f]);
        len += 4;
      });
      children(slots);
      return table;
    }
    if (kind === "vec") {
      align(4);
      const at = len;
      u32(v.length);
      const slots = v.map((c) => { const slot = len; u32(0); return [slot, c]; });
      children(slots);
      return at;
    }
    if (kind === "bytes") {
      while ((len + 4) % 16) { room(1); out[len++] = 0; }
      const at = len;
      u32(v.length);
      room(v.length);
      v.copy(out, len);
      len += v.length;
      return at;
    }
    if (kind === "f32") {
      align(4);
      const at = len;
      u32(v.length);
      room(4 * v.length);
      for (const x of v) { out.writeFloatLE(x, len); len += 4; }
      return at;
    }
    if (kind === "str") {
      align(4);
      const at = len, s = Buffer.from(v, "utf8");
      u32(s.length);
      room(s.length + 1);
      s.copy(out, len);
      len += s.length;
      out[len++] = 0;
      return at;
    }
    throw new Error(`flatbuffer node ${kind}`);
  }
  const root = place(node);
  out.writeUInt32LE(root, 0);
  out.write(identifier, 4, "latin1");
  align(4);
  return { bytes: out.subarray(0, len), ats };
}

// The TFLite MODEL (a "TFL3" flatbuffer) with a TFLITE_METADATA buffer holding a
// ModelMetadata (metadata_schema.fbs, "M001") whose one input tensor has
// NormalizationOptions { mean: [MEAN], std: [STD] }. The model's own bytes move
// unchanged behind a new Model table, 64 bytes aligned as they were.
function withInputNormalization(model, mean, std) {
  if (model.toString("latin1", 4, 8) !== "TFL3") throw new Error("not a TFLite model");
  const metadata = writeForward(["table", [ // ModelMetadata
    ["str", "pose"], // name
    null, null, // description, version
    ["vec", [["table", [ // subgraph_metadata: SubGraphMetadata
      null, null, // name, description
      ["vec", [["table", [ // input_tensor_metadata: TensorMetadata
        ["str", "image"], // name
        null, null, null, // description, dimension_names, content
        ["vec", [["table", [{ u8: 1 }, ["table", [["f32", [mean]], ["f32", [std]]]]]]]], // process_units: NormalizationOptions
      ]]]],
    ]]]],
    null, null, null, // author, license, associated_files
    ["str", "1.0.0"], // min_parser_version
  ]], "M001").bytes;

  // The Model table: version, operator_codes, subgraphs, description, buffers,
  // metadata_buffer, metadata, signature_defs (schema.fbs).
  const table = model.readUInt32LE(0), vt = table - model.readInt32LE(table);
  const fields = (model.readUInt16LE(vt) - 4) / 2;
  // Field I's offset in the table whose vtable is at VTAB (0: absent).
  const slot = (vtab, i) => (i < (model.readUInt16LE(vtab) - 4) / 2 ? model.readUInt16LE(vtab + 4 + 2 * i) : 0);
  const ref = (at) => at + model.readUInt32LE(at);
  const vector = (at) => Array.from({ length: model.readUInt32LE(at) }, (_, i) => ref(at + 4 + 4 * i));
  for (let i = 8; i < fields; i++) if (slot(vt, i)) throw new Error(`Model field ${i} is not known here`);
  const field = (i) => (slot(vt, i) ? table + slot(vt, i) : 0);
  const buffers = field(4) ? vector(ref(field(4))) : [];
  const entries = field(6) ? vector(ref(field(6))) : [];
  for (const e of entries) {
    const evt = e - model.readInt32LE(e), nameSlot = slot(evt, 0);
    if (nameSlot && model.toString("utf8", ref(e + nameSlot) + 4, ref(e + nameSlot) + 4 + model.readUInt32LE(ref(e + nameSlot))) === "TFLITE_METADATA") {
      throw new Error("the model has TFLite metadata already");
    }
  }
  for (const b of buffers) {
    const bvt = b - model.readInt32LE(b);
    if (slot(bvt, 1) || slot(bvt, 2)) throw new Error("a model buffer outside the flatbuffer is not handled here");
  }
  const at = (i) => (field(i) ? ["at", ref(field(i))] : null);
  const head = writeForward(["table", [
    field(0) ? { u32: model.readUInt32LE(field(0)) } : null,
    at(1), at(2), at(3),
    ["vec", [...buffers.map((b) => ["at", b]), ["table", [["bytes", metadata]]]]],
    at(5),
    ["vec", [...entries.map((e) => ["at", e]), ["table", [["str", "TFLITE_METADATA"], { u32: buffers.length }]]]],
    at(7),
  ]], "TFL3");
  const base = Math.ceil(head.bytes.length / 64) * 64;
  const out = Buffer.alloc(base + model.length);
  head.bytes.copy(out, 0);
  model.copy(out, base);
  for (const [s, target] of head.ats) out.writeUInt32LE(base + target - s, s);
  checkMetadata(out, model, mean, std);
  return out;
}

// Reads OUT back as the tasks graphs will: the same subgraphs as MODEL, and a
// TFLITE_METADATA buffer whose ModelMetadata's first input has MEAN and STD.
function checkMetadata(out, model, mean, std) {
  const ref = (b, at) => at + b.readUInt32LE(at);
  const field = (b, table, i) => {
    const vt = table - b.readInt32LE(table);
    const off = i < (b.readUInt16LE(vt) - 4) / 2 ? b.readUInt16LE(vt + 4 + 2 * i) : 0;
    return off ? table + off : 0;
  };
  const vector = (b, at) => Array.from({ length: b.readUInt32LE(at) }, (_, i) => ref(b, at + 4 + 4 * i));
  const str = (b, at) => b.toString("utf8", at + 4, at + 4 + b.readUInt32LE(at));
  const root = ref(out, 0), oldRoot = ref(model, 0);
  const subgraphs = (b, r) => vector(b, ref(b, field(b, r, 2))).length;
  if (out.toString("latin1", 4, 8) !== "TFL3" || subgraphs(out, root) !== subgraphs(model, oldRoot)) {
    throw new Error("the model with metadata does not read back");
  }
  const entry = vector(out, ref(out, field(out, root, 6))).find((e) => str(out, ref(out, field(out, e, 0))) === "TFLITE_METADATA");
  const buffer = vector(out, ref(out, field(out, root, 4)))[out.readUInt32LE(field(out, entry, 1))];
  const data = ref(out, field(out, buffer, 0));
  const meta = out.subarray(data + 4, data + 4 + out.readUInt32LE(data));
  if (meta.toString("latin1", 4, 8) !== "M001") throw new Error("the metadata does not read back");
  const subgraph = vector(meta, ref(meta, field(meta, ref(meta, 0), 3)))[0];
  const input = vector(meta, ref(meta, field(meta, subgraph, 2)))[0];
  const unit = vector(meta, ref(meta, field(meta, input, 4)))[0];
  const options = ref(meta, field(meta, unit, 1));
  const first = (i) => meta.readFloatLE(ref(meta, field(meta, options, i)) + 4);
  if (meta.readUInt8(field(meta, unit, 0)) !== 1 || first(0) !== mean || first(1) !== std) {
    throw new Error("the normalization does not read back");
  }
}

// ---- a zip, stored -------------------------------------------------------------------------
// FILES ([name, bytes]...) stored (no compression), dated 1980-01-01, each file's
// data 64 bytes aligned in the archive (padding in an extra field), as models
// are read in place.
function storedZip(files) {
  const crcTable = Array.from({ length: 256 }, (_, n) => {
    for (let k = 0; k < 8; k++) n = n & 1 ? 0xedb88320 ^ (n >>> 1) : n >>> 1;
    return n >>> 0;
  });
  const crc32 = (b) => {
    let c = 0xffffffff;
    for (const x of b) c = crcTable[(c ^ x) & 0xff] ^ (c >>> 8);
    return (c ^ 0xffffffff) >>> 0;
  };
  const parts = [], central = [];
  let offset = 0;
  for (const [name, data] of files) {
    const n = Buffer.from(name), crc = crc32(data);
    let pad = (64 - ((offset + 30 + n.length + 4) % 64)) % 64;
    const extra = Buffer.alloc(4 + pad);
    extra.writeUInt16LE(0xd935, 0); extra.writeUInt16LE(pad, 2); // Android's alignment field
    const local = Buffer.alloc(30);
    local.writeUInt32LE(0x04034b50, 0); local.writeUInt16LE(10, 4); local.writeUInt16LE(0x21, 12);
    local.writeUInt32LE(crc, 14); local.writeUInt32LE(data.length, 18); local.writeUInt32LE(data.length, 22);
    local.writeUInt16LE(n.length, 26); local.writeUInt16LE(extra.length, 28);
    const dir = Buffer.alloc(46);
    dir.writeUInt32LE(0x02014b50, 0); dir.writeUInt16LE(10, 4); dir.writeUInt16LE(10, 6); dir.writeUInt16LE(0x21, 14);
    dir.writeUInt32LE(crc, 16); dir.writeUInt32LE(data.length, 20); dir.writeUInt32LE(data.length, 24);
    dir.writeUInt16LE(n.length, 28); dir.writeUInt32LE(offset, 42);
    parts.push(local, n, extra, data);
    central.push(dir, n);
    offset += local.length + n.length + extra.length + data.length;
  }
  const size = central.reduce((s, b) => s + b.length, 0);
  const end = Buffer.alloc(22);
  end.writeUInt32LE(0x06054b50, 0); end.writeUInt16LE(files.length, 8); end.writeUInt16LE(files.length, 10);
  end.writeUInt32LE(size, 12); end.writeUInt32LE(offset, 16);
  return Buffer.concat([...parts, ...central, end]);
}
