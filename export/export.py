"""Hydra entry point of the ONNX export (the same code as ``facesynth export``).

    python export/export.py run=outputs/RUN out=model.onnx [opset=18] [check=false] [components=40] [predicted_variance=0.999] [basis=int8|float32]
    python export/export.py run=outputs/RUN out=eri.onnx target=B.png target_landmarks=B.npy [variant=nu_rbf] [raw_ratios=true]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a source checkout


@hydra.main(version_base=None, config_path="conf", config_name="config")
def main(cfg: DictConfig) -> None:
    from facesynth.errors import FacesynthError
    from facesynth.runtime.export_cli import export_eri_model, export_model

    try:
        if cfg.get("target"):
            summary = export_eri_model(cfg.run, cfg.out, cfg.target, cfg.get("target_landmarks"), cfg.get("target_frame"),
                                       cfg.get("variant"), bool(cfg.get("raw_ratios")), int(cfg.opset), bool(cfg.check))
        else:
            comps = None if cfg.components is None else int(cfg.components)
            q = None if cfg.predicted_variance is None else float(cfg.predicted_variance)
            summary = export_model(cfg.run, cfg.out, int(cfg.opset), comps, q, check=bool(cfg.check),
                                   basis=str(cfg.get("basis", "int8")))
    except FacesynthError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
