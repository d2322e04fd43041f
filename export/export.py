"""Hydra entry point of the ONNX export (the same code as ``facesynth export``).

    python export/export.py run=outputs/RUN out=model.onnx [opset=18] [check=false] [components=40] [predicted_variance=0.999]
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
    from facesynth.export_onnx import check_export, export_run

    try:
        if cfg.get("target"):
            summary = export_eri(cfg)
            print(json.dumps(summary))
            return
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


def export_eri(cfg: DictConfig) -> dict:
    """The run's ERI model for the target face named by ``cfg.target`` (as ``facesynth export --target``)."""
    from types import SimpleNamespace

    from facesynth.eri.cli import _target
    from facesynth.eri.export import check_eri_export, export_eri_run

    args = SimpleNamespace(target=str(cfg.target), target_landmarks=cfg.get("target_landmarks"),
                           target_frame=cfg.get("target_frame"))
    image, landmarks, desc = _target(args)
    path, syn, meta = export_eri_run(cfg.run, cfg.out, image, landmarks, cfg.get("variant"), bool(cfg.get("raw_ratios")),
                                     int(cfg.opset))
    summary = {"out": str(path), "bytes": path.stat().st_size, "target": desc, **meta, "opset": int(cfg.opset)}
    if cfg.check:
        summary["max_abs_diff_vs_torch"] = check_eri_export(syn, path)
    return summary


if __name__ == "__main__":
    main()
