"""Train and evaluate a per-subject facesynth model (Hydra).

    python train.py                                   # synthetic subject, krr SADM (the default regressor)
    python train.py data=video data.path=DIR regressor=svr
    python train.py -m regressor=krr,linear,poly2,mlp,svr data=video data.path=DIR   # sweep + table
    python train.py model=eri data=video data.path=DIR                          # an ERI model instead
"""

import logging
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from facesynth.errors import FacesynthError
from facesynth.io import install_sigterm_handler
from facesynth.runs.config import register_configs
from facesynth.runs.rundir import summary_lines
from facesynth.runs.training import run_training

register_configs()
log = logging.getLogger("train")
_task_started = False  # set once Hydra has composed and validated the config


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig) -> None:
    global _task_started
    _task_started = True
    install_sigterm_handler()  # SIGTERM unwinds: temporary files are removed
    out_dir = HydraConfig.get().runtime.output_dir
    try:
        metrics = run_training(cfg, out_dir)
    except FacesynthError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    if "psnr_ref" in metrics:
        print("\n".join(summary_lines(metrics)))
    elif (Path(out_dir) / "eri_report.md").is_file():
        print((Path(out_dir) / "eri_report.md").read_text())
    print(f"run directory: {out_dir}")


if __name__ == "__main__":
    try:
        main()
    except SystemExit as exc:
        # Hydra prints a config error (unknown group option, typo, wrong type) and exits 1;
        # like every other bad input it is exit status 2
        if exc.code == 1 and not _task_started:
            sys.exit(2)
        raise
