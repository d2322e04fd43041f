"""Outputs that would destroy an input are refused before any work; a full disk is one line
naming the path (``no space left on device writing PATH``), exit 2, and no partial file.

The full-disk cases run twice: with a faked ENOSPC (everywhere) and, as root, on a real
2 MB tmpfs filled with dd (skipped when not root or when the mount fails)."""

from __future__ import annotations

import errno
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from _disk import full_tmpfs
from _errors import one_error_line
from test_reliability_io import fake_ingest  # noqa: F401 - a fixture

from facesynth.cli import main


def _listing(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir())


@pytest.fixture
def stream(tmp_path) -> Path:
    """A small lossless .fsgv stream (2 frames, 16x16x3)."""
    vid = np.random.default_rng(0).integers(0, 65535, (2, 16, 16, 3), dtype=np.uint16)
    np.save(tmp_path / "v.npy", vid)
    assert main(["codec", "encode", str(tmp_path / "v.npy"), str(tmp_path / "s.fsgv"), "--lossless", "--quiet"]) == 0
    return tmp_path / "s.fsgv"


@pytest.fixture
def cli_ingest(fake_ingest, monkeypatch):  # noqa: F811
    """``facesynth ingest`` on the fake detector (no dlib needed)."""
    from facesynth.data import ingest

    path, det, calls = fake_ingest
    monkeypatch.setattr(ingest, "check_extra", lambda: None)
    monkeypatch.setattr(ingest, "LandmarkDetector", lambda **kw: det)
    return fake_ingest


# ------------------------------------------------------------------ outputs that are inputs
@pytest.mark.parametrize("how", ["same", "symlink", "hardlink", "dotted"])
def test_codec_decode_onto_its_input_is_refused(stream, tmp_path, capsys, how):
    out = {"same": stream, "symlink": tmp_path / "link.npy", "hardlink": tmp_path / "hard.npy",
           "dotted": tmp_path / "." / "s.fsgv"}[how]
    if how == "symlink":
        out.symlink_to(stream)
    if how == "hardlink":
        os.link(stream, out)
    before, listing = stream.read_bytes(), _listing(tmp_path)
    capsys.readouterr()
    assert main(["codec", "decode", str(stream), str(out)]) == 2
    one_error_line(capsys.readouterr().err, str(out), "is the input", str(stream), progress=True)
    assert stream.read_bytes() == before and _listing(tmp_path) == listing


def test_codec_encode_and_rd_outputs_onto_inputs_are_refused(stream, tmp_path, capsys):
    v = tmp_path / "v.npy"
    before = v.read_bytes()
    capsys.readouterr()
    assert main(["codec", "encode", str(v), str(v), "--qp", "30"]) == 2
    one_error_line(capsys.readouterr().err, str(v), "is the input", progress=True)
    assert main(["codec", "encode", str(v), str(tmp_path / "o.fsgv"), "--qp", "30", "--preview", str(v)]) == 2
    one_error_line(capsys.readouterr().err, "is the input", progress=True)
    assert main(["codec", "rd", "--input", str(v), "--plot", str(v)]) == 2
    one_error_line(capsys.readouterr().err, "is the input", progress=True)
    assert main(["codec", "decode", str(stream), str(tmp_path / "d.npy"), "--preview", str(stream),
                 "--reference", str(v)]) == 2
    one_error_line(capsys.readouterr().err, "is the input", progress=True)
    assert v.read_bytes() == before and not (tmp_path / "o.fsgv").exists() and not (tmp_path / "d.npy").exists()


def test_ingest_out_holding_its_input_video_is_refused(cli_ingest, tmp_path, capsys):
    path, det, calls = cli_ingest
    folder = tmp_path / "clip"
    folder.mkdir()
    video = folder / "video.avi"
    shutil.copyfile(path, video)
    assert main(["ingest", str(video), "--out", str(folder)]) == 2
    one_error_line(capsys.readouterr().err, str(folder), "holds the input", progress=True)
    assert calls["n"] == 0 and _listing(folder) == ["video.avi"]
    assert main(["ingest", str(path), "--out", str(path)]) == 2  # the video itself as the folder
    assert "error: " in capsys.readouterr().err and path.is_file()


