"""Issue 16: help on every option, --quiet, the report (every plot written, report.html
self-contained), frame-level evaluation equal to pasting into whole frames, the shared
neutral-frame rule, the ERI driver rule and the compact ERI artifact."""

import argparse
import base64
import importlib
import re
from html.parser import HTMLParser

import numpy as np
import pytest

from facesynth.cli import SUBCOMMANDS, _add_quiet, main
from facesynth.compositing import composite
from facesynth.data import temporal_split
from facesynth.data.synthetic import make_synthetic_sequence
from facesynth.eval.frame_level import frame_level, subset
from facesynth.eval.report import below_mean, write_plots, write_report
from facesynth.eval.sadm_eval import EvalConfig, _key, _predict, evaluate_sadm, noisy_landmarks
from facesynth.model import FaceModel, FaceModelConfig
from facesynth.sadm.fit import SADMConfig, fit_sadm


def _options_without_help(parser, name, out):
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            for sub_name, sub in a.choices.items():
                _options_without_help(sub, f"{name} {sub_name}", out)
        elif not isinstance(a, argparse._HelpAction) and not a.help:
            out.append(f"{name} {a.option_strings or a.dest}")


def test_every_option_of_every_subcommand_has_help_and_quiet():
    missing = []
    for name, (module, _) in SUBCOMMANDS.items():
        if name == "train":
            continue  # Hydra parses its arguments (--help lists the config; quiet=true is its --quiet)
        try:
            mod = importlib.import_module(module)
        except ModuleNotFoundError:
            continue
        p = argparse.ArgumentParser()
        mod.add_arguments(p)
        _add_quiet(p)
        _options_without_help(p, name, missing)
        assert "--quiet" in p._option_string_actions
    assert missing == []


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    seq = make_synthetic_sequence(48, 192, seed=1)
    tr, te = temporal_split(len(seq), 0.75)
    model, tex = FaceModel.fit_with_textures(seq, FaceModelConfig(), rows=tr, progress=False)
    sadm = fit_sadm(model, seq, tr, tex, "linear", {"ridge": 1.0}, SADMConfig())
    return seq, tr, te, sadm


def test_report_writes_every_plot_and_a_self_contained_html(run, tmp_path):
    seq, tr, te, sadm = run
    metrics, extras = evaluate_sadm(sadm, seq, tr, te, EvalConfig(noise=[0, 2], max_test_frames=5))
    assert metrics["frame_level_frames"] == {"evaluated": 5, "test_frames": len(te), "max_test_frames": 5,
                                             "spacing": "evenly spaced"}
    plots = write_plots(metrics, extras, tmp_path / "plots")
    assert set(plots) == {"psnr_vs_noise.png", "psnr_over_time.png", "test_grid.png", "error_map.png", "ncc.png",
                          "motion_strip.png"}
    strip = extras["strip"]  # consecutive held-out frames, one frame box: every tile the same size
    assert len(strip) == min(8, len(te)) and len({t["real"].shape for t in strip} | {t["synth"].shape for t in strip}) == 1
    assert np.diff([t["frame"] for t in strip]).min() >= 1 and all(t["frame"] in te for t in strip)
    doc = write_report(metrics, tmp_path, plots, worst_frames=extras["worst_frames"])
    html = (tmp_path / "report.html").read_text()
    md = (tmp_path / "report.md").read_text()
    for p in plots:
        data = (tmp_path / "plots" / p).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n"
        assert base64.b64encode(data).decode() in html  # inlined, no link to the file
        assert f"(plots/{p})" in md
    assert len(re.findall(r"<img ", html)) == len(plots) == len(doc.images)
    for row in ("sadm", "mean_texture", "oracle", "rewarp", "s0..s3", "ncc"):
        assert row in html and row in md  # the legend
    assert "src='plots/" not in html
    assert "Weak regions" in md and ("WARNING" in md) == bool(below_mean(metrics))


class _FirstScreen(HTMLParser):
    """The report's body up to its first <details>: tags, list items, images and headings."""

    def __init__(self):
        super().__init__()
        self.done, self.tags, self.items, self.images, self.headings, self._text = False, [], [], [], [], None
        self.details = self.summaries = 0

    def handle_starttag(self, tag, attrs):
        self.details += tag == "details"
        self.summaries += tag == "summary"
        self.done = self.done or tag == "details"
        if self.done:
            return
        self.tags.append(tag)
        if tag == "img":
            self.images.append(dict(attrs)["src"])
        if tag in ("li", "h2"):
            self._text = [tag, ""]

    def handle_data(self, data):
        if self._text is not None and not self.done:
            self._text[1] += data

    def handle_endtag(self, tag):
        if self._text is not None and tag == self._text[0]:
            (self.items if tag == "li" else self.headings).append(self._text[1])
            self._text = None


