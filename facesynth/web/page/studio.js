// facesynth studio: record a guided clip (the live page's tracker in its worker, a coverage meter),
// train an avatar of it on this machine (the local server runs ingest, train and export), and
// drive it live with the same worker. Every request stays on 127.0.0.1; the server's writes need
// the token this page reads from api/session (docs/studio.md).
// URL option: ?seconds=F multiplies each prompt's duration (the tests' short recordings).
import { coverage, DIRECTIONS, KEEP_FPS, ReachReadout } from './coverage.js';
import { selectNeutral } from './neutral.js';
import { onnxMetadata } from './onnxmeta.js';
import { spawnWorker } from './workers.js';

const $ = (id) => document.getElementById(id);
const SCALE = Number(new URLSearchParams(location.search).get('seconds') ?? 1);
const base = new URL('.', location.href).href;
// The script: [id, what the user reads, seconds, the directions it covers (coverage.js)]
const PROMPTS = [
  ['neutral', 'Relax: a neutral face, looking at the camera', 4, []],
  ['speech', 'Say: "The quick brown fox jumps over the lazy dog."', 6, ['speech']],
  ['smile', 'Smile broadly, showing your teeth', 3, ['smile']],
  ['open', 'Open your mouth wide', 3, ['mouth_open']],
  ['oo', 'Say a long "oo"', 3, ['oo']],
  ['brows', 'Raise your eyebrows', 3, ['brows_up']],
  ['frown', 'Frown', 3, ['frown']],
  ['blink', 'Blink a few times', 3, ['blink']],
  ['left', 'Look to your left (eyes only)', 2.5, ['gaze_left']],
  ['right', 'Look to your right (eyes only)', 2.5, ['gaze_right']],
  ['up', 'Look up (eyes only)', 2.5, ['gaze_up']],
  ['down', 'Look down (eyes only)', 2.5, ['gaze_down']],
  ['turn', 'Turn your head slowly left, then right', 4, ['turn_left', 'turn_right']],
].map(([id, text, seconds, directions]) => ({ id, text, seconds, directions, points: [], frames: null }));
const JPEG_QUALITY = 0.92;
// frames kept a second while recording (a camera may give 30-60): half of lp_d6's 30 frames/s
// cost its held-out PSNR 0.13 dB, and the training's time grows faster than the frame count
// (docs/studio.md); KEEP_FPS lives in coverage.js, whose self-reach counts its blocks in these frames
const NEUTRAL_MS = 1000;
const state = { token: null, schemes: null, worker: null, busy: false, points: null, recording: null, messages: [],
  frames: 0, firstFrameAt: null, avatar: null, neutral: null, neutralSamples: [], neutralStart: null, job: null,
  coverage: null, calls: 0, pending: new Map() };
window.studio = { state, PROMPTS };

function message(text, error = false) {
  $('message').textContent = text;
  $('message').className = error ? 'error' : '';
  state.messages.push({ text, error });
}

function step(name) {
  for (const s of ['record', 'train', 'drive']) $(`step-${s}`).classList.toggle('on', s === name);
}

function call(type, payload, transfer = []) {
  const id = ++state.calls;
  return new Promise((resolve, reject) => {
    state.pending.set(id, { resolve, reject });
    state.worker.postMessage({ type, id, ...payload }, transfer);
  });
}

// -- the camera and the tracker (the live page's worker.js) ---------------------------------
function startWorker() {
  return spawnWorker({
    base, tracker: true, pending: state.pending,
    on: { points: onPoints, frame: onFrame },
    onError: (m) => { state.busy = false; message(`Worker error: ${m.message}`, true); },
    onStartFailed: (e) => { message(`The page's worker failed to start (${e.message || 'worker.js'}).`, true); return e; },
  });
}

