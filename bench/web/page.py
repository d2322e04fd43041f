"""The live page's speed, load time, memory and offline state, with a clip as the camera.

Builds the page for ``--model`` (``facesynth web build``), serves it on 127.0.0.1, opens it in
headless system Chromium with the clip's first ``--frames`` frames (looped) as the fake camera,
blocks every request off 127.0.0.1, waits for the first avatar frame, then measures for
``--seconds``:

* ``tracker_ms`` / ``avatar_ms`` / ``composite_ms``: per frame, ``wall``: the page's own
  ``performance.now()`` timings (median) of the worker's tracking, its talking-head run and the
  page's copy of the frame into the canvas; ``cpu``: CPU time per rendered frame from /proc.
  The tracker and the avatar share the worker's thread (``workers`` 1; with 2, each has a worker),
  whose CPU time (``worker_cpu_ms``, all worker threads) is split between them in proportion to
  their wall times (``cpu_is`` says so); the composite's is the page's main thread
  (``main_cpu_ms``: drawing, neutral capture, messages). ``--workers`` / ``--stage-ms`` set the page's mode.
  ``reach_ms``: the reach readout's update per tracked frame, on the main thread (None for an
  avatar without its recording);
  ``renderer_cpu_ms``: all renderer threads, ``chromium_cpu_ms``: every Chromium process;
* ``e2e_fps``: rendered avatar frames per second of wall time; ``frames``: frames rendered;
* ``load_s``: page open -> first avatar frame (includes the ~1 s neutral capture, ``neutral_s``);
* ``page_mb``: the page's memory: its renderer process's own resident memory (RssAnon: what
  Chrome's task manager counts as its footprint, without shared libraries, files and the
  compositor's discardable image cache), the median of samples every 0.5 s through the run
  (it moves with V8's garbage collections), ``page_mb_max`` their maximum; ``page_rss_mb`` the
  renderer's VmRSS at the end (shared libraries and that cache included); ``page_js_mb`` the page's and its worker's
  JavaScript and WebAssembly memory (``performance.measureUserAgentSpecificMemory``, which the
  page's cross-origin isolation allows; Chromium may delay its answer by up to ~20 s);
* ``offline``: no request left 127.0.0.1; ``python_avatar_ms``: Python ONNX Runtime, one
  thread, the same talking-head file (:class:`facesynth.runtime.TalkingHead`) with the avatar's
  neutral as driver and driver neutral, median of 200 runs in this process;
  ``avatar_alone_ms``: the page's run of the same file on the same landmarks with the tracker
  paused (median of 100, ``performance.now()``, the worker's message round trip included), and
  ``avatar_vs_python`` their ratio.

    python -m bench.web.page --model M.onnx --video CLIP.mp4 [--seconds 30] [--workers 1|2|auto] [--stage-ms 33.3]

Prints ONE JSON line.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
import uuid
from pathlib import Path

import numpy as np

from bench import browser  # noqa: E402
from bench.browser import chromium_tree, memory_mb  # noqa: E402
from bench.harness import emit, load_average
from facesynth.runtime.cpu import cpu_flags  # noqa: E402
from facesynth.web import site  # noqa: E402

TICK = os.sysconf("SC_CLK_TCK")
# the page's figures, and only them: serialising the whole state (the avatar's metadata, its
# neutral frame as JPEG) made 25 MB of garbage in the page being measured
STATS = """(({ frames, firstFrameMs, trackerMs, avatarMs, compositeMs, latencyMs, reachMs, messages, workers }) =>
    ({ frames, firstFrameMs, trackerMs, avatarMs, compositeMs, latencyMs, reachMs, messages, workers }))(window.facesynth.state)"""


def thread_cpu(pid: int) -> dict[str, float]:
    """Thread name -> CPU seconds (summed over threads of that name) of process ``pid``."""
    out: dict[str, float] = {}
    for t in Path(f"/proc/{pid}/task").iterdir():
        try:
            name = "main" if t.name == str(pid) else (t / "comm").read_text().strip()
            f = (t / "stat").read_text()
        except OSError:
            continue
        v = f[f.rindex(")") + 2:].split()
        out[name] = out.get(name, 0.0) + (int(v[11]) + int(v[12])) / TICK
    return out


def process_cpu(pids) -> float:
    total = 0.0
    for pid in pids:
        try:
            f = Path(f"/proc/{pid}/stat").read_text()
        except OSError:
            continue
        v = f[f.rindex(")") + 2:].split()
        total += (int(v[11]) + int(v[12])) / TICK
    return total


def python_avatar_ms(model: Path, n: int = 200) -> float:
    from facesynth.runtime.talking_head import TalkingHead

    th = TalkingHead(model, threads=1)
    lm = np.asarray(th.avatar.neutral, np.float32)
    th.use_neutral(lm)
    for _ in range(10):
        th.run(lm[None])
    t = []
    for _ in range(n):
        a = time.perf_counter()
        th.run(lm[None])
        t.append(time.perf_counter() - a)
    return float(np.median(t) * 1e3)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True, type=Path)
    ap.add_argument("--video", required=True, type=Path)
    ap.add_argument("--seconds", type=float, default=30.0,
                    help="the measured run (page_mb is a median over V8's ~30 MB garbage-collection sawtooth)")
    ap.add_argument("--frames", type=int, default=150, help="camera clip length (looped by Chromium)")
    ap.add_argument("--size", default="640x480", help="camera frame size WxH")
    ap.add_argument("--workers", default="auto", choices=["1", "2", "auto"],
                    help="the page's ?workers= (auto: one, two if its stage is over --stage-ms)")
    ap.add_argument("--stage-ms", type=float, default=1000 / 30,
                    help="the page's ?stage_ms= (auto's budget per stage; the page's default, a frame at 30 frames/s)")
    args = ap.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    marker = f"--facesynth-bench={uuid.uuid4().hex}"
    with tempfile.TemporaryDirectory(prefix="bench_web_") as tmp:
        tmp = Path(tmp)
        folder = site.build_site(args.model, tmp / "site")
        page_bytes = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())
        y4m = tmp / "cam.y4m"
        browser.write_y4m(args.video, y4m, args.frames, size)
        with browser.served(folder) as url, browser.browser_page(
                y4m, extra_args=[marker, "--enable-blink-features=ForceEagerMeasureMemory"]) as (page, blocked):
            t0 = time.perf_counter()
            page.goto(f"{url}?workers={args.workers}&stage_ms={args.stage_ms:g}")
            page.wait_for_function("window.facesynth && window.facesynth.state.frames >= 1", timeout=120_000)
            st = page.evaluate(STATS)
            pids, renderers = chromium_tree(marker)
            f0, p0, w0 = st["frames"], process_cpu(pids), time.perf_counter()
            c0 = {r: thread_cpu(r) for r in renderers}
            anon = {r: [] for r in renderers}  # RssAnon through the run: V8 frees spent buffers only at its GCs
            while time.perf_counter() - w0 < args.seconds:
                page.wait_for_timeout(500)  # (not time.sleep: Playwright serves the page's requests meanwhile)
                for r in renderers:
                    anon[r].append(memory_mb(r).get("RssAnon", 0.0))
            st = page.evaluate(STATS)
            f1, p1, w1 = st["frames"], process_cpu(pids), time.perf_counter()
            c1 = {r: thread_cpu(r) for r in renderers}
            renderer = max(renderers, key=lambda r: sum(c1[r].values()) - sum(c0[r].values()))  # the page's
            c0, c1 = c0[renderer], c1[renderer]
            mem = memory_mb(renderer)
            js_mb = page.evaluate("""async () => crossOriginIsolated && performance.measureUserAgentSpecificMemory
                ? (await performance.measureUserAgentSpecificMemory()).bytes / 2 ** 20 : null""")
            # the talking-head graph alone (tracking paused), on the avatar's neutral: the ratio to Python
            page.evaluate("window.facesynth.state.ready = false")
            page.wait_for_timeout(500)
            alone = page.evaluate("""async (n) => {
                const a = window.facesynth.state.avatar, x = Float32Array.from(a.meta.avatar_neutral.flat()), t = [];
                for (let i = 0; i < 10; i++) await a.render(x, x);
                for (let i = 0; i < n; i++) { const t0 = performance.now(); await a.render(x, x); t.push(performance.now() - t0); }
                t.sort((p, q) => p - q);
                return t[n >> 1];
            }""", 100)
            errors = [m["text"] for m in st["messages"] if m["error"]]
    n = max(f1 - f0, 1)
    d = {k: (c1.get(k, 0.0) - c0.get(k, 0.0)) * 1e3 / n for k in c1}
    worker = sum(v for k, v in d.items() if "Worker" in k)
    main_thread = d.get("main", float("nan"))
    med = lambda k: round(float(np.median(st[k][-n:])), 2) if st[k] else None  # noqa: E731
    share = med("trackerMs") / (med("trackerMs") + med("avatarMs"))  # the tracker's part of the worker's thread
    split = "the worker's thread, split by wall time"
    out = {
        "bench": "web", "model": str(args.model), "video": str(args.video), "size": list(size),
        "tracker_ms": {"wall": med("trackerMs"), "cpu": round(worker * share, 2), "cpu_is": split},
        "avatar_ms": {"wall": med("avatarMs"), "cpu": round(worker * (1 - share), 2), "cpu_is": split},
        "composite_ms": {"wall": med("compositeMs"), "cpu": round(main_thread, 2), "cpu_is": "the page's main thread"},
        "reach_ms": round(float(np.median(st["reachMs"][-n:])), 3) if st["reachMs"] else None,
        "worker_cpu_ms": round(worker, 2), "main_cpu_ms": round(main_thread, 2), "workers": st["workers"],
        "latency_ms": med("latencyMs"),
        "renderer_cpu_ms": round(sum(d.values()), 2),
        "chromium_cpu_ms": round((p1 - p0) * 1e3 / n, 2),
        "e2e_fps": round((f1 - f0) / (w1 - w0), 2), "frames": f1,
        "load_s": round(st["firstFrameMs"] / 1e3, 2), "neutral_s": 1.0, "open_s": round(w0 - t0, 2),
        "page_mb": round(float(np.median(anon[renderer])), 1), "page_mb_max": max(anon[renderer]),
        "page_rss_mb": mem.get("VmRSS"),
        "page_js_mb": round(js_mb, 1) if js_mb is not None else None, "site_mb": round(page_bytes / 2**20, 1),
        "offline": not blocked, "blocked": blocked[:5], "errors": errors,
        "python_avatar_ms": round(python_avatar_ms(args.model), 3),
        "busiest_threads_ms": dict(sorted(((k, round(v, 2)) for k, v in d.items()), key=lambda kv: -kv[1])[:6]),
        "cpu_flags": sorted(cpu_flags(Path("/proc/cpuinfo").read_text()) & {"avx2", "avx512_vnni", "avx_vnni"}),
        "load_avg": load_average(),
    }
    out["avatar_alone_ms"] = round(alone, 3)
    out["avatar_vs_python"] = round(alone / out["python_avatar_ms"], 2)
    emit(out)
if __name__ == "__main__":
    main()
