"""Does the studio's coverage meter predict held-out quality? For each shared clip: MediaPipe's 478
points (``facesynth ingest --landmarker mediapipe``), split as training splits it (the first
75 % trains: the "recording"), the recording thinned to the frames the page keeps (at most
``KEEP_FPS`` a second, the page's rule); and the clip's trained default run (``--runs``, only
read), evaluated per frame (:func:`evaluate_per_frame`: every held-out frame and
up to :data:`RUN_FRAMES` training frames rendered, pasted into the real frame and compared over the
common region: PSNR, face and mouth LPIPS).

``per_frame``, within each clip: each held-out frame's distance to the recording as the meter
measures it (``coverage.distance``, its reach before clipping: ``reach = 1 - distance / REACH``)
against that frame's PSNR and LPIPS. Spearman's correlation per clip (signed so that positive
is the right way: nearer frames render better), then over the clips its median, a 95 %
bootstrap interval of the median (clips resampled 2000 times, seed 0), the clips with a
positive correlation and the two-sided sign test's p. Comparing frames of one clip removes each
clip's own difficulty (lighting, texture, camera). The other readings: the same with the time
after the recording held fixed (partial Spearman: later frames are farther in shape and in
lighting alike); two baselines, time alone and the distance from the recording's median (how
unusual a frame is rather than how far from the nearest recorded ones); two variants of the
distance, the 10 nearest frames instead of :data:`~facesynth.coverage.NEAREST`, and the
68-point shape (MediaPipe's iBUG-68 view, Procrustes-aligned to the recording) instead of the
8 features; and the dlib 68 points the model is trained on, aligned alike (not known to the
page); and the live page's reach readout (:func:`live_readout`, 1 - the reach shown).

``clips`` and ``correlations``, across clips: readings of the recording (``self_reach``, the
page's headline, with blocks of 1 s, 0.5 s and 2 s and of an eighth of the recording; ``prior``,
the mean of the 13 prompt bars, each bar in ``directions``; ``spread``, the mean distance from the mean shape; ``heldout``,
the reach of the real held-out frames, not known while recording; ``readout``, the mean of the
live page's reach readout over them, :func:`live_readout`) against the held-out
PSNR and face LPIPS (means over the held-out frames) and the generalisation gap (held-out mean
minus the mean over the run's training frames, same measure; and the training frames' own PSNR), with Spearman's and Pearson's
correlation, a 95 % bootstrap interval of Spearman's and its range leaving one clip out.
Prints ONE JSON line.

    python -m bench.studies.coverage_heldout --runs DIR [--ingested DIR] [--evaluated DIR]

``--runs``: one default training run per clip, ``DIR/CLIP`` or ``DIR/CLIP__*`` (``facesynth train
data=video data.path=.../faces/CLIP``); ``--ingested``: MediaPipe ingest folders ``DIR/CLIP`` to
reuse (made when missing); ``--evaluated``: per-frame evaluations ``DIR/CLIP.npz`` to reuse
(made when missing, about a minute a clip).
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np

from bench.harness import emit, host

RUN_FRAMES = 100  # training frames evaluated per run (evenly spaced): the training-level figure
N_BOOT = 2000


def correlations(x: list[float], y: list[float], rng: np.random.Generator, n_boot: int = N_BOOT) -> dict:
    from scipy.stats import pearsonr, spearmanr

    x, y = np.asarray(x), np.asarray(y)
    boot = []
    for _ in range(n_boot):
        i = rng.integers(0, len(x), len(x))
        if np.ptp(x[i]) > 0 and np.ptp(y[i]) > 0:
            boot.append(spearmanr(x[i], y[i])[0])
    loo = [spearmanr(np.delete(x, i), np.delete(y, i))[0] for i in range(len(x))]
    return {"spearman": round(float(spearmanr(x, y)[0]), 3), "pearson": round(float(pearsonr(x, y)[0]), 3),
            "spearman_95": [round(float(v), 2) for v in np.percentile(boot, [2.5, 97.5])],
            "spearman_leave_one_out": [round(float(min(loo)), 2), round(float(max(loo)), 2)]}


def partial_spearman(x: np.ndarray, y: np.ndarray, t: np.ndarray) -> float:
    """Spearman's correlation of ``x`` and ``y`` with ``t`` held fixed: the Pearson correlation
    of their ranks' residuals after a least-squares line on the ranks of ``t``."""
    from scipy.stats import rankdata

    rt = np.stack([rankdata(t), np.ones(len(t))], 1)
    res = [r - rt @ np.linalg.lstsq(rt, r, rcond=None)[0] for r in (rankdata(x), rankdata(y))]
    return float(np.corrcoef(*res)[0, 1])


