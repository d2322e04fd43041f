// The driver's neutral among the frames of the page's capture, by the project's one rule
// (facesynth/neutral.py, select_neutral, step for step): among the frames with a closed mouth
// (the mean inner-lip gap 61-67, 62-66, 63-65 over the outer-eye-corner distance 36-45 at most
// 0.03; if none is, the 10 % with the smallest gap), the one closest to the mean shape of a
// generalised Procrustes alignment (facesynth.geometry.generalised_procrustes). On the frames'
// iBUG-68 view. Tested against Python on the same frames (tests/test_web_page.py).

import { toScheme } from './schemes.js';

const INNER_UPPER = [61, 62, 63], INNER_LOWER = [67, 66, 65], EYES = [36, 45], MOUTH_CLOSED_MAX = 0.03;

// a frame (P x 2 flat) -> its 68 points [[x, y], ...] through the scheme's to_ibug68 rows
function view68(points, rows) {
  const v = toScheme(points, rows, Float64Array);  // in double precision, as numpy
  return Array.from({ length: v.length / 2 }, (_, k) => [v[2 * k], v[2 * k + 1]]);
}

const dist = (a, b) => Math.hypot(a[0] - b[0], a[1] - b[1]);
const mouthOpen = (s) => INNER_UPPER.reduce((acc, u, k) => acc + dist(s[u], s[INNER_LOWER[k]]), 0) / 3 / dist(s[EYES[0]], s[EYES[1]]);

function normalise(s) {  // centred, unit Frobenius norm
  const n = s.length, mx = s.reduce((a, p) => a + p[0], 0) / n, my = s.reduce((a, p) => a + p[1], 0) / n;
  const c = s.map((p) => [p[0] - mx, p[1] - my]), norm = Math.sqrt(c.reduce((a, p) => a + p[0] * p[0] + p[1] * p[1], 0));
  return c.map((p) => [p[0] / norm, p[1] / norm]);
}

// the least-squares similarity mapping src onto dst (geometry.similarity_fit), applied to src
function fitted(src, dst) {
  const n = src.length, mean = (s, k) => s.reduce((a, p) => a + p[k], 0) / n;
  const sx = mean(src, 0), sy = mean(src, 1), dx = mean(dst, 0), dy = mean(dst, 1);
  let a = 0, b = 0, v = 0;
  for (let i = 0; i < n; i++) {
    const s0 = src[i][0] - sx, s1 = src[i][1] - sy, d0 = dst[i][0] - dx, d1 = dst[i][1] - dy;
    a += s0 * d0 + s1 * d1; b += s0 * d1 - s1 * d0; v += s0 * s0 + s1 * s1;
  }
  const norm = Math.hypot(a, b), scale = v > 0 ? norm / v : 1, cos = norm > 0 ? a / norm : 1, sin = norm > 0 ? b / norm : 0;
  const r = [[cos * scale, -sin * scale], [sin * scale, cos * scale]];
  const tx = dx - (sx * r[0][0] + sy * r[0][1]), ty = dy - (sx * r[1][0] + sy * r[1][1]);
  return src.map((p) => [r[0][0] * p[0] + r[0][1] * p[1] + tx, r[1][0] * p[0] + r[1][1] * p[1] + ty]);
}

function procrustes(shapes, maxIter = 100, tol = 1e-10) {
  const ref = normalise(shapes[0]);
  let mean = ref;
  for (let it = 0; it < maxIter; it++) {
    const aligned = shapes.map((s) => fitted(s, mean));
    const avg = mean.map((_, k) => [0, 1].map((c) => aligned.reduce((acc, s) => acc + s[k][c], 0) / aligned.length));
    const next = normalise(fitted(normalise(avg), ref));
    const delta = Math.sqrt(next.reduce((acc, p, k) => acc + (p[0] - mean[k][0]) ** 2 + (p[1] - mean[k][1]) ** 2, 0));
    mean = next;
    if (delta < tol) break;
  }
  return { aligned: shapes.map((s) => fitted(s, mean)), mean };
}

// frames (each P x 2 flat, the scheme's points) -> the index of the neutral one; rows: the scheme's to_ibug68
export function selectNeutral(frames, rows) {
  const shapes = frames.map((f) => view68(f, rows)), gap = shapes.map(mouthOpen);
  let cand = gap.map((g, i) => i).filter((i) => gap[i] <= MOUTH_CLOSED_MAX);
  if (!cand.length) cand = gap.map((g, i) => i).sort((i, j) => gap[i] - gap[j]).slice(0, Math.max(1, Math.floor(frames.length / 10)));
  const { aligned, mean } = shapes.length > 1 ? procrustes(shapes) : { aligned: shapes, mean: shapes[0] };
  const d = aligned.map((s) => Math.sqrt(s.reduce((acc, p, k) => acc + (p[0] - mean[k][0]) ** 2 + (p[1] - mean[k][1]) ** 2, 0)));
  return cand.reduce((best, i) => (d[i] < d[best] ? i : best), cand[0]);
}
