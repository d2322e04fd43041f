"""The settings of an export, with their defaults and help: one declaration that both front
ends read (``facesynth export``'s argparse options, :func:`add_arguments`, and the Hydra entry
point ``export/export.py``, :class:`ExportConfig` as its schema). Torch-free, so that
``facesynth export --help`` stays fast."""

from __future__ import annotations

import argparse
from dataclasses import MISSING as NO_DEFAULT
from dataclasses import dataclass, field, fields
from typing import Optional

from omegaconf import MISSING

from facesynth.contract import OPSET
from facesynth.eri.config import SVR_VARIANTS

DEFAULT_COMPONENTS = 40  # appearance components kept at export (docs/runtime.md has the measurements)
BASIS_KINDS = ("int8", "float32")
DEFAULT_BASIS = "int8"  # the exported appearance basis (facesynth.sadm.quantize; docs/runtime.md)
ERI_GROUP = "ERI model (exported when --target is given)"


def _option(default, help: str, **argparse_kw):
    """A field of :class:`ExportConfig`: its default, its help, and what argparse needs besides
    (``choices``, ``metavar``, ``type`` where the default does not show it, ``group``)."""
    return field(default=default, metadata={"help": help, **argparse_kw})


@dataclass
class ExportConfig:
    """One export: of a run's SADM model (the default), its whole talking head
    (``talking_head``) or its ERI model for a target face (``target``). Each field's help is
    its ``facesynth export`` option's help (``metadata["help"]``)."""

    run: str = _option(MISSING, "training run directory (face_model/ and sadm/regressor.*; or eri/ with --target)",
                       positional=True)
    out: str = _option(MISSING, "output .onnx file (written atomically)")
    opset: int = _option(OPSET, f"ONNX opset (default {OPSET})")
    check: bool = _option(True, "skip the ONNX Runtime vs torch check")
    components: Optional[int] = _option(
        DEFAULT_COMPONENTS, "appearance components kept: those of largest predicted variance over the training "
        f"landmarks, the rest folded into the mean (default {DEFAULT_COMPONENTS}; 0 = all, no compression)", type=int)
    predicted_variance: Optional[float] = _option(
        None, "instead of --components: keep the fewest components holding this fraction of the predicted variance",
        type=float)
    basis: str = _option(DEFAULT_BASIS, f"appearance basis storage (default {DEFAULT_BASIS}): int8 is 4x smaller, an "
                         "integer matmul, its PSNR against float32 measured and recorded; or float32",
                         choices=list(BASIS_KINDS))
    landmarks: Optional[str] = _option(
        None, "training landmarks (.npy (N, P, 2), run's scheme) for the compression (default: reloaded from "
        "RUN/config.yaml)")
    talking_head: bool = _option(
        False, "export the whole talking head: driver landmarks + driver neutral -> the avatar's frame, its head "
        "warped with the face (run it with 'facesynth app --model' or 'facesynth serve')")
    target: Optional[str] = _option(None, "target neutral face: an image, or a folder in ingest layout (its neutral "
                                    "frame is used)", metavar="IMAGE_OR_DIR", group=ERI_GROUP)
    target_landmarks: Optional[str] = _option(
        None, "landmarks of the target image (.npy (68, 2)/(N, 68, 2) or .pts)", metavar="L", group=ERI_GROUP)
    target_frame: Optional[int] = _option(None, "row of the target folder / landmarks used as neutral", type=int,
                                          metavar="ROW", group=ERI_GROUP)
    variant: Optional[str] = _option(None, "SVR variant (default: the model's)", choices=list(SVR_VARIANTS),
                                     group=ERI_GROUP)
    raw_ratios: bool = _option(False, "no edge confidence / brightening cap (as transfer-expression)", group=ERI_GROUP)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``facesynth export``'s options, one per :class:`ExportConfig` field: ``run`` positional,
    a field without a default required, a True boolean as ``--no-NAME``, a False one as a flag."""
    groups: dict[str, argparse._ActionsContainer] = {}
    for f in fields(ExportConfig):
        meta = dict(f.metadata)
        where = p if "group" not in meta else groups.setdefault(meta["group"], p.add_argument_group(meta["group"]))
        meta.pop("group", None)
        if meta.pop("positional", False):
            where.add_argument(f.name, **meta)
            continue
        flag = "--" + f.name.replace("_", "-")
        required = f.default is MISSING or f.default is NO_DEFAULT
        if f.default is True:
            where.add_argument(f"--no-{flag[2:]}", dest=f.name, action="store_false", **meta)
        elif f.default is False:
            where.add_argument(flag, action="store_true", **meta)
        elif required:
            where.add_argument(flag, required=True, **meta)
        else:
            meta.setdefault("type", type(f.default) if f.default is not None else str)
            where.add_argument(flag, default=f.default, **meta)


def from_args(args: argparse.Namespace) -> ExportConfig:
    """The :class:`ExportConfig` that parsed ``facesynth export`` options name."""
    return ExportConfig(**{f.name: getattr(args, f.name) for f in fields(ExportConfig)})
