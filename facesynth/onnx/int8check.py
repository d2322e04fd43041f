"""The int8 appearance matmul of an exported file, checked against int64 arithmetic.

Two checks, one CPU-independent and one of this CPU:

* :func:`pair_sum_worst` reads the file's weight codes and bounds, in int64, the largest sum
  of two u8 x s8 products any column can form (two largest |codes| x 255): the file is exact
  on every CPU when it fits int16 (:data:`facesynth.contract.INT16_MAX`), whichever pairs a
  kernel forms;
* :func:`matmul_errors` runs the file's own ``MatMulInteger`` (the same codes, zero point and
  shapes, one node) in ONNX Runtime on worst-case activations and compares it with int64
  arithmetic: what this CPU computes.

``facesynth export`` uses the second to name the cause when its parity check fails;
``tests/test_int8_cpus.py`` uses both, and the second under an emulated CPU without VNNI.

And the int8 parity contract (:data:`facesynth.contract.FLOAT_PARITY_TOL`, stated there):
:func:`scaled_coefficients` reads the coefficients a file rounds, and :func:`tie_allowance`
checks that every code on which ONNX Runtime and torch disagree sits on a rounding tie and
differs by one step, and returns what those steps may move each frame's crop by.
"""

from __future__ import annotations

import os

import numpy as np

from facesynth.contract import COEF_LEVELS, INT8_TIE_TOL, U8_MAX, ZERO_POINT
from facesynth.errors import FacesynthError


def matmul_integer_codes(model_path: str | os.PathLike) -> np.ndarray:
    """(K, D) int8 weight codes of the file's one ``MatMulInteger`` (FacesynthError if none)."""
    import onnx
    from onnx import numpy_helper

    model = onnx.load(str(model_path))
    inits = {i.name: i for i in model.graph.initializer}
    nodes = [n for n in model.graph.node if n.op_type == "MatMulInteger"]
    if len(nodes) != 1 or nodes[0].input[1] not in inits:
        raise FacesynthError(f"{model_path}: expected one MatMulInteger with constant weights, found {len(nodes)}")
    return numpy_helper.to_array(inits[nodes[0].input[1]])


def pair_sum_worst(codes: np.ndarray) -> int:
    """Largest |u8 x s8 + u8 x s8| over any two rows of a column, activations in [0, 255] (int64)."""
    q = np.sort(np.abs(np.asarray(codes, np.int64)), axis=0)
    top2 = q[-2:].sum(0) if len(q) >= 2 else q.sum(0)
    return int(U8_MAX * top2.max()) if top2.size else 0


def worst_activations(k: int, seed: int = 0) -> np.ndarray:
    """(6, K) uint8 coefficient codes ``a + 128``: all at +127 and at -127 (the largest pair
    sums of same-signed codes), alternating, zero, and two random rows."""
    rng = np.random.default_rng(seed)
    hi, lo = ZERO_POINT + COEF_LEVELS, ZERO_POINT - COEF_LEVELS
    alt = np.where(np.arange(k) % 2 == 0, hi, lo)
    rows = [np.full(k, hi), np.full(k, lo), alt, np.full(k, ZERO_POINT), *rng.integers(lo, hi + 1, (2, k))]
    return np.stack(rows).astype(np.uint8)


