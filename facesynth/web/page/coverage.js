// The studio's coverage meter: how well the recording reaches the expressions the avatar will be
// driven through, per prompt and overall, and which prompts are missing or weak. Step for step the Python reference
// facesynth/coverage.py (its docstring gives the measure); tested against it on the same
// points (tests/test_web_studio.py).
import { toScheme } from './schemes.js';

export const FEATURES = ['mouth_open', 'mouth_width', 'brow_height', 'brow_gap', 'eye_open', 'gaze_x', 'gaze_y', 'yaw'];
export const DIRECTIONS = {  // name -> [feature, sign, target change from the neutral]
  speech: ['mouth_open', 1, 0.12], smile: ['mouth_width', 1, 0.12], mouth_open: ['mouth_open', 1, 0.30],
  oo: ['mouth_width', -1, 0.10], brows_up: ['brow_height', 1, 0.05], frown: ['brow_gap', -1, 0.04],
  blink: ['eye_open', -1, 0.07], gaze_left: ['gaze_x', 1, 0.03], gaze_right: ['gaze_x', -1, 0.03],
  gaze_up: ['gaze_y', -1, 0.02], gaze_down: ['gaze_y', 1, 0.02], turn_left: ['yaw', 1, 0.08], turn_right: ['yaw', -1, 0.08],
};
export const SCALE = [0.12, 0.10, 0.05, 0.04, 0.07, 0.03, 0.02, 0.08];  // each feature's unit
export const NEAREST = 3, REACH = 1.0, WEAK = 0.5;
export const DRIVE_REACH = 2.0;  // the reach's scale for a driver's frame (coverage.py DRIVE_REACH)
// selfReach's blocks: one second of the recording at the frames a second the page keeps (studio.js's KEEP_FPS)
export const KEEP_FPS = 15, BLOCK = KEEP_FPS;
const IRIS = [468, 473];

// one frame's 478 points (flat) -> its features (FEATURES' order); rows: mediapipe478's to_ibug68
export function features(points, rows) {
  const f = toScheme(points, rows, Float64Array), P = (i) => [f[2 * i], f[2 * i + 1]];
  const sub = (a, b) => [a[0] - b[0], a[1] - b[1]], dot = (a, b) => a[0] * b[0] + a[1] * b[1];
  const norm = (a) => Math.hypot(a[0], a[1]), gap = (a, b) => norm(sub(P(a), P(b)));
  const iod = gap(45, 36), d = sub(P(45), P(36)), u = [d[0] / iod, d[1] / iod], v = [-u[1], u[0]];
  const mean = (idx) => { let x = 0, y = 0; for (const i of idx) { const p = P(i); x += p[0]; y += p[1]; } return [x / idx.length, y / idx.length]; };
  const range = (a, b) => Array.from({ length: b - a }, (_, k) => a + k);
  const eyes = mean(range(36, 48));
  const iris = [(points[2 * IRIS[0]] + points[2 * IRIS[1]]) / 2, (points[2 * IRIS[0] + 1] + points[2 * IRIS[1] + 1]) / 2];
  const mid = [(P(0)[0] + P(16)[0]) / 2, (P(0)[1] + P(16)[1]) / 2];
  return [
    (gap(61, 67) + gap(62, 66) + gap(63, 65)) / 3 / iod,
    gap(48, 54) / iod,
    range(17, 27).reduce((acc, i) => acc + dot(sub(eyes, P(i)), v), 0) / 10 / iod,
    gap(21, 22) / iod,
    (gap(37, 41) + gap(38, 40) + gap(43, 47) + gap(44, 46)) / 4 / iod,
    dot(sub(iris, eyes), u) / iod,
    dot(sub(iris, eyes), v) / iod,
    dot(sub(P(30), mid), u) / gap(16, 0),
  ];
}

const median = (xs) => { const s = [...xs].sort((a, b) => a - b), n = s.length; return n % 2 ? s[n >> 1] : (s[n / 2 - 1] + s[n / 2]) / 2; };
const avg = (xs) => xs.reduce((a, b) => a + b, 0) / xs.length;