function sendFrame() {
  const v = $('camera');
  if (state.paused || state.busy || v.readyState < 2 || v.currentTime === state.lastTime) return;
  // while recording, at most KEEP_FPS frames a second (those the tracker sees are those kept)
  if (state.recording && performance.now() - (state.keptAt ?? -1e9) < 1000 / KEEP_FPS - 2) return;
  state.keptAt = performance.now();
  state.lastTime = v.currentTime;
  state.busy = true;
  // while a prompt records, the frame the tracker gets is kept too (a JPEG), paired with its points
  state.inflight = state.recording;
  if (state.recording) {
    state.grab ??= document.createElement('canvas');
    [state.grab.width, state.grab.height] = [v.videoWidth, v.videoHeight];
    state.grab.getContext('2d').drawImage(v, 0, 0);
    state.recording.frames.push(new Promise((resolve) => state.grab.toBlob(resolve, 'image/jpeg', JPEG_QUALITY)));
  }
  createImageBitmap(v).then((bitmap) => state.worker.postMessage({ type: 'frame', bitmap, t: performance.now() }, [bitmap]))
    .catch(() => { state.busy = false; if (state.inflight) state.inflight.points.push(null); });
}

function pump() {
  sendFrame();
  const v = $('camera');
  if (v.requestVideoFrameCallback) v.requestVideoFrameCallback(pump); else requestAnimationFrame(pump);
}

function onPoints(m) {
  state.busy = false;
  state.points = m.points;
  if (state.inflight) { state.inflight.points.push(m.points ? Array.from(m.points) : null); state.inflight = null; }
  if (state.avatar && !state.neutral && m.points) {
    state.neutralStart ??= performance.now();
    state.neutralSamples.push(m.points);
    if (performance.now() - state.neutralStart >= NEUTRAL_MS && state.neutralSamples.length >= 3) {
      state.neutral = state.neutralSamples[selectNeutral(state.neutralSamples, state.schemes.mediapipe478.to_ibug68)];
      state.worker.postMessage({ type: 'neutral', points: state.neutral });
      message(`Live: ${state.avatar.name} follows your face.`);
    }
  }
  sendFrame();
  if (state.avatar && m.points) state.reach.update(m.points, state.neutral);  // the live page's readout (main.js)
}

function onFrame(m) {
  const a = state.avatar;
  if (!m.data || !a || m.dims[1] !== a.height || m.dims[2] !== a.width) return;
  const src = m.data, px = a.rgba.data;
  for (let i = 0, j = 0; j < src.length; i += 4, j += 3) { px[i] = src[j]; px[i + 1] = src[j + 1]; px[i + 2] = src[j + 2]; px[i + 3] = 255; }
  a.ctx.putImageData(a.rgba, 0, 0);
  state.frames++;
  state.firstFrameAt ??= Date.now();
  $('stats').textContent = `${state.frames} frames`;
}

// training: no frames to the tracker and the video element stopped (both cores to the job)
function pauseCamera(paused) {
  state.paused = paused;
  if (paused) $('camera').pause(); else $('camera').play().catch(() => {});
}

async function startCamera() {
  let stream;
  try { stream = await navigator.mediaDevices.getUserMedia({ video: { width: 640, height: 480 }, audio: false }); }
  catch (e) {
    if (e.name === 'NotAllowedError') throw new Error('Camera permission denied: allow the camera for this page and reload.');
    throw new Error(`The camera could not start (${e.name}: ${e.message}).`);
  }
  state.stream = stream;
  $('camera').srcObject = stream;
  await $('camera').play();
}

// -- step 1: record, guided ------------------------------------------------------------------
function drawPrompts() {
  const rows = PROMPTS.map((p) => {
    const c = state.coverage?.prompts[p.id];
    const weak = p.frames && state.coverage?.missing.includes(p.id) ? ' class="weak"' : '';
    return `<tr id="row-${p.id}"${weak}><td>${p.text}</td><td><meter min="0" max="1" value="${c ?? 0}"></meter></td>` +
      `<td>${p.frames ? Math.round(100 * c) + ' %' : '-'}</td><td><button data-redo="${p.id}" ${p.frames ? '' : 'disabled'}>Redo</button></td></tr>`;
  });
  $('prompts').innerHTML = rows.join('');
  for (const b of document.querySelectorAll('[data-redo]')) b.onclick = () => record([PROMPTS.find((p) => p.id === b.dataset.redo)]);
}

