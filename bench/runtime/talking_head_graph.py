"""Speed and parity of the talking-head ONNX graph (facesynth.onnx.talking_head) against the
face-only synthesis graph, the bare frame read and the numpy reference pipeline, in one run;
one JSON line.

    OMP_NUM_THREADS=1 python -m bench.runtime.talking_head_graph [--pairs lp_d3<-lp_d6,...]
        [--frames 0] [--work /tmp/facesynth_th_graph] [--against DIR] [--profile 60]
        [--split 60] [--page HEAD.onnx,... --page-video CLIP.mp4]

Per pair AVATAR<-DRIVER: a linear model of the first 75 % of the avatar's clip (every 3rd
frame), exported as the synthesis file (with its avatar metadata) and as the talking-head
file. Timing: ONNX Runtime, one intra-op thread, batch 1, interleaved frame by frame (medians
of wall time, ``*_ms``, and of the calling thread's CPU time, ``*_cpu_ms``: on a host shared
with other jobs the CPU time moves less) of

* the talking head (``talking_head``) and the face-only synthesis graph (``face_only``);
* the bare frame read (``frame_read``): the full-frame warp's read alone, as one graph from the
  node maps (B, 2, Hn, Wn) to the uint8 (B, H, W, 3) frame: the node maps mirrored and upsampled
  by one Resize, twelve element gathers (a tap and a colour each) and their lerps, the rounding,
  the cast and the transpose (:class:`BareRead`, the floor a bilinear full-frame warp costs in ONNX
  Runtime's kernels), fed the numpy warp's node maps of the same frame;
* with ``--against DIR``: ``DIR/AVATAR_head.onnx``, the same avatar's talking head exported by
  another version of the code (``against``; ``speedup`` = its time over this one's, CPU time).

``profile``: this talking-head file run ``--profile`` more frames with ONNX Runtime's profiler:
per operator type, ms per frame and share of the kernels' time (the profiler's own cost
included; the ranking is the point), the ``against`` file's as ``profile_against``; both also
printed as a table on stderr.

``split_cpu_ms`` (``--split N``, N frames): where the talking head's time goes, per step
(:func:`split`: the graph cut after each step, timed interleaved; CPU-time medians).

``--page``: talking-head files (MediaPipe-scheme avatars, as the live page takes: README step
5's) run on the live page by ``bench/web/page.py`` (one worker, ``--page-video`` as the
camera, ``--page-seconds``), one after the other: per file ``page``: the page's avatar step
(``avatar_alone_ms``, its wall time with the tracker paused; ``avatar_ms``, per frame while
tracking), Python's one-thread time of the same file (``python_avatar_ms``), their ratio
(``avatar_vs_python``), ``e2e_fps`` and the load average at its end.
Parity: each driver frame (``--frames 0``: every one; else that many,
evenly spread) against :class:`facesynth.runtime.Reenactor` (full-frame warp, relative
motion, the graph's feather): the largest pixel difference (0-255), the frames' pixels above
2, the largest retargeted landmark difference (px). ``max_pixel_diff`` over all pairs at the
top level.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from bench.harness import load_average
from facesynth.runtime.cpu import cpu_flags  # noqa: E402


def build(avatar: str, work: Path) -> tuple[Path, Path]:
    from facesynth.data import load_sequence, temporal_split
    from facesynth.model import FaceModel
    from facesynth.onnx.avatar import avatar_metadata
    from facesynth.onnx.synthesis import export_synthesizer
    from facesynth.onnx.talking_head import export_talking_head
    from facesynth.regressors import REGISTRY
    from facesynth.sadm.synthesis import GlobalAppearance, Synthesizer

    seq = load_sequence(Path("../shared/data/faces") / avatar)
    train, _ = temporal_split(len(seq))
    rows = train[::3]
    model = FaceModel.fit(seq, rows=rows, progress=False)
    x = model.shape_params(seq.landmarks[rows], clamp=True)
    y = model.appearance_params(model.sample_textures(seq, rows), clamp=True)
    syn = Synthesizer(model, GlobalAppearance(model, REGISTRY["linear"].fit(x, y, seed=0))).eval()
    meta = avatar_metadata(syn, seq.landmarks[train], train, seq)
    face, head = work / f"{avatar}_face.onnx", work / f"{avatar}_head.onnx"
    export_synthesizer(syn, face, meta)
    export_talking_head(syn, meta, head)
    return face, head, syn, meta


class BareRead:
    """The full-frame warp's bilinear read alone, (B, 2, Hn, Wn) node maps -> uint8 (B, H, W, 3),
    exported as an ONNX file: one Resize of the mirrored node maps, twelve GatherElements, the
    lerps, the rounding, the cast and the transpose. Fixed here as the floor the talking head
    is measured against, whatever the graph itself does."""

    @staticmethod
    def export(fw, path: Path) -> Path:
        import torch
        from torch import nn
        from torch.nn import functional as F

        from facesynth.geometry import mirror
        from facesynth.onnx.passes import int32_indices

        w, h = fw.size

        class Read(nn.Module):
            def __init__(self):
                super().__init__()
                tex = np.pad(fw.frame.astype(np.float32), ((0, 1), (0, 1), (0, 0)), mode="edge")
                self.register_buffer("texture", torch.from_numpy(np.ascontiguousarray(tex.transpose(2, 0, 1).reshape(3, 1, -1))))
                self.register_buffer("uv_max", torch.tensor([float(w - 1), float(h - 1)]).reshape(1, 2, 1, 1))

            def forward(self, nodes):
                uv = torch.clamp(F.interpolate(mirror(nodes, self.uv_max), size=(h, w), mode="bilinear", align_corners=True),
                                 min=0.0)
                fl = torch.floor(uv)
                fx, fy = uv[:, 0:1] - fl[:, 0:1], uv[:, 1:2] - fl[:, 1:2]
                base = (fl[:, 1:2] * float(w + 1) + fl[:, 0:1]).to(torch.int64)
                index = [(base + k).reshape(1, -1) for k in (0, 1, w + 1, w + 2)]
                out = []
                for ch in range(3):
                    t = [torch.gather(self.texture[ch], 1, i).reshape_as(fx) for i in index]
                    top = t[0] + fx * (t[1] - t[0])
                    out.append(top + fy * (t[2] + fx * (t[3] - t[2]) - top))
                return torch.floor(torch.cat(out, 1) + 0.5).to(torch.uint8).permute(0, 2, 3, 1)

        import warnings

        import onnx

        example = torch.zeros((1, 2, len(fw.nodes[1]), len(fw.nodes[0])))
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")
            torch.onnx.export(Read().eval(), (example,), str(path), input_names=["nodes"], output_names=["frame"],
                              opset_version=18, dynamo=False, dynamic_axes={"nodes": {0: "batch"}})
        model = onnx.load(str(path))
        int32_indices(model)
        onnx.save(model, str(path))
        return path


STEPS = ("retarget", "node_maps", "read", "synthesis", "layers", "placement")


def split(syn, meta: dict, work: Path, avatar: str, feeds: list[dict]) -> dict:
    """Per step of the talking head, ms of CPU time per frame (one thread, medians): the graph
    cut after each step (:data:`STEPS`: the retargeting; the warp's node maps; the frame read;
    the synthesis; the seam's layers in the crop; the seam's placement and composite, on a
    constant frame) exported and timed interleaved, each step's time its cut's less the cut
    it follows; ``all`` the whole graph's."""
    import torch
    from torch import nn

    from facesynth.onnx.common import save_graph
    from facesynth.onnx.talking_head import INPUTS, OUTPUTS, TalkingHeadGraph
    from facesynth.runtime.reenact import Avatar
    from facesynth.runtime.renderer import _session

    graph = TalkingHeadGraph(syn, Avatar(meta, avatar)).eval()
    h, w = graph.frame_warp.frame_size

    class Cut(nn.Module):
        def __init__(self, last: str):
            super().__init__()
            self.g, self.last = graph, last
            self.register_buffer("still", torch.zeros((1, 3, h, w), dtype=torch.uint8))

        def forward(self, driver, neutral):
            g = self.g
            face = g.retarget(driver, neutral)
            if self.last in ("retarget", "node_maps", "read"):
                out = {"retarget": lambda: face * 1.0, "node_maps": lambda: g.frame_warp.node_maps(face),
                       "read": lambda: g.frame_warp.read(face)}[self.last]()
                return out, face
            crop, mask, placement = g.synthesis(face)
            if self.last == "synthesis":
                return crop, face
            if self.last == "layers":
                return g.seam.layers(crop, mask)
            frame = g.frame_warp.read(face) if self.last == "all" else self.still.expand(face.shape[0], -1, -1, -1)
            return g.seam(crop, mask, placement, frame, face), face

    n = np.asarray(meta["avatar_neutral"], np.float32)
    example = (torch.from_numpy(np.stack([n + 1.5, n * 1.01 - 2.0])), torch.from_numpy(n + 0.5))
    sessions = {}
    for last in (*STEPS, "all"):
        path = work / f"{avatar}_cut_{last}.onnx"
        save_graph(Cut(last).eval(), example, path, INPUTS, OUTPUTS, {"format": "cut"}, 18, "the talking head cut")
        sessions[last] = _session(path, 1, False)
    cpu = {k: [] for k in sessions}
    for feed in feeds:
        for k, sess in sessions.items():
            c0 = time.thread_time()
            sess.run(None, feed)
            cpu[k].append(time.thread_time() - c0)
    ms = {k: 1e3 * float(np.median(v)) for k, v in cpu.items()}
    after = {"retarget": None, "node_maps": "retarget", "read": "node_maps", "synthesis": "retarget",
             "layers": "synthesis", "placement": "layers"}
    out = {k: round(ms[k] - (ms[after[k]] if after[k] else 0.0), 3) for k in STEPS}
    return {**out, "all": round(ms["all"], 3)}


