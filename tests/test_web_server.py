"""The local web server (facesynth.web.server; ``facesynth serve``) as a foreign web page or a
careless user would meet it: a foreign Host (DNS rebinding) or Origin is refused, NUL bytes and
traversal get a 4xx without a traceback, no directory listings, the headers, idle sockets are
closed, bad ports are one argparse error, and nothing is left on disk by a killed server."""

from __future__ import annotations

import logging
import os
import select
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from facesynth.cli import main
from facesynth.web import server, site


@pytest.fixture
def folder(tmp_path):
    root = tmp_path / "site"
    (root / "ort").mkdir(parents=True)
    (root / "models").mkdir()
    (root / "index.html").write_text("<title>facesynth live</title>")
    (root / "avatar.onnx").write_bytes(b"AVATAR" * 100)
    (root / "ort" / "a.wasm").write_bytes(b"\0asm")
    (root / "models" / "m.onnx").write_bytes(b"model")
    (tmp_path / "secret.txt").write_text("secret")
    (root / "link.txt").symlink_to(tmp_path / "secret.txt")  # a symlink out of the folder
    return root


@pytest.fixture(params=["folder", "memory"])
def url(request, folder):
    """The folder served from disk (browser.served, the tests' server) and from memory (``serve``'s)."""
    sock = server.listen(0)
    app = server.folder_app(folder) if request.param == "folder" else server.Files.of_folder(folder)
    with server.running(server.create_app(sock.getsockname()[1], app=app), sock) as u:
        yield u


def _raw(url: str, request: bytes) -> tuple[int, dict, bytes]:
    """Send ``request`` as is; (status, headers with lower-case names, body)."""
    host, port = url.split("/")[2].split(":")
    with socket.create_connection((host, int(port)), timeout=10) as s:
        s.sendall(request)
        data = b""
        while chunk := s.recv(65536):
            data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = {}
    for line in lines[1:]:
        k, _, v = line.partition(":")
        headers[k.strip().lower()] = v.strip()
    return int(lines[0].split()[1]), headers, body


def _get(url: str, path: str, host: str | None = None, extra: str = "") -> tuple[int, dict, bytes]:
    host = host if host is not None else url.split("/")[2]
    return _raw(url, f"GET {path} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n{extra}\r\n".encode("latin-1"))


def test_headers_and_types(url):
    for path, mime in (("/ort/a.wasm", "application/wasm"), ("/", "text/html")):
        status, h, _ = _get(url, path)
        assert status == 200 and h["content-type"].split(";")[0] == mime
        assert h["x-content-type-options"] == "nosniff"
        assert h["cross-origin-opener-policy"] == "same-origin" and h["cross-origin-embedder-policy"] == "require-corp"
        assert h["cross-origin-resource-policy"] == "same-origin" and h["cache-control"] == "no-store"
        assert "server" not in h
    status, h, _ = _get(url, "/missing")  # error responses carry them too
    assert status == 404 and h["x-content-type-options"] == "nosniff" and "server" not in h


def test_foreign_host_and_origin_are_refused(url):
    port = url.split(":")[2].rstrip("/")
    for host in (f"127.0.0.1:{port}", f"localhost:{port}", f"LOCALHOST:{port}"):
        status, _, body = _get(url, "/avatar.onnx", host=host)
        assert status == 200 and body.startswith(b"AVATAR"), host
    for host in ("attacker.example", f"attacker.example:{port}", "127.0.0.1", f"127.0.0.1:{int(port) + 1}",
                 f"localhost.attacker.example:{port}", f"127.0.0.1:{port}.attacker.example", ""):
        status, _, body = _get(url, "/avatar.onnx", host=host)
        assert status in (400, 403) and b"AVATAR" not in body, host
    # two Host headers, and none (HTTP/1.0)
    status, _, body = _get(url, "/avatar.onnx", extra="Host: attacker.example\r\n")
    assert status in (400, 403) and b"AVATAR" not in body
    status, _, body = _raw(url, b"GET /avatar.onnx HTTP/1.0\r\n\r\n")
    assert status in (400, 403) and b"AVATAR" not in body
    own = url.rstrip("/")
    for origin, ok in ((own, True), (own.replace("127.0.0.1", "localhost"), True), ("http://attacker.example", False),
                       ("null", False), (own.replace("http", "https"), False), (own + "0", False)):
        status, _, body = _get(url, "/avatar.onnx", extra=f"Origin: {origin}\r\n")
        assert (status == 200) == ok and (b"AVATAR" in body) == ok, origin


