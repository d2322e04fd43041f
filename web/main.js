// facesynth live: the webcam drives an avatar, on the CPU (WebAssembly), offline.
// The tracker runs in a worker (tracker.js); this page runs the avatar graph and draws it.
import * as ort from './ort/ort.wasm.min.mjs';
import { onnxMetadata } from './onnxmeta.js';

const SYNTHESIS_FORMAT = 'facesynth.synthesis.onnx/1';
const NEUTRAL_MS = 1000, NO_FACE_FRAMES = 15;
const base = new URL('.', location.href).href;
const $ = (id) => document.getElementById(id);
const state = { frames: 0, trackerMs: [], avatarMs: [], compositeMs: [], latencyMs: [], messages: [], firstFrameMs: null,
  avatar: null, neutral: null, neutralSamples: [], neutralStart: null, noFace: 0, busy: false, ready: false };
window.facesynth = { state };

function message(text, error = false) {
  const el = $('message');
  el.textContent = text;
  el.className = error ? 'error' : '';
  state.messages.push({ text, error });
}

// Driver points (478, MediaPipe's order) -> the avatar's scheme, with the landmark tables of the project.
function toScheme(points, scheme, schemes) {
  if (scheme === 'mediapipe478') return points;
  const rows = schemes[scheme].to_ibug68, out = new Float32Array(rows.length * 2);
  rows.forEach((row, i) => { for (const [j, w] of row) { out[2 * i] += w * points[2 * j]; out[2 * i + 1] += w * points[2 * j + 1]; } });
  return out;
}
const EYE_CORNERS = { ibug68: [36, 45], mediapipe478: [33, 263] };
const dist = (p, a, b) => Math.hypot(p[2 * a] - p[2 * b], p[2 * a + 1] - p[2 * b + 1]);

// The avatar's shape PCA ({mean (2P), components (K, 2P), limit (K)}, metadata shape_pca): the
// nearest model shape with parameters clamped to +-limit, in the shape's own frame. Python's
// retarget.ShapeSpace.project with keep_eyes=False (the eyes are clamped with the rest).
function projectShape(x, pca) {
  const n = x.length / 2, mean = pca.mean, comps = pca.components, lim = pca.limit;
  let mx = 0, my = 0, ux = 0, uy = 0;
  for (let i = 0; i < n; i++) { mx += x[2 * i] / n; my += x[2 * i + 1] / n; ux += mean[2 * i] / n; uy += mean[2 * i + 1] / n; }
  let var_ = 0, ca = 0, sa = 0;
  for (let i = 0; i < n; i++) {
    const xc = x[2 * i] - mx, yc = x[2 * i + 1] - my, mcx = mean[2 * i] - ux, mcy = mean[2 * i + 1] - uy;
    var_ += xc * xc + yc * yc; ca += xc * mcx + yc * mcy; sa += xc * mcy - yc * mcx;
  }
  var_ = var_ || 1; ca /= var_; sa /= var_;
  const al = new Float64Array(2 * n);
  for (let i = 0; i < n; i++) {
    const xc = x[2 * i] - mx, yc = x[2 * i + 1] - my;
    al[2 * i] = ca * xc - sa * yc + ux; al[2 * i + 1] = sa * xc + ca * yc + uy;
  }
  const rec = Float64Array.from(al);
  for (let k = 0; k < lim.length; k++) {
    const c = comps[k];
    let b = 0;
    for (let j = 0; j < 2 * n; j++) b += (al[j] - mean[j]) * c[j];
    const ex = Math.max(b - lim[k], 0) + Math.min(b + lim[k], 0);
    if (ex) for (let j = 0; j < 2 * n; j++) rec[j] -= ex * c[j];
  }
  const nn = ca * ca + sa * sa, out = new Float32Array(2 * n);
  for (let i = 0; i < n; i++) {
    const rx = rec[2 * i] - ux, ry = rec[2 * i + 1] - uy;
    out[2 * i] = (ca * rx + sa * ry) / nn + mx; out[2 * i + 1] = (-sa * rx + ca * ry) / nn + my;
  }
  return out;
}