// how well frames (their z: SCALE units from the neutral) reach one shape z: 1 - the mean
// distance to its NEAREST nearest frames / scale (REACH; DRIVE_REACH for a driver's frame),
// clipped to [0, 1]; its NaN features are free
export function reach(framesZ, shapeZ, scale = REACH) {
  if (!framesZ.length) return 0;
  const d = framesZ.map((z) => Math.sqrt(z.reduce((acc, v, k) => acc + (Number.isNaN(shapeZ[k]) ? 0 : (shapeZ[k] - v) ** 2), 0)))
    .sort((a, b) => a - b);
  return Math.min(1, Math.max(0, 1 - avg(d.slice(0, NEAREST)) / scale));
}

const toZ = (f, neutral) => f.map((v, k) => (v - neutral[k]) / SCALE[k]);

// coverage in [0, 1] of a direction (its target shape) by frames' features against the neutral's
export function directionCoverage(feats, neutral, direction) {
  const [name, sign, target] = DIRECTIONS[direction], k = FEATURES.indexOf(name);
  const shape = FEATURES.map((_, j) => (j === k ? sign * target / SCALE[k] : NaN));
  return reach(feats.map((f) => toZ(f, neutral)), shape);
}

// the recording's reach of itself, cross-validated in time: its frames' features in recording
// order, cut into blocks of BLOCK frames; each frame's reach by the frames of the other blocks;
// the mean over the frames (0 without a frame). What predicts the avatar's held-out quality.
export function selfReach(feats) {
  const z = feats.map((f) => f.map((v, k) => v / SCALE[k]));
  if (!z.length) return 0;
  let sum = 0;
  for (let s = 0; s < z.length; s += BLOCK) {
    const others = z.slice(0, s).concat(z.slice(s + BLOCK));
    for (const shape of z.slice(s, s + BLOCK)) sum += reach(others, shape);
  }
  return sum / z.length;
}

// prompts: [{id, directions, points: [flat 478 x 2 or null per frame]}] (the prompt without
// directions is the neutral) -> {prompts: {id: coverage}, directions: {name: coverage}, overall,
// self_reach (selfReach of every frame, prompt after prompt), missing}
export function coverage(prompts, rows) {
  const per = prompts.map((p) => [p, p.points.filter((x) => x).map((x) => features(x, rows))]);
  const every = per.flatMap(([, f]) => f);
  const n = per.find(([p, f]) => !p.directions.length && f.length);
  const neutralFeats = n ? n[1] : every;
  const dirNames = Object.keys(DIRECTIONS);
  if (!neutralFeats.length) {
    return { prompts: Object.fromEntries(prompts.map((p) => [p.id, 0])), directions: Object.fromEntries(dirNames.map((d) => [d, 0])), overall: 0,
      self_reach: 0, missing: prompts.map((p) => p.id) };
  }
  const neutral = FEATURES.map((_, k) => median(neutralFeats.map((f) => f[k])));
  const out = {};
  for (const [p, f] of per) {
    out[p.id] = p.directions.length ? avg(p.directions.map((d) => directionCoverage(f, neutral, d))) : f.length / Math.max(1, p.points.length);
  }
  const dirs = Object.fromEntries(dirNames.map((d) => [d, directionCoverage(every, neutral, d)]));
  return { prompts: out, directions: dirs, overall: avg(Object.values(dirs)), self_reach: selfReach(every),
    missing: prompts.filter((p) => out[p.id] < WEAK).map((p) => p.id) };
}

// -- the live reach: how well the avatar's recording reaches the driver's expression -----------
// The avatar's file carries its training frames as this meter reads them (metadata
// coverage_recording, facesynth/coverage.py recording_entry: z from the avatar's neutral); a
// driver frame's z is taken from the driver's neutral. Python reference: driver_reach.
export const RECORDING_KEY = 'coverage_recording';

