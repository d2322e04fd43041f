"""``facesynth studio [--library DIR] [--port N]``: record, train and drive your own avatar in one
local page on 127.0.0.1 (docs/studio.md)."""

from __future__ import annotations

DEFAULT_LIBRARY = "facesynth-avatars"


def add_arguments(parser) -> None:
    from facesynth.web.server import add_port

    parser.add_argument("--library", default=DEFAULT_LIBRARY, metavar="DIR",
                        help=f"the folder of your avatars: each one's .onnx, training run and report.html "
                             f"(created; default ./{DEFAULT_LIBRARY})")
    add_port(parser)


def run(args) -> int:
    from facesynth.web.server import announce
    from facesynth.web.studio import run_studio

    run_studio(args.library, args.port, ready=announce(f"; avatars go to {args.library}/"))
    return 0
