"""``facesynth studio``: one local page to record a guided clip, train an avatar of it on this
machine and drive it live, with a library of the avatars made before (docs/studio.md).

The endpoints are mounted on :func:`facesynth.web.server.create_app`, so the page and its API sit
behind the same checks as ``facesynth serve`` (127.0.0.1 only, ``Host`` and ``Origin`` its own,
no control characters, the security headers). On top of them, every request that writes or
starts work (``POST``) must carry the run's token (``X-Facesynth-Token``), which the page reads
from ``GET api/session`` when it loads: a foreign page can send a request but cannot read that
answer (no CORS, ``Cross-Origin-Resource-Policy: same-origin``), so it cannot forge the header.

- ``GET api/session``: ``{token, max_upload_bytes, library}``;
- ``GET api/library``: the avatars, newest first; ``GET library/NAME/avatar.onnx``, ``.../report.html``;
- ``POST api/train?name=NAME``: the body is the recording, its frames in order, each a 4-byte
  big-endian length and then the frame as a JPEG (the frames the page's tracker saw); starts the
  job (202) unless one is running (409), the name is bad or taken (400, 409), the body is too
  large (413) or the library's disk has too little free space (507);
- ``POST api/cancel``; ``GET api/progress``: the job's state as Server-Sent Events.

The job (:mod:`facesynth.web.studio_job`) runs in a process of its own (cancel terminates it) in a
hidden work folder inside the library (``.studio-work-PID-...``), renamed to ``NAME`` once the
avatar is exported (the job then writes the run's evaluation and report in it while the page
drives the avatar) and removed when the job fails before that: the library never holds a
half-made avatar.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import secrets
import shutil
import tempfile
import threading
import time
from pathlib import Path

from facesynth.errors import FacesynthError
from facesynth.io import remove_dead_pid_folders
from facesynth.web.studio_job import UPLOAD

NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,39}$")
WORK_PREFIX = ".studio-work-"  # + PID + "-": a job's folder inside the library
MAX_UPLOAD = 400 * 2**20  # bytes of recording accepted (40 s of 640x480 JPEG frames: about 20-60 MB)
DISK_FACTOR = 3  # the work folder's peak size per uploaded byte (the upload, the Motion-JPEG video, its copy)
DISK_MARGIN = 300 * 2**20  # + the run folder and the model
DEFAULT_OVERRIDES = ("eval.common_region=false",)  # no dlib landmarks beside a studio recording
MIN_FRAMES = 150  # frames a recording needs (the page keeps the frames its tracker sees: 10-30 a second)
MIN_FACE = 0.5
TOKEN_HEADER = "x-facesynth-token"
PAGE_FILES = ("workers.js", "worker.js", "tracker.js", "schemes.js", "onnxmeta.js", "neutral.js", "coverage.js", "studio.js",
              "studio.css")
SSE_MAX_S = 15.0  # one progress stream's length (a stopping server waits for it); EventSource reconnects


def page_files() -> dict[str, bytes]:
    """The studio page: its own files, the live page's modules it imports (the tracker and avatar
    worker, the ONNX metadata reader, the landmark tables), onnxruntime-web and the tracker models."""
    from facesynth.web import site

    dist = site.ort_dist()
    files = {f: (site.PAGE / f).read_bytes() for f in PAGE_FILES}
    files["index.html"] = (site.PAGE / "studio.html").read_bytes()
    files.update({f"ort/{f}": (dist / f).read_bytes() for f in site.ORT_FILES})
    models = site.tracker_dir()
    files.update({f"models/{p.name}": p.read_bytes() for p in sorted(models.iterdir()) if p.is_file()})
    files["schemes.json"] = json.dumps(site.schemes_json()).encode()
    return files


def remove_stale_work(library: Path) -> list[Path]:
    """Work folders in ``library`` left by a studio that was killed (its PID is gone)."""
    return remove_dead_pid_folders(library, WORK_PREFIX)


class Studio:
    """The studio's state: the library folder, the run's token, the one job."""

    def __init__(self, library: str | Path, overrides=(), min_frames: int = MIN_FRAMES, min_face: float = MIN_FACE,
                 max_upload: int = MAX_UPLOAD, disk_margin: int = DISK_MARGIN):
        self.library = Path(library)
        if self.library.exists() and not self.library.is_dir():
            raise FacesynthError(f"{self.library}: the library must be a folder")
        self.library.mkdir(parents=True, exist_ok=True)
        remove_stale_work(self.library)
        self.token = secrets.token_urlsafe(32)
        self.overrides = [*DEFAULT_OVERRIDES, *overrides]
        self.min_frames = int(min_frames)
        self.min_face, self.max_upload, self.disk_margin = min_face, max_upload, disk_margin
        self.lock = threading.Lock()
        self.state = {"state": "idle", "version": 0}
        self.proc = None
        self.cancelled = False
        self.closing = False

    # -- the job --------------------------------------------------------------------------
    def _set(self, **kw) -> None:
        with self.lock:
            self.state = {**self.state, **kw, "version": self.state["version"] + 1}

    def busy(self) -> bool:
        """A job is uploading, training, or writing the report of the avatar it made."""
        return self.state["state"] in ("uploading", "running") or self.state.get("report") == "writing"

    def start(self, name: str, work: Path) -> None:
        import subprocess
        import sys

        args = {"work": str(work), "overrides": self.overrides, "min_frames": self.min_frames, "min_face": self.min_face}
        self.cancelled = False
        self.proc = subprocess.Popen([sys.executable, "-m", "facesynth.web.studio_job", json.dumps(args)],
                                     stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
        self._set(state="running", name=name, stage="decode", percent=0.0, eta_s=None, elapsed_s=0.0, message="",
                  started=time.time(), report=None, report_stage=None, summary=None)
        threading.Thread(target=self._watch, args=(self.proc, name, work), daemon=True).start()

    @staticmethod
    def _read(proc, messages) -> None:
        """The job's messages (its MARK lines on stdout) into ``messages``; None when it closes."""
        from facesynth.web.studio_job import MARK

        for line in proc.stdout:
            text = line.decode(errors="replace")
            if text.startswith(MARK):
                try:
                    messages.put(json.loads(text[len(MARK):]))
                except ValueError:
                    pass
        messages.put(None)

    def _watch(self, proc, name: str, work: Path) -> None:
        """Follows the job: its stages into the state (percent, time left), the work folder renamed
        to ``name`` when the avatar is live (state ``done``; ``report``: ``writing``, then
        ``written`` or ``failed``), removed when the job fails or is cancelled before that."""
        import queue

        from facesynth.web.studio_job import STAGES, estimate

        order = [s for s, _ in STAGES]
        t0 = time.time()
        result, live = None, False
        messages: queue.Queue = queue.Queue()
        threading.Thread(target=self._read, args=(proc, messages), daemon=True).start()
        at = ("decode", 0.0)
        while True:
            try:
                msg = messages.get(timeout=0.25)
            except queue.Empty:  # the estimate of the time left moves on between two reports too
                if not live:
                    elapsed = time.time() - t0
                    self._set(elapsed_s=elapsed, eta_s=estimate(*at, elapsed)[1])
                continue
            if msg is None:  # the job's stdout closed: it ended
                break
            if "stage" in msg and not live:
                if msg["stage"] in order:
                    at = max(at, (msg["stage"], msg["fraction"]), key=lambda x: (order.index(x[0]), x[1]))
                    elapsed = time.time() - t0
                    percent, eta = estimate(*at, elapsed)
                    self._set(stage=at[0], percent=round(min(99.9, percent), 1), eta_s=eta, elapsed_s=elapsed)
            elif "stage" in msg:
                self._set(report_stage=msg["stage"])
            elif "live" in msg:
                target = self.library / name
                try:
                    if target.exists():
                        raise FileExistsError(f"{target} appeared meanwhile")
                    os.replace(work, target)  # the job works on in it (its working folder)
                except OSError as exc:
                    proc.terminate()
                    proc.wait()
                    shutil.rmtree(work, ignore_errors=True)
                    self._set(state="failed", message=f"The avatar could not be saved: {exc}")
                    return
                live = True
                self._set(state="done", percent=100.0, eta_s=0.0, elapsed_s=time.time() - t0, summary=msg["live"],
                          report="writing", report_stage="evaluation", message=f"{name} is ready.")
            else:
                result = msg
        proc.wait()
        if live:
            ok = bool(result and "done" in result)
            self._set(report="written" if ok else "failed", report_s=time.time() - t0,
                      **({"summary": result["done"]} if ok else {}),
                      report_message="" if ok else (result or {}).get("error", f"exit status {proc.returncode}"))
        elif self.cancelled:
            shutil.rmtree(work, ignore_errors=True)
            self._set(state="cancelled", message="Training cancelled: nothing was added to the library.", eta_s=None)
        else:
            shutil.rmtree(work, ignore_errors=True)
            why = result["error"] if result else f"the training process stopped (exit status {proc.returncode})"
            self._set(state="failed", message=f"Training failed: {why}", eta_s=None)

    def cancel(self) -> bool:
        proc = self.proc
        if proc is None or proc.poll() is not None or self.state["state"] != "running":
            return False
        self.cancelled = True
        proc.terminate()  # SIGTERM: the job unwinds (install_sigterm_handler), its temporary files removed
        return True

    def close(self) -> None:
        self.closing = True
        if not self.cancel() and self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()  # a live avatar's report still being written: the avatar stays, without it
        if self.proc is not None:
            try:
                self.proc.wait(30)
            except Exception:  # noqa: BLE001 - subprocess.TimeoutExpired: it is killed
                self.proc.kill()
                self.proc.wait()

    # -- the library ----------------------------------------------------------------------
    def avatars(self) -> list[dict]:
        out = []
        for d in self.library.iterdir():
            if d.name.startswith(".") or not NAME.match(d.name) or not (d / "avatar.onnx").is_file():
                continue
            info = {"name": d.name, "created": d.stat().st_mtime, "report": (d / "run" / "report.html").is_file()}
            try:
                info["summary"] = json.loads((d / "studio.json").read_text())
            except (OSError, ValueError):
                pass
            out.append(info)
        return sorted(out, key=lambda a: -a["created"])

    # -- the endpoints --------------------------------------------------------------------
    def routes(self):
        from starlette.routing import Route

        return [Route("/api/session", self.session, methods=["GET"]),
                Route("/api/library", self.library_list, methods=["GET"]),
                Route("/api/progress", self.progress, methods=["GET"]),
                Route("/api/train", self.train, methods=["POST"]),
                Route("/api/cancel", self.cancel_endpoint, methods=["POST"]),
                Route("/library/{name}/{file}", self.library_file, methods=["GET", "HEAD"])]

    def _refuse_token(self, request):
        from starlette.responses import JSONResponse

        sent = request.headers.get(TOKEN_HEADER, "")
        if not secrets.compare_digest(sent.encode(), self.token.encode()):
            return JSONResponse({"error": "forbidden: this request needs the studio page's token"}, 403)
        return None

    async def session(self, request):
        from starlette.responses import JSONResponse

        return JSONResponse({"token": self.token, "max_upload_bytes": self.max_upload, "library": str(self.library),
                             "min_frames": self.min_frames})

    async def library_list(self, request):
        from starlette.responses import JSONResponse

        return JSONResponse({"avatars": self.avatars()})

    async def library_file(self, request):
        from starlette.responses import FileResponse, PlainTextResponse

        name, file = request.path_params["name"], request.path_params["file"]
        where = {"avatar.onnx": ("avatar.onnx", "application/octet-stream"), "report.html": ("run/report.html", "text/html")}
        if not NAME.match(name) or file not in where or not (self.library / name / where[file][0]).is_file():
            return PlainTextResponse("not found", 404)
        return FileResponse(self.library / name / where[file][0], media_type=where[file][1])

    async def progress(self, request):
        from starlette.responses import StreamingResponse

        async def events():
            yield "retry: 500\n\n"
            last, t0, beat = -1, time.monotonic(), 0.0
            while not self.closing and time.monotonic() - t0 < SSE_MAX_S:
                state = self.state
                if state["version"] != last or time.monotonic() - beat > 5:
                    last, beat = state["version"], time.monotonic()
                    yield f"data: {json.dumps(state)}\n\n"
                if await request.is_disconnected():
                    break
                await asyncio.sleep(0.2)

        return StreamingResponse(events(), media_type="text/event-stream")

    async def cancel_endpoint(self, request):
        from starlette.responses import JSONResponse

        refused = self._refuse_token(request)
        if refused:
            return refused
        if not self.cancel():
            return JSONResponse({"error": "no training is running"}, 409)
        return JSONResponse({"cancelling": True}, 202)

    async def train(self, request):
        from starlette.responses import JSONResponse

        refused = self._refuse_token(request)
        if refused:
            return refused

        def fail(status: int, text: str):
            return JSONResponse({"error": text}, status)

        name = request.query_params.get("name", "")
        if not NAME.match(name):
            return fail(400, "the avatar's name: 1 to 40 letters, digits, '-' or '_', starting with a letter or digit")
        if (self.library / name).exists():
            return fail(409, f"the library already has an avatar named {name}: choose another name")
        length = request.headers.get("content-length", "")
        if not length.isdigit():
            return fail(411, "the upload needs its length (Content-Length)")
        total = int(length)
        if total == 0:
            return fail(400, "the recording is empty: record the prompts first")
        if total > self.max_upload:
            return fail(413, f"the recording is too large ({total / 2**20:.0f} MB; at most {self.max_upload / 2**20:.0f} MB)")
        free = shutil.disk_usage(self.library).free
        need = total * DISK_FACTOR + self.disk_margin
        if free < need:
            return fail(507, f"not enough free disk space in {self.library}: {free / 2**30:.2f} GB free, "
                             f"{need / 2**30:.2f} GB needed")
        with self.lock:
            if self.busy():
                return fail(409, "a training is already running (or writing its report): wait for it or cancel it")
            self.state = {**self.state, "state": "uploading", "version": self.state["version"] + 1, "name": name,
                          "message": "", "stage": "upload", "percent": 0.0, "eta_s": None}
        try:
            work = Path(tempfile.mkdtemp(prefix=f"{WORK_PREFIX}{os.getpid()}-{name}-", dir=self.library))
        except OSError as exc:
            self._set(state="failed", message=f"Cannot write in the library: {exc}")
            return fail(507, f"cannot write in the library {self.library}: {exc.strerror}")
        try:
            await self._receive(request, work / UPLOAD, total)
        except _UploadError as exc:
            shutil.rmtree(work, ignore_errors=True)
            self._set(state="failed", message=str(exc))
            return fail(exc.status, str(exc))
        except BaseException:
            shutil.rmtree(work, ignore_errors=True)
            self._set(state="failed", message="the upload was interrupted")
            raise
        try:
            self.start(name, work)
        except Exception as exc:  # noqa: BLE001 - the job's process could not start: one line, nothing left
            shutil.rmtree(work, ignore_errors=True)
            self._set(state="failed", message=f"The training could not start: {exc}")
            return fail(500, f"the training could not start: {type(exc).__name__}: {' '.join(str(exc).split())}")
        return JSONResponse({"started": name}, 202)

    async def _receive(self, request, path: Path, total: int) -> None:
        """The body into ``path``: ``total`` bytes, no more, no fewer."""
        from facesynth.io import is_disk_full

        got = 0
        try:
            with open(path, "wb") as f:
                async for chunk in request.stream():
                    got += len(chunk)
                    if got > total:
                        raise _UploadError(413, "the body is longer than its Content-Length")
                    f.write(chunk)
        except OSError as exc:
            if is_disk_full(exc):
                raise _UploadError(507, "the disk is full: free some space and train again") from None
            raise
        if got != total:
            raise _UploadError(400, f"the upload stopped after {got} of {total} bytes")


class _UploadError(Exception):
    def __init__(self, status: int, text: str):
        super().__init__(text)
        self.status = status


def create_studio_app(studio: Studio, port: int):
    """The studio's app on ``127.0.0.1:port``: its endpoints and its page, behind the server's checks."""
    from facesynth.web import server

    return server.create_app(port, routes=studio.routes(), app=server.Files(page_files()))


def run_studio(library: str | Path, port: int = 8000, ready=print, overrides=()) -> None:
    """Serve the studio until interrupted."""
    from facesynth.web import server

    studio = Studio(library, overrides)
    sock = server.listen(port)
    try:
        app = create_studio_app(studio, sock.getsockname()[1])
    except BaseException:
        sock.close()
        raise
    ready(f"http://{server.HOST}:{sock.getsockname()[1]}/")
    try:
        server.run(app, sock)
    finally:
        studio.close()
