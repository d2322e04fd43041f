"""The ``.fsgv`` container and the sequence-level encoder/decoder.

Layout (little-endian)::

    header  : magic b"FSGV", version u8, flags u8 (1 lossless, 2 PDP, 4 PVM, 8 inter,
              16 bbox present), channels u8, bit depth u8, height u16, width u16, QP u8,
              GOP u16, MV range u8, frames u32, bbox lo[3] hi[3] f64, CRC32 of the above
    frames  : per frame, payload length u32, CRC32 u32, payload (see frame.write_frame)

Frames are padded to multiples of 16 by edge replication and cropped on decoding.
Any truncation, corruption or trailing data raises :class:`FacesynthError`.

Limits (checked on the header, before any frame is allocated; the encoder refuses videos
beyond them): a padded frame holds at most :data:`MAX_FRAME_SAMPLES` samples (C x Hp x Wp,
e.g. 1024 x 1024 x 4) and a stream at most :data:`MAX_STREAM_SAMPLES` (frames x C x H x W:
512 MiB of uint16 output); each frame chunk takes at least 11 bytes of the stream, so the
frame count is bounded by the stream's length too.
"""

from __future__ import annotations

import struct
import time
import zlib
from dataclasses import dataclass

import numpy as np

from facesynth.codec.frame import (
    CodecConfig,
    FrameCode,
    decode_frame,
    encode_batch,
    encode_frame,
    mode_set,
    read_frame,
    write_frame,
)
from facesynth.codec.transform import QP_MAX
from facesynth.errors import FacesynthError
from facesynth.progress import bar as progress_bar

MAGIC = b"FSGV"
VERSION = 2  # 2: neighbour contexts for `last`, coded by staggered anti-diagonals
_HDR = struct.Struct("<4sBBBBHHBHBI6d")
_CHUNK = struct.Struct("<II")
MAX_FRAME_SAMPLES = 1 << 22  # per padded frame: C * ceil16(H) * ceil16(W)
MAX_STREAM_SAMPLES = 1 << 28  # per stream: T * C * H * W (uint16 output of 512 MiB)


def check_limits(t: int, h: int, w: int, c: int, where: str) -> None:
    """FacesynthError when a (T, H, W, C) video exceeds the stated limits."""
    per_frame = c * (h + -h % 16) * (w + -w % 16)
    if per_frame > MAX_FRAME_SAMPLES:
        raise FacesynthError(f"{where}: frame {h}x{w}x{c} exceeds the codec's limit of {MAX_FRAME_SAMPLES} samples "
                             "per frame (padded to multiples of 16)")
    if t * c * h * w > MAX_STREAM_SAMPLES:
        raise FacesynthError(f"{where}: {t} frames of {h}x{w}x{c} exceed the codec's limit of {MAX_STREAM_SAMPLES} "
                             "samples per stream")


@dataclass
class StreamInfo:
    height: int
    width: int
    channels: int
    qp: int | None
    gop: int
    mv_range: int
    n_frames: int
    flags: tuple[bool, bool, bool]  # pdp, pvm, inter
    bbox: np.ndarray | None  # (2, 3) lo, hi


def _pad16(frames: np.ndarray) -> np.ndarray:
    t, h, w, c = frames.shape
    ph, pw = -h % 16, -w % 16
    return np.pad(frames, ((0, 0), (0, ph), (0, pw), (0, 0)), mode="edge") if ph or pw else frames