def test_report_first_screen_holds_the_verdicts_the_strip_and_the_weak_regions(run, tmp_path):
    """Before the first <details>: one verdict line per measure with the figures of
    metrics.json, the real | rendered strip, and the weak regions; every table is below,
    inside a collapsible section."""
    seq, tr, te, sadm = run
    metrics, extras = evaluate_sadm(sadm, seq, tr, te, EvalConfig(noise=[0, 2], max_test_frames=5))
    plots = write_plots(metrics, extras, tmp_path / "plots")
    head = {"frames": 7, "neutral_row": 3, **{r: {"psnr_head_db": 20.0 + i, "ssim_head": 0.5, "psnr_frame_db": 25.0,
                                                  "ssim_frame": 0.8} for i, r in enumerate(("static", "warp", "full"))}}
    for with_head in (False, True):
        lp = {"face": {"sadm": 0.1234, "oracle": 0.0456}, "eyes": {"sadm": 0.2346, "oracle": 0.1}}
        m = {**metrics, "talking_head": head, "lpips_frame_common": lp} if with_head else metrics
        write_report(m, tmp_path, plots, worst_frames=extras["worst_frames"])
        page = _FirstScreen()
        page.feed((tmp_path / "report.html").read_text())
        assert "table" not in page.tags and page.details >= 4 and page.details == page.summaries
        verdicts = "\n".join(page.items)
        for key, where in (("psnr_frame", "original frame"), ("psnr_ref", "reference frame")):
            s, mean, oracle = (m[key][r]["0"] for r in ("sadm", "mean_texture", "oracle"))
            line = next(x for x in page.items if x.startswith(f"Held-out PSNR ({where}"))
            assert f"{s:.2f} dB, {s - mean:+.2f} dB over the mean texture ({mean:.2f}), " \
                   f"{oracle - s:.2f} dB below the oracle ({oracle:.2f})" in line
            assert ("NOT LEARNED" in line) == (s <= mean)
        if "lpips_frame_common" in m:
            assert all(f"{reg} {v['sadm']:.3f}" in verdicts for reg, v in m["lpips_frame_common"].items())
            assert "face 0.123, eyes 0.235; on the face, the oracle's 0.046." in verdicts
        else:
            assert "Perceptual distance (LPIPS): not measured" in verdicts
        sharp = m.get("sharpness_frame_common")
        assert (f"Sharpness (rendered / real gradient energy, 1 = as detailed as the real frame): "
                f"{(sharp.get('whole') or next(iter(sharp.values())))['sadm']:.2f}" if sharp else
                "Sharpness: not measured") in verdicts
        if with_head:
            assert "Talking head, driving itself on 7 held-out frames: head PSNR 22.00 dB, SSIM 0.500, better than its " \
                   "still neutral frame (20.00 dB) and +1.00 dB over the warp alone (21.00)." in verdicts
        else:
            assert "Talking head: not measured" in verdicts
        strip = base64.b64encode((tmp_path / "plots" / "motion_strip.png").read_bytes()).decode()
        assert page.images == [f"data:image/png;base64,{strip}"]
        assert page.headings == ["Weak regions"]
        weak = page.items[page.items.index(next(x for x in page.items if x.startswith(("No face part", "WARNING")))):]
        for flag in below_mean(m):
            assert any(flag in x for x in weak)
        table = {p: v for p, v in (m.get("psnr_frame_common_regions") or m["psnr_ref_regions"]).items() if p != "whole"}
        listed = next(x for x in weak if x.startswith("Face parts, weakest first"))
        gains = sorted((v["sadm"]["0"] - v["mean_texture"]["0"], p.replace("_", " ")) for p, v in table.items())
        assert len(gains) >= 2
        positions = [listed.index(f"{name} ") for _, name in gains]
        assert positions == sorted(positions)  # weakest first
        assert f"Worst test frames (reference-frame PSNR, sigma 0): {', '.join(map(str, extras['worst_frames']))}." in weak


