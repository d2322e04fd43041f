"""Hydra entry point of the ONNX export (the same code as ``facesynth export``).

    python export/export.py run=outputs/RUN out=model.onnx [opset=18] [check=false]
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
    from facesynth.export_onnx import check_export, export_synthesizer, load_synthesizer

    try:
        syn, meta = load_synthesizer(cfg.run)
        path = export_synthesizer(syn, cfg.out, meta, int(cfg.opset))
        summary = {"out": str(path), "bytes": path.stat().st_size, **meta, "opset": int(cfg.opset)}
        if cfg.check:
            summary["max_abs_diff_vs_torch"] = check_export(syn, path)
    except FacesynthError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
