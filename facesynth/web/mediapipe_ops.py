"""MediaPipe's custom TFLite ops of the attention face mesh, written in plain ONNX ops, and the
refinement that turns its six outputs into the 478 points of ``refine_landmarks=True``.

``face_landmark_with_attention.tflite`` (the model behind ``facesynth ingest --landmarker
mediapipe``) crops its own feature map around the lips and each eye and regresses those points
again. It does so with three custom ops (version 2), whose semantics are MediaPipe's
``mediapipe/util/tflite/operations``:

- ``Landmarks2TransformMatrix``: points (N, 468, 3) -> (N, 4, 4), the map from a
  ``output_width`` x ``output_height`` crop to point coordinates: the crop is the box of the
  ``subset_idxs`` points in the frame rotated so that point ``left_rotation_idx`` -> point
  ``right_rotation_idx`` lies at ``target_rotation_radians``, grown by ``scale_x``, ``scale_y``;
- ``TransformTensorBilinear``: features (N, H, W, C) sampled bilinearly at that map (pixel
  centres, half a pixel shifted), zero where the sample falls outside [0, W-1] x [0, H-1];
- ``TransformLandmarks``: (N, K, 2) points through the map's 2 x 2 part and translation.

Every function takes the converter (``facesynth.web.convert._Converter``) and writes nodes into it.
"""

from __future__ import annotations

import numpy as np

from facesynth.errors import FacesynthError

# The model's outputs, in the order of the refinement calculator's LANDMARKS:0..5 streams.
REFINE_SOURCES = ("output_mesh_identity", "output_lips", "output_left_eye", "output_right_eye",
                  "output_left_iris", "output_right_iris")
REFINE_STREAMS = ("mesh", "lips", "left_eye", "right_eye", "left_iris", "right_iris")


class _Ops:
    """Fresh-named elementwise helpers over one converter."""

    def __init__(self, conv, tag: str):
        self.c, self.tag, self.k = conv, tag, 0

    def __call__(self, op: str, *ins: str, **attrs) -> str:
        self.k += 1
        out = f"{self.tag}_{op.lower()}{self.k}"
        self.c.node(op, list(ins), [out], **attrs)
        return out

    def const(self, arr, dtype=np.float32) -> str:
        self.k += 1
        return self.c.init(f"{self.tag}_c{self.k}", np.asarray(arr, dtype))

    def take(self, x: str, idx, axis: int) -> str:
        """Gather along ``axis``; a scalar ``idx`` drops the axis."""
        return self("Gather", x, self.const(idx, np.int64), axis=axis)


def landmarks_to_matrix(conv, op, opts: dict) -> None:
    """``Landmarks2TransformMatrix`` v2: (N, P, 3) points -> (N, 4, 4)."""
    f = _Ops(conv, conv.tname(op.Outputs(0)))
    xy = f.take(conv.tname(op.Inputs(0)), [0, 1], axis=2)  # (N, P, 2)
    ends = f.take(xy, [opts["left_rotation_idx"], opts["right_rotation_idx"]], 1)  # (N, 2, 2)
    d = f("Sub", f.take(ends, 1, 1), f.take(ends, 0, 1))  # (N, 2)
    unit = f("Div", d, f("Sqrt", f("ReduceSum", f("Mul", d, d), f.const([1], np.int64), keepdims=1)))  # (cos t, sin t)
    ct, st = f.take(unit, [0], 1), f.take(unit, [1], 1)  # (N, 1) each
    target = float(opts.get("target_rotation_radians", 0.0))
    ca, sa = f.const(np.cos(target)), f.const(np.sin(target))
    c = f("Add", f("Mul", ct, ca), f("Mul", st, sa))  # cos(target - t)
    s = f("Sub", f("Mul", sa, ct), f("Mul", ca, st))  # sin(target - t)
    neg_s = f("Neg", s)
    rows = lambda *e: f("Reshape", f("Concat", *e, axis=1), f.const([-1, 2, 2], np.int64))  # noqa: E731
    rot = rows(c, s, neg_s, c)  # row points @ rot = Rot(r) applied
    unrot = rows(c, neg_s, s, c)  # Rot(-r)
    subset = sorted({int(i) for pair in opts["subset_idxs"] for i in np.ravel(pair)})
    turned = f("MatMul", f.take(xy, subset, 1), rot)  # (N, K, 2)
    lo, hi = f("ReduceMin", turned, axes=[1], keepdims=1), f("ReduceMax", turned, axes=[1], keepdims=1)
    size = f("Sub", hi, lo)  # (N, 1, 2)
    centre = f("Reshape", f("MatMul", f("Mul", f("Add", lo, hi), f.const(0.5)), unrot), f.const([-1, 2], np.int64))
    out_w, out_h = float(opts["output_width"]), float(opts["output_height"])
    k = f("Reshape", f("Mul", size, f.const([opts["scale_x"] / out_w, opts["scale_y"] / out_h])),
          f.const([-1, 2], np.int64))
    kx, ky = f.take(k, [0], 1), f.take(k, [1], 1)
    a00, a01, a10, a11 = f("Mul", c, kx), f("Mul", s, ky), f("Mul", neg_s, kx), f("Mul", c, ky)  # Rot(-r) diag(k)
    half = lambda a, b: f("Add", f("Mul", a, f.const(out_w / 2)), f("Mul", b, f.const(out_h / 2)))  # noqa: E731
    t0 = f("Sub", f.take(centre, [0], 1), half(a00, a01))  # t = centre - A (W/2, H/2)
    t1 = f("Sub", f.take(centre, [1], 1), half(a10, a11))
    zero, one = f("Mul", c, f.const(0.0)), f("Add", f("Mul", c, f.const(0.0)), f.const(1.0))
    flat = f("Concat", a00, a01, zero, t0, a10, a11, zero, t1, zero, zero, one, zero, zero, zero, zero, one, axis=1)
    conv.node("Reshape", [flat, f.const([-1, 4, 4], np.int64)], [conv.tname(op.Outputs(0))])


