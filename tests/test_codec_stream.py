"""Encoder/decoder bit-exactness, lossless coding, corrupt streams and the CLI."""

import json
import struct

import numpy as np
import pytest

from facesynth.cli import main
from facesynth.codec.bitstream import VERSION, decode_video, encode_video
from facesynth.codec.frame import CodecConfig
from facesynth.codec.geometry import build_layout, geometry_video
from facesynth.codec.rd import bd_rate
from facesynth.codec.sources import height_field_mesh
from facesynth.errors import FacesynthError
from facesynth.metrics import psnr


@pytest.fixture(scope="module")
def video():
    m = height_field_mesh(33, n_frames=3)
    keep = np.linalg.norm(m["uv"][m["faces"]].mean(1) - 0.5, axis=1) < 0.45  # a round chart
    lay = build_layout(m["faces"][keep], m["uv"], (40, 48))  # not a multiple of 16: padded
    vid, _ = geometry_video(lay, m["frames"])
    return vid, lay.mask


@pytest.mark.parametrize("cfg", [
    CodecConfig(qp=24, gop=1, pdp=False, pvm=False, inter=False),
    CodecConfig(qp=36, gop=1, block_sizes=(8, 16)),
    CodecConfig(qp=20, gop=3, pdp=True, pvm=True, inter=True, mv_range=2),
    CodecConfig(qp=60, gop=2, pdp=False, pvm=False, inter=True, block_sizes=(16,)),
    CodecConfig(qp=30, gop=3, mv_range=0, size_refresh=0),
], ids=["hip-intra", "pdp-intra-8-16", "ippp-pvm-inter", "hip-inter-coarse", "zero-motion-range"])
def test_decoder_output_equals_encoder_reconstruction(video, cfg):
    vid, mask = video
    data, rec, st = encode_video(vid, cfg, mask)
    dec, info, _ = decode_video(data)
    assert dec.dtype == np.uint16 and dec.shape == vid.shape
    np.testing.assert_array_equal(dec, rec)
    assert 50 < psnr(vid, rec, mask, peak=65535) < 120
    assert sum(st["modes"].values()) == 3 * 48 * 48 * 3  # every (padded) sample has a mode


def test_inter_frames_use_temporal_modes_and_cost_fewer_bits(video):
    vid, mask = video
    still = np.repeat(vid[:1], 3, 0)
    intra = encode_video(still, CodecConfig(qp=24, gop=1), mask)[0]
    inter_data, rec, st = encode_video(still, CodecConfig(qp=24, gop=3), mask)
    assert len(inter_data) < 0.7 * len(intra)
    assert any(k.startswith(("PVM", "INTER")) for k in st["modes"])
    np.testing.assert_array_equal(decode_video(inter_data)[0], rec)


def test_lossless_reproduces_input_exactly(video):
    vid, _ = video
    rng = np.random.default_rng(1)
    noisy = (vid.astype(np.int64) + rng.integers(-300, 300, vid.shape)).clip(0, 65535).astype(np.uint16)
    for cfg in (CodecConfig(qp=None, gop=1), CodecConfig(qp=None, gop=3)):
        data, rec, _ = encode_video(noisy, cfg)
        np.testing.assert_array_equal(rec, noisy)
        np.testing.assert_array_equal(decode_video(data)[0], noisy)


def test_rate_falls_and_distortion_rises_with_qp(video):
    vid, mask = video
    pts = []
    for qp in (12, 30, 48):
        data, rec, _ = encode_video(vid, CodecConfig(qp=qp), mask)
        pts.append((len(data), psnr(vid, rec, mask, peak=65535)))
    assert pts[0][0] > pts[1][0] > pts[2][0]
    assert pts[0][1] > pts[1][1] > pts[2][1]