def profile(path: Path, feeds: list[dict]) -> list[dict]:
    """Per ONNX operator type, ms per frame and share of the kernels' time, over ``feeds``
    (ONNX Runtime's profiler, one thread)."""
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = so.inter_op_num_threads = 1
    so.enable_profiling = True
    so.profile_file_prefix = str(path.with_suffix("")) + "_profile"
    sess = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    for feed in feeds:
        sess.run(None, feed)
    trace = Path(sess.end_profiling())
    events = json.loads(trace.read_text())
    trace.unlink()
    per_op: dict[str, float] = {}
    for e in events:
        if e.get("cat") == "Node" and e["name"].endswith("_kernel_time"):
            op = e["args"]["op_name"]
            per_op[op] = per_op.get(op, 0.0) + e["dur"]
    total = sum(per_op.values())
    rows = sorted(per_op.items(), key=lambda kv: -kv[1])
    return [{"op": op, "ms": round(us / len(feeds) / 1e3, 3), "share": round(us / total, 3)} for op, us in rows[:12]] + \
        [{"op": "(all)", "ms": round(total / len(feeds) / 1e3, 3), "share": 1.0}]


def profile_table(rows: list[dict], against: list[dict] | None = None) -> str:
    """The per-operator profile (:func:`profile`) as a Markdown table, ``against``'s beside it."""
    old = {r["op"]: r for r in against or []}
    head = "| op | ms per frame | share |" + (" against ms | against share |" if against else "")
    lines = [head, "|---" * (5 if against else 3) + "|"]
    for r in rows:
        o = old.get(r["op"])
        extra = (f" {o['ms']:.3f} | {o['share']:.1%} |" if o else " | |") if against else ""
        lines.append(f"| {r['op']} | {r['ms']:.3f} | {r['share']:.1%} |{extra}")
    return "\n".join(lines)