def _affine_rows(f: _Ops, m: str) -> str:
    """(N, 4, 4) -> (N, 2, 3): the x and y rows' linear part and translation."""
    return f.take(f.take(m, [0, 1], 1), [0, 1, 3], 2)


def transform_tensor_bilinear(conv, op, opts: dict) -> None:
    """``TransformTensorBilinear`` v2: features (NCHW here) sampled on an out_h x out_w grid."""
    x, m = op.Inputs(0), op.Inputs(1)
    if x not in conv.nchw:
        raise FacesynthError(f"{conv.name}: TransformTensorBilinear expects a feature map")
    f = _Ops(conv, conv.tname(op.Outputs(0)))
    _, h, w, ch = conv.shape(x)
    oh, ow = int(opts["output_height"]), int(opts["output_width"])
    # half-pixel shift: t3 += 0.5 t0 + 0.5 t1 - 0.5 for both rows
    shift = np.array([[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1]], np.float32)
    rows = f("Add", f("MatMul", _affine_rows(f, conv.tname(m)), f.const(shift)), f.const([0, 0, -0.5]))
    vv, uu = np.mgrid[0:oh, 0:ow]
    grid = np.stack([uu.ravel(), vv.ravel(), np.ones(oh * ow)], 1)  # (G, 3): u, v, 1
    at = f("MatMul", f.const(grid), f("Transpose", rows, perm=[0, 2, 1]))  # (N, G, 2): x, y in the map
    lo = f("Floor", at)
    frac = f("Sub", at, lo)
    limit = f.const([w - 1, h - 1])
    inside = f("Not", f("Or", f("Less", at, f.const([0.0, 0.0])), f("Greater", at, limit)))
    inside = f("ReduceMin", f("Cast", inside, to=1), axes=[2], keepdims=1)  # (N, G, 1): 1 inside, 0 out
    base = f("Cast", f("Min", f("Max", lo, f.const([0.0, 0.0])), limit), to=7)  # (N, G, 2) int64, clamped
    # features zero-padded by one pixel all round, as rows of C: (N, (H+2)(W+2), C)
    padded = f("Pad", conv.tname(x), f.const([0, 0, 1, 1, 0, 0, 1, 1], np.int64))
    table = f("Reshape", f("Transpose", padded, perm=[0, 2, 3, 1]), f.const([0, -1, ch], np.int64))
    idx0 = f("ReduceSum", f("Mul", f("Add", base, f.const([1, 1], np.int64)), f.const([1, w + 2], np.int64)),
             f.const([2], np.int64), keepdims=1)  # (N, G, 1): row of (y0, x0) in the padded table
    fx, fy = f.take(frac, [0], 2), f.take(frac, [1], 2)
    gx, gy = f("Sub", f.const(1.0), fx), f("Sub", f.const(1.0), fy)
    acc = None
    for dy, dx, wgt in ((0, 0, f("Mul", gx, gy)), (0, 1, f("Mul", fx, gy)), (1, 0, f("Mul", gx, fy)), (1, 1, f("Mul", fx, fy))):
        tap = f("GatherND", table, f("Add", idx0, f.const(dy * (w + 2) + dx, np.int64)), batch_dims=1)  # (N, G, C)
        term = f("Mul", tap, wgt)
        acc = term if acc is None else f("Add", acc, term)
    out = f("Reshape", f("Mul", acc, inside), f.const([-1, oh, ow, ch], np.int64))
    conv.node("Transpose", [out], [conv.tname(op.Outputs(0))], perm=[0, 3, 1, 2])
    conv.nchw.add(op.Outputs(0))


