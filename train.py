"""Train and evaluate a per-subject facesynth model (Hydra).

    python train.py                                   # synthetic subject, krr SADM (the default regressor)
    python train.py data=video data.path=DIR regressor=svr
    python train.py -m regressor=krr,linear,poly2,mlp,svr data=video data.path=DIR   # sweep + table
    python train.py model=eri data=video data.path=DIR                          # an ERI model instead

Ctrl-C prints "interrupted" and exits 130 (SIGTERM: "terminated", 143); bad input is one
line ``error: ...`` and exit 2, a run folder in use by another train.py too.
"""

import sys

INFO_FLAGS = ("-h", "--help", "--hydra-help", "-c", "--cfg", "-i", "--info", "-p", "--package", "-sc",
              "--shell-completion", "--version", "-cd", "--config-dir", "-cn", "--config-name")


def _first_line(argv: list[str]) -> None:
    """Say at once that training starts: importing torch and composing the config take seconds
    before the first stage prints (not for --help and the other informational flags, nor
    with quiet=true)."""
    quiet = any(a.lstrip("+~").split("=", 1)[0] == "quiet" and a.split("=", 1)[-1].lower() in ("true", "1", "yes")
                for a in argv)
    if not quiet and not any(a.split("=", 1)[0] in INFO_FLAGS for a in argv):
        print("[facesynth] train.py: starting (loading torch, composing the config)", file=sys.stderr, flush=True)


def _run() -> None:
    from pathlib import Path

    import hydra
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import DictConfig

    from facesynth.errors import FacesynthError
    from facesynth.io import install_sigterm_handler
    from facesynth.runs.config import register_configs
    from facesynth.runs.lock import discard_unused_run_dir
    from facesynth.runs.rundir import summary_lines
    from facesynth.runs.training import run_training

    register_configs()
    task_started = False  # set once Hydra has composed and validated the config

    @hydra.main(version_base="1.3", config_path="conf", config_name="config")
    def main(cfg: DictConfig) -> None:
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
        if "psnr_ref" in metrics:
            print("\n".join(summary_lines(metrics)))
        elif (Path(out_dir) / "eri_report.md").is_file():
            print((Path(out_dir) / "eri_report.md").read_text())
        print(f"run directory: {out_dir}")

    install_sigterm_handler()  # SIGTERM unwinds: temporary files are removed
    try:
        main()
    except SystemExit as exc:
        # Hydra prints a config error (unknown group option, typo, wrong type) and exits 1;
        # like every other bad input it is exit status 2
        if exc.code == 1 and not task_started:
            sys.exit(2)
        raise


if __name__ == "__main__":
    _first_line(sys.argv[1:])
    try:
        _run()
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)
