"""``facesynth studio`` (facesynth.web.studio): the whole flow in headless system Chromium with a
shared clip as the fake camera (record, train with a small configuration, drive the new avatar),
the coverage meter of the page (coverage.js) against its Python reference on the same points,
the checks a foreign page meets (Host, Origin, token), and each bad input's one-line message with
nothing left in the library. Skips without chromium, playwright, MediaPipe or the page's npm
packages (``facesynth web setup``)."""

from __future__ import annotations

import http.client
import json
import os
import re
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from _page import require_page

require_page(open_in_browser=True)

from bench import browser  # noqa: E402
from facesynth import coverage  # noqa: E402
from facesynth.web.studio import Studio  # noqa: E402

SHOTS = Path(os.environ.get("FACESYNTH_WEB_SHOTS", "/tmp"))
def request(url: str, method: str, path: str, body: bytes = b"", headers: dict | None = None, host: str | None = None):
    """(status, JSON or text) of one request with the Host header as given (default: the server's)."""
    netloc = url.split("/")[2]
    conn = http.client.HTTPConnection(netloc, timeout=30)
    try:
        conn.putrequest(method, path, skip_host=True, skip_accept_encoding=True)
        conn.putheader("Host", host or netloc)
        for k, v in (headers or {}).items():
            conn.putheader(k, v)
        conn.putheader("Content-Length", str(len(body)))
        conn.endheaders(body)
        r = conn.getresponse()
        data = r.read()
    finally:
        conn.close()
    try:
        return r.status, json.loads(data)
    except ValueError:
        return r.status, data.decode(errors="replace")


def body_of(frames: list[np.ndarray]) -> bytes:
    """BGR frames as the page uploads them: each a 4-byte big-endian length, then its JPEG."""
    out = []
    for f in frames:
        jpeg = cv2.imencode(".jpg", f, [cv2.IMWRITE_JPEG_QUALITY, 92])[1].tobytes()
        out += [len(jpeg).to_bytes(4, "big"), jpeg]
    return b"".join(out)


def upload(url: str, token: str, name: str, body: bytes, **headers):
    return request(url, "POST", f"/api/train?name={name}", body, {"X-Facesynth-Token": token, **headers})


def wait_state(studio: Studio, states: tuple, timeout_s: float = 600.0) -> dict:
    t0 = time.monotonic()
    while studio.state["state"] not in states:
        assert time.monotonic() - t0 < timeout_s, f"still {studio.state} after {timeout_s} s"
        time.sleep(0.1)
    return studio.state


def library_entries(library: Path) -> list[str]:
    return sorted(p.name for p in library.iterdir())  # hidden work folders included


def video_frames(video: Path, n: int) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(video))
    out = []
    while len(out) < n:
        ok, f = cap.read()
        if not ok:
            break
        out.append(f)
    cap.release()
    return out


@pytest.fixture(scope="module")
def camera(shared_clip_dir, tmp_path_factory):
    y4m = tmp_path_factory.mktemp("cam") / "cam.y4m"
    browser.write_y4m(shared_clip_dir("lp_d6") / "video.mp4", y4m, 150, (640, 480))
    return y4m


# -- the checks a foreign page meets -----------------------------------------------------------
def test_foreign_origin_host_and_missing_token_are_refused(tmp_path, shared_clip_dir):
    lib = tmp_path / "lib"
    body = body_of(video_frames(shared_clip_dir("lp_d6") / "video.mp4", 5))
    with browser.studio_served(lib) as (url, studio):
        status, session = request(url, "GET", "/api/session")
        assert status == 200 and session["token"] == studio.token and len(studio.token) >= 40
        netloc = url.split("/")[2]
        # a foreign Origin (a page on another site), with the right token
        assert upload(url, studio.token, "a", body, Origin="http://evil.example")[0] == 403
        # a foreign Host (DNS rebinding: evil.example resolved to 127.0.0.1), with the right token
        assert request(url, "POST", "/api/train?name=a", body, {"X-Facesynth-Token": studio.token},
                       host=f"evil.example:{netloc.split(':')[1]}")[0] == 403
        assert request(url, "GET", "/api/session", host="evil.example")[0] == 403  # nor its token
        # no token, a wrong one: refused, with the page's own Origin too
        for headers in ({}, {"X-Facesynth-Token": "x" * 43}, {"X-Facesynth-Token": studio.token[:-1]}):
            status, answer = request(url, "POST", "/api/train?name=a", body, {"Origin": f"http://{netloc}", **headers})
            assert status == 403 and "token" in answer["error"]
            assert request(url, "POST", "/api/cancel", b"", headers)[0] == 403
        assert studio.state["state"] == "idle" and library_entries(lib) == []
        # nothing but the page and the library's avatars (their .onnx and report) is served
        for path in ("/library/../x", "/library/a/config.yaml", "/api/../../etc/passwd", "/library/.studio-work-1-a/avatar.onnx"):
            assert request(url, "GET", path)[0] == 404