def encode_video(frames: np.ndarray, cfg: CodecConfig, mask: np.ndarray | None = None,
                 bbox: np.ndarray | None = None) -> tuple[bytes, np.ndarray, dict]:
    """Encode a uint16 video (T, H, W, C) -> (bitstream, reconstruction (T, H, W, C), stats).

    ``mask`` (H, W) bool weights the distortion (outside pixels count ``outside_weight``);
    ``bbox`` (2, 3) (lo, hi of the quantiser) is stored for the decoder.
    """
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.dtype != np.uint16:
        raise FacesynthError(f"frames: expected uint16 (T, H, W, C), got {frames.dtype} {frames.shape}")
    t, h, w, c = frames.shape
    if t == 0 or h == 0 or w == 0 or c == 0 or h > 65535 or w > 65535 or c > 255:
        raise FacesynthError(f"frames: unsupported shape {frames.shape} (T, H, W, C all >= 1)")
    check_limits(t, h, w, c, "frames")
    if cfg.qp is not None and not 0 <= cfg.qp <= QP_MAX:
        raise FacesynthError(f"qp: expected 0..{QP_MAX}, got {cfg.qp}")
    if cfg.gop < 1 or not 0 <= cfg.mv_range <= 32 or not cfg.sizes() or any(n not in (4, 8, 16) for n in cfg.sizes()):
        raise FacesynthError("codec config: gop >= 1, mv_range 0..32, block sizes from {4, 8, 16}")
    flags = (cfg.pdp, cfg.pvm, cfg.inter)
    fl = (cfg.qp is None) | 2 * cfg.pdp | 4 * cfg.pvm | 8 * cfg.inter | 16 * (bbox is not None)
    bb = np.full(6, np.nan) if bbox is None else np.asarray(bbox, np.float64).reshape(6)
    hdr = _HDR.pack(MAGIC, VERSION, fl, c, 16, h, w, 0 if cfg.qp is None else cfg.qp, cfg.gop,
                    cfg.mv_range, t, *bb)
    out = [hdr, struct.pack("<I", zlib.crc32(hdr))]
    x = np.moveaxis(_pad16(frames), -1, 1).astype(np.int64)  # (T, C, Hp, Wp)
    wmask = None
    if mask is not None:
        wmask = _pad16(np.asarray(mask, bool)[None, :, :, None])[0, :, :, 0]
    recs, prev = [], None
    mode_hist: dict[str, int] = {}
    t0 = time.perf_counter()
    last_size: dict[bool, int] = {}
    i = 0
    bar = progress_bar(total=t, desc="encode", unit="frame")
    while i < t:
        if cfg.gop == 1:  # independent frames: a batch shares the wavefront loop
            batch = _intra_batch(x[i:i + max(1, cfg.batch_frames)], i, cfg, wmask, last_size)
        else:
            p = prev if (i % cfg.gop) else None
            full = cfg.size_refresh <= 1 or i % cfg.size_refresh == 0 or (p is not None) not in last_size
            # greedy size search from the last choice of this frame type (P-frames without
            # one: from the largest size, which temporal prediction favours)
            start = last_size.get(p is not None, max(cfg.sizes()) if p is not None else None)
            batch = [encode_frame(x[i], p, cfg, wmask, None if full else (last_size[p is not None],), start)]
            last_size[p is not None] = batch[0][0].n
        for code, rec in batch:
            payload = write_frame(code, flags, cfg.mv_range, x[i].shape)
            out.append(_CHUNK.pack(len(payload), zlib.crc32(payload)))
            out.append(payload)
            _count_modes(mode_hist, code, flags)
            recs.append(rec)
            prev = rec
            i += 1
            bar.update(1)
    bar.close()
    enc_s = time.perf_counter() - t0
    rec = np.moveaxis(np.stack(recs), 1, -1)[:, :h, :w].astype(np.uint16)
    data = b"".join(out)
    stats = {"bytes": len(data), "bits_per_frame": 8 * len(data) / t, "encode_s": enc_s, "modes": mode_hist}
    return data, rec, stats


def _intra_batch(xs: np.ndarray, i0: int, cfg: CodecConfig, wmask, last_size: dict) -> list:
    """Encode consecutive I-frames xs (F, C, H, W) of an all-intra stream together.

    Block sizes follow the sequential rule: frame ``i`` tries all sizes when
    ``i % size_refresh == 0`` (or when no size was chosen yet), otherwise it reuses the
    size of the frame before it. The refresh frames are coded first (all sizes, one
    batch), then the others, grouped by the size they inherit.
    """
    f = len(xs)
    out: list = [None] * f
    idx = [k for k in range(f) if cfg.size_refresh <= 1 or (i0 + k) % cfg.size_refresh == 0
           or (k == 0 and False not in last_size)]
    if idx:
        res = encode_batch(xs[idx], None, cfg, wmask, [cfg.sizes()] * len(idx), last_size.get(False))
        for k, r in zip(idx, res, strict=True):
            out[k] = r
    sizes, cur = [], last_size.get(False)
    for k in range(f):
        cur = out[k][0].n if out[k] is not None else cur
        sizes.append(cur)
    rest = [k for k in range(f) if out[k] is None]
    if rest:
        res = encode_batch(xs[rest], None, cfg, wmask, [(sizes[k],) for k in rest])
        for k, r in zip(rest, res, strict=True):
            out[k] = r
    last_size[False] = out[-1][0].n
    return out


