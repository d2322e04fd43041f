"""External anchors for bench/mesh/codec.py through the ffmpeg command line (optional).

Each channel (x, y, z) of the uint16 geometry video is one plane of a 4:4:4 frame; the
samples are rounded to the codec's bit depth, coded, decoded and scaled back to 16 bits
(bin centres), and PSNR (peak 65535) is measured over the mask as for our codec. Bits
are the size of the elementary stream (h264/hevc) or of the container (FFV1 in NUT,
JPEG 2000 codestreams in NUT). Nothing here is imported by the facesynth package.
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from facesynth.metrics import psnr


def available() -> dict[str, bool]:
    """Which anchor encoders this ffmpeg has (empty when ffmpeg is absent)."""
    exe = shutil.which("ffmpeg")
    if exe is None:
        return {}
    out = subprocess.run([exe, "-hide_banner", "-encoders"], capture_output=True, text=True).stdout
    return {name: f" {name} " in out for name in ("libx264", "libx265", "ffv1", "libopenjpeg")}


def _to_depth(video: np.ndarray, bits: int) -> np.ndarray:
    s = 16 - bits
    return np.clip((video.astype(np.int64) + (1 << s >> 1)) >> s, 0, (1 << bits) - 1).astype(np.uint16) if s else video


def _from_depth(v: np.ndarray, bits: int) -> np.ndarray:
    s = 16 - bits
    return np.clip(v.astype(np.int64) << s, 0, 65535).astype(np.uint16) if s else v


def _planar(video: np.ndarray) -> bytes:
    return np.ascontiguousarray(np.moveaxis(video, -1, 1)).astype("<u2").tobytes()


def _run(args: list[str]) -> None:
    r = subprocess.run(["ffmpeg", "-hide_banner", "-loglevel", "error", "-y", *args], capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(r.stderr.strip()[-400:])


def code(video: np.ndarray, mask: np.ndarray, codec: str, bits: int, q: int | None, intra: bool) -> dict:
    """One anchor point: ``codec`` in libx264, libx265, ffv1, libopenjpeg."""
    t, h, w, _ = video.shape
    # 16-bit goes as planar GBR so that no colour conversion touches the samples
    pix = {10: "yuv444p10le", 12: "yuv444p12le", 16: "gbrp16le"}[bits]
    src = _to_depth(video, bits)
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        (d / "in.raw").write_bytes(_planar(src))
        inp = ["-f", "rawvideo", "-pix_fmt", pix, "-s", f"{w}x{h}", "-r", "25", "-i", str(d / "in.raw")]
        if codec == "libx264":
            out = d / "o.264"
            gop = ["-g", "1"] if intra else ["-g", str(t), "-bf", "0"]
            _run(inp + ["-c:v", "libx264", "-preset", "medium", "-qp", str(q), *gop, "-pix_fmt", pix, "-f", "h264", str(out)])
        elif codec == "libx265":
            out = d / "o.265"
            ki = "keyint=1" if intra else f"keyint={t}:bframes=0"
            _run(inp + ["-c:v", "libx265", "-preset", "medium", "-x265-params", f"qp={q}:{ki}:log-level=error",
                        "-pix_fmt", pix, "-f", "hevc", str(out)])
        elif codec == "ffv1":
            out = d / "o.nut"
            _run(inp + ["-c:v", "ffv1", "-level", "3", "-pix_fmt", pix, "-f", "nut", str(out)])
        elif codec == "libopenjpeg":
            out = d / "o.nut"
            # compression_level c -> target ratio 2c (0: reversible 5/3, lossless); 9/7 when lossy
            _run(inp + ["-c:v", "libopenjpeg", "-format", "j2k", "-compression_level", str(q),
                        "-irreversible", str(int(bool(q))), "-pix_fmt", pix, "-f", "nut", str(out)])
        else:
            raise ValueError(codec)
        nbytes = out.stat().st_size
        _run(["-i", str(out), "-f", "rawvideo", "-pix_fmt", pix, str(d / "dec.raw")])
        dec = np.frombuffer((d / "dec.raw").read_bytes(), "<u2").reshape(t, 3, h, w)
    rec = _from_depth(np.moveaxis(dec, 1, -1), bits)
    p = psnr(video, rec, mask, peak=65535)
    return {"q": q, "bits_per_frame": 8 * nbytes / t, "bpp": 8 * nbytes / (t * h * w),
            "psnr_db": p if np.isfinite(p) else None, "lossless": bool(np.array_equal(rec, video))}


def depth_cap(video: np.ndarray, mask: np.ndarray, bits: int) -> float:
    """PSNR of rounding to ``bits`` and back: the ceiling of a ``bits``-bit anchor."""
    return psnr(video, _from_depth(_to_depth(video, bits), bits), mask, peak=65535)
