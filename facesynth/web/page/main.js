// facesynth live: the webcam drives an avatar, on the CPU (WebAssembly), offline.
// One worker (worker.js) tracks each camera frame and renders the avatar from it, in one ONNX
// Runtime instance (each costs ~60 MB); this page captures the driver's neutral, draws the frames
// and records them. Each avatar is loaded into a new worker and checked there before it replaces
// the current one (loadAvatar): a file that fails leaves with its worker, memory and all. Where that worker's stage (tracker + avatar) takes longer than a frame's
// budget, the avatar moves to a second worker and renders beside the tracker (docs/web.md).
// URL options: ?workers=1|2|auto (default auto) and ?stage_ms=N (auto's budget, default 33.3: one
// frame at 30 frames/s, the page's target; a second worker costs ~60 MB, so only when it is needed).
import { driverReach, ReachReadout, readRecording } from './coverage.js';
import { selectNeutral } from './neutral.js';
import { onnxMetadata } from './onnxmeta.js';
import { spawnWorker } from './workers.js';

// auto: the stage is judged on the median of STAGE_FRAMES frames, once WARMUP_FRAMES frames have
// gone (the first seconds run slower while V8 compiles the hot WebAssembly), every 30 frames
const NEUTRAL_MS = 1000, NO_FACE_FRAMES = 15, STAGE_FRAMES = 90, WARMUP_FRAMES = 120;
const base = new URL('.', location.href).href;
const options = new URLSearchParams(location.search);
const WORKERS = options.get('workers') ?? 'auto', STAGE_MS = Number(options.get('stage_ms') ?? 1000 / 30);
const $ = (id) => document.getElementById(id);
const state = { frames: 0, trackerMs: [], avatarMs: [], compositeMs: [], latencyMs: [], reachMs: [], messages: [], firstFrameMs: null,
  avatar: null, neutral: null, neutralSamples: [], neutralStart: null, noFace: 0, busy: false, ready: false,
  calls: 0, pending: new Map(), workers: 1, latest: null, rendering: false, previous: null, loading: Promise.resolve(),
  camera: false, live: false };
window.facesynth = { state };

function message(text, error = false) {
  const last = state.messages[state.messages.length - 1];
  if (last && last.text === text && last.error === error) return;  // a repeated error is shown once
  const el = $('message');
  el.textContent = text;
  el.className = error ? 'error' : '';
  state.messages.push({ text, error });
}

const SCHEMES = ['ibug68', 'mediapipe478'];  // the avatars the tracker's 478 points drive
// a talking head's input and output names: facesynth/contract.py's TALKING_HEAD_INPUTS and
// TALKING_HEAD_OUTPUTS (tests/test_web_page.py checks they are the same)
const CONTRACT = { inputs: ['driver', 'driver_neutral'], outputs: ['frame', 'avatar_landmarks'] };
window.facesynth.contract = CONTRACT;

