"""``facesynth web build MODEL OUT`` never deletes the user's files and never accepts what
cannot run (issue 43): OUT is written only when missing, empty or made by an earlier build
(its ``.facesynth-site`` mark); every other OUT is one line, exit 2, nothing changed and no
hidden ``.NAME.facesynth-tmp-*`` left; a corrupt talking head or a format string on a
one-node graph is refused before anything is written; the page's files, the avatar's
external weights too, get the usual permissions."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest
from _errors import one_error_line
from _onnx_models import synthetic_talking_head
from _page import require_page
from test_reliability_head import _format_only, _overwrite_weights

from facesynth.cli import main
from facesynth.web import site


def _tree(folder: Path) -> dict:
    """Every entry under ``folder`` (links not followed): its kind and, for a file, its bytes."""
    out = {}
    for p in sorted(folder.rglob("*")):
        key = p.relative_to(folder).as_posix()
        out[key] = os.readlink(p) if p.is_symlink() else p.read_bytes() if p.is_file() else "dir"
    return out


def _no_hidden_temps(*folders: Path) -> None:
    for folder in folders:
        assert not [p.name for p in folder.iterdir() if ".facesynth-tmp-" in p.name], folder


@pytest.fixture(scope="module")
def head(tmp_path_factory) -> Path:
    return synthetic_talking_head(tmp_path_factory.mktemp("head"))


@pytest.fixture
def page_ready(tmp_path, monkeypatch):
    """Skip without what a built page needs (onnxruntime-web from 'facesynth web setup', the
    tracker's converter); the tracker is converted into this test's cache."""
    require_page()
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))


def _user_folder(where: Path) -> Path:
    where.mkdir()
    (where / "thesis.txt").write_text("three years of work")
    (where / "photos").mkdir()
    (where / "photos" / "a.jpg").write_bytes(b"\xff\xd8 not really")
    return where


@pytest.mark.parametrize("case", ["user_folder", "models_own_folder", "page_folder", "a_file", "the_model_itself",
                                  "symlink_to_a_folder", "dot"])
def test_refused_out_is_one_line_and_changes_nothing(head, tmp_path, capsys, monkeypatch, case):
    """Each OUT that is not a missing, empty or facesynth-made folder: exit 2, one line naming
    it, before any work (no npm packages needed); the user's files byte-identical, no hidden
    temporary beside it (was: deleted with exit 0, or IsADirectoryError leaving
    ``.NAME.facesynth-tmp-PID-old-*``)."""
    work = tmp_path / "work"
    work.mkdir()
    model = work / "avatar.onnx"
    model.write_bytes(head.read_bytes())
    if case == "user_folder":
        out = _user_folder(work / "thesis")
    elif case == "models_own_folder":
        (work / "notes.txt").write_text("notes beside the model")
        out = work
    elif case == "page_folder":
        out = site.PAGE
    elif case == "a_file":
        out = work / "report.pdf"
        out.write_bytes(b"%PDF")
    elif case == "the_model_itself":
        out = model
    elif case == "symlink_to_a_folder":
        target = _user_folder(work / "real")
        out = work / "link"
        out.symlink_to(target, target_is_directory=True)
    else:
        empty = tmp_path / "empty"
        empty.mkdir()
        monkeypatch.chdir(empty)
        out = Path(".")
    watched = site.PAGE if case == "page_folder" else tmp_path
    before = _tree(watched)
    assert main(["web", "build", str(model), str(out)]) == 2
    one_error_line(capsys.readouterr().err, str(out))
    assert _tree(watched) == before
    _no_hidden_temps(work, tmp_path)


@pytest.mark.parametrize("case", ["garbage_weights", "broken_indices", "format_only"])
def test_a_file_that_cannot_run_is_refused(head, tmp_path, capsys, monkeypatch, case):
    """64 KiB of the weights overwritten (the metadata intact: renders garbage, or fails to
    run), or a one-node graph carrying only the format string: exit 2, one line naming the
    model, OUT not written (was exit 0 and a page that said "Live." and drew nothing)."""
    monkeypatch.setattr(site, "ort_dist", lambda: tmp_path)  # not needed to refuse: runs without npm packages
    model = {"garbage_weights": lambda: _overwrite_weights(head, tmp_path / "bad.onnx", "synthesis.app_mean"),
             "broken_indices": lambda: _overwrite_weights(head, tmp_path / "bad.onnx", "frame_warp.ev_index"),
             "format_only": lambda: _format_only(tmp_path / "bad.onnx")}[case]()
    out = tmp_path / "site"
    assert main(["web", "build", str(model), str(out)]) == 2
    one_error_line(capsys.readouterr().err, str(model))
    assert not out.exists()
    _no_hidden_temps(tmp_path)


def test_builds_into_a_missing_an_empty_and_its_own_folder(head, tmp_path, capsys, page_ready):
    """A missing folder and an empty one are written, marked as facesynth's, and a rebuild
    replaces the marked folder; every file, the avatar's external weights too, has the mode
    of a normal file (0666 & ~umask; the weights were 0600)."""
    umask = os.umask(0o022)
    try:
        empty = tmp_path / "empty"
        empty.mkdir()
        for out in (tmp_path / "new" / "site", empty, tmp_path / "new" / "site"):
            assert main(["web", "build", str(head), str(out)]) == 0
            assert capsys.readouterr().out.strip() == str(out)
            assert (out / site.SITE_MARK).is_file() and (out / site.AVATAR_DATA).stat().st_size > 0
            modes = {p.relative_to(out).as_posix(): stat.S_IMODE(p.stat().st_mode) for p in out.rglob("*") if p.is_file()}
            assert set(modes.values()) == {0o644}, modes
            _no_hidden_temps(out.parent)
    finally:
        os.umask(umask)


def test_atomic_dir_onto_a_file_leaves_no_hidden_folder(tmp_path):
    """The writer under ``web build``: a folder written onto an existing file cannot move the
    file aside; the error propagates, the file stays and no ``.NAME.facesynth-tmp-*`` folder
    (the new one, or the ``-old-`` one made to hold the file) is left (was both)."""
    from facesynth.io import atomic_dir

    target = tmp_path / "page"
    target.write_text("a file")
    with pytest.raises(OSError), atomic_dir(target) as tmp:
        (tmp / "index.html").write_text("<html>")
    assert target.read_text() == "a file"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["page"]
