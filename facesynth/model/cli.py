"""``facesynth fit-model DATA --out DIR``: fit the face model alone and print its figures."""

from __future__ import annotations

import argparse
from dataclasses import fields
from pathlib import Path

from facesynth import progress
from facesynth.model.face_model import FaceModelConfig

_DEFAULT = {f.name: f.default for f in fields(FaceModelConfig)}  # the help texts quote the dataclass


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", help="a sequence (ingest folder, .pts folder, .npz) or 'synthetic'")
    p.add_argument("--out", type=Path, help="write the model artifact here")
    p.add_argument("--reference-width", type=int,
                   help="width in pixels of the reference (shape-free) frame the textures are sampled in "
                        f"(default {_DEFAULT['reference_width']})")
    p.add_argument("--shape-variance", type=float,
                   help=f"fraction of the landmark shape variance the shape PCA keeps (default {_DEFAULT['shape_variance']})")
    p.add_argument("--appearance-variance", type=float,
                   help=f"fraction of the texture variance the appearance PCA keeps (default {_DEFAULT['appearance_variance']})")
    p.add_argument("--grey", action="store_true", help="grey-level appearance (as in the paper)")
    p.add_argument("--train-fraction", type=float, default=0.75, help="fit on this leading fraction; report test figures on the rest")
    p.add_argument("--seed", type=int, default=0, help="seed of the synthetic subject (data 'synthetic'; default 0)")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from facesynth.data import load_sequence, temporal_split
    from facesynth.landmarks import get_scheme
    from facesynth.metrics import psnr
    from facesynth.model import FaceModel, save_face_model

    if args.data == "synthetic":
        from facesynth.data.synthetic import make_synthetic_sequence

        seq = make_synthetic_sequence(240, 256, seed=args.seed)
    else:
        seq = load_sequence(args.data)
        seq = seq.to_scheme(get_scheme(seq.scheme).base_scheme().name)  # ibug68+iris: the face model takes the 68 points
    tr, te = temporal_split(len(seq), args.train_fraction)
    given = {"shape_variance": args.shape_variance, "appearance_variance": args.appearance_variance,
             "reference_width": args.reference_width}
    cfg = FaceModelConfig(grey=args.grey, **{k: v for k, v in given.items() if v is not None})
    model, tex_tr = FaceModel.fit_with_textures(seq, cfg, rows=tr)
    tex_te = model.sample_textures(seq, te)
    recon = lambda t: np.clip(model.texture_from_params(model.appearance_params(t)), 0, 1) * 255  # noqa: E731
    al_te, _ = model.align(seq.landmarks[te])
    ref_px_per_unit = np.ptp(model.reference.points[:, 0]) / np.ptp(model.mean_shape[:, 0])
    shape_rec = model.shape_from_params(model.shape_params(seq.landmarks[te]))
    figures = {
        **{k: v for k, v in model.describe().items() if k != "config"},
        "train_frames": len(tr), "test_frames": len(te),
        "appearance_recon_psnr_train": psnr(recon(tex_tr), tex_tr * 255),
        "appearance_recon_psnr_test": psnr(recon(tex_te), tex_te * 255),
        # RMS landmark error of the shape PCA on test shapes, in reference-frame pixels
        "shape_recon_rms_test_ref_px": float(np.sqrt(((shape_rec - al_te) ** 2).sum(-1).mean()) * ref_px_per_unit),
        "fit_seconds": model.meta["fit_seconds"],
        "data_fingerprint": seq.fingerprint,
    }
    if args.out:
        save_face_model(model, args.out)
        figures["artifact"] = str(args.out)
    progress.result(f"face model: {figures.get('n_shape')} shape / {figures.get('n_appearance')} appearance "
                    f"components, appearance PSNR train {figures['appearance_recon_psnr_train']:.2f} / test "
                    f"{figures['appearance_recon_psnr_test']:.2f} dB, shape RMS test "
                    f"{figures['shape_recon_rms_test_ref_px']:.2f} px" + (f" -> {args.out}" if args.out else ""), figures)
    return 0
