"""Hydra entry point of the ONNX export (the same code as ``facesynth export``).

    python export/export.py run=outputs/RUN out=model.onnx [opset=18] [check=false] [components=40]
        [predicted_variance=0.999] [basis=int8|float32]
    python export/export.py run=outputs/RUN out=eri.onnx target=B.png target_landmarks=B.npy [variant=nu_rbf] [raw_ratios=true]

Keys and defaults: :class:`facesynth.onnx.config.ExportConfig`.
"""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a source checkout

from facesynth.errors import FacesynthError  # noqa: E402  (after the checkout is on the path)
from facesynth.io import install_sigterm_handler  # noqa: E402
from facesynth.onnx.cli import export_eri_model, export_model, summary_json  # noqa: E402
from facesynth.onnx.config import ExportConfig  # noqa: E402

ConfigStore.instance().store(name="export_schema", node=ExportConfig)


@hydra.main(version_base=None, config_path="conf", config_name="config")
def main(cfg: DictConfig) -> None:
    install_sigterm_handler()  # SIGTERM unwinds: the temporary .onnx is removed
    try:
        if cfg.target:
            summary = export_eri_model(cfg.run, cfg.out, cfg.target, cfg.target_landmarks, cfg.target_frame,
                                       cfg.variant, bool(cfg.raw_ratios), int(cfg.opset), bool(cfg.check))
        else:
            summary = export_model(cfg.run, cfg.out, int(cfg.opset), cfg.components, cfg.predicted_variance,
                                   check=bool(cfg.check), basis=str(cfg.basis))
        print(summary_json(summary))
    except FacesynthError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
