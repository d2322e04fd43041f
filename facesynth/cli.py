"""The ``facesynth`` command: one entry point, one subcommand per pipeline stage.

Each subcommand lives beside the code it drives, in a module that defines
``add_arguments(parser)`` and ``run(args) -> int``. Modules are imported only when
their subcommand runs, so ``facesynth app`` never imports torch and ``--help`` is fast.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from facesynth.errors import DiskFullError, FacesynthError
from facesynth.io import Terminated, install_sigterm_handler, is_disk_full
from facesynth.progress import set_json, set_quiet

# name -> (module, one-line help). Training first, then the rest in pipeline order.
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "train": ("facesynth.runs.train_cli", "train + evaluate a model: Hydra overrides (data=video data.path=DIR ...)"),
    "ingest": ("facesynth.data.ingest_cli", "detect faces and fit 68 landmarks in a video -> training folder"),
    "fit-model": ("facesynth.model.cli", "fit the shape/appearance face model on a sequence and print its figures"),
    "evaluate": ("facesynth.eval.cli", "re-evaluate a saved training run (PSNR under landmark noise, NCC)"),
    "transfer-expression": ("facesynth.eri.cli", "drive a target face with a driver's expressions via ratio images"),
    "transfer3d": ("facesynth.mesh.cli", "drive a 3D face mesh with head pose and expressions from landmarks"),
    "codec": ("facesynth.codec.cli", "encode/decode geometry videos with the PDP codec; RD sweeps"),
    "export": ("facesynth.onnx.cli", "export a trained run to one ONNX file"),
    "app": ("facesynth.runtime.app", "render a talking-head video from landmarks with ONNX Runtime"),
    "batch": ("facesynth.batch.cli", "many videos -> one trained, evaluated, exported subject each + summary (Ray)"),
    "serve": ("facesynth.web.serve_cli", "the live page: your webcam drives the avatar in a browser tab, on 127.0.0.1"),
    "studio": ("facesynth.web.studio_cli", "record, train and drive your own avatar in one local page, on 127.0.0.1"),
    "web": ("facesynth.web.build_cli", "web build MODEL OUT: the live page as a self-contained static folder; "
                                       "web setup: its browser packages (npm), once"),
}


TRAINING_HELP = """\
training (python train.py in a source checkout is the same app):
  facesynth train                                   train + evaluate on the built-in synthetic subject
  facesynth train data=video data.path=DIR          train on an ingest folder (facesynth ingest VIDEO --out DIR)
  facesynth train experiment=NAME ...               a named study (its overrides: facesynth/conf/experiment/)
  facesynth train --help                            every setting (regressor=krr|linear|poly2|mlp|svr, model=eri, ...)
  the run folder (runs/DATE_REGRESSOR) is what 'facesynth evaluate' and 'facesynth export' read"""


def _top_parser() -> argparse.ArgumentParser:
    lines = "\n".join(f"  {name:<21}{help_}" for name, (_, help_) in SUBCOMMANDS.items())
    p = argparse.ArgumentParser(
        prog="facesynth",
        description="facesynth: learning-based facial expression synthesis.\n\n"
                    "Typical use: facesynth ingest VIDEO --out DIR\n"
                    "             facesynth train data=video data.path=DIR      (training: see below)\n"
                    "             facesynth export RUN --out m.onnx\n"
                    "             facesynth app --model m.onnx --landmarks DIR --out o.mp4",
        epilog=f"{TRAINING_HELP}\n\nsubcommands:\n{lines}\n\nRun 'facesynth SUBCOMMAND --help' for each one's options.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("subcommand", nargs="?", choices=list(SUBCOMMANDS), metavar="SUBCOMMAND")
    p.add_argument("--version", action="store_true", help="print the version and exit")
    return p


QUIET_HELP = ("no progress bars, stage timings or info logs (results and errors are still printed); "
              "--no-progress is the same")
JSON_HELP = "print each result as one line of JSON (its full figures) instead of one line for people"


def _add_quiet(parser: argparse.ArgumentParser, default=False) -> None:
    """``--quiet`` (alias ``--no-progress``) and ``--json`` on a command and on each of its
    sub-actions (accepted before or after them): the same output switches on every command."""
    if "--quiet" not in parser._option_string_actions:
        parser.add_argument("--quiet", "--no-progress", dest="quiet", action="store_true", default=default,
                            help=QUIET_HELP)
    if "--json" not in parser._option_string_actions:
        parser.add_argument("--json", action="store_true", default=default, help=JSON_HELP)
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                _add_quiet(sub, argparse.SUPPRESS)  # SUPPRESS: do not reset a --quiet given before the action


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    top = _top_parser()
    if not argv or argv[0] not in SUBCOMMANDS:
        ns = top.parse_args(argv[:1] if argv else ["--help"])
        if ns.version:
            from facesynth import __version__

            print(__version__)
        return 0
    name, rest = argv[0], argv[1:]
    module_name, help_ = SUBCOMMANDS[name]
    if name == "train":  # Hydra parses its own arguments (overrides, --help, -m)
        from facesynth.runs.train_cli import main as train_main

        return train_main(rest)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.startswith("facesynth"):
            print(f"error: subcommand '{name}' is not available in this build", file=sys.stderr)
            return 2
        raise
    parser = argparse.ArgumentParser(prog=f"facesynth {name}", description=help_)
    module.add_arguments(parser)
    _add_quiet(parser)
    # A module with trailing positionals after options (e.g. Hydra overrides) opts in to intermixed parsing.
    parse = parser.parse_intermixed_args if getattr(module, "INTERMIXED_ARGS", False) else parser.parse_args
    args = parse(rest)
    install_sigterm_handler()  # SIGTERM unwinds: temporary outputs are removed
    set_quiet(bool(getattr(args, "quiet", False)))  # every call sets it: an earlier --quiet does not carry over
    set_json(bool(getattr(args, "json", False)))
    if getattr(args, "quiet", False):
        logging.getLogger().setLevel(logging.WARNING)
    try:
        return int(module.run(args) or 0)
    except FacesynthError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a full disk met outside io's writers (they raise DiskFullError themselves)
        if not is_disk_full(exc):
            raise
        print(f"error: {DiskFullError(exc.filename)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        logging.disable(logging.INFO)  # the last line: no library's exit-time info logs after it (torch's cache stats)
        return 130
    except Terminated as exc:
        print("terminated", file=sys.stderr)
        logging.disable(logging.INFO)
        return int(exc.code)