// The avatar: one talking-head graph (facesynth export RUN --talking-head): driver landmarks (1, P, 2)
// and the driver's neutral (P, 2) -> the avatar's whole frame (1, H, W, 3) uint8, its head warped
// with the face. The retargeting, the shape clamp, the synthesis, the warp and the seam are all in
// the graph (Python's facesynth.runtime.TalkingHead runs the same file), which the worker runs; the
// page checks the file, keeps its metadata and draws the frames.
class AvatarGraph {
  // files: () => Promise<{ graph: ArrayBuffer, weights?: ArrayBuffer, weightsPath?: string }>, the
  // avatar's graph and, for a split avatar (as the page's own is built), its weights file (ONNX
  // external data); read again when the avatar moves to another worker. The buffers go to the worker.
  static async create(files, name, schemes, formats, worker) {
    const f = await files();
    try { return await AvatarGraph.#create(f, files, name, schemes, formats, worker); }
    finally { release(f.graph, f.weights); }  // what the worker did not take (a refused file)
  }

  static async #create(f, files, name, schemes, formats, worker) {
    let meta;
    try { meta = onnxMetadata(f.graph); } catch (e) { throw new Error(`${name} is not an ONNX file (${e.message})`); }
    if (meta.format === formats.synthesis) throw new Error(`${name} is a face model, not a talking head: export one with 'facesynth export RUN --talking-head --out ${name}'`);
    if (meta.format !== formats.talking_head) throw new Error(`${name} is not a facesynth avatar (format ${JSON.stringify(meta.format ?? null)}, expected ${formats.talking_head})`);
    const scheme = meta.landmark_scheme;
    if (!SCHEMES.includes(scheme) || !(scheme in schemes)) throw new Error(`${name}: its landmark scheme ${scheme} cannot be driven by the page's tracker (MediaPipe 478 points; it drives mediapipe478 and ibug68 avatars)`);
    if (!Array.isArray(meta.frame_size) || !meta.background_jpeg) throw new Error(`${name}: a talking head without its frame size and neutral frame (re-export it)`);
    const g = new AvatarGraph();
    Object.assign(g, { name, meta, scheme, files, n: schemes[scheme].n_points,
      rows: scheme === 'mediapipe478' ? null : schemes[scheme].to_ibug68 });
    g.bg = new Image();
    g.bg.src = 'data:image/jpeg;base64,' + meta.background_jpeg;
    try { await g.bg.decode(); } catch { throw new Error(`${name}: its neutral frame (background_jpeg) is not a JPEG (re-export it)`); }
    [g.width, g.height] = meta.frame_size;
    if (g.bg.naturalWidth !== g.width || g.bg.naturalHeight !== g.height) {
      throw new Error(`${name}: its neutral frame is ${g.bg.naturalWidth} x ${g.bg.naturalHeight}, its frame_size ${g.width} x ${g.height} (re-export it)`);
    }
    const c = new OffscreenCanvas(g.width, g.height).getContext('2d');
    c.drawImage(g.bg, 0, 0);
    // what the worker checks the file against before it takes it (worker.js: checkAvatar)
    g.check = { ...CONTRACT, neutral: meta.avatar_neutral, background: c.getImageData(0, 0, g.width, g.height).data,
      width: g.width, height: g.height };
    await g.loadInto(worker, f);  // last: the worker takes the avatar only once it has passed the check
    g.rgba = new ImageData(g.width, g.height);
    return g;
  }

  // the avatar's session in a worker (its files read again unless given; they become the worker's)
  async loadInto(worker, f) {
    f ??= await this.files();
    await call(worker, 'avatar', { graph: f.graph, weights: f.weights, weightsPath: f.weightsPath, name: this.name, n: this.n,
      rows: this.rows, check: this.check }, [f.graph, f.weights].filter(Boolean));
  }

  // driver points and the driver's neutral, both in the avatar's scheme (P x 2 flat) -> frame {data: uint8 H x W x 3, dims}
  async render(driver, neutral) {
    return call(state.renderer, 'render', { driver, neutral });
  }

  // one frame from the worker -> the canvas (RGBA)
  draw(frame, ctx) {
    const src = frame.data, px = this.rgba.data, hw = this.width * this.height;
    for (let i = 0, j = 0; i < hw; i++, j += 3) { px[4 * i] = src[j]; px[4 * i + 1] = src[j + 1]; px[4 * i + 2] = src[j + 2]; px[4 * i + 3] = 255; }
    ctx.putImageData(this.rgba, 0, 0);
  }
}

// A request to a worker, answered by a message with the same id.
function call(worker, type, payload, transfer = []) {
  const id = ++state.calls;
  return new Promise((resolve, reject) => {
    state.pending.set(id, { resolve, reject });
    worker.postMessage({ type, id, ...payload }, transfer);
  });
}

// Hand a spent buffer (a drawn avatar frame) back to the worker, which drops it. V8 frees a large
// buffer only at a garbage collection, and this thread allocates too little else to collect often,
// so spent frames piled up here (docs/web.md); the worker, collecting every few frames, frees them.
function release(...buffers) {
  buffers = buffers.filter((b) => b instanceof ArrayBuffer && b.byteLength);  // never wasm memory (a SharedArrayBuffer), nor one sent
  if (state.worker && buffers.length) state.worker.postMessage({ type: 'spent', buffers }, buffers);
}