# -- bad input: a one-line message, nothing in the library ----------------------------------------
def test_bad_inputs_leave_nothing(tmp_path, shared_clip_dir):
    lib = tmp_path / "lib"
    frames = video_frames(shared_clip_dir("lp_d6") / "video.mp4", 300)
    rng = np.random.default_rng(0)
    noise = [rng.integers(0, 255, frames[0].shape, np.uint8) for _ in range(60)]
    with browser.studio_served(lib, min_frames=45, max_upload=50 * 2**20) as (url, studio):
        tok = studio.token
        # refused before anything is written
        assert upload(url, tok, "../x", b"abc")[0] == 400
        status, answer = request(url, "POST", "/api/train?name=big", b"x" * (50 * 2**20 + 1), {"X-Facesynth-Token": tok})
        assert status == 413 and "too large" in answer["error"]
        studio.disk_margin = 1 << 60  # a full disk: far more needed than free
        status, answer = upload(url, tok, "full", b"abc")
        assert status == 507 and "not enough free disk space" in answer["error"]
        studio.disk_margin = 0
        assert library_entries(lib) == []

        cases = [
            ("undecodable", os.urandom(5000), "the recording cannot be decoded (frame 1 is not a JPEG image)"),
            ("truncated", body_of(frames[:50])[:-100], "the recording cannot be decoded (frame 50 is not a JPEG image)"),
            ("short", body_of(frames[:20]), "the recording is too short: 20 frames, at least 45"),
            ("noface", body_of(frames[:30] + noise), "no face in most frames"),
        ]
        for name, body, text in cases:
            assert upload(url, tok, name, body)[0] == 202
            st = wait_state(studio, ("failed", "done"))
            assert st["state"] == "failed" and text in st["message"] and "\n" not in st["message"], st
            assert library_entries(lib) == []

        # a failed training (a bad configuration), then a cancelled one; a second job while one runs is refused
        good = body_of(frames)
        studio.overrides.append("regressor=nonexistent")
        assert upload(url, tok, "failed", good)[0] == 202
        st = wait_state(studio, ("failed", "done"))
        assert st["state"] == "failed" and "regressor" in st["message"] and "\n" not in st["message"], st
        studio.overrides.pop()
        assert library_entries(lib) == []
        assert upload(url, tok, "cancelled", good)[0] == 202
        status, answer = upload(url, tok, "second", good)
        assert status == 409 and "already running" in answer["error"]
        t0 = time.monotonic()
        while studio.state.get("stage") in ("upload", "decode") and time.monotonic() - t0 < 300:
            time.sleep(0.1)
        assert request(url, "POST", "/api/cancel", b"", {"X-Facesynth-Token": tok})[0] == 202
        st = wait_state(studio, ("cancelled", "failed", "done"))
        assert st["state"] == "cancelled" and "nothing was added" in st["message"]
        assert library_entries(lib) == []
        assert request(url, "POST", "/api/cancel", b"", {"X-Facesynth-Token": tok})[0] == 409


# -- the progress's percent and time left ---------------------------------------------------------
@pytest.mark.parametrize("speed", [0.5, 1.0, 3.0])
def test_time_left_is_exact_for_a_job_at_the_measured_ratios(speed):
    """A job whose stages take their measured seconds times ``speed`` (a slower or faster host),
    each moving linearly: from 3 % on, the time left is the true time left; before, the measured
    seconds; the percent only grows, from 0 to 100."""
    from facesynth.web.studio_job import STAGES, estimate

    total = sum(s for _, s in STAGES) * speed
    t, last = 0.0, -1.0
    for name, seconds in STAGES:
        for fraction in np.linspace(0, 1, 11):
            elapsed = t + seconds * speed * fraction
            percent, left = estimate(name, fraction, elapsed)
            assert percent >= last and abs(percent - 100 * elapsed / total) < 1e-9
            last = percent
            want = total - elapsed if percent >= 3 else total / speed - percent / 100 * total / speed
            assert abs(left - want) < 1e-6 * total, (name, fraction, left, want)
        t += seconds * speed
    assert last == pytest.approx(100.0)


