"""``facesynth serve MODEL.onnx [--port N]``: the live page for an avatar on 127.0.0.1."""

from __future__ import annotations


def add_arguments(parser) -> None:
    from facesynth.web.server import add_port

    parser.add_argument("model", help="an avatar exported by 'facesynth export' (.onnx)")
    add_port(parser)


def run(args) -> int:
    from facesynth.web.server import announce
    from facesynth.web.site import serve

    serve(args.model, args.port, ready=announce())
    return 0
