"""The export API: one ONNX file from a training run, checked once with ONNX Runtime against
torch before it is renamed onto its name. :func:`export` takes an
:class:`~facesynth.onnx.config.ExportConfig` (what both front ends, ``facesynth export`` and
``export/export.py``, parse); :func:`export_model`, :func:`export_talking_head_model` and
:func:`export_eri_model` are its three kinds, each returning the export's summary (a dict).

* a run's SADM model (:mod:`facesynth.onnx.synthesis`): landmarks -> the rendered face;
* its whole talking head (:mod:`facesynth.onnx.talking_head`): driver landmarks and the
  driver's neutral -> the avatar's composited frame, checked on driver frames made from the
  avatar's own neutral;
* its ERI model for one target face (:mod:`facesynth.onnx.eri`; the target named as in
  ``transfer-expression``): MPEG-4 FAPs (B, 36) -> the target's rendered face.
"""

from __future__ import annotations

import logging
from pathlib import Path

from facesynth.contract import OPSET
from facesynth.errors import FacesynthError
from facesynth.io import atomic_path
from facesynth.onnx.config import DEFAULT_BASIS, DEFAULT_COMPONENTS, ExportConfig
from facesynth.progress import stage

log = logging.getLogger(__name__)


# opsets accepted by --opset: 18 is the tested default; torch's TorchScript exporter writes up
# to 20; the warp's custom symbolics (facesynth.ops) need ops of opset 17 or later
SUPPORTED_OPSETS = range(17, 21)


def check_args(out, opset: int, run_dir=None, inputs=()) -> None:
    """Refuse, before any work, an unsupported ``--opset``, an ``--out`` that cannot be written
    (a folder, a device, a name ending in ``/``: :func:`facesynth.io.check_writable`) or that
    is one of the inputs: a file of the run ``run_dir`` or of its training data
    (:func:`facesynth.rundir.input_files`), or one of ``inputs``."""
    from facesynth.io import check_writable, refuse_overwriting_inputs

    if opset not in SUPPORTED_OPSETS:
        raise FacesynthError(f"--opset: {opset} is not supported (choose {SUPPORTED_OPSETS.start}..{SUPPORTED_OPSETS.stop - 1})")
    check_writable(out)
    if run_dir is not None:
        from facesynth.rundir import input_files  # lazy: keeps --help fast (torch)

        inputs = [*input_files(run_dir), *inputs]
    refuse_overwriting_inputs([out], inputs)


def _run_scheme(run_dir) -> str:
    """The landmark scheme of a run's face model (its manifest): --landmarks are read in it
    (a 478-point folder is mapped for a 68-point model; 68 points for a 478-point one are an error)."""
    from pathlib import Path

    from facesynth.model.artifact import read_manifest

    return read_manifest(Path(run_dir) / "face_model")["landmark_scheme"]


def export(cfg: ExportConfig) -> dict:
    """The export ``cfg`` names (its ERI model with ``target``, its talking head with
    ``talking_head``, else its SADM model); returns the summary."""
    from facesynth.data import load_landmarks  # lazy, as below: keeps --help fast (no torch)

    # before reading --landmarks
    check_args(cfg.out, cfg.opset, cfg.run, [cfg.landmarks, cfg.target, cfg.target_landmarks])

    if cfg.target and cfg.talking_head:
        raise FacesynthError("--talking-head and --target: a talking head is exported from a run's SADM model, not its ERI one")
    if cfg.target:
        return export_eri_model(cfg.run, cfg.out, cfg.target, cfg.target_landmarks, cfg.target_frame,
                                cfg.variant, cfg.raw_ratios, cfg.opset, cfg.check)
    lm = load_landmarks(cfg.landmarks, scheme=_run_scheme(cfg.run)) if cfg.landmarks else None
    comps = DEFAULT_COMPONENTS if cfg.components is None else cfg.components
    kind = export_talking_head_model if cfg.talking_head else export_model
    return kind(cfg.run, cfg.out, cfg.opset, comps, cfg.predicted_variance, lm, cfg.check, cfg.basis)


def summary_line(summary: dict) -> str:
    """The export's result for a person: what was written, its size and its check."""
    kind = "ERI model" if "target" in summary else "talking head" if summary.get("talking_head") else "model"
    check = summary.get("max_abs_diff_vs_torch")
    checked = "not checked" if check is None else f"ONNX Runtime vs torch max |diff| {check:.3g}"
    return f"wrote {summary['out']} ({kind}, {summary['bytes'] / 1e6:.1f} MB, opset {summary['opset']}; {checked})"


def export_model(run_dir, out, opset: int = OPSET, components: int | None = DEFAULT_COMPONENTS,
                 predicted_variance: float | None = None, landmarks=None, check: bool = True,
                 basis: str = DEFAULT_BASIS) -> dict:
    """Export a run's landmark-driven synthesis model (``facesynth export`` and
    ``export/export.py``); returns the JSON summary (file, size, metadata, and the ONNX
    Runtime vs torch difference when ``check``)."""
    from facesynth.onnx.synthesis import check_export, export_run  # lazy: keeps --help fast (torch)
    from facesynth.rundir import is_eri_run

    check_args(out, opset, run_dir)
    run_dir = Path(run_dir)
    if is_eri_run(run_dir):
        raise FacesynthError(f"{run_dir}: holds an ERI model only; pass --target IMAGE_OR_DIR to export it for a target face")
    with atomic_path(out) as tmp:  # renamed onto --out only once the check has passed
        with stage("ONNX export"):
            _, syn, meta = export_run(run_dir, tmp, opset, components, predicted_variance, landmarks, basis)
        summary = {"out": str(out), "bytes": tmp.stat().st_size, **brief(meta), "opset": opset}
        if check:
            with stage("ONNX Runtime vs torch check"):
                summary["max_abs_diff_vs_torch"] = _checked(out, tmp, lambda p: check_export(syn, p), meta)
    log.info("exported %s (%s regressor, %.1f MB)", out, meta.get("regressor"), summary["bytes"] / 1e6)
    return summary


