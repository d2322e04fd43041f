"""Hydra entry point of the ONNX export (the same code and options as ``facesynth export``).

    python export/export.py run=outputs/RUN out=model.onnx [opset=18] [check=false] [components=40]
        [predicted_variance=0.999] [basis=int8|float32] [talking_head=true] [json=true]
    python export/export.py run=outputs/RUN out=eri.onnx target=B.png target_landmarks=B.npy [variant=nu_rbf] [raw_ratios=true]

Keys and defaults: :class:`facesynth.onnx.config.ExportConfig`, one declaration with
``facesynth export``'s options. Prints one line, or the summary as JSON with ``json=true``.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import hydra
from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, OmegaConf

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a source checkout, as train.py

from facesynth import progress  # noqa: E402  (after the checkout is on the path)
from facesynth.errors import FacesynthError  # noqa: E402
from facesynth.io import install_sigterm_handler  # noqa: E402
from facesynth.onnx.config import ExportConfig  # noqa: E402


@dataclass
class HydraExportConfig(ExportConfig):
    """ExportConfig plus the front end's output switch (``--json`` of ``facesynth export``)."""

    json: bool = False


ConfigStore.instance().store(name="export_schema", node=HydraExportConfig)


@hydra.main(version_base=None, config_path="conf", config_name="config")
def main(cfg: DictConfig) -> None:
    from facesynth.onnx.export import export, summary_line

    install_sigterm_handler()  # SIGTERM unwinds: the temporary .onnx is removed
    settings = OmegaConf.to_object(cfg)
    progress.set_json(settings.json)
    try:
        summary = export(ExportConfig(**{k: v for k, v in vars(settings).items() if k != "json"}))
        progress.result(summary_line(summary), summary)
    except FacesynthError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