def test_frame_level_equals_pasting_into_the_whole_frame(run):
    """The region-of-interest paste gives the same squared errors as compositing each
    rendering into the whole frame (the reference computation)."""
    seq, tr, te, sadm = run
    model, syn = sadm.model, sadm.synthesizer()
    cfg = EvalConfig(noise=[0, 1.5], max_test_frames=4, batch_size=3)
    keys = [_key(s) for s in cfg.noise]
    tex_te = model.sample_textures(seq, te)
    oracle = np.clip(model.texture_from_params(model.appearance_params(tex_te)), 0, 1)
    pooled, per_frame, _ = frame_level(model, lambda lm: _predict(syn, lm, 8), seq, te, tex_te, oracle, cfg, 0, keys,
                                       noisy_landmarks)
    pick = subset(len(te), cfg.max_test_frames)
    lm = seq.landmarks[te[pick]]
    mean = np.ascontiguousarray(np.broadcast_to(np.clip(model.appearance_pca.mean, 0, 1), (len(pick), tex_te.shape[1])))
    import cv2

    for s, k in zip(cfg.noise, keys, strict=True):
        lmn = np.concatenate([noisy_landmarks(lm[j : j + 1], s, 17 * int(r)) for j, r in enumerate(te[pick])])
        sources = {"sadm": _predict(syn, lmn, 8), "mean_texture": mean, "oracle": oracle[pick], "rewarp": tex_te[pick]}
        _, cmask, cplace = model.render(mean, lm)
        for name, tex in sources.items():
            crops, masks, places = model.render(np.asarray(tex), lmn)
            sse, n = 0.0, 0
            for j, frame in enumerate(seq.iter_frames(te[pick])):
                h, w = frame.shape[:2]
                region = cv2.warpAffine(cmask[j], cplace[j], (w, h)) > 0.999
                region = cv2.erode(region.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
                out = composite(crops[j], masks[j], places[j], frame, cfg.feather)
                d = (out.astype(np.float64) - frame)[region]
                sse, n = sse + float((d**2).sum()), n + d.size
            # 5e-4 dB: cv2.warpAffine rounds map coordinates to 1/32 px, and a shifted map rounds a
            # few of them the other way, on the seam's outline (measured differences up to 1.2e-4 dB)
            assert pooled[name][k] == pytest.approx(10 * np.log10(255.0**2 / (sse / n)), abs=5e-4)
    assert per_frame["psnr"]["sadm"].shape == (len(pick),)


def test_transfer3d_and_eri_share_the_neutral_rule():
    from facesynth.eri import geometry
    from facesynth.neutral import select_neutral

    assert geometry.select_neutral is select_neutral
    lm = make_synthetic_sequence(40, 192, seed=2).landmarks
    i, info = select_neutral(lm)
    assert 0 <= i < len(lm) and info["mouth_open"] <= 0.03


def test_driver_rule_prefers_linear_unless_rbf_is_better_on_validation():
    from facesynth.eri.driving import choose_driver

    rep = {"eps_linear": {"val_mse": 0.5}, "eps_rbf": {"val_mse": 0.6}, "nu_linear": {"val_mse": 0.4},
           "nu_rbf": {"val_mse": 0.45}}
    assert choose_driver(rep)[0] == "nu_linear"
    rep["eps_rbf"]["val_mse"] = 0.3
    assert choose_driver(rep)[0] == "eps_rbf"
    rep["eps_rbf"]["val_mse"] = 0.4  # a tie is not better: linear stays
    assert choose_driver(rep)[0] == "nu_linear"


def test_eri_artifact_round_trip_with_compact_svr_banks(tmp_path):
    import torch

    from facesynth.eri.model import EriModel

    seq = make_synthetic_sequence(40, 192, seed=0)
    model = EriModel.fit(seq, np.arange(32), {"compare": []})
    model.save(tmp_path / "eri")
    back = EriModel.load(tmp_path / "eri")
    faps = model.faps(seq.landmarks[32:])
    for v, bank in model.regressors.items():
        np.testing.assert_array_equal(back.regressors[v].sv.numpy(), bank.sv.numpy())
        torch.testing.assert_close(back.regressors[v].weights, bank.weights)
        np.testing.assert_allclose(back.predict_coefficients(faps, v), model.predict_coefficients(faps, v), atol=1e-5)
    from safetensors.numpy import load_file

    names = load_file(tmp_path / "eri" / "eri_model.safetensors")
    assert not any(k.endswith(".weights") for k in names)


def test_quiet_silences_progress(tmp_path, capsys):
    assert main(["codec", "geometry", str(tmp_path / "x.npy"), "--frames", "1", "--size", "16", "--quiet"]) in (0, 2)
    assert "[facesynth]" not in capsys.readouterr().err


def test_below_mean_flags_exactly_the_parts_under_the_mean_texture():
    rows = {"eyes": (18.0, 17.0), "mouth_interior": (19.36, 21.14), "rest": (30.0, 30.0)}
    m = {"psnr_frame_common_regions": {p: {"sadm": {"0": s, "2": 0.0}, "mean_texture": {"0": t, "2": 99.0}}
                                       for p, (s, t) in rows.items()}}
    assert below_mean(m) == ["mouth_interior (frame, common region): sadm 19.36 dB < mean texture 21.14 dB"]
    assert len(below_mean(m, "2")) == 3 and below_mean({}) == []