def export_talking_head_model(run_dir, out, opset: int = OPSET, components: int | None = DEFAULT_COMPONENTS,
                              predicted_variance: float | None = None, landmarks=None, check: bool = True,
                              basis: str = DEFAULT_BASIS) -> dict:
    """Export a run's talking head (``facesynth export RUN --talking-head``): the synthesizer
    as :func:`export_model` compresses it, in one graph with the retargeting, the full-frame
    warp and the seam; returns the JSON summary (the ONNX Runtime vs torch difference, 0-255,
    when ``check``)."""
    from facesynth.onnx.synthesis import prepare_run  # lazy: keeps --help fast (torch)
    from facesynth.onnx.talking_head import check_talking_head, export_talking_head
    from facesynth.rundir import is_eri_run, read_config

    check_args(out, opset, run_dir)
    run_dir = Path(run_dir)
    if is_eri_run(run_dir):
        raise FacesynthError(f"{run_dir}: holds an ERI model only; a talking head needs a SADM run")
    read_config(run_dir, "the avatar's neutral and frame come from the run's data")  # named before any work
    with atomic_path(out) as tmp:
        with stage("ONNX export (talking head)"):
            syn, meta = prepare_run(run_dir, components, predicted_variance, landmarks, basis)
            if "avatar_neutral" not in meta or "background_jpeg" not in meta:
                raise FacesynthError(f"{run_dir}: the run's data gives no avatar neutral and frame (its video is needed)")
            export_talking_head(syn, meta, tmp, opset=opset)
        summary = {"out": str(out), "bytes": tmp.stat().st_size, **brief(meta), "opset": opset, "talking_head": True}
        if check:
            with stage("ONNX Runtime vs torch check"):
                summary["max_abs_diff_vs_torch"] = _checked(out, tmp, lambda p: check_talking_head(syn, meta, p), meta)
    log.info("exported %s (talking head, %s regressor, %.1f MB)", out, meta.get("regressor"), summary["bytes"] / 1e6)
    return summary


def brief(meta: dict) -> dict:
    """The metadata for the summary: the avatar's bulky entries (its neutral
    landmarks, shape PCA, neutral frame as base64 JPEG: tens of kB) are stored in the model
    but only described here."""
    out = {k: v for k, v in meta.items() if k not in ("avatar_neutral", "shape_pca", "background_jpeg", "coverage_recording")}
    if "shape_pca" in meta:
        out["shape_pca_components"] = len(meta["shape_pca"]["limit"])
    if "background_jpeg" in meta:
        out["background_jpeg_chars"] = len(meta["background_jpeg"])
    if "coverage_recording" in meta:
        out["coverage_recording_frames"] = len(meta["coverage_recording"]["z"])
    return out


def export_eri_model(run_dir, out, target, target_landmarks=None, target_frame: int | None = None,
                     variant: str | None = None, raw_ratios: bool = False, opset: int = OPSET, check: bool = True) -> dict:
    """Export a run's ERI model for one target face (named as in ``transfer-expression``);
    returns the JSON summary, as :func:`export_model`."""
    from facesynth.eri.target import load_target  # lazy: keeps --help fast (torch)
    from facesynth.onnx.eri import check_eri_export, export_eri_run

    check_args(out, opset, run_dir, [target, target_landmarks])
    image, landmarks, desc = load_target(target, target_landmarks, target_frame)
    with atomic_path(out) as tmp:  # renamed onto --out only once the check has passed
        with stage("ONNX export (ERI)"):
            _, syn, meta = export_eri_run(run_dir, tmp, image, landmarks, variant, raw_ratios, opset)
        summary = {"out": str(out), "bytes": tmp.stat().st_size, "target": desc, **meta, "opset": opset}
        if check:
            with stage("ONNX Runtime vs torch check"):
                summary["max_abs_diff_vs_torch"] = _checked(out, tmp, lambda p: check_eri_export(syn, p), meta)
    log.info("exported %s (ERI, %.1f MB)", out, summary["bytes"] / 1e6)
    return summary


def _checked(out, tmp: Path, check, meta: dict) -> float:
    """``check(tmp)``: the written file against torch. A failure names ``out`` (which is then
    not written) and the cause where it can be found: with an int8 basis, whether this CPU's
    integer matmul is exact on the file's own codes; and the ``--basis float32`` way out."""
    try:
        return check(tmp)
    except FacesynthError as exc:
        detail = str(exc).split(": ", 1)[-1]
        if meta.get("appearance_basis") != "int8":
            raise FacesynthError(f"{out}: not written: {detail}") from None
        from facesynth.onnx.int8check import matmul_errors, matmul_integer_codes

        wrong, worst = matmul_errors(matmul_integer_codes(tmp))
        cause = (f"this CPU's int8 matmul (ONNX Runtime's MatMulInteger) is wrong in {wrong} outputs by up to {worst} "
                 "on the file's own codes" if wrong else "the int8 matmul is exact on this CPU, so the difference "
                 "lies elsewhere in the graph")
        raise FacesynthError(f"{out}: not written: {detail}; {cause}; export with --basis float32 to leave "
                             "the int8 basis out") from None