def test_time_left_from_the_stages_a_job_reports(tmp_path):
    """The server's side: the job's reports (stage, fraction) in the state, the percent never
    going back when a stage's bar restarts, the state ``done`` once the avatar is live while the
    report is written, then ``written``."""
    import subprocess
    import sys

    from facesynth.web.studio_job import MARK

    script = "; ".join([
        "import json, os",
        f"m = lambda d: os.write(1, ({MARK!r} + json.dumps(d) + chr(10)).encode())",
        "m({'stage': 'ingest', 'fraction': 0.5})", "m({'stage': 'face model', 'fraction': 0.2})",
        "m({'stage': 'ingest', 'fraction': 1.0})", "m({'live': {'frames': 3}})", "m({'stage': 'report', 'fraction': 0})",
        "m({'done': {'frames': 3}})",
    ])
    from facesynth.web.studio_job import estimate

    studio = Studio(tmp_path / "lib")
    work = tmp_path / "lib" / ".studio-work-x"
    work.mkdir()
    seen, set_state = [], studio._set
    studio._set = lambda **kw: (seen.append(dict(kw)), set_state(**kw))[1]
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE)
    studio._set(state="running")
    studio._watch(proc, "me", work)
    percents = [s["percent"] for s in seen if "percent" in s and s.get("state") != "done"]
    assert percents == [round(estimate("ingest", 0.5, 1)[0], 1)] + [round(estimate("face model", 0.2, 1)[0], 1)] * 2
    assert studio.state["state"] == "done" and studio.state["report"] == "written"
    assert library_entries(tmp_path / "lib") == ["me"]
    assert [s.get("report_stage") for s in seen if "report_stage" in s][-1] == "report"


def test_the_training_job_runs_its_numerical_libraries_on_one_thread():
    """The job's one_thread (its main calls it first): numpy's BLAS and torch on one thread each, as
    threadpoolctl and torch report them in a fresh process (this one's threads stay as they are)."""
    import subprocess
    import sys

    probe = ("import json, threadpoolctl, torch; from facesynth.web.studio_job import one_thread; one_thread(); "
             "print(json.dumps([threadpoolctl.threadpool_info(), torch.get_num_threads()]))")
    info, torch_threads = json.loads(subprocess.run([sys.executable, "-c", probe], capture_output=True, check=True).stdout)
    blas = [i for i in info if i["user_api"] == "blas"]
    assert blas and all(i["num_threads"] == 1 for i in blas) and torch_threads == 1


# -- the coverage meter: the page's (coverage.js) against the Python reference --------------------
def test_coverage_js_matches_python(tmp_path, shared_clip_dir):
    from facesynth.data.ingest import ingest_video

    seq = ingest_video(shared_clip_dir("lp_d6") / "video.mp4", tmp_path / "ing", landmarker="mediapipe", max_frames=240)
    pts = seq.landmarks.astype(np.float32)
    prompts, k = [], 0
    for pid, dirs, n in [("neutral", [], 20), ("speech", ["speech"], 40), ("smile", ["smile"], 30), ("open", ["mouth_open"], 30),
                         ("oo", ["oo"], 2), ("turn", ["turn_left", "turn_right"], 60), ("blink", ["blink"], 0)]:
        frames = [p.ravel().tolist() for p in pts[k:k + n]]
        if n > 5:
            frames[3] = None  # a frame without a face
        prompts.append({"id": pid, "directions": dirs, "points": frames})
        k += n
    want = coverage.coverage([{**p, "points": [None if x is None else np.asarray(x, np.float32).reshape(-1, 2)
                                                for x in p["points"]]} for p in prompts])
    assert 0 < want["overall"] < 1 and want["prompts"]["blink"] == 0.0 and 0 < want["self_reach"] < 1
    with browser.studio_served(tmp_path / "lib") as (url, _), browser.browser_page(camera=False) as (page, blocked):
        page.goto(url)
        page.wait_for_function("window.studio && typeof window.studio.coverage === 'function'")
        got = page.evaluate("(p) => window.studio.coverage(p)", prompts)
        assert page.evaluate("window.studio.directions") == list(coverage.DIRECTIONS)
    assert blocked == []
    assert got["prompts"].keys() == want["prompts"].keys() and got["directions"].keys() == want["directions"].keys()
    for key in want["prompts"]:
        assert abs(got["prompts"][key] - want["prompts"][key]) < 1e-9, key
    for key in want["directions"]:
        assert abs(got["directions"][key] - want["directions"][key]) < 1e-9, key
    assert abs(got["overall"] - want["overall"]) < 1e-9
    assert abs(got["self_reach"] - want["self_reach"]) < 1e-9
    # the summary lists exactly the prompts whose bars are below WEAK, in both
    assert got["missing"] == want["missing"] == [k for k, v in want["prompts"].items() if v < coverage.WEAK]
    assert "blink" in want["missing"]