def test_nul_traversal_listings_and_methods_are_4xx_without_traceback(url, caplog, capfd):
    caplog.set_level(logging.DEBUG)
    for path in ("/%00", "/index.html%00", "/index.html%00.js", "/ort/%00/../a.wasm", "/%0a", "/a%1fb", "/%7f"):
        status, _, _ = _get(url, path)
        assert status == 400, path
    status, _, _ = _raw(url, b"GET /\x00 HTTP/1.1\r\nHost: x\r\n\r\n")  # a raw NUL: the HTTP parser's 400
    assert status == 400
    traversal = ["/../secret.txt", "/..%2fsecret.txt", "/%2e%2e/secret.txt", "/%2e%2e%2fsecret.txt", "/ort/../../secret.txt",
                 "/ort/..%2f..%2fsecret.txt", "/ort/%2e%2e/%2e%2e/secret.txt", "/..\\secret.txt", "/..%5csecret.txt",
                 "//secret.txt", "/./../secret.txt", "/ort/./../../secret.txt", "/%252e%252e/secret.txt",
                 "/.%2e/secret.txt", "/link.txt", "/%2fetc%2fpasswd", "//etc/passwd", "/../../../../etc/passwd",
                 "/ort/../../../../../etc/passwd"]
    for path in traversal:
        status, _, body = _get(url, path)
        assert 400 <= status < 500 and b"secret" not in body and b"root:" not in body, path
    for path in ("/ort/", "/models/", "/ort", "/models"):  # folders without index.html: no listing
        status, _, body = _get(url, path)
        assert status == 404 and b"a.wasm" not in body and b"m.onnx" not in body, path
    status, h, _ = _raw(url, f"POST /avatar.onnx HTTP/1.1\r\nHost: {url.split('/')[2]}\r\nContent-Length: 0\r\n"
                             "Connection: close\r\n\r\n".encode())
    assert status == 405
    out = capfd.readouterr()
    assert "Traceback" not in caplog.text + out.err + out.out


def test_port_out_of_range_is_one_argparse_error(tmp_path, capsys):
    for port in ("-1", "65536", "70000", "eighty"):
        with pytest.raises(SystemExit) as exc:
            main(["serve", str(tmp_path / "a.onnx"), "--port", port])
        assert exc.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1].startswith("facesynth serve: error: argument --port:") and f"'{port}' is not a port" in err[-1], err
        assert not [line for line in err if "Traceback" in line or "Error:" in line]


def test_port_in_use_is_one_line(tmp_path, capsys, monkeypatch):
    from test_web_site import _site_avatar

    model = _site_avatar(tmp_path)  # a real talking head: serve checks it before it listens
    taken = server.listen(0)
    try:
        assert main(["serve", str(model), "--port", str(taken.getsockname()[1])]) == 2
    finally:
        taken.close()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot listen on 127.0.0.1:" in err[0], err


def _threads_fds(pid: int) -> tuple[int, int]:
    return len(os.listdir(f"/proc/{pid}/task")), len(os.listdir(f"/proc/{pid}/fd"))


def _idle_sockets_closed(url: str, pid: int, n: int = 400) -> dict:
    """Open ``n`` idle sockets; the server's threads and fds while they are open, and after it has
    closed them all (polled, with a bound)."""
    host, port = url.split("/")[2].split(":")
    before = _threads_fds(pid)
    socks = [socket.create_connection((host, int(port)), timeout=10) for _ in range(n)]
    try:
        t0 = time.monotonic()
        opened = _threads_fds(pid)
        deadline = t0 + 10 * server.IDLE_S
        open_ = set(socks)
        while open_ and time.monotonic() < deadline:  # poll: each socket reads EOF when the server closes it
            ready, _, _ = select.select(list(open_)[:500], [], [], 1.0)
            for s in ready:
                if s.recv(1) == b"":
                    open_.discard(s)
        closed_s = time.monotonic() - t0
        closed = _threads_fds(pid)
    finally:
        for s in socks:
            s.close()
    return {"before": before, "opened": opened, "closed": closed, "still_open": len(open_), "closed_after_s": closed_s}


