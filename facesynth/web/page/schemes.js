// Landmarks of one scheme -> another through the project's landmark tables (schemes.json, from
// facesynth.landmarks: each target point's [[source index, weight], ...]).

// points (P x 2 flat) -> rows.length x 2 flat, an Out (Float32Array: an ONNX Runtime input; Float64Array
// for measures taken as Python takes them); rows null: the points as they are
export function toScheme(points, rows, Out = Float32Array) {
  if (!rows) return points;
  const out = new Out(rows.length * 2);
  rows.forEach((row, i) => { for (const [j, w] of row) { out[2 * i] += w * points[2 * j]; out[2 * i + 1] += w * points[2 * j + 1]; } });
  return out;
}