function updateCoverage() {
  const done = PROMPTS.filter((p) => p.frames);
  state.coverage = coverage(done, state.schemes.mediapipe478.to_ibug68);
  for (const p of PROMPTS) if (!p.frames) state.coverage.prompts[p.id] = 0;
  // the headline: the recording's reach of its own unseen seconds (what predicts held-out quality)
  $('overall').value = state.coverage.self_reach;
  $('overall-text').textContent = `${Math.round(100 * state.coverage.self_reach)} %`;
  // the prompts whose bar is below WEAK (coverage.js lists them: the same numbers as the bars)
  const missing = state.coverage.missing.map((id) => PROMPTS.find((p) => p.id === id).text);
  $('missing').textContent = missing.length ? `Missing or weak (redo): ${missing.join('; ')}` : 'Every prompt is covered.';
  drawPrompts();
}

// record one prompt: the camera's frames the tracker saw (JPEG) and its points
function recordPrompt(p) {
  return new Promise((resolve) => {
    const take = { frames: [], points: [] };
    $('prompt').textContent = p.text;
    for (const r of document.querySelectorAll('#prompts tr')) r.classList.toggle('now', r.id === `row-${p.id}`);
    state.recording = take;
    setTimeout(async () => {
      state.recording = null;
      const frames = await Promise.all(take.frames);
      for (let i = 0; i < 250 && take.points.length < frames.length; i++) await new Promise((r) => setTimeout(r, 20));  // the last frame's points
      while (take.points.length < frames.length) take.points.push(null);
      p.frames = frames; p.points = take.points;
      resolve();
    }, p.seconds * SCALE * 1000);
  });
}

async function record(list = PROMPTS) {
  $('record').disabled = $('train').disabled = true;
  step('record');
  try {
    for (const p of list) { await recordPrompt(p); updateCoverage(); }
    const empty = PROMPTS.filter((p) => p.frames && !p.frames.length).map((p) => p.text);
    if (empty.length) message(`No frame was recorded for: ${empty.join('; ')}. Redo it.`, true);
    else message('Recorded. Redo any prompt whose meter is low, then train.');
  } catch (e) { message(e.message, true); }
  $('prompt').textContent = '';
  $('record').disabled = false;
  $('train').disabled = !PROMPTS.every((p) => p.frames?.length);
}

// -- step 2: train on this machine -----------------------------------------------------------
const fmtS = (s) => (s == null ? '' : s >= 60 ? `${Math.floor(s / 60)} min ${Math.round(s % 60)} s` : `${Math.round(s)} s`);

async function train() {
  const name = $('name').value.trim(), parts = [];
  for (const f of PROMPTS.flatMap((p) => p.frames)) {  // each frame: its length (4 bytes, big-endian), its JPEG
    const n = new DataView(new ArrayBuffer(4));
    n.setUint32(0, f.size);
    parts.push(n.buffer, f);
  }
  step('train');
  $('train').disabled = $('record').disabled = true;
  pauseCamera(true);  // the training gets both cores
  state.trainPressedAt = Date.now();
  let r;
  try {
    r = await fetch(`api/train?name=${encodeURIComponent(name)}`, { method: 'POST', body: new Blob(parts),
      headers: { 'X-Facesynth-Token': state.token, 'Content-Type': 'application/octet-stream' } });
  } catch (e) { r = { ok: false, json: async () => ({ error: `the upload failed (${e.message})` }) }; }
  if (!r.ok) {
    const { error } = await r.json().catch(() => ({ error: `HTTP ${r.status}` }));
    pauseCamera(false);
    message(`Cannot train: ${error}`, true);
    $('train').disabled = $('record').disabled = false;
    return;
  }
  $('cancel').disabled = false;
  message(`Training ${name} on this machine...`);
  follow(name);
}

