"""Decoder fuzz worker, run in a subprocess by tests/test_reliability_codec.py under an
address-space limit: mutates a small real stream N ways, decodes each, prints one JSON
line (counts per outcome, per-case time, traced peak memory, any foreign exception)."""

from __future__ import annotations

import json
import resource
import struct
import sys
import time
import tracemalloc
import zlib

import numpy as np

from facesynth.codec.bitstream import _CHUNK, _HDR, decode_video, encode_video
from facesynth.codec.frame import CodecConfig
from facesynth.errors import FacesynthError

FIELDS = ["magic", "ver", "fl", "c", "depth", "h", "w", "qp", "gop", "mvr", "t"]
RANGES = {"ver": 255, "fl": 255, "c": 255, "depth": 255, "h": 65535, "w": 65535, "qp": 255, "gop": 65535,
          "mvr": 255, "t": 2**32 - 1}


def small_stream() -> bytes:
    """A real 4-frame 32x32x3 stream: intra and P-frames (PDP, PVM, inter)."""
    yy, xx = np.mgrid[:32, :32]
    v = np.stack([np.stack([xx * 900 + yy * 400 + 3000 * k + 700 * i + 50 * ((xx * yy + i) % 7) for k in range(3)], -1)
                  for i in range(4)]).astype(np.uint16)
    data, _, _ = encode_video(v, CodecConfig(qp=30, gop=2))
    return data


def forge_header(data: bytes, rng) -> bytes:
    f = list(_HDR.unpack_from(data))
    for name in rng.choice(FIELDS[1:], size=rng.integers(1, 4), replace=False):
        hi = RANGES[name]
        # half small plausible values, half anywhere in the field's range
        f[FIELDS.index(name)] = int(rng.integers(0, min(hi, 80) + 1) if rng.random() < 0.5 else rng.integers(0, hi + 1))
    hdr = _HDR.pack(*f)
    return hdr + struct.pack("<I", zlib.crc32(hdr)) + data[_HDR.size + 4:]


def forge_chunk(data: bytes, rng) -> bytes:
    """Mutate one frame payload and recompute its CRC, so the frame parser sees it."""
    off, chunks = _HDR.size + 4, []
    while off < len(data):
        ln, _ = _CHUNK.unpack_from(data, off)
        chunks.append((off, ln))
        off += _CHUNK.size + ln
    off, ln = chunks[rng.integers(len(chunks))]
    payload = bytearray(data[off + 8: off + 8 + ln])
    kind = rng.integers(3)
    if kind == 0:
        for _ in range(rng.integers(1, 6)):
            payload[rng.integers(len(payload))] ^= 1 << int(rng.integers(8))
    elif kind == 1:
        payload[: 3] = bytes(rng.integers(0, 256, 3, dtype=np.uint8))  # frame header: type, size, motion range
    else:
        payload = payload[: rng.integers(0, len(payload))]
    payload = bytes(payload)
    return data[:off] + _CHUNK.pack(len(payload), zlib.crc32(payload)) + payload + data[off + 8 + ln:]


def mutations(data: bytes, n: int, seed: int):
    rng = np.random.default_rng(seed)
    kinds = ["bitflip", "overwrite", "truncate", "garbage", "forged_header", "forged_chunk"]
    for i in range(n):
        kind = kinds[i % len(kinds)]
        b = bytearray(data)
        if kind == "bitflip":
            for _ in range(rng.integers(1, 9)):
                b[rng.integers(len(b))] ^= 1 << int(rng.integers(8))
        elif kind == "overwrite":
            pos = int(rng.integers(len(b)))
            b[pos:pos + int(rng.integers(1, 9))] = bytes(rng.integers(0, 256, 8, dtype=np.uint8))[:len(b[pos:pos + 8])]
        elif kind == "truncate":
            b = b[: rng.integers(0, len(b))]
        elif kind == "garbage":
            g = bytes(rng.integers(0, 256, int(rng.integers(0, 2 * len(data))), dtype=np.uint8))
            b = bytearray((b"FSGV" + g) if rng.random() < 0.5 else g)
        elif kind == "forged_header":
            b = bytearray(forge_header(data, rng))
        else:
            b = bytearray(forge_chunk(data, rng))
        yield kind, bytes(b)


def main(n: int, seed: int, limit_mb: int) -> None:
    data = small_stream()
    resource.setrlimit(resource.RLIMIT_AS, (limit_mb << 20, limit_mb << 20))
    decode_video(data)  # the clean stream decodes
    out = {"cases": 0, "decoded": 0, "rejected": 0, "foreign": [], "max_case_s": 0.0, "max_traced_mb": 0.0,
           "by_kind": {}, "stream_bytes": len(data)}
    tracemalloc.start()
    for kind, b in mutations(data, n, seed):
        tracemalloc.reset_peak()
        t0 = time.perf_counter()
        try:
            decode_video(b)
            res = "decoded"
        except FacesynthError:
            res = "rejected"
        except BaseException as exc:  # noqa: BLE001 - what the test looks for
            res = "foreign"
            out["foreign"].append(f"{kind}: {type(exc).__name__}: {str(exc)[:160]}")
        dt = time.perf_counter() - t0
        out["cases"] += 1
        out[res if res != "foreign" else "rejected"] += 0 if res == "foreign" else 1
        out["by_kind"].setdefault(kind, {}).setdefault(res, 0)
        out["by_kind"][kind][res] += 1
        out["max_case_s"] = max(out["max_case_s"], dt)
        out["max_traced_mb"] = max(out["max_traced_mb"], tracemalloc.get_traced_memory()[1] / 2**20)
    print(json.dumps(out))


if __name__ == "__main__":
    main(int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]))