def test_corrupt_and_truncated_streams_are_rejected(video):
    vid, mask = video
    data, _, _ = encode_video(vid[:2], CodecConfig(qp=30, gop=2), mask)
    with pytest.raises(FacesynthError, match="truncated"):
        decode_video(data[:-5])
    with pytest.raises(FacesynthError, match="truncated"):
        decode_video(data[:30])
    bad = bytearray(data)
    bad[len(bad) // 2] ^= 0x10
    with pytest.raises(FacesynthError, match="CRC32 mismatch in frame"):
        decode_video(bytes(bad))
    bad = bytearray(data)
    bad[10] ^= 1
    with pytest.raises(FacesynthError, match="header CRC32"):
        decode_video(bytes(bad))
    with pytest.raises(FacesynthError, match="magic"):
        decode_video(b"XXXX" + data[4:])
    with pytest.raises(FacesynthError, match="unexpected bytes"):
        decode_video(data + b"\0")
    # a well-formed chunk (valid CRC) whose payload is garbage is still an error, not a crash
    hdr_len = 4 + struct.calcsize("<4sBBBBHHBHBI6d")
    ln = struct.unpack_from("<I", data, hdr_len)[0]
    import zlib
    junk = b"\x00\x07\x04" + b"\x01" * 5
    forged = data[:hdr_len] + struct.pack("<II", len(junk), zlib.crc32(junk)) + junk + data[hdr_len + 8 + ln:]
    with pytest.raises(FacesynthError, match="frame 0"):
        decode_video(forged)
    # CRC-valid payloads of random words: an error or some frame, never another exception
    rng = np.random.default_rng(3)
    for _ in range(30):
        junk = b"\x00\x04\x02" + rng.integers(0, 256, 4 * int(rng.integers(1, 40))).astype(np.uint8).tobytes()
        forged = data[:hdr_len] + struct.pack("<II", len(junk), zlib.crc32(junk)) + junk + data[hdr_len + 8 + ln:]
        try:
            decode_video(forged)
        except FacesynthError:
            pass
    # a forged header (valid CRC) claiming a million 60000x60000 frames: clean error, no huge allocation
    hdr = struct.pack("<4sBBBBHHBHBI6d", b"FSGV", VERSION, 0, 3, 16, 60000, 60000, 30, 1, 2, 10**6, *([0.0] * 6))
    with pytest.raises(FacesynthError, match="truncated"):
        decode_video(hdr + struct.pack("<I", zlib.crc32(hdr)) + b"\0" * 100)
    # a stream of another format version (its header CRC valid) is refused, not misread
    old = bytearray(data[:hdr_len - 4])
    old[4] = VERSION - 1
    with pytest.raises(FacesynthError, match="unsupported header"):
        decode_video(bytes(old) + struct.pack("<I", zlib.crc32(bytes(old))) + data[hdr_len:])


def test_encoder_rejects_bad_input():
    with pytest.raises(FacesynthError, match="uint16"):
        encode_video(np.zeros((1, 16, 16, 3), np.float32), CodecConfig())
    with pytest.raises(FacesynthError, match="qp"):
        encode_video(np.zeros((1, 16, 16, 3), np.uint16), CodecConfig(qp=200))


def test_bd_rate_closed_form():
    # B uses exactly 20 % fewer bits at every PSNR -> BD-rate -20 %
    p = [50.0, 55.0, 60.0, 65.0]
    r = [100.0, 200.0, 400.0, 800.0]
    out = bd_rate(r, p, [0.8 * x for x in r], p)
    assert out["bd_rate_pct"] == pytest.approx(-20.0, abs=1e-9)
    assert out["psnr_range_db"] == [50.0, 65.0]


def test_cli_encode_decode_round_trip(tmp_path, video, capsys):
    vid, mask = video
    np.save(tmp_path / "v.npy", vid)
    np.save(tmp_path / "v.mask.npy", mask)
    assert main(["codec", "encode", str(tmp_path / "v.npy"), str(tmp_path / "v.fsgv"), "--qp", "30",
                 "--modes", "hip+pdp", "--gop", "3", "--json"]) == 0
    enc = json.loads(capsys.readouterr().out)
    assert enc["bytes"] == (tmp_path / "v.fsgv").stat().st_size and enc["psnr_db"] > 60
    assert main(["codec", "decode", str(tmp_path / "v.fsgv"), str(tmp_path / "d.npy")]) == 0
    dec = np.load(tmp_path / "d.npy")
    assert psnr(vid, dec, mask, peak=65535) == pytest.approx(enc["psnr_db"])
    assert main(["codec", "encode", str(tmp_path / "v.npy"), str(tmp_path / "t4.fsgv"), "--qp", "30",
                 "--no-transform8", "--block-sizes", "4,8,16", "--json"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["bytes"] > 0
    assert main(["codec", "decode", str(tmp_path / "t4.fsgv"), str(tmp_path / "t4.npy")]) == 0
    assert main(["codec", "encode", str(tmp_path / "v.npy"), str(tmp_path / "l.fsgv"), "--lossless"]) == 0
    assert main(["codec", "decode", str(tmp_path / "l.fsgv"), str(tmp_path / "l.npy")]) == 0
    np.testing.assert_array_equal(np.load(tmp_path / "l.npy"), vid)
    (tmp_path / "bad.fsgv").write_bytes(b"FSGV" + b"\0" * 10)
    assert main(["codec", "decode", str(tmp_path / "bad.fsgv"), str(tmp_path / "x.npy")]) == 2
    assert "error: bitstream" in capsys.readouterr().err
    assert not (tmp_path / "x.npy").exists()


def test_cli_rd_writes_json_and_plot(tmp_path, video, capsys):
    vid, mask = video
    np.save(tmp_path / "v.npy", vid[:2])
    np.save(tmp_path / "v.mask.npy", mask)
    assert main(["codec", "rd", "--input", str(tmp_path / "v.npy"), "--qps", "20,32,44",
                 "--configs", "hip-intra,hip+pdp-intra", "--block-sizes", "4",
                 "--plot", str(tmp_path / "rd.png"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out["points"]) == {"hip-intra", "hip+pdp-intra"}
    assert all(p["bit_exact"] for pts in out["points"].values() for p in pts)
    assert (tmp_path / "rd.png").stat().st_size > 1000