def transform_landmarks(conv, op) -> None:
    """``TransformLandmarks`` v2 on (N, K, 2) points: p -> A p + t."""
    f = _Ops(conv, conv.tname(op.Outputs(0)))
    rows = _affine_rows(f, conv.tname(op.Inputs(1)))  # (N, 2, 3)
    lin = f("Transpose", f.take(rows, [0, 1], 2), perm=[0, 2, 1])
    t = f("Transpose", f.take(rows, [2], 2), perm=[0, 2, 1])  # (N, 1, 2)
    conv.node("Add", [f("MatMul", conv.tname(op.Inputs(0)), lin), t], [conv.tname(op.Outputs(0))])


def refine(conv, sources: list[str], out: str) -> None:
    """The six outputs (REFINE_SOURCES, flat (N, 1, 1, 3 K) or (N, 1, 1, 2 K)) -> ``out`` (N, 478, 2)
    crop pixels: their (x, y) rows stacked, then one Gather by ``refinement_table``."""
    f = _Ops(conv, out)
    rows = []
    for name, dims in zip(sources, (3, 2, 2, 2, 2, 2), strict=True):
        pts = f("Reshape", name, f.const([0, -1, dims], np.int64))
        rows.append(f.take(pts, [0, 1], 2) if dims == 3 else pts)
    conv.node("Gather", [f("Concat", *rows, axis=1), f.const(refinement_table(), np.int64)], [out], axis=1)


def refinement_table() -> np.ndarray:
    """(478,) int64: for each of the 478 points of ``refine_landmarks=True``, its row in the six
    outputs (REFINE_SOURCES, as (x, y) rows) stacked: the mesh, then each refinement overwriting
    the points it maps, as MediaPipe's LandmarksRefinementCalculator does. The mapping is read
    from the graph inside the installed wheel's bindings (the calculator's serialized options)."""
    from pathlib import Path

    from facesynth.web.convert import mediapipe_modules

    so = sorted((mediapipe_modules().parent / "python").glob("_framework_bindings*.so"))
    if not so:
        raise FacesynthError("the mediapipe wheel has no _framework_bindings library to read the refinement from")
    spec = _refinement_options(Path(so[0]).read_bytes())
    sizes = [468, 80, 71, 71, 5, 5]
    table = np.full(478, -1, np.int64)
    start = 0
    for ref, n in zip(spec.refinement, sizes, strict=True):
        mapping = np.asarray(ref.indexes_mapping, np.int64)
        if mapping.size != n:
            raise FacesynthError(f"mediapipe refinement maps {mapping.size} points where the model gives {n}")
        table[mapping] = start + np.arange(n)
        start += n
    if (table < 0).any():
        raise FacesynthError("mediapipe refinement leaves points of the 478 unmapped")
    return table


def _refinement_options(blob: bytes):
    from mediapipe.calculators.util import landmarks_refinement_calculator_pb2 as lrc
    from mediapipe.framework import calculator_pb2

    key = b"\x12\x1dLandmarksRefinementCalculator"  # the Node's 'calculator' field
    at = blob.find(key)
    while at >= 0:
        for back in range(2, 6):  # the Node is a length-delimited field 1: 0x0a, varint length
            if blob[at - back] != 0x0A:
                continue
            n, shift, p = 0, 0, at - back + 1
            while p < at:
                n |= (blob[p] & 0x7F) << shift
                shift, p = shift + 7, p + 1
            node = calculator_pb2.CalculatorGraphConfig.Node()
            try:
                node.ParseFromString(blob[at:at + n])
            except Exception:  # noqa: BLE001 - not this occurrence
                continue
            streams = [s.split(":")[-1] for s in node.input_stream]
            if streams == [f"{s}_landmarks" for s in REFINE_STREAMS]:
                return node.options.Extensions[lrc.LandmarksRefinementCalculatorOptions.ext]
        at = blob.find(key, at + 1)
    raise FacesynthError("the mediapipe wheel's face mesh graph with its landmark refinement was not found")
