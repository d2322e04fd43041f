"""``facesynth serve MODEL.onnx [--port N]``: the live page for an avatar on 127.0.0.1."""

from __future__ import annotations


def add_arguments(parser) -> None:
    from facesynth.web.server import port_number

    parser.add_argument("model", help="an avatar exported by 'facesynth export' (.onnx)")
    parser.add_argument("--port", type=port_number, default=8000, help="port on 127.0.0.1 (0: any free one; default 8000)")


def run(args) -> int:
    from facesynth.web.site import serve

    def ready(url: str) -> None:
        print(f"open {url} (Ctrl-C stops)", flush=True)

    serve(args.model, args.port, ready=ready)
    return 0


