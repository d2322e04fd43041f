// The page's worker: the face tracker (tracker.js) and the avatar's talking-head graph, both in
// this one ONNX Runtime instance. Each ONNX Runtime Web instance costs about 60 MB before any
// model (docs/web.md), so the page keeps one where it can; a camera frame is tracked and then
// rendered here, and the page only draws the frame. On a machine where that is too slow, the
// page starts a second worker without the tracker, which renders the points the page sends it
// ('live') while this one tracks the next frame.
//
// Messages in:
// - {type:'init', base, tracker} (tracker false: no tracker);
// - {type:'avatar', id, graph, weights?, weightsPath?, name, n, rows, check}: an avatar's graph bytes (null
//   drops the avatar), its weights file (ONNX external data) if apart, its point count and its rows
//   of the 478 -> scheme table (null for mediapipe478); check {inputs, outputs, neutral, background,
//   width, height}: the contract's input and output names, the avatar's own neutral landmarks (its
//   metadata's avatar_neutral) and its neutral frame (RGBA), what the file must pass before it is taken
//   (checkAvatar);
// - {type:'neutral', points}: the driver's neutral, 478 x 2, or null while it is captured again;
// - {type:'frame', bitmap, t}: a camera frame, tracked (and rendered when there is an avatar);
// - {type:'live', points, t}: render these points (a frame with data null when there is no avatar
//   or neutral);
// - {type:'render', id, driver, neutral}: both already in the avatar's scheme (the replay hook);
// - {type:'pixels', id, data, width, height, region}: track RGBA pixels (region: read only the
//   tracker's region() of them, as camera frames are);
// - {type:'reset'}; {type:'spent', buffers}: the page's spent frames, dropped here.
// Out: {type:'ready'}; {type:'points', points | null, t, ms, stage}; {type:'frame', data (H x W x 3
// uint8), dims, t, ms} after each tracked frame once the avatar and the neutral are there;
// {type:'reply', id, ...} to the messages with an id; {type:'error', id?, message}; {type:'avatar-failed',
// name, message} once when the avatar fails on a live frame (it is not run again).
import * as ort from './ort/ort.wasm.min.mjs';
import { toScheme } from './schemes.js';
import { Tracker } from './tracker.js';

let tracker = null, avatar = null, neutral = null, canvas, ctx;
let chain = Promise.resolve();
// one piece of ONNX Runtime work at a time, in the order the messages came
const serial = (fn) => { const p = chain.then(fn); chain = p.catch(() => {}); return p; };

// driver and driver neutral, P x 2 flat in the avatar's scheme -> its frame (ort.Tensor, uint8 1 x H x W x 3)
async function render(a, driver, driverNeutral) {
  const out = await a.session.run({ driver: new ort.Tensor('float32', driver, [1, a.n, 2]),
    driver_neutral: new ort.Tensor('float32', driverNeutral, [a.n, 2]) });
  return out.frame;
}

// the box {x, y, width, height} of an RGBA frame {data, width}, copied
function cut(img, b) {
  const out = new Uint8ClampedArray(b.width * b.height * 4);
  for (let r = 0; r < b.height; r++) {
    const i = ((b.y + r) * img.width + b.x) * 4;
    out.set(img.data.subarray(i, i + b.width * 4), r * b.width * 4);
  }
  return out;
}

async function loadAvatar(msg) {
  if (!msg.graph) {
    if (avatar) await avatar.session.release();
    avatar = null;
    return;
  }
  const opts = { executionProviders: ['wasm'] };
  if (msg.weights) opts.externalData = [{ path: msg.weightsPath, data: new Uint8Array(msg.weights) }];
  let session;
  try { session = await ort.InferenceSession.create(new Uint8Array(msg.graph), opts); }
  catch (e) { throw new Error(`${msg.name} is corrupt: ONNX Runtime cannot load it (${clean(e)})`); }
  const a = { session, n: msg.n, rows: msg.rows, name: msg.name, failed: false };
  if (msg.check) {
    try { await checkAvatar(a, msg.check); }
    catch (e) { await session.release(); throw e; }  // the bad session goes at once (the page drops this worker too)
  }
  const old = avatar;
  avatar = a;
  if (old) await old.session.release();
}