# ------------------------------------------------------------------ a full disk, faked
def _enospc(*args, **kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_faked_full_disk_codec_decode(stream, tmp_path, capsys, monkeypatch):
    out = tmp_path / "M" / "d.npy"
    monkeypatch.setattr(np, "save", _enospc)
    capsys.readouterr()
    assert main(["codec", "decode", str(stream), str(out)]) == 2
    one_error_line(capsys.readouterr().err, f"no space left on device writing {out}", progress=True)
    assert not (tmp_path / "M").exists()  # nothing partial, no temporary, not the folder the write made


@pytest.mark.parametrize("copy", [False, True])
def test_faked_full_disk_ingest(cli_ingest, tmp_path, capsys, monkeypatch, copy):
    from facesynth.data import ingest

    path, det, calls = cli_ingest
    out = tmp_path / "M" / "d"
    if copy:
        monkeypatch.setattr(ingest.shutil, "copyfile", _enospc)
    else:
        monkeypatch.setattr(ingest.np, "save", _enospc)
    assert main(["ingest", str(path), "--out", str(out)] + (["--copy"] if copy else [])) == 2
    one_error_line(capsys.readouterr().err, f"no space left on device writing {out}", progress=True)
    assert calls["n"] == 1 and not (tmp_path / "M").exists()


def test_faked_full_disk_outside_the_writers_is_one_line(monkeypatch, capsys):
    """An ENOSPC that no facesynth writer caught (a library writing on its own) is turned
    into the same line by the command line, with the file the OSError names."""
    from facesynth.codec import cli as codec_cli

    def run(args):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "/somewhere/x.bin")

    monkeypatch.setattr(codec_cli, "run", run)
    assert main(["codec", "rd"]) == 2
    one_error_line(capsys.readouterr().err, "no space left on device writing /somewhere/x.bin", progress=True)

    def other(args):
        raise OSError(errno.EIO, "I/O error")

    monkeypatch.setattr(codec_cli, "run", other)
    with pytest.raises(OSError):  # other OS errors are not disguised as a full disk
        main(["codec", "rd"])


# ------------------------------------------------------------------ a full disk, real (root, tmpfs)
def test_full_tmpfs_codec_decode(stream, tmp_path, capsys):
    with full_tmpfs(tmp_path / "M") as m:
        capsys.readouterr()
        assert main(["codec", "decode", str(stream), str(m / "d.npy")]) == 2
        one_error_line(capsys.readouterr().err, f"no space left on device writing {m / 'd.npy'}", progress=True)
        assert _listing(m) == ["filler"]


@pytest.mark.parametrize("copy", [False, True])
def test_full_tmpfs_ingest(cli_ingest, tmp_path, capsys, copy):
    path, det, calls = cli_ingest
    # --copy: room for the landmarks but not the video; without: no room at all
    with full_tmpfs(tmp_path / "M", leave_kb=12 if copy else 0) as m:
        assert main(["ingest", str(path), "--out", str(m / "d")] + (["--copy"] if copy else [])) == 2
        one_error_line(capsys.readouterr().err, f"no space left on device writing {m / 'd'}", progress=True)
        assert _listing(m) == ["filler"]


def test_full_tmpfs_export(tmp_path, capsys):
    from _onnx_models import synthetic_model, synthetic_synthesizer

    from facesynth.rundir import save_run_synthesizer

    syn = synthetic_synthesizer("linear")
    run = save_run_synthesizer(tmp_path / "run", synthetic_model()[0], syn.regressor_)
    with full_tmpfs(tmp_path / "M", size="3M", leave_kb=256) as m:
        code = main(["export", str(run), "--basis", "float32", "--out", str(m / "m.onnx")])
        one_error_line(capsys.readouterr().err, f"no space left on device writing {m / 'm.onnx'}", progress=True)
        assert code == 2 and _listing(m) == ["filler"]
