"""Each concept written once (issue 47, section 2), pinned: where the package defines it (read
from the source, as tests/test_layers.py reads imports) and what it does.

* compositing: one implementation (facesynth/compositing.py); the still-frame form's feather is
  in frame pixels whatever the crop's resolution;
* the driver's neutral chosen online: one OnlineNeutral, the prefix rule of select_neutral;
* the ONNX writer: torch.onnx.export is called in onnx/common.py only;
* "landmarks inside the frame": one check, sizes (W, H), the margin a parameter;
* contact sheets and the grey background: one grid, one GREY;
* the output switches: every command takes --quiet (alias --no-progress) and --json;
* the export's options: one declaration (ExportConfig) for argparse and Hydra.
"""

from __future__ import annotations

import argparse
import ast
import importlib
import runpy
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest

from facesynth.errors import FacesynthError

PACKAGE = Path(__file__).resolve().parents[1] / "facesynth"


def _trees():
    return {p.relative_to(PACKAGE).as_posix(): ast.parse(p.read_text()) for p in sorted(PACKAGE.rglob("*.py"))}


def _defined(name: str) -> list[str]:
    """Modules that define ``name`` at their top level (a function, class or assignment)."""
    out = []
    for mod, tree in _trees().items():
        for node in tree.body:
            names = [node.name] if isinstance(node, (ast.FunctionDef, ast.ClassDef)) else \
                [t.id for t in getattr(node, "targets", []) if isinstance(t, ast.Name)]
            if name in names:
                out.append(mod)
    return out


def _callers(dotted: str) -> list[str]:
    """Modules that call ``dotted`` (e.g. ``torch.onnx.export``) by that spelling."""
    out = []
    for mod, tree in _trees().items():
        if any(isinstance(n, ast.Call) and ast.unparse(n.func) == dotted for n in ast.walk(tree)):
            out.append(mod)
    return out


@pytest.mark.parametrize("name,home", [
    ("composite", "compositing.py"), ("blend_face", "compositing.py"), ("blend_rendered", "compositing.py"),
    ("crop_rgb", "compositing.py"), ("GREY", "compositing.py"), ("STILL_FEATHER", "compositing.py"),
    ("OnlineNeutral", "neutral.py"), ("NEUTRAL_FRAMES", "neutral.py"), ("save_graph", "onnx/common.py"),
    ("check_landmarks_in_frame", "data/sequence.py"), ("ExportConfig", "onnx/config.py"),
    ("export_model", "onnx/export.py"), ("load_target", "eri/target.py"),
])
def test_one_home(name, home):
    assert _defined(name) == [home]


@pytest.mark.parametrize("gone", ["composite_face", "check_in_frame", "summary_json"])
def test_the_second_copies_are_gone(gone):
    assert _defined(gone) == []


def test_one_onnx_writer_and_one_crop_reader():
    assert _callers("torch.onnx.export") == ["onnx/common.py"]
    assert _callers("crop_rgb") == ["compositing.py"]  # callers pass the batch to blend_rendered
    # the three contact sheets choose their tiles; the grid, its header and the PNG are sheet.py's
    assert {"eri/render.py", "mesh/preview.py", "runtime/video.py"} <= set(_callers("grid"))
    assert set(_callers("cv2.putText")) >= {"sheet.py"} and "eri/render.py" not in _callers("cv2.putText")


def _disc(n: int) -> tuple[np.ndarray, np.ndarray]:
    yy, xx = np.mgrid[:n, :n] + 0.5
    mask = (((xx - n / 2) ** 2 + (yy - n / 2) ** 2) < (0.4 * n) ** 2).astype(np.float32)
    return np.full((n, n, 3), 0.9, np.float32) * mask[..., None], mask


def test_the_still_frame_feather_is_in_frame_pixels():
    """The same disc rendered at 40 and at 160 crop pixels, placed at the same 80 frame pixels:
    composite() gives the same seam (feather 4 frame px), where a feather in crop pixels would
    make it four times wider at 40 px than at 160 px."""
    from facesynth.compositing import blend_face, composite

    bg = np.full((100, 100, 3), 30, np.uint8)
    outs = []
    for n in (40, 160):
        crop, mask = _disc(n)
        s = 80 / n
        outs.append(composite(crop, mask, np.array([[s, 0, 10], [0, s, 10]]), bg, 4.0).astype(float))
    assert np.abs(outs[0] - outs[1]).mean() < 3.0  # only the masks' rasterisation differs (2.4)
    crop, mask = _disc(40)
    crop_px = blend_face(crop, mask, np.array([[2.0, 0, 10], [0, 2.0, 10]]), bg, 4.0, match_colour=False).astype(float)
    assert np.abs(crop_px - outs[1]).mean() > 3 * np.abs(outs[0] - outs[1]).mean()