// The avatar graph: driver landmarks (P, 2) + driver neutral (P, 2) -> the avatar's frame.
// INTERIM: until the exported full-frame talking-head graph exists, this class stands in for it
// with the face-only synthesis graph (landmarks -> crop, mask, placement), a relative-motion
// retarget (avatar neutral + scale x (driver - driver neutral), projected on the avatar's shape PCA
// with clamped parameters) and a canvas composite of the
// crop into the avatar's neutral frame. Swapping in the full graph replaces run() with one
// session.run on (driver, neutral) and drawing its frame output.
class InterimAvatarGraph {
  static async create(buffer, name, schemes) {
    let meta;
    try { meta = onnxMetadata(buffer); } catch (e) { throw new Error(`${name} is not an ONNX file (${e.message})`); }
    if (meta.format !== SYNTHESIS_FORMAT) throw new Error(`${name} is not a facesynth avatar (format ${JSON.stringify(meta.format ?? null)}, expected ${SYNTHESIS_FORMAT})`);
    const scheme = meta.landmark_scheme;
    if (!(scheme in EYE_CORNERS) || !(scheme in schemes)) throw new Error(`${name}: its landmark scheme ${scheme} cannot be driven by the page's tracker (MediaPipe 478 points; it drives mediapipe478 and ibug68 avatars)`);
    if (!Array.isArray(meta.avatar_neutral) || !Array.isArray(meta.frame_size) || !meta.background_jpeg) throw new Error(`${name}: a facesynth model without the avatar's neutral and frame (export it from a run with 'facesynth export')`);
    let session;
    try { session = await ort.InferenceSession.create(buffer, { executionProviders: ['wasm'] }); }
    catch (e) { throw new Error(`${name} is corrupt: ONNX Runtime cannot load it (${e.message || e})`); }
    const bg = new Image();
    bg.src = 'data:image/jpeg;base64,' + meta.background_jpeg;
    await bg.decode();
    const g = new InterimAvatarGraph();
    Object.assign(g, { name, meta, scheme, session, schemes, bg, neutral: Float32Array.from(meta.avatar_neutral.flat()) });
    [g.width, g.height] = meta.frame_size;
    return g;
  }

  // landmarks in the avatar's scheme -> {crop, mask, placement} (the synthesis graph's outputs)
  async synthesize(landmarks) {
    const n = landmarks.length / 2;
    const out = await this.session.run({ [this.session.inputNames[0]]: new ort.Tensor('float32', landmarks, [1, n, 2]) });
    return out;
  }

  retarget(driver, driverNeutral) {
    const d = toScheme(driver, this.scheme, this.schemes), dn = toScheme(driverNeutral, this.scheme, this.schemes);
    const [a, b] = EYE_CORNERS[this.scheme], s = dist(this.neutral, a, b) / dist(dn, a, b);
    const x = this.neutral.map((v, i) => v + s * (d[i] - dn[i]));
    return this.meta.shape_pca ? projectShape(x, this.meta.shape_pca) : x;
  }

  async run(driver, driverNeutral, ctx) {
    const t0 = performance.now();
    const out = await this.synthesize(this.retarget(driver, driverNeutral));
    const t1 = performance.now();
    this.composite(out, ctx);
    return { avatarMs: t1 - t0, compositeMs: performance.now() - t1 };
  }

  composite(out, ctx) {  // INTERIM composite: the crop drawn through its placement, feathered mask
    const crop = out.crop, [, C, H, W] = crop.dims, c = crop.data, p = out.placement.data;
    if (!this.face || this.face.width !== W || this.face.height !== H) { this.face = new OffscreenCanvas(W, H); this.fctx = this.face.getContext('2d'); this.rgba = new ImageData(W, H); }
    const alpha = featherMask(out.mask.data, W, H, Math.sqrt(Math.abs(p[0] * p[4] - p[1] * p[3])));
    const px = this.rgba.data, hw = H * W;
    for (let i = 0; i < hw; i++) {
      for (let k = 0; k < 3; k++) px[4 * i + k] = c[(C === 3 ? k : 0) * hw + i] * 255 + 0.5;
      px[4 * i + 3] = alpha[i] * 255 + 0.5;
    }
    this.fctx.putImageData(this.rgba, 0, 0);
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.drawImage(this.bg, 0, 0);
    ctx.setTransform(p[0], p[3], p[1], p[4], p[2], p[5]);
    ctx.drawImage(this.face, 0, 0);
    ctx.setTransform(1, 0, 0, 1, 0, 0);
  }
}

