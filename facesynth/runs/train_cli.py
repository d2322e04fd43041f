"""``facesynth train`` and ``python train.py``: the Hydra app that trains and evaluates one model.

    facesynth train                                   # synthetic subject, krr SADM (the default regressor)
    facesynth train data=video data.path=DIR regressor=svr
    facesynth train experiment=rigid_features data=video data.path=DIR   # a named study (conf/experiment/)
    facesynth train -m regressor=krr,linear,poly2,mlp,svr data=video data.path=DIR   # sweep + table
    facesynth train model=eri data=video data.path=DIR                          # an ERI model instead
    facesynth train --json data=video data.path=DIR   # the result as one JSON line (run folder, headline figures)

The arguments are Hydra's (overrides, ``--help``, ``-m``, ``--cfg job``); the configs ship
inside the package (``facesynth/conf``). Ctrl-C prints "interrupted" and exits 130
(SIGTERM: "terminated", 143); bad input is one line ``error: ...`` and exit 2, a run folder
in use by another training run too.
"""

from __future__ import annotations

import sys

HEADLINE = ("psnr_ref", "psnr_frame", "psnr_frame_common", "lpips_frame_common", "sharpness_frame_common",
            "talking_head")  # metrics.json's figures that --json prints (all of them: the run's metrics.json)
INFO_FLAGS = ("-h", "--help", "--hydra-help", "-c", "--cfg", "-i", "--info", "-p", "--package", "-sc",
              "--shell-completion", "--version", "-cd", "--config-dir", "-cn", "--config-name")


def _first_line(argv: list[str], prog: str) -> None:
    """Say at once that training starts: importing torch and composing the config take seconds
    before the first stage prints (not for --help and the other informational flags, nor
    with quiet=true)."""
    quiet = any(a.lstrip("+~").split("=", 1)[0] == "quiet" and a.split("=", 1)[-1].lower() in ("true", "1", "yes")
                for a in argv)
    if not quiet and not any(a.split("=", 1)[0] in INFO_FLAGS for a in argv):
        print(f"[facesynth] {prog}: starting (loading torch, composing the config)", file=sys.stderr, flush=True)


def _hydra_app() -> None:
    """Run the Hydra app on ``sys.argv[1:]`` (Hydra reads them there)."""
    from pathlib import Path

    import hydra
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import DictConfig

    from facesynth import progress
    from facesynth.errors import FacesynthError
    from facesynth.eval.summary import summary_lines
    from facesynth.runs.config import CONF_DIR, register_configs
    from facesynth.runs.lock import discard_unused_run_dir
    from facesynth.runs.training import run_training

    register_configs()
    task_started = False  # set once Hydra has composed and validated the config

    @hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="config")
    def app(cfg: DictConfig) -> None:
        nonlocal task_started
        task_started = True
        out_dir = HydraConfig.get().runtime.output_dir
        try:
            metrics = run_training(cfg, out_dir)
        except FacesynthError as exc:
            print(f"error: {exc}", file=sys.stderr)
            # refused before anything was written: no run folder (only Hydra's own files were there)
            discard_unused_run_dir(out_dir, {".hydra", f"{HydraConfig.get().job.name}.log"})
            sys.exit(2)
        if progress.is_json():  # --json: the run's folder and its headline figures, one line
            progress.result("", {"run_dir": out_dir, **{k: metrics[k] for k in HEADLINE if k in metrics}})
            return
        if "psnr_ref" in metrics:
            print("\n".join(summary_lines(metrics)))
        elif (Path(out_dir) / "eri_report.md").is_file():
            print((Path(out_dir) / "eri_report.md").read_text())
        print(f"run directory: {out_dir}")

    try:
        app()
    except SystemExit as exc:
        # Hydra prints a config error (unknown group option, typo, wrong type) and exits 1;
        # like every other bad input it is exit status 2
        if exc.code == 1 and not task_started:
            sys.exit(2)
        raise


def main(argv: list[str], prog: str = "facesynth train") -> int:
    """Train with Hydra arguments ``argv``; the exit status (0, 2 bad input, 130 Ctrl-C, 143 SIGTERM)."""
    from facesynth import progress
    from facesynth.io import Terminated, install_sigterm_handler

    if "--json" in argv:  # ours, not Hydra's: the result as one JSON line (as every command's --json)
        argv = [a for a in argv if a != "--json"]
        progress.set_json(True)
    _first_line(argv, prog)
    saved = sys.argv
    sys.argv = [prog, *argv]
    install_sigterm_handler()  # SIGTERM unwinds: temporary files are removed
    try:
        _hydra_app()
    except Terminated as exc:
        print("terminated", file=sys.stderr)
        return int(exc.code)
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    finally:
        sys.argv = saved
    return 0