def probe_model(codes: np.ndarray) -> bytes:
    """A one-node ONNX model: uint8 activations (B, K) -> int32 (B, D) = MatMulInteger with ``codes``."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    k, d = codes.shape
    graph = helper.make_graph(
        [helper.make_node("MatMulInteger", ["a", "q", "zp"], ["y"])], "int8_probe",
        [helper.make_tensor_value_info("a", TensorProto.UINT8, [None, k])],
        [helper.make_tensor_value_info("y", TensorProto.INT32, [None, d])],
        [numpy_helper.from_array(np.asarray(codes, np.int8), "q"), numpy_helper.from_array(np.array(ZERO_POINT, np.uint8), "zp")],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    return model.SerializeToString()


def reference(codes: np.ndarray, activations: np.ndarray) -> np.ndarray:
    """The exact products in int64: ``(a - 128) @ q``."""
    return (np.asarray(activations, np.int64) - ZERO_POINT) @ np.asarray(codes, np.int64)


def matmul_errors(codes: np.ndarray, activations: np.ndarray | None = None) -> tuple[int, int]:
    """(wrong outputs, largest absolute error) of ONNX Runtime's ``MatMulInteger`` on this CPU
    against int64 arithmetic, on :func:`worst_activations` by default."""
    import onnxruntime as ort

    a = worst_activations(codes.shape[0]) if activations is None else np.asarray(activations, np.uint8)
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    sess = ort.InferenceSession(probe_model(codes), so, providers=["CPUExecutionProvider"])
    got = sess.run(None, {"a": a})[0].astype(np.int64)
    err = np.abs(got - reference(codes, a))
    return int((err > 0).sum()), int(err.max()) if err.size else 0


def _rounded_input(graph) -> str:
    """Name of the tensor the int8 basis rounds: the input of the ``Round`` behind the one
    ``MatMulInteger``'s activations (``Cast(Add(Round(x)))``)."""
    producer = {o: n for n in graph.node for o in n.output}
    node = producer.get(next(n for n in graph.node if n.op_type == "MatMulInteger").input[0])
    while node is not None and node.op_type != "Round":
        node = producer.get(node.input[0]) if node.op_type in ("Cast", "Add") else None
    if node is None:
        raise FacesynthError("the int8 basis's activations do not come from a Round")
    return node.input[0]


def scaled_coefficients(model_path: str | os.PathLike, feeds: dict) -> np.ndarray:
    """(B, K) float64: the scaled coefficients ``b * COEF_LEVELS / limit`` that ONNX Runtime
    rounds to codes in the file's int8 basis (one thread), for the inputs ``feeds``."""
    import onnx
    import onnxruntime as ort

    model = onnx.load(str(model_path))
    matmul_integer_codes(model_path)  # one MatMulInteger, or a FacesynthError naming the file
    model.graph.output.append(onnx.helper.make_tensor_value_info(_rounded_input(model.graph), onnx.TensorProto.FLOAT, None))
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    sess = ort.InferenceSession(model.SerializeToString(), so, providers=["CPUExecutionProvider"])
    return sess.run([model.graph.output[-1].name], feeds)[0].astype(np.float64)


def tie_allowance(codes: np.ndarray, col_scale: np.ndarray, x_ort: np.ndarray, x_torch: np.ndarray) -> np.ndarray:
    """The int8 parity contract (:data:`facesynth.contract.FLOAT_PARITY_TOL`) for one batch.

    Parameters
    ----------
    codes : (K, D) int8 weight codes q; col_scale : (D,) their scales s
    x_ort, x_torch : (B, K) the scaled coefficients each side rounded (:func:`scaled_coefficients`)

    Returns
    -------
    (B,) float64: per frame, the largest sum over texels of ``|q_kn| s_n`` over the codes k that
    the two sides rounded differently (0 for a frame where none differ): what those codes
    may move a texel, and so the crop, by. Raises FacesynthError when a code differs by more
    than one step, or where the two values are not within ``INT8_TIE_TOL`` of each other (not a
    tie: a wrong file or a wrong kernel).
    """
    xo, xt = np.asarray(x_ort, np.float64), np.asarray(x_torch, np.float64)
    if xo.shape != xt.shape or xo.ndim != 2 or xo.shape[1] != len(codes):
        raise FacesynthError(f"int8 parity: coefficients {xo.shape} and {xt.shape} do not fit {len(codes)} codes")
    step = np.rint(xo) - np.rint(xt)
    bad = (np.abs(step) > 1) | ((step != 0) & ~(np.abs(xo - xt) <= INT8_TIE_TOL))
    if bad.any():
        b, k = np.argwhere(bad)[0]
        raise FacesynthError(f"int8 parity: frame {b} coefficient {k} rounds to codes {np.rint(xo[b, k]):.0f} in ONNX Runtime "
                             f"and {np.rint(xt[b, k]):.0f} in torch from {xo[b, k]:.6f} and {xt[b, k]:.6f}: not a rounding tie")
    one_step = np.abs(np.asarray(codes, np.float64)) * np.asarray(col_scale, np.float64)[None]  # (K, D)
    return ((step != 0).astype(np.float64) @ one_step).max(1) if one_step.size else np.zeros(len(xo))