def test_reach_against_scikit_learn_neighbours():
    """The meter's reach: 1 - the mean distance to the NEAREST nearest frames / REACH, clipped,
    against scikit-learn's exact neighbour search; a clip's own frames reach themselves."""
    from sklearn.neighbors import NearestNeighbors

    rng = np.random.default_rng(0)
    frames, shapes = rng.normal(0, 0.2, (300, 8)), rng.normal(0, 0.3, (30, 8))
    dist, _ = NearestNeighbors(n_neighbors=coverage.NEAREST).fit(frames).kneighbors(shapes)
    want = np.clip(1 - dist.mean(1) / coverage.REACH, 0, 1)
    np.testing.assert_allclose(coverage.reach(frames, shapes), want, atol=1e-12)
    assert ((want > 0) & (want < 1)).sum() > 10  # most inside the clip's range...
    assert coverage.reach(frames, np.full((1, 8), 9.0))[0] == 0.0  # ...and a shape far from every frame
    assert coverage.reach(np.zeros((0, 8)), shapes).tolist() == [0.0] * 30
    # a direction's target shape sits on its feature's axis, target / SCALE from the neutral
    z = coverage.direction_z("mouth_open")
    k = coverage.FEATURES.index("mouth_open")
    assert z[k] == 0.30 / 0.12 and np.isnan(np.delete(z, k)).all()
    dist, _ = NearestNeighbors(n_neighbors=coverage.NEAREST).fit(frames[:, [k]]).kneighbors(z[None, [k]])
    assert coverage.reach(frames, z)[0] == np.clip(1 - dist.mean() / coverage.REACH, 0, 1)  # over that feature alone


def test_self_reach_against_scikit_learn_neighbours():
    """The page's headline: each frame's reach by the frames outside its BLOCK-frame block (in
    SCALE units), the mean over the frames, against scikit-learn's exact neighbour search block
    by block; a still recording reaches itself fully, one that never returns to an expression not
    at all."""
    from sklearn.neighbors import NearestNeighbors

    rng = np.random.default_rng(1)
    t = np.arange(70)[:, None]  # blocks of 15, 15, 15, 15 and 10 frames
    wave = np.sin(2 * np.pi * t / 25) * rng.uniform(0.5, 1.5, 8)  # an expression, again and again
    feats = (wave + rng.normal(0, 0.15, (70, 8))) * coverage.SCALE
    z, b = feats / np.asarray(coverage.SCALE), coverage.BLOCK
    want = []
    for s in range(0, len(z), b):
        others = np.concatenate([z[:s], z[s + b:]])
        dist, _ = NearestNeighbors(n_neighbors=coverage.NEAREST).fit(others).kneighbors(z[s:s + b])
        want += list(np.clip(1 - dist.mean(1) / coverage.REACH, 0, 1))
    assert abs(coverage.self_reach(feats) - np.mean(want)) < 1e-12 and 0 < min(want) and max(want) < 1
    assert coverage.self_reach(np.tile(feats[:1], (40, 1))) == 1.0
    steps = np.repeat(np.arange(4)[:, None] * 10.0 * np.asarray(coverage.SCALE), b, axis=0)  # 4 expressions, one block each
    assert coverage.self_reach(steps) == 0.0 and coverage.self_reach(np.zeros((0, 8))) == 0.0
    # the page keeps KEEP_FPS frames a second: coverage.js's blocks are the same second
    js = (Path(coverage.__file__).parent / "web" / "page" / "coverage.js").read_text()
    assert re.search(r"KEEP_FPS = (\d+), BLOCK = KEEP_FPS", js).group(1) == str(coverage.KEEP_FPS) == str(coverage.BLOCK)