// 1-D min (erosion; the outside does not erode, as OpenCV's default) or box mean (zeros outside,
// a running sum) over a window of radius r, along rows (stride 1) or columns (stride W)
function filter1d(src, W, H, r, horizontal, op) {
  const out = new Float32Array(src.length);
  const n = horizontal ? W : H, lines = horizontal ? H : W, step = horizontal ? 1 : W, lineStep = horizontal ? W : 1;
  for (let l = 0; l < lines; l++) {
    const o = l * lineStep;
    if (op === 'mean') {
      let acc = 0;
      for (let j = 0; j < Math.min(r, n); j++) acc += src[o + j * step];
      for (let i = 0; i < n; i++) {
        if (i + r < n) acc += src[o + (i + r) * step];
        if (i - r - 1 >= 0) acc -= src[o + (i - r - 1) * step];
        out[o + i * step] = acc / (2 * r + 1);
      }
    } else {
      for (let i = 0; i < n; i++) {
        let acc = 1;
        const j1 = Math.min(n - 1, i + r);
        for (let j = Math.max(0, i - r); j <= j1 && acc > 0; j++) acc = Math.min(acc, src[o + j * step]);
        out[o + i * step] = acc;
      }
    }
  }
  return out;
}

// The mask's soft edge, as facesynth.runtime.blend.blend_face makes it (approximately): a seam of
// f = max(2, 4 % of the face's size) frame pixels (crop pixels / scale), the mask eroded by f and
// blurred (two box blurs ~ a Gaussian of sigma f / 2), kept inside the hard mask. (H*W) in [0, 1].
function featherMask(mask, W, H, scale) {
  const hard = new Float32Array(W * H);
  let x0 = W, x1 = -1, y0 = H, y1 = -1;
  for (let y = 0; y < H; y++) for (let x = 0; x < W; x++) {
    if (mask[y * W + x] > 0.5) { hard[y * W + x] = 1; x0 = Math.min(x0, x); x1 = Math.max(x1, x); y0 = Math.min(y0, y); y1 = Math.max(y1, y); }
  }
  if (x1 < 0) return hard;
  const f = Math.max(2, 0.04 * Math.max(x1 - x0, y1 - y0) * scale) / scale, r = Math.max(1, Math.ceil(f));
  let a = filter1d(filter1d(hard, W, H, r, true, 'min'), W, H, r, false, 'min');
  const b = Math.max(1, Math.round((f / 2) * Math.sqrt(3) / Math.SQRT2));  // two boxes: sigma^2 = 2 (b^2 + b) / 3
  for (let k = 0; k < 2; k++) a = filter1d(filter1d(a, W, H, b, true, 'mean'), W, H, b, false, 'mean');
  for (let i = 0; i < a.length; i++) a[i] *= hard[i];
  return a;
}

async function loadAvatar(buffer, name) {
  const g = await InterimAvatarGraph.create(buffer, name, state.schemes);
  state.avatar = g;
  const cv = $('avatar');
  cv.width = g.width; cv.height = g.height;
  state.ctx = cv.getContext('2d');
  state.ctx.drawImage(g.bg, 0, 0);
  $('avatarname').textContent = `avatar: ${name} (${g.scheme})`;
}

// replay hook for tests and tools: landmarks (P, 2) flat in the avatar's scheme -> its synthesis outputs
window.facesynth.synthesize = async (flat) => {
  const out = await state.avatar.synthesize(Float32Array.from(flat));
  return Object.fromEntries(Object.entries(out).map(([k, t]) => [k, { dims: t.dims, data: Array.from(t.data) }]));
};

// replay hook for tests and tools: frames of RGBA pixels (base64) through a tracker worker of its own
// (its tracking state apart from the camera's) -> each frame's points (478 x 2 flat) or null
window.facesynth.track = async (width, height, frames) => {
  const w = new Worker('tracker.js', { type: 'module' });
  const reply = () => new Promise((resolve, reject) => {
    w.onmessage = (ev) => (ev.data.type === 'error' ? reject(new Error(ev.data.message)) : resolve(ev.data));
  });
  let r = reply();
  w.postMessage({ type: 'init', base });
  await r;
  const out = [];
  for (const b64 of frames) {
    const data = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0)).buffer;
    r = reply();
    w.postMessage({ type: 'pixels', data, width, height }, [data]);
    const m = await r;
    out.push(m.points ? Array.from(m.points) : null);
  }
  w.terminate();
  return out;
};

