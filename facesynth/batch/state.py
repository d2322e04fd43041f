"""A subject folder's layout, and whether each stage's outputs are complete and valid.

``DIR/<subject>/`` holds::

    data/            ``facesynth ingest`` output (landmarks.npy + meta.json; the ingest
                     replaces this folder as a whole, so it holds nothing else;
                     ``train.py data=video data.path=DIR/<subject>/data`` reads it)
    run/             train.py run layout (config.yaml, face_model/, sadm/, metrics.json, report.md, plots/)
    model.onnx       ``facesynth export`` of run/
    export.json      the export summary and the options it was made with
    subject.log      this subject's log (every run appends)
    result.json      the subject's summary row (status, failure reason, figures, times)

A stage is redone unless its outputs load and match what this run asks for: the video's
hash and the ingest options for the ingest files; the composed training config, the data
fingerprint and a loadable model for ``run/``; a loadable ONNX file whose metadata carries
the run's data fingerprint and regressor, made with the same export options, for
``model.onnx``. ``result.json`` is a record, never the proof that a stage is done.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from facesynth.provenance import file_sha256

DATA_DIR = "data"
RUN_DIR = "run"
MODEL_FILE = "model.onnx"
EXPORT_FILE = "export.json"
LOG_FILE = "subject.log"
RESULT_FILE = "result.json"

#: landmarker name -> how its ingest records the detector (meta.json landmarks.detector).
LANDMARKERS = {"dlib": "dlib "}


def _load_json(path: Path) -> dict:
    return json.loads(path.read_text())


def ingest_state(data_dir: Path, video: Path, every: int, max_frames: int | None, landmarker: str) -> tuple[bool, str]:
    """(complete, why not) for the ingest files in ``data_dir`` (the subject folder): landmarks.npy (T, 68, 2) float32 as meta.json
    describes it, ingested from this very video (SHA-256) with these options."""
    meta_path, lm_path = data_dir / "meta.json", data_dir / "landmarks.npy"
    if not meta_path.is_file() or not lm_path.is_file():
        return False, "not ingested yet"
    try:
        meta = _load_json(meta_path)
        lm = np.load(lm_path, allow_pickle=False, mmap_mode="r")
    except (OSError, ValueError) as exc:
        return False, f"unreadable ingest output ({exc})"
    lmeta = meta.get("landmarks", {})
    if lm.dtype != np.float32 or lm.ndim != 3 or lm.shape[1:] != (68, 2) or list(lm.shape) != lmeta.get("shape"):
        return False, f"landmarks.npy {lm.shape} {lm.dtype} does not match meta.json {lmeta.get('shape')}"
    if lmeta.get("every") != every or lmeta.get("max_frames") != max_frames:
        return False, f"ingested with every={lmeta.get('every')} max_frames={lmeta.get('max_frames')}"
    if not str(lmeta.get("detector", "")).startswith(LANDMARKERS[landmarker]):
        return False, f"ingested with another landmarker ({str(lmeta.get('detector'))[:40]}...)"
    if meta.get("video", {}).get("sha256") != file_sha256(video):
        return False, "the video changed since it was ingested"
    return True, ""


def train_state(run_dir: Path, config: dict, fingerprint: str) -> tuple[bool, str]:
    """(complete, why not) for ``run/``: metrics.json with held-out PSNR for this data
    fingerprint, config.yaml equal to the requested config, and a loadable model."""
    from omegaconf import OmegaConf

    from facesynth.errors import FacesynthError
    from facesynth.sadm.fit import load_sadm

    metrics_path, cfg_path = run_dir / "metrics.json", run_dir / "config.yaml"
    if not metrics_path.is_file() or not cfg_path.is_file():
        return False, "not trained yet"
    try:
        metrics = _load_json(metrics_path)
        saved = OmegaConf.to_container(OmegaConf.load(cfg_path), resolve=True)
    except (OSError, ValueError) as exc:
        return False, f"unreadable run output ({exc})"
    if "psnr_ref" not in metrics:
        return False, "metrics.json has no held-out PSNR"
    if metrics.get("data", {}).get("fingerprint") != fingerprint:
        return False, "trained on other data (fingerprint differs)"
    if saved != config:
        return False, "trained with another configuration"
    try:
        load_sadm(run_dir)
    except (FacesynthError, OSError, ValueError, KeyError, RuntimeError) as exc:
        return False, f"model does not load ({exc})"
    return True, ""


def export_state(model_path: Path, export_path: Path, options: dict, fingerprint: str, regressor: str) -> tuple[bool, str]:
    """(complete, why not) for ``model.onnx``: loads in ONNX Runtime, its metadata names
    this data fingerprint and regressor, and export.json records the same options."""
    from facesynth.errors import FacesynthError
    from facesynth.runtime.renderer import read_metadata

    if not model_path.is_file() or not export_path.is_file():
        return False, "not exported yet"
    try:
        record = _load_json(export_path)
        meta = read_metadata(model_path)
    except (OSError, ValueError, FacesynthError) as exc:
        return False, f"unreadable export ({exc})"
    if record.get("options") != options:
        return False, "exported with other options"
    if meta.get("data_fingerprint") != fingerprint or meta.get("regressor") != regressor:
        return False, "model.onnx was exported from another run"
    return True, ""