// the job's progress until the avatar is live; then its report (written meanwhile) until it is
function follow(name) {
  const es = new EventSource('api/progress');
  let driving = false;
  es.onmessage = async (ev) => {
    const s = JSON.parse(ev.data);
    state.job = s;
    if (s.state === 'running' || s.state === 'uploading') {
      $('progress').value = s.percent ?? 0;
      $('progress-text').textContent = `${s.stage}: ${Math.round(s.percent ?? 0)} %` + (s.eta_s != null ? `, about ${fmtS(s.eta_s)} left` : '');
      return;
    }
    $('cancel').disabled = true;
    if (s.state === 'done') {
      $('progress').value = 100;
      const report = s.report === 'writing' ? `; writing its report (${s.report_stage})...`
        : s.report === 'failed' ? `; its report failed: ${s.report_message}` : '';
      $('progress-text').textContent = `live in ${fmtS(s.elapsed_s)}${report}`;
      if (!driving) { driving = true; pauseCamera(false); await refreshLibrary(); await drive(name); }
      if (s.report === 'writing') return;
      es.close();
      $('train').disabled = $('record').disabled = false;
      await refreshLibrary();
    } else {
      es.close();
      $('train').disabled = $('record').disabled = false;
      pauseCamera(false);
      $('progress-text').textContent = '';
      message(s.message, true);
    }
  };
}

async function cancel() {
  const r = await fetch('api/cancel', { method: 'POST', headers: { 'X-Facesynth-Token': state.token } });
  if (!r.ok) message((await r.json()).error, true);
}

// -- step 3: drive it, and the library ------------------------------------------------------
async function refreshLibrary() {
  const { avatars } = await (await fetch('api/library')).json();
  $('library').innerHTML = avatars.length ? '' : '<li class="hint">No avatar yet.</li>';
  for (const a of avatars) {
    const li = document.createElement('li'), b = document.createElement('button');
    b.textContent = `Drive ${a.name}`;
    b.onclick = () => drive(a.name);
    li.append(b);
    if (a.report) {
      const l = document.createElement('a');
      Object.assign(l, { href: `library/${encodeURIComponent(a.name)}/report.html`, target: '_blank', textContent: ' report' });
      li.append(l);
    }
    $('library').append(li);
  }
  state.library = avatars.map((a) => a.name);
}

async function drive(name) {
  step('drive');
  try {
    const r = await fetch(`library/${encodeURIComponent(name)}/avatar.onnx`);
    if (!r.ok) throw new Error(`${name}: its avatar.onnx is missing (HTTP ${r.status})`);
    const graph = await r.arrayBuffer(), meta = onnxMetadata(graph), scheme = meta.landmark_scheme;
    if (!(scheme in state.schemes)) throw new Error(`${name}: landmark scheme ${scheme} cannot be driven by the tracker`);
    const [width, height] = meta.frame_size;
    await call('avatar', { graph, name, n: state.schemes[scheme].n_points, rows: scheme === 'mediapipe478' ? null : state.schemes[scheme].to_ibug68 }, [graph]);
    const cv = $('avatar');
    cv.width = width; cv.height = height; cv.hidden = false;
    $('view').classList.add('driving');
    const ctx = cv.getContext('2d'), bg = new Image();
    bg.src = 'data:image/jpeg;base64,' + meta.background_jpeg;
    await bg.decode();
    ctx.drawImage(bg, 0, 0);
    state.avatar = { name, width, height, ctx, rgba: new ImageData(width, height) };
    state.reach.setAvatar(meta);
    state.neutral = null; state.neutralSamples = []; state.neutralStart = null; state.frames = 0; state.firstFrameAt = null;
    state.worker.postMessage({ type: 'neutral', points: null });
    message(`Look at the camera with a neutral face: ${name} starts in a second...`);
  } catch (e) { message(e.message, true); }
}

async function main() {
  const session = await (await fetch('api/session')).json();
  state.token = session.token;
  state.schemes = await (await fetch('schemes.json')).json();
  state.reach = new ReachReadout($('reach'), $('reach-note'), state.schemes.mediapipe478.to_ibug68);
  window.studio.coverage = (prompts) => coverage(prompts, state.schemes.mediapipe478.to_ibug68);  // the tests' hook
  window.studio.directions = Object.keys(DIRECTIONS);
  drawPrompts();
  $('record').onclick = () => record();
  $('train').onclick = train;
  $('cancel').onclick = cancel;
  await refreshLibrary();
  state.worker = startWorker();
  try { await startCamera(); } catch (e) { message(e.message, true); return; }
  await state.worker.ready;
  pump();
  $('record').disabled = false;
  message('Press Record and follow the prompts (about 40 s).');
  state.ready = true;
}

main().catch((e) => message(`Unexpected error: ${e.message || e}`, true));
