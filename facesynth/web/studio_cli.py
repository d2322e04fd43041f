"""``facesynth studio [--library DIR] [--port N]``: record, train and drive your own avatar in one
local page on 127.0.0.1 (docs/studio.md)."""

from __future__ import annotations

DEFAULT_LIBRARY = "facesynth-avatars"


def add_arguments(parser) -> None:
    from facesynth.web.server import port_number

    parser.add_argument("--library", default=DEFAULT_LIBRARY, metavar="DIR",
                        help=f"the folder of your avatars: each one's .onnx, training run and report.html "
                             f"(created; default ./{DEFAULT_LIBRARY})")
    parser.add_argument("--port", type=port_number, default=8000, help="port on 127.0.0.1 (0: any free one; default 8000)")


def run(args) -> int:
    from facesynth.web.studio import run_studio

    def ready(url: str) -> None:
        print(f"open {url} (Ctrl-C stops); avatars go to {args.library}/", flush=True)

    run_studio(args.library, args.port, ready=ready)
    return 0