// An avatar into a new worker (with the tracker when there is one worker), checked there; only then
// does it replace the current avatar and its worker. On failure the new worker is terminated: the
// file's session and whatever memory it took go with it, and the current avatar runs on untouched.
// One load at a time, in the order asked.
function loadAvatar(files, name) {
  const run = state.loading.then(() => swapInAvatar(files, name));
  state.loading = run.catch(() => {});
  return run;
}

async function swapInAvatar(files, name) {
  const two = state.workers === 2, w = state.fresh ?? startWorker(!two);
  state.fresh = null;
  let g;
  try {  // the file is read and checked while the worker starts (its messages wait for its start)
    [, g] = await Promise.all([w.ready, AvatarGraph.create(files, name, state.schemes, state.formats, w)]);
  } catch (e) {
    w.terminate();
    throw e;
  }
  const old = state.renderer;
  if (state.neutral) w.postMessage({ type: 'neutral', points: state.neutral });
  if (two) { state.renderer = w; state.rendering = false; }
  else { state.worker = state.renderer = w; state.busy = false; }  // the frame the old worker had is dropped with it
  if (old) old.terminate();
  if (state.avatar) state.previous = state.avatar;
  state.avatar = g;
  const cv = $('avatar');
  cv.width = g.width; cv.height = g.height;
  state.ctx = cv.getContext('2d');
  state.ctx.drawImage(g.bg, 0, 0);
  $('avatarname').textContent = `avatar: ${name} (${g.scheme})`;
  const note = state.reach.setAvatar(g.meta);
  if (note) state.messages.push({ text: note, error: false });
  if (state.ready) sendFrame();
}

// The avatar failed on a live frame (its worker reports it once and stops running it): back to the
// avatar before it, in a new worker, or none.
async function onAvatarFailed(m, worker) {
  if (worker !== state.renderer || !state.avatar) return;
  const bad = state.avatar, prev = state.previous;
  if (!prev) { message(`${bad.name} failed on a live frame (${m.message}). Drop another avatar.`, true); return; }
  message(`${bad.name} failed on a live frame (${m.message}); back to ${prev.name}.`, true);
  state.previous = null;
  try { await loadAvatar(prev.files, prev.name); state.previous = null; }
  catch (e) { message(`${e.message} Drop another avatar.`, true); }
}

// replay hook for tests and tools: driver points and the driver's neutral (P x 2 flat, the avatar's
// scheme) -> the avatar's frame: {dims, data: base64 of its uint8 H x W x 3 pixels}
window.facesynth.render = async (driver, neutral) => {
  const f = await state.avatar.render(Float32Array.from(driver), Float32Array.from(neutral));
  let bin = '';
  for (let i = 0; i < f.data.length; i += 8192) bin += String.fromCharCode(...f.data.subarray(i, i + 8192));
  return { dims: f.dims, data: btoa(bin) };
};

// replay hook for tests and tools: frames of RGBA pixels (base64) through a tracker worker of its own
// (its tracking state apart from the camera's) -> each frame's points (478 x 2 flat) or null;
// region: each frame read only where the tracker looks, as the camera's frames are
window.facesynth.track = async (width, height, frames, region = false) => {
  const w = startWorker(true), out = [];
  try {
    await w.ready;
    for (const b64 of frames) {
      const data = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0)).buffer;
      const m = await call(w, 'pixels', { data, width, height, region }, [data]);
      out.push(m.points ? Array.from(m.points) : null);
    }
  } finally {
    w.terminate();
  }
  return out;
};

// replay hook for tests and tools: an avatar's coverage_recording entry, frames and the driver's
// neutral (each 478 x 2 flat, the tracker's points) -> each frame's reach (coverage.js), null for NaN
window.facesynth.driverReach = (entry, frames, neutral) => {
  const rec = readRecording(entry), rows = state.schemes.mediapipe478.to_ibug68;
  return frames.map((f) => driverReach(rec, f, neutral, rows));
};