def within_clips(per_clip: dict[str, float], rng: np.random.Generator, n_boot: int = N_BOOT) -> dict:
    """Per-clip correlations -> their median, a 95 % bootstrap interval of the median (clips
    resampled), how many are positive and the two-sided sign test's p (clips with no
    correlation, NaN, left out)."""
    from scipy.stats import binomtest

    v = np.array([r for r in per_clip.values() if np.isfinite(r)])
    boot = [np.median(v[rng.integers(0, len(v), len(v))]) for _ in range(n_boot)]
    pos = int((v > 0).sum())
    return {"median": round(float(np.median(v)), 3), "median_95": [round(float(b), 2) for b in np.percentile(boot, [2.5, 97.5])],
            "positive": pos, "clips": len(v), "sign_p": round(float(binomtest(pos, len(v)).pvalue), 4),
            "per_clip": {k: round(float(r), 3) for k, r in per_clip.items()}}


def run_dir(runs: Path, clip: str) -> Path:
    """The trained run of ``clip`` in ``runs``: a folder ``CLIP`` or the one ``CLIP__*``."""
    found = [p for p in [runs / clip, *sorted(runs.glob(f"{clip}__*"))] if (p / "config.yaml").is_file()]
    if len(found) != 1:
        raise SystemExit(f"{runs}: expected one run folder {clip} or {clip}__*, found {len(found)}")
    return found[0]


def evaluate_per_frame(run: Path, out: Path) -> None:
    """Per-frame figures of a trained run (the run folder is only read): the held-out frames
    (every one) and up to :data:`RUN_FRAMES` evenly spaced training frames, each rendered, pasted into
    its real frame and compared over the common region (``psnr_frame_common``'s measure, and
    its face and mouth LPIPS), rows sadm and oracle, written to ``out`` (.npz, by video frame)."""
    from facesynth.eval.common_region import common_landmarks
    from facesynth.eval.frame_level import subset
    from facesynth.eval.sadm_eval import EvalConfig, evaluate_sadm
    from facesynth.rundir import read_config, run_data
    from facesynth.sadm.fit import load_sadm

    sadm, cfg = load_sadm(run), read_config(run)
    seq, tr, te = run_data(cfg)
    common = common_landmarks(seq)
    ecfg = EvalConfig(noise=[0.0], train_level=False, max_test_frames=0, talking_head=False, flicker_frames=0)
    arrays = {}
    for part, rows in (("test", te), ("train", tr[subset(len(tr), RUN_FRAMES)])):
        _, ex = evaluate_sadm(sadm, seq, tr, rows, ecfg, int(cfg.seed), common=common)
        pf = ex["per_frame"]
        arrays[f"{part}_frame"] = np.asarray(pf["frame"])[pf["frame_index"]]
        for row in ("sadm", "oracle"):
            arrays[f"{part}_psnr_{row}"] = pf["psnr_frame_common"][row]
            for reg in ("face", "mouth"):
                arrays[f"{part}_lpips_{reg}_{row}"] = pf["lpips_frame_common"][reg][row]
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(out, **arrays)


def shape_distance(recording: np.ndarray, frames: np.ndarray, nearest: int) -> np.ndarray:
    """(T, K, 2) recorded and (S, K, 2) other shapes -> (S,): each shape's mean distance to its
    ``nearest`` nearest recorded ones, all similarity-aligned to the recording's Procrustes mean."""
    from facesynth.geometry import apply_affine, generalised_procrustes, similarity_fit

    rec, mean = generalised_procrustes(recording)
    q = apply_affine(np.asarray(frames, np.float64), similarity_fit(np.asarray(frames, np.float64), mean[None]))
    d = np.linalg.norm(q.reshape(len(q), 1, -1) - rec.reshape(1, len(rec), -1), axis=-1)
    return np.sort(d, 1)[:, :nearest].mean(1)


