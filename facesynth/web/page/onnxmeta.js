// The metadata of an ONNX file (ModelProto.metadata_props, field 14), read from its bytes:
// onnxruntime-web does not expose it. Values that are JSON are decoded, as facesynth writes them.

function varint(b, p) {
  let v = 0, mul = 1;
  for (;;) {
    if (p.i >= b.length) throw new Error('truncated varint');
    const x = b[p.i++];
    v += (x & 0x7f) * mul;
    if (!(x & 0x80)) return v;
    mul *= 128;
  }
}

function* fields(b, start, end) {
  const p = { i: start };
  while (p.i < end) {
    const key = varint(b, p), field = Math.floor(key / 8), wire = key & 7;
    if (wire === 0) { yield [field, wire, varint(b, p)]; continue; }
    if (wire === 1) { p.i += 8; continue; }
    if (wire === 5) { p.i += 4; continue; }
    if (wire !== 2) throw new Error(`unsupported protobuf wire type ${wire}`);
    const len = varint(b, p);
    if (p.i + len > end) throw new Error('truncated field');
    yield [field, wire, [p.i, p.i + len]];
    p.i += len;
  }
}

/** ArrayBuffer of an .onnx file -> {key: value} of its metadata; throws on a file that is not ONNX. */
export function onnxMetadata(buffer) {
  const b = new Uint8Array(buffer), dec = new TextDecoder();
  const out = {};
  let sawGraph = false;
  for (const [field, wire, v] of fields(b, 0, b.length)) {
    if (field === 7 && wire === 2) sawGraph = true;
    if (field !== 14 || wire !== 2) continue;
    let k = '', val = '';
    for (const [f, w, r] of fields(b, v[0], v[1])) {
      if (w !== 2) continue;
      const s = dec.decode(b.subarray(r[0], r[1]));
      if (f === 1) k = s; else if (f === 2) val = s;
    }
    try { out[k] = JSON.parse(val); } catch { out[k] = val; }
  }
  if (!sawGraph) throw new Error('no ONNX graph in this file');
  return out;
}