def page_step(model: Path, video: Path, seconds: float) -> dict:
    """bench/web/page.py on ``model`` with one worker: the page's avatar step beside Python's."""
    import subprocess

    cmd = [sys.executable, "-m", "bench.web.page", "--model", str(model), "--video", str(video),
           "--workers", "1", "--seconds", f"{seconds:g}"]
    res = subprocess.run(cmd, capture_output=True, text=True, check=False, cwd=Path(__file__).resolve().parents[2])
    if res.returncode != 0:
        return {"model": str(model), "error": res.stderr.strip().splitlines()[-1:]}
    web = json.loads(res.stdout.strip().splitlines()[-1])
    keep = ("avatar_alone_ms", "avatar_ms", "python_avatar_ms", "avatar_vs_python", "tracker_ms", "e2e_fps", "workers",
            "page_mb", "load_avg")
    return {"model": str(model), **{k: web.get(k) for k in keep}}


def run_pair(avatar: str, driver: str, frames: int, work: Path, against: Path | None = None, n_profile: int = 60,
             n_split: int = 0) -> dict:
    from facesynth.runtime import Reenactor, Renderer
    from facesynth.runtime.reenact import driver_neutral_of
    from facesynth.runtime.renderer import _session
    from facesynth.runtime.talking_head import TalkingHead

    face, head, syn, meta = build(avatar, work)
    lm = np.load(Path("../shared/data/faces") / driver / "landmarks.npy").astype(np.float32)
    neutral, _ = driver_neutral_of(lm)
    picked = range(len(lm)) if frames <= 0 else np.linspace(0, len(lm) - 1, frames).astype(int)
    rows = [i for i in picked if np.isfinite(lm[i]).all()]
    th = TalkingHead(head, driver_neutral=neutral, threads=1)
    renderer = Renderer(face, threads=1)
    ref = Reenactor(face, driver_neutral=neutral, feather=th.feather, full_frame=True)
    fw = ref.frame_warp
    read = _session(BareRead.export(fw, work / f"{avatar}_read.onnx"), 1, False)
    old = None
    if against is not None:
        old_path = against / f"{avatar}_head.onnx"
        old = TalkingHead(old_path, driver_neutral=neutral, threads=1)
    names = ["talking_head", "face_only", "frame_read"] + (["against"] if old is not None else [])
    wall, cpu = {k: [] for k in names}, {k: [] for k in names}
    worst, beyond, worst_lm = 0, [], 0.0
    for i in rows:
        want, want_lm = ref.step(lm[i])
        nodes = fw.node_maps(fw.control_points(want_lm))[None].astype(np.float32)
        d, a = lm[i][None], want_lm[None]
        calls = {"talking_head": lambda d=d: th.run(d), "face_only": lambda a=a: renderer.render(a),
                 "frame_read": lambda x=nodes: read.run(None, {"nodes": x}), "against": lambda d=d: old.run(d)}
        got = None
        for k in names:
            t0, c0 = time.perf_counter(), time.thread_time()
            out = calls[k]()
            cpu[k].append(time.thread_time() - c0)
            wall[k].append(time.perf_counter() - t0)
            if k == "talking_head":
                got, got_lm = out
        diff = np.abs(got[0].astype(int) - want).max(-1)
        worst, worst_lm = max(worst, int(diff.max())), max(worst_lm, float(np.abs(got_lm[0] - want_lm).max()))
        beyond.append(int((diff > 2).sum()))
    ms = {k: 1e3 * float(np.median(v)) for k, v in wall.items()}
    cpu_ms = {k: 1e3 * float(np.median(v)) for k, v in cpu.items()}
    w, h = th.frame_size
    out = {
        "avatar": avatar, "driver": driver, "frames": len(rows), "frame_size": [w, h], "threads": 1,
        "talking_head_ms": round(ms["talking_head"], 2), "talking_head_fps": round(1e3 / ms["talking_head"], 1),
        "face_only_ms": round(ms["face_only"], 3), "face_only_fps": round(1e3 / ms["face_only"], 1),
        "frame_read_ms": round(ms["frame_read"], 2),
        "cpu_ms": {k: round(v, 3) for k, v in cpu_ms.items()},
        "ratio_head_to_face": round(ms["talking_head"] / ms["face_only"], 1),
        "ratio_head_to_read": round(cpu_ms["talking_head"] / cpu_ms["frame_read"], 2),
        "feather_px": th.feather,
        "max_pixel_diff": worst, "max_pixels_above_2": max(beyond), "mean_pixels_above_2": round(float(np.mean(beyond)), 1),
        "max_landmark_diff_px": round(worst_lm, 5), "head_onnx_mb": round(head.stat().st_size / 1e6, 1),
    }
    if old is not None:
        out.update({"against": str(old.path), "against_ms": round(ms["against"], 2),
                    "speedup": round(cpu_ms["against"] / cpu_ms["talking_head"], 2),
                    "speedup_wall": round(ms["against"] / ms["talking_head"], 2),
                    "ratio_against_to_read": round(cpu_ms["against"] / cpu_ms["frame_read"], 2)})
    dn = np.asarray(th.driver_neutral, np.float32)
    if n_split > 0:
        feeds = [{"driver": lm[i][None], "driver_neutral": dn} for i in np.resize(np.asarray(rows), n_split)]
        out["split_cpu_ms"] = split(syn, meta, work, avatar, feeds)
    if n_profile > 0:
        feeds = [{"driver": lm[i][None], "driver_neutral": dn} for i in np.resize(np.asarray(rows), n_profile)]
        out["profile"] = profile(head, feeds)
        if old is not None:
            out["profile_against"] = profile(old.path, feeds)
        print(f"{avatar}<-{driver}, ms per frame with the profiler on (this file | against):\n"
              + profile_table(out["profile"], out.get("profile_against")), file=sys.stderr)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", default="lp_d3<-lp_d6", help="AVATAR<-DRIVER,... (a clip driving itself: lp_d3<-lp_d3)")
    ap.add_argument("--frames", type=int, default=60, help="driver frames per pair, evenly spread (0: every frame)")
    ap.add_argument("--work", default="/tmp/facesynth_th_graph")
    ap.add_argument("--against", default=None, help="a folder of AVATAR_head.onnx files exported by another version, "
                                                    "timed interleaved with this one's")
    ap.add_argument("--profile", type=int, default=60, help="frames run with ONNX Runtime's profiler (0: none)")
    ap.add_argument("--split", type=int, default=0, help="frames timed for the per-step split (0: none)")
    ap.add_argument("--page", default=None, help="talking-head files (MediaPipe avatars) for bench/web/page.py, comma-separated")
    ap.add_argument("--page-video", default="../shared/data/faces/lp_d3/video.mp4", help="the page's camera clip")
    ap.add_argument("--page-seconds", type=float, default=20.0)
    args = ap.parse_args()
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    against = Path(args.against) if args.against else None
    pairs = [run_pair(*p.split("<-"), args.frames, work, against, args.profile, args.split) for p in args.pairs.split(",")]
    out = {"cpu_flags": sorted(cpu_flags(Path("/proc/cpuinfo").read_text()) & {"avx2", "avx512_vnni", "avx_vnni"}),
           "load_avg": round(load_average(), 2), "max_pixel_diff": max(p["max_pixel_diff"] for p in pairs),
           "max_landmark_diff_px": max(p["max_landmark_diff_px"] for p in pairs), "pairs": pairs}
    if args.page:
        out["page"] = [page_step(Path(m), Path(args.page_video), args.page_seconds) for m in args.page.split(",")]
    print(json.dumps(out))


if __name__ == "__main__":
    main()
