"""facesynth's local web server: a Starlette app served by uvicorn on 127.0.0.1, behind one set of
checks that every page and endpoint of it shares (``facesynth serve`` today; a page that writes
mounts its endpoints on :func:`create_app` and gets the same checks).

The checks (:class:`LocalOnly`, a middleware around the whole app), for a server that any web page
the user visits can reach:

- the ``Host`` header must be ``127.0.0.1:PORT`` or ``localhost:PORT``: a foreign name that
  resolves to 127.0.0.1 (DNS rebinding) is refused (403);
- an ``Origin`` header, when sent, must be the server's own (403);
- a path with a NUL or another control character is refused (400) before any file lookup;
- every response carries ``X-Content-Type-Options: nosniff``, ``Cross-Origin-Resource-Policy:
  same-origin`` (no other site embeds its files), the COOP/COEP pair that WebAssembly threads need,
  and ``Cache-Control: no-store``; no ``Server`` header.

Files are served from a fixed table (:class:`Files`, the bytes in memory) or a folder
(:func:`folder_app`: Starlette's ``StaticFiles``, no directory listings, nothing outside the
folder, symlinks out of it refused). Each socket that stays idle for :data:`IDLE_S` seconds,
before its first request or between two, is closed.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import threading
from pathlib import Path

from facesynth.errors import FacesynthError

HOST = "127.0.0.1"
IDLE_S = 5.0  # seconds an idle connection is kept open
HEADERS = {"Cross-Origin-Opener-Policy": "same-origin", "Cross-Origin-Embedder-Policy": "require-corp",
           "Cross-Origin-Resource-Policy": "same-origin", "Cache-Control": "no-store",
           "X-Content-Type-Options": "nosniff"}
MEDIA_TYPES = {".html": "text/html", ".js": "text/javascript", ".mjs": "text/javascript", ".css": "text/css",
               ".json": "application/json", ".wasm": "application/wasm", ".onnx": "application/octet-stream",
               ".data": "application/octet-stream", ".png": "image/png", ".jpg": "image/jpeg", ".webm": "video/webm"}


def media_type(path: str | Path) -> str:
    """The Content-Type of a served file, by its suffix (the page's own types; others are bytes)."""
    return MEDIA_TYPES.get(Path(str(path)).suffix.lower(), "application/octet-stream")


def port_number(text: str) -> int:
    """argparse type of a ``--port``: an integer in 0..65535 (0: any free port)."""
    try:
        port = int(text)
    except ValueError:
        port = -1
    if not 0 <= port <= 65535:
        import argparse

        raise argparse.ArgumentTypeError(f"{text!r} is not a port (an integer from 0 to 65535; 0: any free one)")
    return port


def add_port(parser) -> None:
    """The ``--port`` option of each local server's command (``serve``, ``studio``)."""
    parser.add_argument("--port", type=port_number, default=8000, help="port on 127.0.0.1 (0: any free one; default 8000)")


def announce(after: str = ""):
    """The ``ready`` callback of a local server's command: one line saying where to open it."""

    def ready(url: str) -> None:
        print(f"open {url} (Ctrl-C stops){after}", flush=True)

    return ready


class LocalOnly:
    """ASGI middleware: the checks of this module's docstring, in front of ``app``, for a server
    listening on ``127.0.0.1:port``."""

    def __init__(self, app, port: int):
        self.app = app
        self.hosts = {f"127.0.0.1:{port}".encode(), f"localhost:{port}".encode()}
        self.origins = {b"http://" + h for h in self.hosts}
        self.headers = [(k.lower().encode(), v.encode()) for k, v in HEADERS.items()]

    def refusal(self, scope) -> tuple[int, str] | None:
        headers: dict[bytes, list[bytes]] = {}
        for k, v in scope["headers"]:
            headers.setdefault(k.lower(), []).append(v)
        host = headers.get(b"host", [])
        if len(host) != 1 or host[0].lower() not in self.hosts:
            return 403, "forbidden: this server answers only to 127.0.0.1 and localhost on its own port"
        origin = headers.get(b"origin")
        if origin is not None and (len(origin) != 1 or origin[0].lower() not in self.origins):
            return 403, "forbidden: a request from another origin"
        if any(ord(c) < 32 or c == "\x7f" for c in scope["path"]):
            return 400, "bad request: a control character in the path"
        return None

    async def __call__(self, scope, receive, send):
        if scope["type"] not in ("http", "websocket"):
            return await self.app(scope, receive, send)

        async def send_with_headers(message):
            if message["type"] == "http.response.start":
                keep = [(k, v) for k, v in message.get("headers", []) if k.lower() not in {h for h, _ in self.headers}]
                message = {**message, "headers": keep + self.headers}
            await send(message)

        problem = self.refusal(scope)
        if problem is not None:
            from starlette.responses import PlainTextResponse

            if scope["type"] == "websocket":
                await send({"type": "websocket.close", "code": 1008})
                return
            return await PlainTextResponse(problem[1], problem[0])(scope, receive, send_with_headers)
        await self.app(scope, receive, send_with_headers)


class Files:
    """ASGI app: GET/HEAD of a fixed table of files ``{relative path: bytes}`` ("a/b.js"); a path
    ending in "/" serves that folder's index.html; anything else is 404 (405 for other methods)."""

    def __init__(self, files: dict[str, bytes]):
        self.files = dict(files)

    @classmethod
    def of_folder(cls, folder: str | Path) -> "Files":
        """Every regular file under ``folder``, read into memory (symlinks are not followed)."""
        root = Path(folder)
        return cls({p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*"))
                    if p.is_file() and not p.is_symlink()})

    async def __call__(self, scope, receive, send):
        from starlette.responses import PlainTextResponse, Response

        path = scope["path"].lstrip("/")
        if path == "" or path.endswith("/"):
            path += "index.html"
        if scope["method"] not in ("GET", "HEAD"):
            response = PlainTextResponse("method not allowed", 405, headers={"Allow": "GET, HEAD"})
        elif path not in self.files:
            response = PlainTextResponse("not found", 404)
        else:
            response = Response(self.files[path], media_type=media_type(path))
        await response(scope, receive, send)


def folder_app(folder: str | Path):
    """ASGI app serving ``folder`` (Starlette's StaticFiles: index.html for "/", no listings, nothing
    outside the folder), with the page's media types."""
    from starlette.staticfiles import StaticFiles

    class _Static(StaticFiles):
        def file_response(self, full_path, *args, **kwargs):
            response = super().file_response(full_path, *args, **kwargs)
            response.headers["content-type"] = media_type(full_path) + (
                "; charset=utf-8" if media_type(full_path).startswith("text/") else "")
            return response

    return _Static(directory=str(folder), html=True)


def create_app(port: int, routes=(), app=None):
    """The Starlette app for a server on ``127.0.0.1:port``: ``routes`` (Starlette routes; e.g. a
    page's endpoints) and then ``app`` (an ASGI app for every other path, e.g. :class:`Files`),
    all behind :class:`LocalOnly`."""
    from starlette.applications import Starlette
    from starlette.middleware import Middleware
    from starlette.routing import Mount

    routes = list(routes) + ([Mount("/", app=app)] if app is not None else [])
    return Starlette(routes=routes, middleware=[Middleware(LocalOnly, port=port)])


def listen(port: int = 0) -> socket.socket:
    """A listening socket on 127.0.0.1:``port`` (0: a free one); FacesynthError when it cannot."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((HOST, port))
        sock.listen(128)
    except OSError as exc:
        sock.close()
        raise FacesynthError(f"cannot listen on {HOST}:{port} ({exc.strerror})") from None
    sock.set_inheritable(True)
    return sock


def _idle_protocol():
    """uvicorn's h11 protocol, with its keep-alive timer also started when a connection opens: a
    socket that never sends a request is closed after IDLE_S like one idle between requests."""
    from uvicorn.protocols.http.h11_impl import H11Protocol

    class IdleClosing(H11Protocol):
        def connection_made(self, transport: asyncio.Transport) -> None:
            super().connection_made(transport)
            self.timeout_keep_alive_task = self.loop.call_later(self.timeout_keep_alive, self.timeout_keep_alive_handler)

    return IdleClosing


def _server(app):
    import uvicorn

    config = uvicorn.Config(app, http=_idle_protocol(), ws="none", lifespan="off", loop="asyncio",
                            timeout_keep_alive=IDLE_S, server_header=False, access_log=False, log_config=None,
                            log_level="warning")
    return uvicorn.Server(config)


def run(app, sock: socket.socket) -> None:
    """Serve ``app`` on the listening ``sock`` until interrupted (Ctrl-C, SIGTERM)."""
    server = _server(app)
    try:
        server.run(sockets=[sock])
    finally:
        sock.close()


@contextlib.contextmanager
def running(app, sock: socket.socket):
    """Serve ``app`` on ``sock`` in a thread for the duration of the block; yields the base URL."""
    server = _server(app)
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    try:
        while not server.started:
            if not thread.is_alive():
                raise FacesynthError("the local server did not start")
            thread.join(0.01)
        yield f"http://{HOST}:{sock.getsockname()[1]}/"
    finally:
        server.should_exit = True
        thread.join(30)
        sock.close()