// an avatar's coverage_recording entry, checked -> {z: [[F numbers]], scale: [F]}; throws an
// Error naming the field for a malformed entry (read_recording's checks)
export function readRecording(entry) {
  const bad = (what) => new Error(`${RECORDING_KEY}: ${what} (re-export the avatar)`);
  if (!entry || typeof entry !== 'object' || Array.isArray(entry)) throw bad('expected an object');
  if (JSON.stringify(entry.features) !== JSON.stringify(FEATURES)) throw bad(`its features are not the meter's ${FEATURES.join(', ')}`);
  const num = (v) => typeof v === 'number' && Number.isFinite(v);
  const vec = (key, v) => {
    if (!Array.isArray(v) || v.length !== FEATURES.length) throw bad(`${key} must hold ${FEATURES.length} numbers`);
    if (!v.every(num)) throw bad(`${key} has values that are not finite`);
    return v;
  };
  const scale = vec('scale', entry.scale);
  vec('neutral', entry.neutral);
  if (!scale.every((s) => s > 0)) throw bad('scale has values that are not positive');
  if (!Array.isArray(entry.z) || !entry.z.length) throw bad('z must hold at least one row');
  return { z: entry.z.map((row) => vec('z', row)), scale };
}

// a driver frame's reach by a recording (readRecording's): points and the driver's neutral, both
// 478 x 2 flat (the tracker's), rows: mediapipe478's to_ibug68; NaN when its features are not finite
export function driverReach(rec, points, neutral, rows, neutralFeatures = features(neutral, rows)) {
  const f = features(points, rows), z = f.map((v, k) => (v - neutralFeatures[k]) / rec.scale[k]);
  return z.every(Number.isFinite) ? reach(rec.z, z, DRIVE_REACH) : NaN;
}

// The readout beside the avatar (the live page's and the studio's): the current frame's reach
// (a <meter>) and the mean over the drive so far (since the avatar or the driver's neutral
// changed); hidden without an entry; `note` shows why a malformed entry has none. No colour
// marks a low reading: the prompts' WEAK level does not carry over (on the shared clips,
// self-driven, 61-67 % of held-out frames read below it, and a level taken from the
// recording's own self-reach is 0 on half of them).
export class ReachReadout {
  constructor(el, note, rows) {
    Object.assign(this, { el, note, rows, rec: null, neutral: null, now: NaN, sum: 0, n: 0 });
  }

  // an avatar's metadata -> null, or the one-line note for a malformed entry (readout hidden)
  setAvatar(meta) {
    this.rec = null; this.neutral = null;
    this.el.hidden = true;
    let text = null;
    if (meta && RECORDING_KEY in meta) {  // absent: exported before the entry, or an iBUG-68 avatar
      try { this.rec = readRecording(meta[RECORDING_KEY]); }
      catch (e) { text = `No reach readout: ${e.message}. The avatar drives as usual.`; }
    }
    this.note.textContent = text ?? '';
    this.note.hidden = !text;
    return text;
  }

  // a tracked frame (and the driver's neutral, null while it is captured) -> the readout
  update(points, neutral) {
    if (!this.rec || !points || !neutral) return;
    if (neutral !== this.neutral) { this.neutral = neutral; this.nf = features(neutral, this.rows); this.sum = 0; this.n = 0; }
    const r = driverReach(this.rec, points, neutral, this.rows, this.nf);
    if (Number.isNaN(r)) return;
    this.now = r; this.sum += r; this.n++;
    // the page changes only when a shown percent does (each change costs the page a style and paint pass)
    const shown = [Math.round(100 * r), Math.round(100 * this.sum / this.n)];
    if (this.el.hidden || shown.join() !== this.shown?.join()) {
      this.shown = shown;
      this.el.querySelector('meter').value = shown[0] / 100;
      this.el.querySelector('.now').textContent = `${shown[0]} %`;
      this.el.querySelector('.mean').textContent = `${shown[1]} %`;
      this.el.hidden = false;
    }
  }
}
