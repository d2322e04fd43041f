"""``facesynth web build MODEL.onnx OUT/``: the live page as a self-contained static folder;
``facesynth web setup``: the page's browser packages (npm ci of its lockfile), once."""

from __future__ import annotations


def add_arguments(parser) -> None:
    sub = parser.add_subparsers(dest="action", required=True)
    b = sub.add_parser("build", help="write the page, onnxruntime-web, the tracker and the avatar into OUT/")
    b.add_argument("model", help="an avatar exported by 'facesynth export' (.onnx)")
    b.add_argument("out", help="folder to write: a new or empty one, or one an earlier build wrote (replaced as a "
                               "whole; any other folder is refused); serve it over http(s) with "
                               "Cross-Origin-Opener-Policy same-origin and Cross-Origin-Embedder-Policy require-corp")
    sub.add_parser("setup", help="install the page's browser packages (onnxruntime-web) with npm ci from the page's "
                                 "lockfile: beside the page, or in the cache folder when that is read-only")


def run(args) -> int:
    from facesynth import progress
    from facesynth.runtime.talking_head import check_talking_head_file
    from facesynth.web.site import build_site, check_avatar, check_site_folder, ort_dist, setup_npm

    if args.action == "setup":
        where = setup_npm()
        progress.result(str(where), {"packages": str(where)})
        return 0
    check_site_folder(args.out, args.model)  # before any work: the user's files are never replaced
    check_avatar(args.model)  # a face model is named as such, with the export that makes its talking head
    ort_dist()
    check_talking_head_file(args.model)  # its graph against the contract, a first run on its own neutral
    site = build_site(args.model, args.out)
    progress.result(str(site), {"out": str(site)})
    return 0
