"""What the example-based detail costs the exported graphs, interleaved in one run; one JSON line.

    OMP_NUM_THREADS=1 python -m bench.runtime.detail_cost [--avatar lp_d3] [--driver lp_d6] [--frames 60]
        [--variant NAME=KEY=VALUE,...] [--keep DIR] [--against DIR] [--split N] [--profile N]

Per variant (``--variant NAME=KEY=VALUE[,KEY=VALUE...]`` of the face model's settings; default:
``today`` (no setting), ``detail`` (``detail=1``), ``auto_restore_detail``
(``reference_width=auto,restore=true,detail=1``)): a linear model of the first 75 % of the
avatar's clip (every 3rd frame, as ``bench_talking_head_graph.py`` builds it), exported as the
face-only synthesis file and as the talking-head file (``--product``: compressed to
``DEFAULT_COMPONENTS`` components and quantized to the ``DEFAULT_BASIS`` basis first, as
``facesynth export`` writes them; else all components, float32). Timing: ONNX Runtime, one intra-op
thread, batch 1, every variant's two graphs and the floor at its reference size
(``bench_render_floor.floor_step``: one 40-component matmul and one bilinear remap) called in
turn frame by frame; medians of wall time (``*_ms``) and of the calling thread's CPU time
(``*_cpu_ms``: on a shared host it moves less); ``head_ratio`` and ``face_ratio``: CPU time
over the first variant's. ``face_over_floor``: the face-only graph's time over
the floor's; ``head_fps``: the talking head's frames/s at the avatar video's size. Also per
variant: the files' sizes, the bank's size (face model meta), and the largest difference
(0-255) between the talking-head file and its torch graph on the timed frames.

``--keep DIR``: the exported files are written to DIR (``NAME_face.onnx``, ``NAME_head.onnx``)
and kept. ``--against DIR``: the files of the same names in DIR (exported by another version
of the code, with ``--keep``) timed in the same loop (``against_*``; their ratios are to the
first variant's ``against`` time, so that "before" and "after" share one yardstick).
``--split N``: per variant, the talking head's time per step (``split_cpu_ms``,
:func:`bench.runtime.talking_head_graph.split`); ``--profile N``: per variant, ONNX Runtime's
per-operator profile of the talking head (``profile_head``) and the face-only graph
(``profile_face``) over N frames, also printed as tables on stderr.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from bench.harness import emit
from bench.runtime.render_floor import floor_step
from bench.runtime.talking_head_graph import profile, profile_table, split
from facesynth.data import load_sequence, temporal_split
from facesynth.data.shared import shared_data_dir
from facesynth.model import FaceModel, FaceModelConfig
from facesynth.onnx.avatar import avatar_metadata
from facesynth.onnx.config import DEFAULT_BASIS, DEFAULT_COMPONENTS
from facesynth.onnx.synthesis import compress_for_export, export_synthesizer, quantize_for_export
from facesynth.onnx.talking_head import TalkingHeadGraph, export_talking_head
from facesynth.regressors import REGISTRY
from facesynth.runtime import Renderer
from facesynth.runtime.reenact import Avatar, driver_neutral_of
from facesynth.runtime.talking_head import TalkingHead
from facesynth.sadm.synthesis import GlobalAppearance, Synthesizer


def parse(v: str):
    return {"true": True, "false": False}.get(v, v if not v.replace(".", "", 1).isdigit() else (float(v) if "." in v else int(v)))


def build(seq, settings: dict, work: Path, name: str, product: bool = False):
    train, _ = temporal_split(len(seq))
    rows = train[::3]
    t0 = time.perf_counter()
    model = FaceModel.fit(seq, FaceModelConfig(**settings), rows=rows, progress=False)
    x = model.shape_params(seq.landmarks[rows], clamp=True)
    y = model.appearance_params(model.sample_textures(seq, rows), clamp=True)
    syn = Synthesizer(model, GlobalAppearance(model, REGISTRY["linear"].fit(x, y, seed=0))).eval()
    fit_s = time.perf_counter() - t0
    meta = avatar_metadata(syn, seq.landmarks[train], train, seq)
    if product:  # as `facesynth export` writes it: the components of largest predicted variance, the int8 basis
        syn, info = compress_for_export(syn, seq.landmarks[rows], DEFAULT_COMPONENTS)
        syn, _ = quantize_for_export(syn, seq.landmarks[rows], DEFAULT_BASIS)
        meta = {**meta, **info}
    face, head = work / f"{name}_face.onnx", work / f"{name}_head.onnx"
    export_synthesizer(syn, face, meta)
    export_talking_head(syn, meta, head)
    return model, syn, meta, face, head, fit_s


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--avatar", default="lp_d3")
    ap.add_argument("--driver", default="lp_d6")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--variant", action="append", default=[])
    ap.add_argument("--product", action="store_true", help="export as `facesynth export` does (DEFAULT_COMPONENTS "
                                                             "components, DEFAULT_BASIS basis)")
    ap.add_argument("--keep", default=None, help="write the exported files to this folder and keep them")
    ap.add_argument("--against", default=None, help="a folder of NAME_face.onnx / NAME_head.onnx timed in the same loop")
    ap.add_argument("--split", type=int, default=0, help="frames for the talking head's per-step split (0: none)")
    ap.add_argument("--profile", type=int, default=0, help="frames run with ONNX Runtime's profiler (0: none)")
    args = ap.parse_args()
    faces = shared_data_dir() / "faces" if shared_data_dir() else None
    if faces is None or not faces.is_dir():
        sys.exit("bench_detail_cost: ../shared/data/faces is absent")
    variants = {"today": {}, "detail": {"detail": 1.0},
                "auto_restore_detail": {"reference_width": "auto", "restore": True, "detail": 1.0}}
    if args.variant:
        variants = {}
        for v in args.variant:
            name, _, kv = v.partition("=")
            variants[name] = {k: parse(val) for k, _, val in (p.partition("=") for p in kv.split(",") if p)}
    seq = load_sequence(faces / args.avatar)
    lm = np.load(faces / args.driver / "landmarks.npy").astype(np.float32)
    neutral, _ = driver_neutral_of(lm)
    rows = [int(i) for i in np.linspace(0, len(lm) - 1, args.frames).astype(int) if np.isfinite(lm[i]).all()]
    out = {"bench": "detail_cost", "product": args.product, "avatar": args.avatar, "driver": args.driver,
           "frames": len(rows), "threads": 1, "variants": {}}
    against = Path(args.against) if args.against else None
    with (contextlib.nullcontext(args.keep) if args.keep else tempfile.TemporaryDirectory()) as tmp:
        Path(tmp).mkdir(parents=True, exist_ok=True)
        built, old, extra = {}, {}, {}
        for name, settings in variants.items():
            model, syn, meta, face, head, fit_s = build(seq, settings, Path(tmp), name, args.product)
            extra[name] = (syn, meta, face, head)
            if against is not None:
                old[name] = (TalkingHead(against / f"{name}_head.onnx", driver_neutral=neutral, threads=1),
                             Renderer(against / f"{name}_face.onnx", threads=1))
            th = TalkingHead(head, driver_neutral=neutral, threads=1)
            graph = TalkingHeadGraph(syn, Avatar(meta, str(head)), th.feather).eval()
            built[name] = (model, syn, th, Renderer(face, threads=1), graph, floor_step(model))
            out["variants"][name] = {"settings": settings, "reference_size": list(model.reference.size),
                                     "face_onnx_mb": round(face.stat().st_size / 1e6, 2),
                                     "head_onnx_mb": round(head.stat().st_size / 1e6, 2),
                                     "bank": model.meta.get("detail"), "fit_s": round(fit_s, 1), "frame_size": list(th.frame_size)}
        times = {n: {"head": [], "face": [], "floor": []} for n in built}
        cpu = {n: {k: [] for k in ("head", "face", "floor", "against_head", "against_face")} for n in built}
        worst = dict.fromkeys(built, 0)
        dn = torch.from_numpy(np.asarray(built[next(iter(built))][2].driver_neutral, np.float32))
        for i in rows:
            d = lm[i][None]
            for name, (_model, _syn, th, renderer, graph, floor) in built.items():
                t, c = time.perf_counter(), time.thread_time()
                frame, face_lm = th.run(d)
                times[name]["head"].append(time.perf_counter() - t)
                cpu[name]["head"].append(time.thread_time() - c)
                t, c = time.perf_counter(), time.thread_time()
                renderer.render(face_lm)
                times[name]["face"].append(time.perf_counter() - t)
                cpu[name]["face"].append(time.thread_time() - c)
                t, c = time.perf_counter(), time.thread_time()
                floor(0)
                times[name]["floor"].append(time.perf_counter() - t)
                cpu[name]["floor"].append(time.thread_time() - c)
                if name in old:
                    c = time.thread_time()
                    old[name][0].run(d)
                    cpu[name]["against_head"].append(time.thread_time() - c)
                    c = time.thread_time()
                    old[name][1].render(face_lm)
                    cpu[name]["against_face"].append(time.thread_time() - c)
                if i in rows[:: max(1, len(rows) // 10)]:
                    with torch.no_grad():
                        want, _ = graph(torch.from_numpy(d), dn)
                    worst[name] = max(worst[name], int(np.abs(want.numpy().astype(int) - frame.astype(int)).max()))
        for name, t in times.items():
            ms = {k: 1e3 * float(np.median(v)) for k, v in t.items()}
            out["variants"][name].update({"head_ms": round(ms["head"], 2), "head_fps": round(1e3 / ms["head"], 1),
                                          "face_ms": round(ms["face"], 3), "floor_ms": round(ms["floor"], 3),
                                          "face_over_floor": round(ms["face"] / ms["floor"], 2),
                                          "head_torch_max_diff": worst[name]})
        first = next(iter(built))
        med = {n: {k: 1e3 * float(np.median(v)) for k, v in c.items() if v} for n, c in cpu.items()}
        for name, m in med.items():
            o = out["variants"][name]
            o.update({f"{k}_cpu_ms": round(v, 3) for k, v in m.items()})
            o["head_ratio"] = round(m["head"] / med[first]["head"], 2)
            o["face_ratio"] = round(m["face"] / med[first]["face"], 2)
            if "against_head" in m:
                o["against_head_ratio"] = round(m["against_head"] / med[first]["against_head"], 2)
                o["against_face_ratio"] = round(m["against_face"] / med[first]["against_face"], 2)
                o["head_ratio_to_against_first"] = round(m["head"] / med[first]["against_head"], 2)
                o["face_ratio_to_against_first"] = round(m["face"] / med[first]["against_face"], 2)
        dn = np.asarray(built[first][2].driver_neutral, np.float32)
        if args.split > 0:
            feeds = [{"driver": lm[i][None], "driver_neutral": dn} for i in np.resize(np.asarray(rows), args.split)]
            for name, (syn, meta, _face, _head) in extra.items():
                out["variants"][name]["split_cpu_ms"] = split(syn, meta, Path(tmp), name, feeds)
        if args.profile > 0:
            feeds = [{"driver": lm[i][None], "driver_neutral": dn} for i in np.resize(np.asarray(rows), args.profile)]
            for name, (_syn, _meta, face, head) in extra.items():
                o = out["variants"][name]
                o["profile_head"] = profile(head, feeds)
                face_feeds = [{"landmarks": built[name][2].run(f["driver"])[1]} for f in feeds]
                o["profile_face"] = profile(face, face_feeds)
                print(f"{name}: talking head, ms per frame with the profiler on\n" + profile_table(o["profile_head"]),
                      file=sys.stderr)
                print(f"{name}: face-only graph\n" + profile_table(o["profile_face"]), file=sys.stderr)
    emit(out)  # with the host (CPU model, flags, cores) and the load average at the end


if __name__ == "__main__":
    main()