window.facesynth.projectShape = (flat) => Array.from(projectShape(Float32Array.from(flat), state.avatar.meta.shape_pca));

function captureNeutral() {
  state.neutral = null; state.neutralSamples = []; state.neutralStart = null;
  message('Look at the camera with a neutral face...');
}

function median(rows) {
  const out = new Float32Array(rows[0].length);
  for (let i = 0; i < out.length; i++) { const v = rows.map((r) => r[i]).sort((a, b) => a - b); out[i] = v[v.length >> 1]; }
  return out;
}

const recent = (arr, v) => { arr.push(v); if (arr.length > 300) arr.shift(); };

async function onPoints(msg) {
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
      state.neutral = median(state.neutralSamples);
      message('Live.');
      $('neutral').disabled = false; $('record').disabled = false;
    }
    return;
  }
  if (!state.avatar) return;
  state.latest = msg;  // one avatar run at a time, on the newest points (older ones are dropped)
  if (state.rendering) return;
  state.rendering = true;
  try {
    while (state.latest) {
      const m = state.latest;
      state.latest = null;
      await renderAvatar(m);
    }
  } finally {
    state.rendering = false;
  }
}

async function renderAvatar(msg) {
  const r = await state.avatar.run(msg.points, state.neutral, state.ctx);
  recent(state.avatarMs, r.avatarMs); recent(state.compositeMs, r.compositeMs);
  const now = performance.now();
  recent(state.latencyMs, now - msg.t);
  state.frames++;
  state.firstFrameMs ??= now;
  state.frameTimes = (state.frameTimes || []).filter((t) => t > now - 1000).concat(now);
  const avg = (a) => (a.slice(-30).reduce((x, y) => x + y, 0) / Math.min(a.length, 30)).toFixed(1);
  $('stats').textContent = `${state.frameTimes.length} frames/s, latency ${avg(state.latencyMs)} ms ` +
    `(tracker ${avg(state.trackerMs)}, avatar ${avg(state.avatarMs)}, composite ${avg(state.compositeMs)} ms)`;
}

// Send the camera's newest frame to the tracker when it is idle and the frame is new. Called when
// the camera has a frame (requestVideoFrameCallback, or each animation frame where that is
// missing) and as soon as the tracker answers, before the avatar renders the answer: the tracker
// works on frame n + 1 while the page renders frame n.
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
    try { await loadAvatar(await file.arrayBuffer(), file.name); message(`Loaded ${file.name}.`); }
    catch (err) { message(`${err.message} The current avatar is kept.`, true); }
  };
}

async function main() {
  if (typeof WebAssembly !== 'object') { message('WebAssembly is unavailable in this browser: the page needs it to run the models.', true); return; }
  ort.env.wasm.wasmPaths = base + 'ort/';
  ort.env.wasm.numThreads = 1;
  setupDrop(); setupRecording();
  $('neutral').onclick = captureNeutral;
  $('showcam').onchange = (e) => { $('camera').style.display = e.target.checked ? '' : 'none'; };
  const site = await (await fetch('site.json')).json();
  state.schemes = await (await fetch('schemes.json')).json();
  try { await loadAvatar(await (await fetch(site.avatar)).arrayBuffer(), site.avatar_name); }
  catch (e) { message(e.message, true); }
  state.worker = new Worker('tracker.js', { type: 'module' });
  const workerReady = new Promise((resolve, reject) => {
    state.worker.onmessage = (ev) => {
      const m = ev.data;
      if (m.type === 'ready') resolve();
      else if (m.type === 'points') onPoints(m).catch((e) => message(`Avatar error: ${e.message}`, true));
      else if (m.type === 'error') { state.busy = false; message(`Tracker error: ${m.message}`, true); reject(new Error(m.message)); }
    };
  });
  state.worker.postMessage({ type: 'init', base });
  try { await startCamera(); } catch (e) { message(e.message, true); window.facesynth.cameraError = e.message; return; }
  await workerReady;
  state.ready = true;
  if (!state.avatar) return;
  captureNeutral();
  pump();
}

main().catch((e) => message(`Unexpected error: ${e.message || e}`, true));