function captureNeutral() {
  state.neutral = null; state.neutralSamples = []; state.neutralStart = null;
  state.reach.el.hidden = true;
  state.renderer.postMessage({ type: 'neutral', points: null });
  message('Look at the camera with a neutral face...');
}

// replay hook for tests and tools: frames (each P x 2 flat, the scheme's points) -> the index of
// the one the page takes as the driver's neutral (neutral.js)
window.facesynth.selectNeutral = (frames, scheme = 'mediapipe478') =>
  selectNeutral(frames.map((f) => Float32Array.from(f)), state.schemes[scheme].to_ibug68);

const recent = (arr, v) => { arr.push(v); if (arr.length > 300) arr.shift(); };

function onPoints(msg) {
  state.busy = false;
  sendFrame();
  recent(state.trackerMs, msg.ms);
  window.facesynth.lastStage = msg.stage;
  if (!msg.points) {
    if (++state.noFace === NO_FACE_FRAMES) message('No face in view: face the camera, in good light.', true);
    return;
  }
  if (state.noFace >= NO_FACE_FRAMES) message(state.neutral ? 'Live.' : 'Look at the camera with a neutral face...');
  state.noFace = 0;
  if (!state.neutral) {
    state.neutralStart ??= performance.now();
    state.neutralSamples.push(msg.points);
    if (performance.now() - state.neutralStart >= NEUTRAL_MS && state.neutralSamples.length >= 3) {
      // the project's neutral rule over the captured frames (a closed mouth, the frame nearest the mean
      // shape): a real frame, where a per-point median mixed the poses of a head that moved
      state.neutral = state.neutralSamples[selectNeutral(state.neutralSamples, state.schemes.mediapipe478.to_ibug68)];
      state.renderer.postMessage({ type: 'neutral', points: state.neutral });
      message('Live.');
      $('neutral').disabled = false; $('record').disabled = false;
    }
    return;
  }
  // the reach readout, here on the main thread while the worker renders this frame: 8 features and
  // up to 1000 distances, 0.2-0.5 ms (bench/web/page.py's reach_ms)
  const t0 = performance.now();
  state.reach.update(msg.points, state.neutral);
  if (state.reach.rec) recent(state.reachMs, performance.now() - t0);
  if (state.renderer !== state.worker) {  // two workers: the renderer takes the newest points when idle
    state.latest = msg;
    feedRenderer();
  }
}

function feedRenderer() {
  if (state.rendering || !state.latest) return;
  const { points, t } = state.latest;
  state.latest = null;
  state.rendering = true;
  state.renderer.postMessage({ type: 'live', points, t });
}

function onFrame(msg, worker) {
  if (worker === state.renderer && state.renderer !== state.worker) { state.rendering = false; feedRenderer(); }
  const g = state.avatar;
  if (!msg.data) return;  // no avatar or neutral there yet
  if (g && msg.dims[1] === g.height && msg.dims[2] === g.width) {  // not a frame of an avatar just replaced
    const t0 = performance.now();
    g.draw(msg, state.ctx);
    recent(state.avatarMs, msg.ms); recent(state.compositeMs, performance.now() - t0);
    const now = performance.now();
    recent(state.latencyMs, now - msg.t);
    state.frames++;
    state.firstFrameMs ??= now;
    state.frameTimes = (state.frameTimes || []).filter((t) => t > now - 1000).concat(now);
    const avg = (a) => (a.slice(-30).reduce((x, y) => x + y, 0) / Math.min(a.length, 30)).toFixed(1);
    $('stats').textContent = `${state.frameTimes.length} frames/s, latency ${avg(state.latencyMs)} ms ` +
      `(tracker ${avg(state.trackerMs)}, avatar ${avg(state.avatarMs)}, composite ${avg(state.compositeMs)} ms; ` +
      `${state.workers} worker${state.workers > 1 ? 's' : ''})`;
    if (WORKERS === 'auto' && state.workers === 1 && state.frames >= WARMUP_FRAMES + STAGE_FRAMES && state.frames % 30 === 0) {
      const med = (a) => a.slice(-STAGE_FRAMES).sort((x, y) => x - y)[STAGE_FRAMES >> 1];
      if (med(state.trackerMs) + med(state.avatarMs) > STAGE_MS) useTwoWorkers();
    }
  }
  release(msg.data.buffer);
}

