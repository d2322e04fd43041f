"""Hydra entry point of the ONNX export (the same code as ``facesynth export``).

    python export/export.py run=outputs/RUN out=model.onnx [opset=18] [check=false] [components=40] [predicted_variance=0.999]
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
    from facesynth.export_onnx import check_export, export_run

    try:
        comps = None if cfg.components is None else int(cfg.components)
        q = None if cfg.predicted_variance is None else float(cfg.predicted_variance)
        path, syn, meta = export_run(cfg.run, cfg.out, int(cfg.opset), comps, q)
        summary = {"out": str(path), "bytes": path.stat().st_size, **meta, "opset": int(cfg.opset)}
        if cfg.check:
            summary["max_abs_diff_vs_torch"] = check_export(syn, path)
    except FacesynthError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
