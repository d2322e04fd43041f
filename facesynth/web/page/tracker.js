// The face tracker, in a Web Worker: MediaPipe's detector and attention mesh (478 points with
// irises, the model of `facesynth ingest --landmarker mediapipe`; converted to ONNX at build
// time, refined inside the graph) with MediaPipe's crop-and-track steps. Mirrors
// facesynth/web/track.py step for step (its Python reference, tested against MediaPipe).
// Messages in: {type:'init', base}, {type:'frame', bitmap, t}, {type:'pixels', data, width, height}, {type:'reset'}.
// Out: {type:'ready'}, {type:'points', points: Float32Array(478*2) | null, t, ms} ('tracked' for 'pixels'),
// {type:'error', message}.
import * as ort from './ort/ort.wasm.min.mjs';

const MESH = 192, DET = 128, FACE_SCALE = 1.5;
let det, mesh, anchors, prev = null, canvas, ctx;
const stage = {};

function makeAnchors() {
  const out = [];
  for (const [stride, n] of [[8, 2], [16, 6]]) {
    const g = DET / stride;
    for (let y = 0; y < g; y++) for (let x = 0; x < g; x++) for (let k = 0; k < n; k++) out.push((x + 0.5) / g, (y + 0.5) / g);
  }
  return Float32Array.from(out);
}

// (2, 3) map from crop coordinates to frame pixels, row-major [a, b, tx, d, e, ty] (track.crop_matrix)
export function cropMatrix(cx, cy, ang, size, out) {
  const c = Math.cos(ang), s = Math.sin(ang), k = size / out, h = out / 2;
  const a = c * k, b = -s * k, d = s * k, e = c * k;
  return [a, b, cx - (a * h + b * h), d, e, cy - (d * h + e * h)];
}
const apply = (m, x, y) => [m[0] * x + m[1] * y + m[2], m[3] * x + m[4] * y + m[5]];

// bilinear sampling of an RGBA frame at M(u, v) + 0.5 (track._crop: cv2.warpAffine, zeros outside),
// scaled from [0, 255] to [lo, hi]; (1, out, out, 3) float32
function crop(img, m, out, lo, hi) {
  const { data, width: W, height: H } = img, t = new Float32Array(out * out * 3), sc = (hi - lo) / 255;
  const px = (xx, yy) => (xx < 0 || yy < 0 || xx >= W || yy >= H ? -1 : (yy * W + xx) * 4);
  let o = 0;
  for (let v = 0; v < out; v++) {
    let x = m[1] * v + m[2] + 0.5, y = m[4] * v + m[5] + 0.5;  // MediaPipe's half pixel (track._crop)
    for (let u = 0; u < out; u++, x += m[0], y += m[3], o += 3) {
      const x0 = Math.floor(x), y0 = Math.floor(y), fx = x - x0, fy = y - y0;
      const w00 = (1 - fx) * (1 - fy), w10 = fx * (1 - fy), w01 = (1 - fx) * fy, w11 = fx * fy;
      if (x0 >= 0 && y0 >= 0 && x0 + 1 < W && y0 + 1 < H) {
        const i00 = (y0 * W + x0) * 4, i10 = i00 + 4, i01 = i00 + W * 4, i11 = i01 + 4;
        for (let c = 0; c < 3; c++) {
          t[o + c] = (w00 * data[i00 + c] + w10 * data[i10 + c] + w01 * data[i01 + c] + w11 * data[i11 + c]) * sc + lo;
        }
      } else {
        const idx = [px(x0, y0), px(x0 + 1, y0), px(x0, y0 + 1), px(x0 + 1, y0 + 1)], w = [w00, w10, w01, w11];
        for (let c = 0; c < 3; c++) {
          let acc = 0;
          for (let k = 0; k < 4; k++) if (idx[k] >= 0) acc += w[k] * data[idx[k] + c];
          t[o + c] = acc * sc + lo;
        }
      }
    }
  }
  return new ort.Tensor('float32', t, [1, out, out, 3]);
}