def frame_readings(lm: np.ndarray, dlib: np.ndarray, rec: np.ndarray, frames: np.ndarray, fps: float) -> dict[str, np.ndarray]:
    """Per held-out frame (video frames ``frames``), distances to the recording (video frames
    ``rec``): larger is farther, i.e. expected worse. ``lm``: the clip's MediaPipe points,
    ``dlib``: its dlib 68 points."""
    from facesynth.coverage import SCALE, distance, features
    from facesynth.landmarks import get_scheme

    z = features(lm) / np.asarray(SCALE)
    mp68 = np.einsum("kp,tpc->tkc", get_scheme("mediapipe478").ibug68_matrix(), lm.astype(np.float64))
    dlib = np.asarray(dlib, np.float64)
    d10 = np.sort(np.linalg.norm(z[frames][:, None] - z[rec][None], axis=-1), 1)[:, :10].mean(1)
    return {"meter": distance(z[rec], z[frames]), "time": (frames - rec.max()) / fps,
            "from_median": np.linalg.norm(z[frames] - np.median(z[rec], 0), axis=1), "meter_10_nearest": d10,
            "shape_68": shape_distance(mp68[rec], mp68[frames], 3), "dlib_68": shape_distance(dlib[rec], dlib[frames], 3)}


def live_readout(lm: np.ndarray, train: np.ndarray, frames: np.ndarray, fps: float) -> tuple[dict[str, np.ndarray], float]:
    """The live page's reach readout on each held-out frame (video frames ``frames``), as a 478-point
    avatar of the clip's training frames ``train`` would show it: the recording its export writes
    (:func:`facesynth.coverage.recording_entry`: kept at KEEP_FPS, z from the avatar's neutral,
    ``select_neutral`` over the training frames, rounded as the metadata rounds it) reaching each
    frame from the driver's neutral (:func:`~facesynth.coverage.driver_reach`). ``readout``: that
    neutral as the page captures it, ``select_neutral`` over the first second of the held-out frames;
    ``readout_avatar_neutral``: the avatar's own neutral (the neutral cancels: the meter's reach).
    And how far the first neutral is from the avatar's (the norm of their z difference)."""
    from facesynth.coverage import SCALE, driver_reach, features, recording_entry
    from facesynth.neutral import select_neutral

    lm = np.asarray(lm, np.float64)
    neutral = np.round(lm[train][select_neutral(lm[train])[0]], 3)
    entry = recording_entry(lm[train], neutral, train / fps)
    first = lm[np.sort(frames)[:round(fps)]]
    driver_neutral = first[select_neutral(first)[0]]
    offset = (features(driver_neutral[None]) - features(neutral[None]))[0] / np.asarray(SCALE)
    return {"readout": driver_reach(entry, lm[frames], driver_neutral),
            "readout_avatar_neutral": driver_reach(entry, lm[frames], neutral)}, float(np.linalg.norm(offset))


def per_frame_study(data: dict, rng: np.random.Generator) -> dict:
    """``data``: {clip: (readings, targets)}, each {name: (S,) per held-out frame} -> {reading:
    {target: :func:`within_clips`}}; targets signed so that larger is better, readings so that
    larger is worse (the correlation is of minus the reading)."""
    from scipy.stats import spearmanr

    clips = list(data)
    readings = [*data[clips[0]][0], "meter_time_fixed"]
    out = {}
    for name in readings:
        out[name] = {}
        for t in data[clips[0]][1]:
            per = {}
            for c in clips:
                rd, tg = data[c]
                ok = np.isfinite(tg[t])
                if name == "meter_time_fixed":
                    per[c] = partial_spearman(-rd["meter"][ok], tg[t][ok], rd["time"][ok])
                else:
                    per[c] = float(spearmanr(-rd[name][ok], tg[t][ok])[0])
            out[name][t] = within_clips(per, rng)
    return out


