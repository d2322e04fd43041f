"""Drive the page in headless Chromium (Playwright for Python, the system ``chromium``): a clip as
the fake camera, every request off 127.0.0.1 blocked and counted. Used by the tests,
``bench/web/page.py`` and ``bench/web/studio.py``.
"""

from __future__ import annotations

import contextlib
import shutil
from pathlib import Path
from urllib.parse import urlparse

import cv2
import numpy as np

from facesynth.errors import FacesynthError

CHROMIUM = ("/usr/bin/chromium", "/usr/bin/chromium-browser")


def chromium_path() -> str | None:
    for p in CHROMIUM:
        if Path(p).is_file():
            return p
    return shutil.which("chromium")


def write_y4m(video: str | Path, out: str | Path, max_frames: int = 150, size: tuple[int, int] | None = None) -> int:
    """The first ``max_frames`` frames of ``video`` as a YUV4MPEG2 file (4:2:0, 30 frames/s), what
    Chromium's fake camera reads; ``size`` (W, H) resizes. Returns the number of frames."""
    cap = cv2.VideoCapture(str(video))
    n = 0
    with open(out, "wb") as f:
        while n < max_frames:
            ok, bgr = cap.read()
            if not ok:
                break
            if size is not None:
                bgr = cv2.resize(bgr, size, interpolation=cv2.INTER_AREA)
            h, w = bgr.shape[:2]
            bgr = bgr[: h // 2 * 2, : w // 2 * 2]
            if n == 0:
                f.write(f"YUV4MPEG2 W{bgr.shape[1]} H{bgr.shape[0]} F30:1 Ip A1:1 C420jpeg\n".encode())
            f.write(b"FRAME\n")
            f.write(np.ascontiguousarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV_I420)).tobytes())
            n += 1
    cap.release()
    if n == 0:
        raise FacesynthError(f"{video}: no frame could be read")
    return n


@contextlib.contextmanager
def served(folder: str | Path):
    """Serve ``folder`` on 127.0.0.1 in a thread, as ``facesynth serve`` serves its page (the same
    app and checks, :mod:`facesynth.web.server`); yields the base URL."""
    from facesynth.web import server

    sock = server.listen(0)
    app = server.create_app(sock.getsockname()[1], app=server.folder_app(folder))
    with server.running(app, sock) as url:
        yield url


def _procs() -> dict[int, tuple[int, str]]:
    """pid -> (parent pid, command line) of every process."""
    out = {}
    for p in Path("/proc").iterdir():
        if not p.name.isdigit():
            continue
        try:
            stat = (p / "stat").read_text()
            cmd = (p / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        out[int(p.name)] = (int(stat[stat.rindex(")") + 2:].split()[1]), cmd)
    return out


def chromium_tree(marker: str) -> tuple[list[int], list[int]]:
    """(pids of the Chromium launched with ``marker`` among its switches and its descendants, its
    renderers' pids); a page's dedicated workers are threads of its renderer."""
    procs = _procs()
    roots = [pid for pid, (_, cmd) in procs.items() if marker in cmd and "--type=" not in cmd]
    tree = set(roots)
    grew = True
    while grew:
        grew = False
        for pid, (ppid, _) in procs.items():
            if ppid in tree and pid not in tree:
                tree.add(pid)
                grew = True
    return sorted(tree), [p for p in tree if "--type=renderer" in procs[p][1]]


def memory_mb(pid: int) -> dict[str, float]:
    """The process's resident memory: VmRSS (shared libraries included) and RssAnon (its own)."""
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key = line.split(":")[0]
        if key in ("VmRSS", "RssAnon"):
            out[key] = round(int(line.split()[1]) / 1024, 1)
    return out


@contextlib.contextmanager
def browser_page(camera_y4m: str | Path | None = None, camera: bool = True, deny_camera: bool = False,
                 extra_args: list[str] | None = None):
    """A Playwright page in headless system Chromium; yields (page, blocked), ``blocked`` the list of
    URLs off 127.0.0.1 that the page asked for (each aborted). ``camera`` False: no camera device;
    ``extra_args``: more Chromium switches."""
    from playwright.sync_api import sync_playwright

    exe = chromium_path()
    if exe is None:
        raise FacesynthError("chromium is not installed (apt-get install chromium)")
    args = ["--no-sandbox", "--use-fake-ui-for-media-stream" if not deny_camera else "--deny-permission-prompts"]
    if camera:
        args.append("--use-fake-device-for-media-stream")
        if camera_y4m is not None:
            args.append(f"--use-file-for-fake-video-capture={camera_y4m}")
    args += list(extra_args or [])
    blocked: list[str] = []
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=exe, headless=True, args=args)
        try:
            context = browser.new_context(permissions=[] if deny_camera else ["camera"])

            def route(r):
                host = urlparse(r.request.url).hostname
                if host in ("127.0.0.1",) or r.request.url.startswith(("data:", "blob:")):
                    r.continue_()
                else:
                    blocked.append(r.request.url)
                    r.abort()

            context.route("**/*", route)
            yield context.new_page(), blocked
        finally:
            browser.close()


