// The face tracker: MediaPipe's detector and attention mesh (478 points with irises, the model of
// `facesynth ingest --landmarker mediapipe`; converted to ONNX at build time, refined inside the
// graph) with MediaPipe's crop-and-track steps. Mirrors facesynth/web/track.py step for step (its
// Python reference, tested against MediaPipe). Runs in the page's worker (worker.js).
import * as ort from './ort/ort.wasm.min.mjs';

const MESH = 192, DET = 128, FACE_SCALE = 1.5;

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

const crops = {};  // one input buffer per crop size, rewritten by each crop (ONNX Runtime copies it in)

// bilinear sampling of an RGBA frame at M(u, v) + 0.5 (track._crop: cv2.warpAffine, zeros outside),
// scaled from [0, 255] to [lo, hi]; (1, out, out, 3) float32. img: {data, width, height, x?, y?}, the
// frame or a region of it at (x, y) that holds every pixel the crop reads inside the frame (region())
function crop(img, m, out, lo, hi) {
  const { data, width: W, height: H } = img, sc = (hi - lo) / 255;
  const t = (crops[out] ??= new Float32Array(out * out * 3)), ox = img.x || 0, oy = img.y || 0;
  const px = (xx, yy) => (xx < 0 || yy < 0 || xx >= W || yy >= H ? -1 : (yy * W + xx) * 4);
  let o = 0;
  for (let v = 0; v < out; v++) {
    let x = m[1] * v + m[2] + 0.5 - ox, y = m[4] * v + m[5] + 0.5 - oy;  // MediaPipe's half pixel (track._crop)
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

export class Tracker {
  // base: the page's URL folder (the models are in base/models/)
  static async create(base) {
    const t = new Tracker(), opts = { executionProviders: ['wasm'] };
    [t.det, t.mesh] = await Promise.all(['face_detection', 'face_landmark']
      .map((n) => ort.InferenceSession.create(base + `models/${n}.onnx`, opts)));
    Object.assign(t, { anchors: makeAnchors(), prev: null, stage: {} });
    return t;
  }

  reset() { this.prev = null; }

  // The part of a W x H frame that the next track() reads, {x, y, width, height}, or null for the
  // whole frame (the detector's): the box of the mesh crop's bilinear taps, placed from the last
  // points, 1 px to spare. The worker reads only it from the camera frame.
  region(W, H) {
    if (!this.prev) return null;
    const m = cropMatrix(...roi(this.prev, 33, 263, FACE_SCALE, ALL), MESH), e = MESH - 1, xs = [], ys = [];
    for (const [u, v] of [[0, 0], [e, 0], [0, e], [e, e]]) { const [x, y] = apply(m, u, v); xs.push(x + 0.5); ys.push(y + 0.5); }
    const x0 = Math.max(0, Math.floor(Math.min(...xs)) - 1), y0 = Math.max(0, Math.floor(Math.min(...ys)) - 1);
    const x1 = Math.min(W, Math.floor(Math.max(...xs)) + 3), y1 = Math.min(H, Math.floor(Math.max(...ys)) + 3);
    return x1 > x0 && y1 > y0 ? { x: x0, y: y0, width: x1 - x0, height: y1 - y0 } : null;
  }

  async detect(img) {
    const side = Math.max(img.width, img.height);
    const m = cropMatrix((img.width - 1) / 2, (img.height - 1) / 2, 0, side, DET);
    const r = await this.det.run({ input: crop(img, m, DET, -1, 1) });
    const raw = r.regressors.data, logit = r.classificators.data;
    let k = 0;
    for (let i = 1; i < 896; i++) if (logit[i] > logit[k]) k = i;
    if (sigmoid(logit[k]) < 0.5) return null;
    const q = (j) => raw[k * 16 + j] / DET;
    const px = (x, y) => apply(m, x * DET, y * DET);
    const [cx, cy] = px(this.anchors[2 * k] + q(0), this.anchors[2 * k + 1] + q(1));
    const [ax, ay] = px(this.anchors[2 * k] + q(4), this.anchors[2 * k + 1] + q(5));
    const [bx, by] = px(this.anchors[2 * k] + q(6), this.anchors[2 * k + 1] + q(7));
    return [cx, cy, Math.atan2(by - ay, bx - ax), Math.max(q(2), q(3)) * side * FACE_SCALE];
  }

  // RGBA frame {data, width, height} -> Float32Array(478 * 2) frame pixels, or null (no face)
  async track(img) {
    const r = this.prev ? roi(this.prev, 33, 263, FACE_SCALE, ALL) : await this.detect(img);
    if (!r) return null;
    const m = cropMatrix(...r, MESH);
    const tc = performance.now(), x = crop(img, m, MESH, 0, 1);
    this.stage.crop = performance.now() - tc;
    const tm = performance.now(), out = await this.mesh.run({ input: x });
    this.stage.mesh = performance.now() - tm;
    const lm = out.landmarks.data, presence = out.conv_faceflag.data[0];
    if (sigmoid(presence) < 0.5) { this.prev = null; return null; }
    const pts = new Float32Array(478 * 2);
    for (let i = 0; i < 478; i++) { const [x, y] = apply(m, lm[2 * i], lm[2 * i + 1]); pts[2 * i] = x; pts[2 * i + 1] = y; }
    this.prev = pts.slice();
    return pts;
  }
}
