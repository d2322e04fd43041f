"""``facesynth web build MODEL.onnx OUT/``: the live page as a self-contained static folder;
``facesynth web setup``: the page's browser packages (npm ci of its lockfile), once."""

from __future__ import annotations


def add_arguments(parser) -> None:
    sub = parser.add_subparsers(dest="action", required=True)
    b = sub.add_parser("build", help="write the page, onnxruntime-web, the tracker and the avatar into OUT/")
    b.add_argument("model", help="an avatar exported by 'facesynth export' (.onnx)")
    b.add_argument("out", help="folder to write (replaced as a whole); serve it over http(s) with "
                               "Cross-Origin-Opener-Policy same-origin and Cross-Origin-Embedder-Policy require-corp")
    sub.add_parser("setup", help="install the page's browser packages (onnxruntime-web) with npm ci from the page's "
                                 "lockfile: beside the page, or in the cache folder when that is read-only")


def run(args) -> int:
    from facesynth.web.site import build_site, setup_npm

    print(setup_npm() if args.action == "setup" else build_site(args.model, args.out))
    return 0
