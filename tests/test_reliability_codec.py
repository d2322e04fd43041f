"""Issue 15, codec rows: output names (row 1), forged header sizes (row 3), bad --mask and
0 channels (row 9), and the decoder fuzz test (>= 500 mutated streams in a subprocess
under an address-space limit)."""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest

from facesynth.cli import main
from facesynth.codec.bitstream import _HDR, MAX_FRAME_SAMPLES, decode_video, encode_video
from facesynth.codec.frame import CodecConfig
from facesynth.errors import FacesynthError

ROOT = Path(__file__).resolve().parents[1]


def _video(t=2, h=16, w=16, c=3) -> np.ndarray:
    yy, xx = np.mgrid[:h, :w]
    return np.stack([np.stack([xx * 2000 + yy * 700 + 5000 * k + 300 * i for k in range(c)], -1)
                     for i in range(t)]).astype(np.uint16)


def _listing(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir())


@pytest.fixture(scope="module")
def stream(tmp_path_factory) -> tuple[Path, np.ndarray]:
    d = tmp_path_factory.mktemp("codec")
    v = _video()
    data, rec, _ = encode_video(v, CodecConfig(qp=None))
    (d / "v.fsgv").write_bytes(data)
    return d / "v.fsgv", rec


@pytest.mark.parametrize("name", ["decoded.raw", "decoded", "decoded.npy", "out.bin"])
def test_row1_decode_writes_exactly_the_named_file(stream, tmp_path, name, capsys):
    src, rec = stream
    assert main(["codec", "decode", str(src), str(tmp_path / name), "--json"]) == 0
    assert _listing(tmp_path) == [name]  # no hidden .npy temp left beside it
    np.testing.assert_array_equal(np.load(tmp_path / name), rec)
    assert json.loads(capsys.readouterr().out)["output"] == str(tmp_path / name)


def test_row1_geometry_writes_exactly_the_named_files(tmp_path, shared_mesh):
    assert main(["codec", "geometry", str(tmp_path / "g.raw"), "--frames", "1", "--size", "32"]) == 0
    assert _listing(tmp_path) == ["g.mask.npy", "g.raw"]
    assert np.load(tmp_path / "g.raw").dtype == np.uint16


def _forge(data: bytes, **fields) -> bytes:
    names = ["magic", "ver", "fl", "c", "depth", "h", "w", "qp", "gop", "mvr", "t"]
    f = list(_HDR.unpack_from(data))
    for k, v in fields.items():
        f[names.index(k)] = v
    hdr = _HDR.pack(*f)
    return hdr + struct.pack("<I", zlib.crc32(hdr)) + data[_HDR.size + 4:]


@pytest.mark.parametrize("fields, needle", [
    ({"h": 65535, "w": 65535, "c": 255}, "limit"),
    ({"h": 4096, "w": 4096, "c": 3}, "limit"),
    ({"t": 10_000}, "cannot hold"),
    ({"t": 2**32 - 1, "h": 1024, "w": 1024, "c": 4}, "cannot hold"),
])
def test_row3_forged_header_sizes_are_refused_before_allocation(stream, tmp_path, fields, needle, capsys):
    """Checked on the header alone: the CLI runs it in-process, and a subprocess under a
    256 MiB address-space cap shows that nothing frame-sized is allocated first."""
    src, _ = stream
    forged = tmp_path / "forged.fsgv"
    forged.write_bytes(_forge(src.read_bytes(), **fields))
    with pytest.raises(FacesynthError, match=needle):
        decode_video(forged.read_bytes())
    assert main(["codec", "decode", str(forged), str(tmp_path / "out.npy")]) == 2
    assert "bitstream" in capsys.readouterr().err
    assert _listing(tmp_path) == ["forged.fsgv"]
    code = ("import resource, sys\n"
            "from facesynth.codec.bitstream import decode_video\nfrom facesynth.errors import FacesynthError\n"
            "data = open(sys.argv[1], 'rb').read()\n"
            "resource.setrlimit(resource.RLIMIT_AS, (256 << 20, 256 << 20))\n"
            "try:\n    decode_video(data)\nexcept FacesynthError as e:\n    print('refused', e)\n")
    r = subprocess.run([sys.executable, "-c", code, str(forged)], capture_output=True, text=True, timeout=120,
                       cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT), "OPENBLAS_NUM_THREADS": "1"})
    assert r.returncode == 0 and r.stdout.startswith("refused"), r.stderr[-500:]


def test_row3_encoder_refuses_videos_beyond_the_limit():
    side = int(np.sqrt(MAX_FRAME_SAMPLES)) + 16
    with pytest.raises(FacesynthError, match="limit"):
        encode_video(np.zeros((1, side, side, 1), np.uint16), CodecConfig(qp=None))


@pytest.mark.parametrize("mask", ["missing", "garbage", "wrong_shape", "object"])
def test_row9_bad_mask_is_a_one_line_error(tmp_path, mask, capsys):
    v = _video()
    np.save(tmp_path / "v.npy", v)
    m = tmp_path / "m.npy"
    if mask == "garbage":
        m.write_bytes(b"\x93NUMPY garbage" * 10)
    elif mask == "wrong_shape":
        np.save(m, np.ones((3, 3), bool))
    elif mask == "object":
        np.save(m, np.array([{"a": 1}] * 4, dtype=object).reshape(2, 2), allow_pickle=True)
    before = _listing(tmp_path)
    assert main(["codec", "encode", str(tmp_path / "v.npy"), str(tmp_path / "o.fsgv"), "--lossless", "--mask", str(m)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and str(m) in err and err.count("\n") == 1
    assert _listing(tmp_path) == before


def test_row9_zero_channels_is_a_one_line_error(tmp_path, capsys):
    np.save(tmp_path / "v.npy", np.zeros((2, 16, 16, 0), np.uint16))
    assert main(["codec", "encode", str(tmp_path / "v.npy"), str(tmp_path / "o.fsgv"), "--lossless"]) == 2
    err = capsys.readouterr().err
    assert "frames: unsupported shape" in err and err.count("\n") == 1
    assert _listing(tmp_path) == ["v.npy"]


def test_decoder_fuzz():
    """>= 500 mutations of a real 4-frame stream (bit flips, byte overwrites, truncations,
    garbage, forged headers and frame payloads with recomputed CRCs), decoded in a
    subprocess whose address space is capped at 1 GiB: each decodes or raises
    FacesynthError, nothing else; the slowest case is reported and bounded (a hang
    guard, far above the measured figures; see docs/reliability.md)."""
    n = 540
    r = subprocess.run([sys.executable, str(ROOT / "tests" / "_fuzz_codec.py"), str(n), "0", "1024"],
                       capture_output=True, text=True, timeout=600, cwd=ROOT,
                       env={**os.environ, "PYTHONPATH": str(ROOT), "OPENBLAS_NUM_THREADS": "1"})
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["cases"] == n
    assert out["foreign"] == []
    assert out["decoded"] + out["rejected"] == n
    for kind in ("bitflip", "overwrite", "truncate", "garbage"):  # CRCs catch every unforged corruption
        assert out["by_kind"][kind] == {"rejected": n // 6}
    assert out["max_case_s"] < 60  # no hang
    assert out["max_traced_mb"] < 8 * 2 * MAX_FRAME_SAMPLES / 2**20 * 4  # a few frame-sized int64 arrays at most