// An error's text for a message: printable, one line, short. ONNX Runtime's messages can carry raw
// bytes of its memory, which differ each time and would defeat the page's repeat check; its call
// prefix and source paths say nothing to the user, and the cause comes last, so a long text keeps its end.
function clean(e, max = 160) {
  const s = String((e && e.message) || e).replace(/[\x00-\x1f\x7f-\x9f\ufffd]+/g, ' ')
    .replace(/^failed to call OrtRun\(\)\. ERROR_CODE: \d+, ERROR_MESSAGE: /, '')
    .replace(/\S*\/[\w.-]+\.(cc|cpp|h):\d+ /g, '').replace(/\s+/g, ' ').trim();
  return s.length > max ? '...' + s.slice(-max) : s;
}

// What a file must pass before the page takes it: its graph takes and gives the contract's names, and
// one run at its own neutral (driver = driver neutral = avatar_neutral) gives a frame of its size, the
// avatar's landmarks where its neutral is (within NEUTRAL_PX) and, as a sound avatar at its neutral
// does, its own neutral frame again (mean difference within NEUTRAL_GREY grey levels; sound avatars
// measure about 1, files with 64 KiB of a weight overwritten 12 to 22; docs/web.md).
const NEUTRAL_PX = 0.5, NEUTRAL_GREY = 6;
async function checkAvatar(a, c) {
  const names = (l) => `(${l.join(', ')})`;
  const ins = [...a.session.inputNames].sort(), outs = [...a.session.outputNames].sort();
  if (ins.join() !== [...c.inputs].sort().join() || outs.join() !== [...c.outputs].sort().join()) {
    throw new Error(`${a.name} is not a talking head the page can run: its graph takes ${names(a.session.inputNames)} and gives ` +
      `${names(a.session.outputNames)}, a talking head takes ${names(c.inputs)} and gives ${names(c.outputs)}`);
  }
  const flat = Array.isArray(c.neutral) ? c.neutral.flat() : [];
  if (flat.length !== 2 * a.n || !flat.every((v) => typeof v === 'number' && Number.isFinite(v))) {
    throw new Error(`${a.name}: a talking head without its neutral landmarks (avatar_neutral, ${a.n} x 2; re-export it)`);
  }
  const n = Float32Array.from(flat);
  let out;
  try {
    out = await a.session.run({ [c.inputs[0]]: new ort.Tensor('float32', n, [1, a.n, 2]),
      [c.inputs[1]]: new ort.Tensor('float32', n.slice(), [a.n, 2]) });
  } catch (e) { throw new Error(`${a.name} is corrupt: its first frame, at its own neutral, fails (${clean(e)})`); }
  const frame = out[c.outputs[0]], lm = out[c.outputs[1]];
  const want = [1, c.height, c.width, 3];
  if (frame.type !== 'uint8' || frame.dims.join() !== want.join()) {
    throw new Error(`${a.name} is corrupt: its first frame is ${frame.type} ${frame.dims.join(' x ')}, its metadata says ${want.join(' x ')} uint8`);
  }
  let moved = 0;
  for (let i = 0; i < n.length; i++) { const d = Math.abs(lm.data[i] - n[i]); moved = d <= moved ? moved : (d > moved ? d : Infinity); }
  if (lm.data.length !== n.length || !(moved <= NEUTRAL_PX)) {
    throw new Error(`${a.name} is corrupt: at its own neutral its landmarks move by ${moved.toFixed(1)} px (a sound avatar: 0)`);
  }
  const px = frame.data, bg = new Uint8ClampedArray(c.background), hw = c.width * c.height;
  let sum = 0;
  for (let i = 0, j = 0; i < hw; i++, j += 3) sum += Math.abs(px[j] - bg[4 * i]) + Math.abs(px[j + 1] - bg[4 * i + 1]) + Math.abs(px[j + 2] - bg[4 * i + 2]);
  const grey = sum / (3 * hw);
  if (!(grey <= NEUTRAL_GREY)) {
    throw new Error(`${a.name} is corrupt: at its own neutral its frame differs from its neutral frame by ${grey.toFixed(1)} grey levels ` +
      `on average (a sound avatar: about 1)`);
  }
}

