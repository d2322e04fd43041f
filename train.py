"""Train and evaluate a per-subject facesynth model (Hydra).

    python train.py                                   # synthetic subject, linear SADM
    python train.py data=video data.path=DIR regressor=svr
    python train.py -m regressor=linear,poly2,mlp,svr data=video data.path=DIR   # sweep + table
"""

import logging
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from facesynth.config import register_configs
from facesynth.errors import FacesynthError

register_configs()
log = logging.getLogger("train")


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig) -> None:
    from facesynth.pipeline import run_training, summary_lines

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
    main()