def test_idle_sockets_are_closed(url):
    """400 idle sockets: no thread each, and the server closes them all (in this process, a thread's server)."""
    got = _idle_sockets_closed(url, os.getpid())
    assert got["still_open"] == 0, got
    assert max(got["opened"][0], got["closed"][0]) <= got["before"][0] + 2, got  # no thread per socket


def _serve(model: Path, tmp: Path, cache: Path):
    env = {**os.environ, "XDG_CACHE_HOME": str(cache), "TMPDIR": str(tmp)}
    proc = subprocess.Popen([sys.executable, "-m", "facesynth", "serve", str(model), "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    line = proc.stdout.readline()
    if not line.startswith("open http://127.0.0.1:"):
        proc.kill()
        raise AssertionError(line + proc.stderr.read())
    return proc, line.split()[1]


def _listening(port: int) -> list[str]:
    """Local addresses (hex, as /proc/net/tcp* gives them) listening on ``port``."""
    out = []
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        if not Path(table).exists():
            continue
        for row in Path(table).read_text().splitlines()[1:]:
            f = row.split()
            addr, p = f[1].split(":")
            if int(p, 16) == port and f[3] == "0A":
                out.append(addr)
    return out


@pytest.mark.slow
def test_serve_process(tmp_path):
    """``facesynth serve`` itself: bound to 127.0.0.1 only; a foreign Host, NUL bytes and listings
    refused with nothing on its terminal; 400 idle sockets closed with its threads and fds back
    to where they were; stale build folders of dead processes removed, and a SIGKILL leaves none."""
    from test_web_site import _site_avatar

    model = _site_avatar(tmp_path)
    tmp, cache = tmp_path / "tmp", tmp_path / "cache"
    tmp.mkdir()
    dead = subprocess.Popen(["true"])
    dead.wait()
    stale, alive = tmp / f"facesynth-web-{dead.pid}-x1", tmp / f"facesynth-web-{os.getpid()}-x2"
    for d in (stale, alive):
        (d / "site").mkdir(parents=True)
    proc, url = _serve(model, tmp, cache)
    try:
        port = int(url.split(":")[2].rstrip("/"))
        assert _listening(port) == ["0100007F"]  # 127.0.0.1, nothing else
        assert not stale.exists() and alive.exists()
        assert sorted(p.name for p in tmp.glob("facesynth-web-*")) == [alive.name]  # its own build folder is gone already
        status, _, body = _get(url, "/avatar.onnx.data", host="attacker.example")
        assert status == 403 and len(body) < 200
        status, _, body = _get(url, "/avatar.onnx.data")
        split = tmp_path / "split"
        split.mkdir()
        site.split_avatar(model, split)
        assert status == 200 and body == (split / "avatar.onnx.data").read_bytes()  # the avatar's weights
        for path in ("/%00", "/avatar.onnx%00", "/ort/", "/models/", "/../site.json"):
            assert 400 <= _get(url, path)[0] < 500, path
        got = _idle_sockets_closed(url, proc.pid)
        assert got["still_open"] == 0, got
        assert max(got["opened"][0], got["closed"][0]) <= got["before"][0] + 2, got
        end = time.monotonic() + 30
        while _threads_fds(proc.pid)[1] > got["before"][1] + 4 and time.monotonic() < end:
            select.select([], [], [], 0.1)  # the server's fds of the closed sockets go as it sees them closed
        assert _threads_fds(proc.pid)[1] <= got["before"][1] + 4, (got, _threads_fds(proc.pid))  # not one per socket
    finally:
        proc.kill()  # SIGKILL: nothing to clean up after it
        proc.wait(timeout=30)
    err = proc.stderr.read()
    assert not [line for line in err.splitlines() if "Traceback" in line or "uvicorn" in line or "Error" in line], err
    assert sorted(p.name for p in tmp.glob("facesynth-web-*")) == [alive.name]