def test_online_neutral_is_select_neutral_over_the_frames_seen():
    from facesynth.data.synthetic import make_synthetic_sequence
    from facesynth.neutral import OnlineNeutral, select_neutral

    lm = make_synthetic_sequence(n_frames=12, size=128, seed=3).landmarks
    online = OnlineNeutral(frames=8)
    for k in range(8):
        assert online.choosing
        np.testing.assert_array_equal(online.see(lm[k]), lm[select_neutral(lm[: k + 1])[0]])
    assert not online.choosing
    with pytest.raises(FacesynthError, match="chosen already"):
        online.see(lm[9])
    with pytest.raises(FacesynthError, match="neutral_frames"):
        OnlineNeutral(0)


def test_landmarks_in_frame_take_width_then_height():
    from facesynth.data.sequence import check_landmarks_in_frame

    lm = np.array([[[150.0, 50.0]] * 68], np.float32)  # inside a 200 x 100 frame, outside a 100 x 200 one
    check_landmarks_in_frame(lm, (200, 100), "a", margin=0.0)
    with pytest.raises(FacesynthError, match="outside the 100x200 frame"):
        check_landmarks_in_frame(lm, (100, 200), "a", margin=0.0)
    far = lm + [250.0, 0.0]  # 2x the width: within one frame size of it, not within 25 %
    check_landmarks_in_frame(far, (200, 100), "a", margin=1.0)
    with pytest.raises(FacesynthError, match="by more than 25%"):
        check_landmarks_in_frame(far, (200, 100), "a")


def test_the_sheet_grid_names_its_columns():
    from facesynth.sheet import HEADER_PX, grid

    tiles = [[np.full((10, 30, 3), v, np.uint8) for v in (0, 100)], [np.full((10, 30, 3), v, np.uint8) for v in (50, 200)]]
    plain = grid(tiles)
    assert plain.shape == (20, 60, 3)
    for r in range(2):
        for c in range(2):
            np.testing.assert_array_equal(plain[10 * r:10 * (r + 1), 30 * c:30 * (c + 1)], tiles[r][c])
    named = grid(tiles, ("a", "b"))
    assert named.shape == (HEADER_PX + 20, 60, 3) and (named[:HEADER_PX] < 255).any()
    np.testing.assert_array_equal(named[HEADER_PX:], plain)


def _subcommand_parsers():
    from facesynth.cli import SUBCOMMANDS, _add_quiet

    for name, (module, _) in SUBCOMMANDS.items():
        if name == "train":  # Hydra's: quiet=true
            continue
        p = argparse.ArgumentParser(prog=name)
        importlib.import_module(module).add_arguments(p)
        _add_quiet(p)
        yield name, p
        for action in p._actions:
            if isinstance(action, argparse._SubParsersAction):
                yield from ((f"{name} {k}", sub) for k, sub in action.choices.items())


def test_every_command_has_the_same_output_switches():
    for name, p in _subcommand_parsers():
        opts = p._option_string_actions
        assert opts["--quiet"] is opts["--no-progress"] and opts["--quiet"].dest == "quiet", name
        assert opts["--json"].dest == "json" and opts["--json"].nargs == 0, name  # a switch, never a file


def test_export_options_are_declared_once():
    """facesynth export's options are ExportConfig's fields; the Hydra front end's schema is
    ExportConfig (plus its json switch), so --talking-head reaches it too."""
    from facesynth.onnx.config import ExportConfig, add_arguments

    p = argparse.ArgumentParser()
    add_arguments(p)
    dests = {a.dest for a in p._actions} - {"help"}
    assert dests == {f.name for f in fields(ExportConfig)}
    for f in fields(ExportConfig):
        assert any(a.help == f.metadata["help"] for a in p._actions if a.dest == f.name), f.name
    front = runpy.run_path(str(PACKAGE.parent / "export" / "export.py"), run_name="export_front_end")
    schema = {f.name for f in fields(front["HydraExportConfig"])}
    assert schema == {f.name for f in fields(ExportConfig)} | {"json"} and "talking_head" in schema


def test_train_takes_the_same_json_switch(tmp_path):
    """``facesynth train --json`` (Hydra's app, not argparse) prints its result as one JSON line:
    the run folder and the headline figures of its metrics.json, equal to them. (A subprocess:
    Hydra configures logging onto the streams of the process it runs in.)"""
    import json
    import subprocess
    import sys

    from facesynth.runs.train_cli import HEADLINE

    run = tmp_path / "run"
    res = subprocess.run([sys.executable, "-m", "facesynth", "train", "--json", f"hydra.run.dir={run}", "quiet=true",
                          "data.n_frames=60", "eval.talking_head=false", "sadm.region_shrink=false"],
                         cwd=tmp_path, capture_output=True, text=True, check=False)
    assert res.returncode == 0, res.stderr
    lines = res.stdout.strip().splitlines()
    assert len(lines) == 1, lines
    out = json.loads(lines[0])
    metrics = json.loads((run / "metrics.json").read_text())
    assert out["run_dir"] == str(run) and "psnr_ref" in out
    assert {k: v for k, v in out.items() if k != "run_dir"} == {k: metrics[k] for k in HEADLINE if k in metrics}