// Two workers (two ONNX Runtime instances, ~60 MB more): one tracks, the other renders the newest
// points meanwhile; for a machine on which one worker's stage is over budget. Both are new, so that
// the one worker's heap, grown by the avatar (WebAssembly memory never shrinks), is freed with it.
// In the avatar loads' queue (loadAvatar): a load and the switch each replace workers, so neither may
// run across the other (a load begun with one worker would take the switch's tracker for its old
// renderer and stop it: the page would freeze).
function useTwoWorkers() {
  if (state.workers === 2 || state.switching) return state.loading;
  state.switching = true;
  const run = state.loading.then(switchToTwoWorkers).finally(() => { state.switching = false; });
  state.loading = run.catch(() => {});
  return run;
}

async function switchToTwoWorkers() {
  const t = startWorker(true), r = startWorker(false), g = state.avatar;
  try {
    await Promise.all([t.ready, r.ready]);
    if (g) await g.loadInto(r);
    if (state.neutral) r.postMessage({ type: 'neutral', points: state.neutral });
    const one = state.worker;
    [state.worker, state.renderer, state.workers, state.rendering] = [t, r, 2, false];
    one.terminate();
    state.busy = false;  // the frame that worker had is dropped with it
    sendFrame();
  } catch (e) {
    t.terminate(); r.terminate();
    message(`A second worker could not start (${e.message}); the page goes on with one.`, true);
  }
}

// replay hook for tests and tools: the switch to two workers, now (as auto makes it on a slow
// machine), queued with the avatar loads; settles when done
window.facesynth.useTwoWorkers = () => useTwoWorkers();

// A worker (worker.js): with the tracker (the camera's) or without (a second worker, the avatar's).
function startWorker(tracker) {
  return spawnWorker({
    base, tracker, pending: state.pending,
    on: { points: onPoints, frame: onFrame, 'avatar-failed': onAvatarFailed },
    onError: (m, w) => {
      if (w === state.worker) state.busy = false;
      if (w === state.renderer) state.rendering = false;
      if (w === state.worker || w === state.renderer) message(`Worker error: ${m.message}`, true);  // not from one let go
    },
    onStartFailed: (e) => {  // a broken or partial page folder
      const err = new Error(`The page's worker failed to start (${e.message || 'worker.js'}): rebuild the page.`);
      for (const p of state.pending.values()) p.reject(err);
      state.pending.clear();
      message(err.message, true);
      return err;
    },
  });
}

// Send the camera's newest frame to the worker when its tracker is idle and the frame is new.
// Called when the camera has a frame (requestVideoFrameCallback, or each animation frame where
// that is missing) and as soon as the tracker answers, before the worker renders the answer: the
// next frame is read from the camera while the avatar renders.
function sendFrame() {
  const v = $('camera');
  if (!state.ready || state.busy || v.readyState < 2 || v.currentTime === state.lastTime) return;
  state.lastTime = v.currentTime;
  state.busy = true;
  const t = performance.now();
  createImageBitmap(v).then((bitmap) => state.worker.postMessage({ type: 'frame', bitmap, t }, [bitmap]))
    .catch(() => { state.busy = false; });
}

function pump() {
  const v = $('camera');
  sendFrame();
  if (v.requestVideoFrameCallback) v.requestVideoFrameCallback(pump);
  else requestAnimationFrame(pump);
}

async function startCamera() {
  if (!navigator.mediaDevices?.getUserMedia) throw new Error('No camera access in this browser (it needs a secure page: http://127.0.0.1 or https).');
  let stream;
  try { stream = await navigator.mediaDevices.getUserMedia({ video: { width: 640, height: 480 }, audio: false }); }
  catch (e) {
    if (e.name === 'NotAllowedError') throw new Error('Camera permission denied: allow the camera for this page and reload.');
    if (e.name === 'NotFoundError' || e.name === 'OverconstrainedError') throw new Error('No camera found: connect one and reload.');
    throw new Error(`The camera could not start (${e.name}: ${e.message}).`);
  }
  const v = $('camera');
  v.srcObject = stream;
  await v.play();
}