# -- the studio: record, train, drive (tests/test_web_studio.py and bench/web/studio.py) -------
# a small training (the flow test stays short): the linear regressor, a 64 px reference, no
# augmentation, region folds or gaze path (its folds: 6x the rest of the fit's CPU time on 120
# frames), the evaluation on clean landmarks only, no frame-level measures
STUDIO_SMALL = ["regressor=linear", "model.reference_width=64", "sadm.augment_copies=0", "sadm.region_shrink=false",
                "sadm.gaze=false", "eval.noise=[0.0]", "eval.frame_level=false", "eval.train_level=false",
                "eval.talking_head=false"]


@contextlib.contextmanager
def studio_served(library: Path, **kwargs):
    """A :class:`~facesynth.web.studio.Studio` on ``library`` served on a free port: ``(url, studio)``."""
    from facesynth.web import server
    from facesynth.web.studio import Studio, create_studio_app

    studio = Studio(library, **kwargs)
    sock = server.listen(0)
    try:
        with server.running(create_studio_app(studio, sock.getsockname()[1]), sock) as url:
            yield url, studio
    finally:
        studio.close()


def run_studio_flow(page, url: str, name: str, seconds: float, shots: Path | None = None, timeout_s: float = 900) -> dict:
    """Record (every prompt, ``seconds`` times its duration), train, wait for the first live frame
    of the new avatar; the page's times (ms since the epoch) of each step."""
    page.goto(f"{url}?seconds={seconds}")
    page.wait_for_function("!document.getElementById('record').disabled", timeout=120_000)
    t_record = page.evaluate("Date.now()")
    page.click("#record")
    page.wait_for_function("!document.getElementById('train').disabled", timeout=300_000)
    t_recorded = page.evaluate("Date.now()")
    if shots:
        page.screenshot(path=str(shots / "facesynth_studio_record.png"), full_page=True)
    page.fill("#name", name)
    page.click("#train")
    page.wait_for_function("window.studio.state.job && (window.studio.state.job.percent > 20 || "
                           "['failed', 'cancelled'].includes(window.studio.state.job.state))", timeout=timeout_s * 1000)
    if shots:
        page.screenshot(path=str(shots / "facesynth_studio_train.png"), full_page=True)
    page.wait_for_function("window.studio.state.frames >= 10 || (window.studio.state.job && "
                           "['failed', 'cancelled'].includes(window.studio.state.job.state))", timeout=timeout_s * 1000)
    job = page.evaluate("window.studio.state.job")
    assert job["state"] == "done", job
    first_frame = page.evaluate("window.studio.state.firstFrameAt")
    if shots:
        page.screenshot(path=str(shots / "facesynth_studio_drive.png"), full_page=True)
    # the run's evaluation and report are written while the avatar drives
    page.wait_for_function("window.studio.state.job.report !== 'writing'", timeout=timeout_s * 1000)
    job = page.evaluate("window.studio.state.job")
    return {"record": t_record, "recorded": t_recorded, "train_pressed": page.evaluate("window.studio.state.trainPressedAt"),
            "first_frame": first_frame, "report_written": page.evaluate("Date.now()"), "job": job,
            "coverage": page.evaluate("window.studio.state.coverage")}
