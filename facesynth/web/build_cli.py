"""``facesynth web build MODEL.onnx OUT/``: the live page as a self-contained static folder."""

from __future__ import annotations


def add_arguments(parser) -> None:
    sub = parser.add_subparsers(dest="action", required=True)
    b = sub.add_parser("build", help="write the page, onnxruntime-web, the tracker and the avatar into OUT/")
    b.add_argument("model", help="an avatar exported by 'facesynth export' (.onnx)")
    b.add_argument("out", help="folder to write (replaced as a whole); serve it over http(s) with "
                               "Cross-Origin-Opener-Policy same-origin and Cross-Origin-Embedder-Policy require-corp")


def run(args) -> int:
    from facesynth.web.site import build_site

    print(build_site(args.model, args.out))
    return 0