# -- the whole flow in the page ---------------------------------------------------------------
def test_record_train_drive(tmp_path, camera):
    lib = tmp_path / "lib"
    with browser.studio_served(lib, overrides=browser.STUDIO_SMALL, min_frames=10) as (url, studio), \
            browser.browser_page(camera) as (page, blocked):
        t = browser.run_studio_flow(page, url, "me-small", 0.2, SHOTS)
        assert t["first_frame"] > t["train_pressed"] > t["record"]
        assert 0 < t["coverage"]["overall"] <= 1 and len(t["coverage"]["prompts"]) == 13 and 0 <= t["coverage"]["self_reach"] <= 1
        # the library: the avatar, its run with report.html; listed in the page with its report link
        assert t["job"]["report"] == "written", t["job"]
        assert library_entries(lib) == ["me-small"]
        assert {"avatar.onnx", "run", "ingest", "studio.json"} <= set(os.listdir(lib / "me-small"))
        assert (lib / "me-small" / "run" / "report.html").is_file()
        assert page.locator("#library a", has_text="report").count() == 1
        status, html = request(url, "GET", "/library/me-small/report.html")
        assert status == 200 and "<html" in html.lower()
        # the avatar drives: frames keep coming and differ from the still neutral frame
        n = page.evaluate("window.studio.state.frames")
        page.wait_for_function(f"window.studio.state.frames >= {n + 10}", timeout=60_000)
        assert not [m for m in page.evaluate("window.studio.state.messages") if m["error"]]
        # the live reach readout: the new avatar carries its recording (coverage.js, as the live page's)
        page.wait_for_function("!document.getElementById('reach').hidden", timeout=30_000)
        assert re.fullmatch(r"Reach:\s+\d+ %\s+\(mean \d+ %\)", page.inner_text("#reach").strip())
        assert page.evaluate("window.studio.state.reach.n") > 0 and page.is_hidden("#reach-note")
        page.screenshot(path=str(SHOTS / "facesynth_studio_reach.png"), full_page=True)
        # a name already in the library: a one-line message in the page, nothing started
        page.click("#train")
        page.wait_for_function("document.getElementById('message').className === 'error'")
        assert "already has an avatar named me-small" in page.inner_text("#message")
    assert blocked == []


def test_page_shows_a_failed_training(tmp_path, camera):
    """A recording the server refuses (here: too short) ends in a one-line message in the page."""
    lib = tmp_path / "lib"
    with browser.studio_served(lib, overrides=browser.STUDIO_SMALL, min_frames=100000) as (url, studio), \
            browser.browser_page(camera) as (page, blocked):
        page.goto(f"{url}?seconds=0.2")
        page.wait_for_function("!document.getElementById('record').disabled", timeout=120_000)
        page.click("#record")
        page.wait_for_function("!document.getElementById('train').disabled", timeout=300_000)
        page.click("#train")
        page.wait_for_function("window.studio.state.job && window.studio.state.job.state === 'failed'", timeout=120_000)
        text = page.inner_text("#message")
        assert text.startswith("Training failed: the recording is too short") and "\n" not in text, text
        assert library_entries(lib) == []
    assert blocked == []


def test_cli_serves_the_studio_and_refuses_a_file_as_library(tmp_path):
    """``facesynth studio`` (``python -m facesynth``: the job's process must not start a second
    server) answers on the port it prints; a file as the library is one line, exit 2."""
    import signal
    import subprocess
    import sys

    (tmp_path / "file").write_text("x")
    done = subprocess.run([sys.executable, "-m", "facesynth", "studio", "--library", str(tmp_path / "file"), "--port", "0"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and done.stderr.strip() == f"error: {tmp_path / 'file'}: the library must be a folder"
    proc = subprocess.Popen([sys.executable, "-m", "facesynth", "studio", "--library", str(tmp_path / "lib"), "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        line = proc.stdout.readline()
        assert line.startswith("open http://127.0.0.1:"), line
        url = line.split()[1]
        status, session = request(url, "GET", "/api/session")
        assert status == 200 and len(session["token"]) >= 40 and session["library"] == str(tmp_path / "lib")
        status, html = request(url, "GET", "/")
        assert status == 200 and "facesynth studio" in html
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(60)
    assert (tmp_path / "lib").is_dir() and library_entries(tmp_path / "lib") == []