function roi(pts, a, b, scale, idx) {
  let x0 = Infinity, y0 = Infinity, x1 = -Infinity, y1 = -Infinity;
  for (const i of idx) { const x = pts[2 * i], y = pts[2 * i + 1]; x0 = Math.min(x0, x); y0 = Math.min(y0, y); x1 = Math.max(x1, x); y1 = Math.max(y1, y); }
  const ang = Math.atan2(pts[2 * b + 1] - pts[2 * a + 1], pts[2 * b] - pts[2 * a]);
  return [(x0 + x1) / 2, (y0 + y1) / 2, ang, Math.max(x1 - x0, y1 - y0) * scale];
}
const sigmoid = (x) => 1 / (1 + Math.exp(-Math.max(-100, Math.min(100, x))));
const ALL = Array.from({ length: 478 }, (_, i) => i);

async function detect(img) {
  const side = Math.max(img.width, img.height);
  const m = cropMatrix((img.width - 1) / 2, (img.height - 1) / 2, 0, side, DET);
  const r = await det.run({ input: crop(img, m, DET, -1, 1) });
  const raw = r.regressors.data, logit = r.classificators.data;
  let k = 0;
  for (let i = 1; i < 896; i++) if (logit[i] > logit[k]) k = i;
  if (sigmoid(logit[k]) < 0.5) return null;
  const q = (j) => raw[k * 16 + j] / DET;
  const px = (x, y) => apply(m, x * DET, y * DET);
  const [cx, cy] = px(anchors[2 * k] + q(0), anchors[2 * k + 1] + q(1));
  const [ax, ay] = px(anchors[2 * k] + q(4), anchors[2 * k + 1] + q(5));
  const [bx, by] = px(anchors[2 * k] + q(6), anchors[2 * k + 1] + q(7));
  return [cx, cy, Math.atan2(by - ay, bx - ax), Math.max(q(2), q(3)) * side * FACE_SCALE];
}

async function track(img) {
  const r = prev ? roi(prev, 33, 263, FACE_SCALE, ALL) : await detect(img);
  if (!r) return null;
  const m = cropMatrix(...r, MESH);
  const tc = performance.now(), x = crop(img, m, MESH, 0, 1);
  stage.crop = performance.now() - tc;
  const tm = performance.now(), out = await mesh.run({ input: x });
  stage.mesh = performance.now() - tm;
  const lm = out.landmarks.data, presence = out.conv_faceflag.data[0];
  if (sigmoid(presence) < 0.5) { prev = null; return null; }
  const pts = new Float32Array(478 * 2);
  for (let i = 0; i < 478; i++) { const [x, y] = apply(m, lm[2 * i], lm[2 * i + 1]); pts[2 * i] = x; pts[2 * i + 1] = y; }
  prev = pts.slice();
  return pts;
}

self.onmessage = async (ev) => {
  const msg = ev.data;
  try {
    if (msg.type === 'init') {
      ort.env.wasm.wasmPaths = msg.base + 'ort/';
      ort.env.wasm.numThreads = 1;
      const opts = { executionProviders: ['wasm'] };
      [det, mesh] = await Promise.all(['face_detection', 'face_landmark']
        .map((n) => ort.InferenceSession.create(msg.base + `models/${n}.onnx`, opts)));
      anchors = makeAnchors();
      self.postMessage({ type: 'ready' });
    } else if (msg.type === 'spent') {  // the page's spent buffers, handed here to be freed sooner (main.js: release)
    } else if (msg.type === 'reset') {
      prev = null;
    } else if (msg.type === 'pixels') {  // replay: RGBA pixels in, points out (the tests' hook)
      const img = { data: new Uint8ClampedArray(msg.data), width: msg.width, height: msg.height };
      const points = await track(img);
      self.postMessage({ type: 'tracked', points }, points ? [points.buffer] : []);
    } else if (msg.type === 'frame') {
      const t0 = performance.now();
      const bm = msg.bitmap;
      if (!canvas || canvas.width !== bm.width || canvas.height !== bm.height) {
        canvas = new OffscreenCanvas(bm.width, bm.height);
        ctx = canvas.getContext('2d', { willReadFrequently: true });
      }
      ctx.drawImage(bm, 0, 0);
      bm.close();
      const img = ctx.getImageData(0, 0, canvas.width, canvas.height);
      stage.read = performance.now() - t0;
      const points = await track(img);
      self.postMessage({ type: 'points', points, t: msg.t, ms: performance.now() - t0, stage: { ...stage }, width: img.width, height: img.height },
        points ? [points.buffer] : []);
    }
  } catch (e) {
    self.postMessage({ type: 'error', message: String(e && e.message || e) });
  }
};