def _count_modes(hist: dict, code: FrameCode, flags) -> None:
    names = mode_set(*flags, code.n, code.p_frame).names()
    cnt = np.bincount(code.modes.ravel(), minlength=len(names))
    for name, k in zip(names, cnt, strict=True):
        if k == 0:
            continue
        key = f"{name}@{code.n}" if name.startswith("HIP") else name
        hist[key] = hist.get(key, 0) + int(k) * code.n * code.n  # in pixels


def read_header(data: bytes) -> tuple[StreamInfo, int]:
    """Parse and check the stream header -> (info, offset of the first frame chunk)."""
    if len(data) < _HDR.size + 4:
        raise FacesynthError(f"bitstream: truncated header ({len(data)} bytes)")
    if data[:4] != MAGIC:
        raise FacesynthError("bitstream: not an FSGV stream (bad magic)")
    (crc,) = struct.unpack_from("<I", data, _HDR.size)
    if zlib.crc32(data[:_HDR.size]) != crc:
        raise FacesynthError("bitstream: header CRC32 mismatch (corrupt stream)")
    _, ver, fl, c, depth, h, w, qp, gop, mvr, t, *bb = _HDR.unpack_from(data)
    if ver != VERSION or depth != 16 or c < 1 or h < 1 or w < 1 or gop < 1 or t < 1 or qp > QP_MAX:
        raise FacesynthError(f"bitstream: unsupported header (version {ver}, depth {depth}, {h}x{w}x{c})")
    if fl & ~31 or mvr > 32:
        raise FacesynthError(f"bitstream: unsupported header (flags {fl}, motion range {mvr})")
    if (len(data) - _HDR.size - 4) < t * (_CHUNK.size + 3):
        raise FacesynthError(f"bitstream: truncated ({len(data)} bytes cannot hold {t} frames)")
    check_limits(t, h, w, c, "bitstream header")
    if fl & 16 and not np.isfinite(bb).all():
        raise FacesynthError("bitstream: the header's bounding box is not finite")
    bbox = np.asarray(bb).reshape(2, 3) if fl & 16 else None
    info = StreamInfo(h, w, c, None if fl & 1 else qp, gop, mvr, t, (bool(fl & 2), bool(fl & 4), bool(fl & 8)), bbox)
    return info, _HDR.size + 4


def decode_video(data: bytes) -> tuple[np.ndarray, StreamInfo, dict]:
    """Decode an ``.fsgv`` stream -> (uint16 frames (T, H, W, C), info, timing stats)."""
    info, off = read_header(data)
    hp, wp = info.height + (-info.height % 16), info.width + (-info.width % 16)
    shape = (info.channels, hp, wp)
    if len(data) - off < info.n_frames * (_CHUNK.size + 3):
        raise FacesynthError(f"bitstream: truncated ({len(data)} bytes cannot hold {info.n_frames} frames)")
    out = []  # frames are allocated as they decode, so a forged header cannot force a huge allocation
    prev = None
    t0 = time.perf_counter()
    for i in progress_bar(range(info.n_frames), desc="decode", unit="frame"):
        if len(data) < off + _CHUNK.size:
            raise FacesynthError(f"bitstream: truncated at frame {i} of {info.n_frames} (chunk header)")
        ln, crc = _CHUNK.unpack_from(data, off)
        off += _CHUNK.size
        payload = data[off:off + ln]
        if len(payload) != ln:
            raise FacesynthError(f"bitstream: truncated at frame {i} of {info.n_frames} "
                                 f"({len(payload)} of {ln} payload bytes)")
        if zlib.crc32(payload) != crc:
            raise FacesynthError(f"bitstream: CRC32 mismatch in frame {i} (corrupt stream)")
        off += ln
        try:
            code, mvr = read_frame(payload, info.flags, shape, info.qp is None)
            if code.p_frame != bool(i % info.gop) or mvr != info.mv_range:
                raise ValueError("frame type or motion range disagrees with the header")
            rec = decode_frame(code, prev if code.p_frame else None, info.qp, info.flags, mvr, shape)
        except (ValueError, IndexError, RuntimeError, OverflowError, AssertionError, TypeError, KeyError,
                ZeroDivisionError) as exc:  # constriction asserts; any inconsistency of a CRC-valid frame
            raise FacesynthError(f"bitstream: frame {i} is malformed ({exc})") from None
        out.append(np.moveaxis(rec, 0, -1)[:info.height, :info.width].astype(np.uint16))
        prev = rec
    dec_s = time.perf_counter() - t0
    if off != len(data):
        raise FacesynthError(f"bitstream: {len(data) - off} unexpected bytes after the last frame")
    return np.stack(out), info, {"decode_s": dec_s}