def main() -> None:
    import argparse

    from facesynth.coverage import KEEP_FPS, SCALE, coverage, features, heldout_coverage, kept, self_reach
    from facesynth.data import temporal_split
    from facesynth.data.ingest import ingest_video
    from facesynth.data.shared import shared_data_dir

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", required=True, help="a folder of trained default runs, DIR/CLIP or DIR/CLIP__* (only read)")
    p.add_argument("--ingested", help="a folder of mediapipe ingest folders, one per clip (made when missing)")
    p.add_argument("--evaluated", help="a folder of per-frame evaluations CLIP.npz (made when missing)")
    a = p.parse_args()
    runs = Path(a.runs)
    faces = shared_data_dir() / "faces"
    clips = sorted(c.name for c in faces.iterdir() if (c / "video.mp4").is_file())
    found = {c: run_dir(runs, c) for c in clips if any(runs.glob(f"{c}__*")) or (runs / c).is_dir()}
    if len(found) < 3:
        raise SystemExit(f"{runs}: runs of {len(found)} shared clips found, the study needs at least 3")
    clips = sorted(found)
    out, frames_data = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        where, evaluated = Path(a.ingested or tmp), Path(a.evaluated or tmp)
        for clip in clips:
            if not (where / clip / "landmarks.npy").is_file():
                ingest_video(faces / clip / "video.mp4", where / clip, landmarker="mediapipe")
            if not (evaluated / f"{clip}.npz").is_file():
                evaluate_per_frame(found[clip], evaluated / f"{clip}.npz")
            ev = dict(np.load(evaluated / f"{clip}.npz"))
            lm = np.load(where / clip / "landmarks.npy")  # (T, 478, 2), every frame with a face on these clips
            fps = json.loads((where / clip / "meta.json").read_text())["video"]["fps"]
            tr, te = temporal_split(len(lm))
            if not np.array_equal(np.sort(ev["test_frame"]), te):
                raise SystemExit(f"{found[clip]}: its held-out frames are not the last 25 % of {clip}'s {len(lm)} frames")
            rec = tr[kept(np.arange(len(tr)) / fps)]
            c = coverage([{"id": "recording", "directions": [], "points": list(lm[rec])}])
            f = features(lm[rec])
            z = f / np.asarray(SCALE)
            psnr_te, psnr_tr = float(ev["test_psnr_sadm"].mean()), float(ev["train_psnr_sadm"].mean())
            lp_te, lp_tr = float(np.nanmean(ev["test_lpips_face_sadm"])), float(np.nanmean(ev["train_lpips_face_sadm"]))
            out[clip] = {"run": str(found[clip]), "frames_kept": len(rec), "heldout_frames": len(te),
                         "self_reach": round(c["self_reach"], 3), "self_reach_0.5s": round(self_reach(f, KEEP_FPS // 2), 3),
                         "self_reach_2s": round(self_reach(f, 2 * KEEP_FPS), 3),
                         "self_reach_eighths": round(self_reach(f, -(-len(rec) // 8)), 3), "prior": round(c["overall"], 3),
                         "spread": round(float(np.linalg.norm(z - z.mean(0), axis=1).mean()), 3),
                         "heldout": round(heldout_coverage(lm[tr], lm[te]), 3),
                         "psnr": round(psnr_te, 2), "psnr_train": round(psnr_tr, 2), "psnr_gap": round(psnr_te - psnr_tr, 2),
                         "lpips_face": round(lp_te, 4), "lpips_face_gap": round(lp_te - lp_tr, 4),
                         "directions": {k: round(v, 2) for k, v in c["directions"].items()}}
            dlib = np.load(faces / clip / "landmarks.npy")
            targets = {"psnr": ev["test_psnr_sadm"], "lpips_face": -ev["test_lpips_face_sadm"],
                       "lpips_mouth": -ev["test_lpips_mouth_sadm"], "psnr_over_oracle": ev["test_psnr_sadm"] - ev["test_psnr_oracle"]}
            readings = frame_readings(lm, dlib, rec, ev["test_frame"], fps)
            live, out[clip]["readout_neutral_offset"] = live_readout(lm, tr, ev["test_frame"], fps)
            for name, r in live.items():
                readings[name] = 1.0 - r  # larger is worse, as the other readings
                out[clip][name] = round(float(r.mean()), 3)
            out[clip]["readout_neutral_offset"] = round(out[clip]["readout_neutral_offset"], 2)
            frames_data[clip] = (readings, targets)
    rng = np.random.default_rng(0)
    corr = {m: {t: correlations([out[k][m] for k in clips], [out[k][t] for k in clips], rng)
                for t in ("psnr", "psnr_gap", "psnr_train", "lpips_face", "lpips_face_gap")}
            for m in ("self_reach", "self_reach_0.5s", "self_reach_2s", "self_reach_eighths", "prior", "spread", "heldout",
                      "readout", "readout_avatar_neutral")}
    emit({"bench": "coverage_heldout", **host(), "n": len(clips), "keep_fps": KEEP_FPS, "run_frames": RUN_FRAMES,
          "per_frame": per_frame_study(frames_data, rng), "clips": out, "correlations": corr})


if __name__ == "__main__":
    main()