function setupRecording() {
  let rec = null, chunks = [];
  $('record').onclick = () => {
    if (rec) { rec.stop(); return; }
    rec = new MediaRecorder($('avatar').captureStream(30), { mimeType: 'video/webm' });
    chunks = [];
    rec.ondataavailable = (e) => chunks.push(e.data);
    rec.onstop = () => {
      const a = document.createElement('a');
      a.href = URL.createObjectURL(new Blob(chunks, { type: 'video/webm' }));
      a.download = 'facesynth-live.webm';
      a.click();
      rec = null; $('record').textContent = 'Record';
    };
    rec.start(); $('record').textContent = 'Stop and download';
  };
}

function setupDrop() {
  document.addEventListener('dragover', (e) => { e.preventDefault(); document.body.classList.add('dragging'); });
  document.addEventListener('dragleave', () => document.body.classList.remove('dragging'));
  document.addEventListener('drop', async (e) => {
    e.preventDefault(); document.body.classList.remove('dragging');
    const f = e.dataTransfer.files[0];
    if (f) await window.facesynth.loadFile(f);
  });
  window.facesynth.loadFile = async (file) => {
    const had = state.avatar;
    try { await loadAvatar(async () => ({ graph: await file.arrayBuffer() }), file.name); message(`Loaded ${file.name}.`); }
    catch (err) { message(`${err.message} ${had ? 'The current avatar is kept.' : 'Drop another avatar.'}`, true); return; }
    goLive();
  };
}

async function main() {
  if (typeof WebAssembly !== 'object') { message('WebAssembly is unavailable in this browser: the page needs it to run the models.', true); return; }
  setupDrop(); setupRecording();
  $('neutral').onclick = captureNeutral;
  $('showcam').onchange = (e) => { $('camera').style.display = e.target.checked ? '' : 'none'; };
  // the tracker's worker is the avatar's too (made by loadAvatar), unless there are two from the start;
  // the first avatar's is started now, while the page's files come
  if (WORKERS === '2') { state.worker = startWorker(true); state.workers = 2; }
  state.fresh = startWorker(WORKERS !== '2');
  const site = await (await fetch('site.json')).json();
  state.schemes = await (await fetch('schemes.json')).json();
  state.formats = site.formats;
  state.reach = new ReachReadout($('reach'), $('reach-note'), state.schemes.mediapipe478.to_ibug68);
  // the avatar as built: its graph and its weights apart (ONNX external data), so that ONNX Runtime
  // reads each weight straight into its tensor instead of copying and parsing one whole file in a
  // WebAssembly heap that never shrinks (the page's memory, docs/web.md)
  const files = async () => {
    const [graph, weights] = await Promise.all([site.avatar, site.avatar_data].map(async (f) => {
      const r = await fetch(f);
      if (!r.ok) throw new Error(`The page's avatar file ${f} is missing (HTTP ${r.status}): rebuild the page.`);
      return r.arrayBuffer();
    }));
    return { graph, weights, weightsPath: site.avatar_data };
  };
  const camera = startCamera().then(() => { state.camera = true; },  // the camera starts while the avatar loads
    (e) => { message(e.message, true); window.facesynth.cameraError = e.message; });
  try { await loadAvatar(files, site.avatar_name); } catch (e) { message(`${e.message} Drop another avatar.`, true); }
  await camera;
  await goLive();
}

// Live once there are both a camera and an avatar (the page's own, or the first one dropped).
async function goLive() {
  if (!state.camera || !state.avatar || state.live) return;
  state.live = true;
  await state.worker.ready;
  state.ready = true;
  captureNeutral();
  pump();
}

main().catch((e) => message(`Unexpected error: ${e.message || e}`, true));