async function onFrame(msg) {
  const t0 = performance.now(), bm = msg.bitmap;
  if (!canvas || canvas.width !== bm.width || canvas.height !== bm.height) {
    canvas = new OffscreenCanvas(bm.width, bm.height);
    ctx = canvas.getContext('2d', { willReadFrequently: true });
  }
  ctx.drawImage(bm, 0, 0);
  bm.close();
  const box = tracker.region(canvas.width, canvas.height) ?? { x: 0, y: 0, width: canvas.width, height: canvas.height };
  const img = { data: ctx.getImageData(box.x, box.y, box.width, box.height).data, ...box };
  tracker.stage.read = performance.now() - t0;
  const points = await tracker.track(img);
  // copied, not transferred: the avatar renders from the same points (3.8 kB)
  self.postMessage({ type: 'points', points, t: msg.t, ms: performance.now() - t0, stage: { ...tracker.stage } });
  if (points) await renderLive(points, msg.t);
}

// the tracker's points (478 x 2) -> the avatar's frame, posted; false when there is no avatar or neutral
// (an avatar that fails on a live frame is reported once and not run again: the page goes back to the
// avatar before it)
async function renderLive(points, t) {
  if (!avatar || !neutral || avatar.failed) return false;
  const a = avatar, t1 = performance.now();
  let f;
  try { f = await render(a, toScheme(points, a.rows), toScheme(neutral, a.rows)); }
  catch (e) {
    a.failed = true;
    self.postMessage({ type: 'avatar-failed', name: a.name, message: clean(e) });
    return false;
  }
  self.postMessage({ type: 'frame', data: f.data, dims: f.dims, t, ms: performance.now() - t1 }, [f.data.buffer]);
  return true;
}

async function handle(msg) {
  switch (msg.type) {
    case 'init':
      ort.env.wasm.wasmPaths = msg.base + 'ort/';
      ort.env.wasm.numThreads = 1;
      if (msg.tracker !== false) tracker = await Tracker.create(msg.base);
      return { type: 'ready' };
    case 'avatar': await loadAvatar(msg); return {};
    case 'frame': await onFrame(msg); return null;
    case 'live':
      if (!(await renderLive(msg.points, msg.t))) self.postMessage({ type: 'frame', data: null, t: msg.t });
      return null;
    case 'render': {
      const f = await render(avatar, msg.driver, msg.neutral);
      return { data: f.data, dims: f.dims };
    }
    case 'pixels': {  // replay: RGBA pixels in, points out (the tests' hook); region: read as live frames are
      let img = { data: new Uint8ClampedArray(msg.data), width: msg.width, height: msg.height };
      const box = msg.region && tracker.region(msg.width, msg.height);
      if (box) img = { data: cut(img, box), ...box };
      return { points: await tracker.track(img) };
    }
    default: return null;
  }
}

self.onmessage = (ev) => {
  const msg = ev.data;
  if (msg.type === 'spent') return;  // the page's spent buffers, freed here sooner (main.js: release)
  if (msg.type === 'neutral') { neutral = msg.points; return; }
  if (msg.type === 'reset') { tracker?.reset(); return; }
  serial(() => handle(msg)).then((r) => {
    if (!r) return;
    if (r.type === 'ready') { self.postMessage(r); return; }
    const buffers = [r.data?.buffer, r.points?.buffer].filter(Boolean);
    self.postMessage({ type: 'reply', id: msg.id, ...r }, buffers);
  }, (e) => self.postMessage({ type: 'error', id: msg.id, message: clean(e, 400) }));
};
