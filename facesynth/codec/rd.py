"""Rate-distortion sweeps, Bjontegaard deltas and RD plots.

Rates are the real bitstream sizes (header included); distortion is PSNR with peak
65535 over the coverage mask, i.e. vertex PSNR relative to the bounding-box diagonal.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.interpolate import PchipInterpolator

from facesynth.codec.bitstream import decode_video, encode_video
from facesynth.codec.frame import CodecConfig
from facesynth.io import atomic_path
from facesynth.metrics import psnr

# Named configurations compared by the benchmark: everything else equal.
CONFIGS: dict[str, dict] = {
    "hip-intra": dict(pdp=False, pvm=False, inter=False, gop=1),
    "hip+pdp-intra": dict(pdp=True, pvm=False, inter=False, gop=1),
    "hip+pdp+pvm": dict(pdp=True, pvm=True, inter=False, gop=10**4),
    "hip-ippp": dict(pdp=False, pvm=False, inter=True, gop=10**4),
    "hip+pdp+pvm-ippp": dict(pdp=True, pvm=True, inter=True, gop=10**4),
}


def modes_config(modes: str, gop: int, inter: bool) -> dict:
    """CLI ``--modes`` (hip, hip+pdp, hip+pdp-spatial) -> CodecConfig keyword arguments."""
    table = {"hip": (False, False), "hip+pdp": (True, True), "hip+pdp-spatial": (True, False)}
    pdp, pvm = table[modes]
    return dict(pdp=pdp, pvm=pvm and gop > 1, inter=inter and gop > 1, gop=gop)


def rd_point(video: np.ndarray, mask: np.ndarray | None, cfg: CodecConfig, check: bool = True) -> dict:
    """Encode (and decode) ``video`` (T, H, W, C) uint16 once -> figures of one RD point."""
    t0 = time.perf_counter()
    data, rec, st = encode_video(video, cfg, mask)
    enc_s = time.perf_counter() - t0
    out = {"qp": cfg.qp, "bytes": len(data), "bits_per_frame": 8 * len(data) / len(video),
           "bpp": 8 * len(data) / (len(video) * video.shape[1] * video.shape[2]),
           "psnr_db": psnr(video, rec, mask, peak=65535), "encode_fps": len(video) / enc_s}
    total = sum(st["modes"].values())
    out["mode_share"] = {k: round(v / total, 4) for k, v in sorted(st["modes"].items())}
    if check:
        t0 = time.perf_counter()
        dec, _, _ = decode_video(data)
        out["decode_fps"] = len(video) / (time.perf_counter() - t0)
        out["bit_exact"] = bool(np.array_equal(dec, rec))
    return out


def rd_sweep(video: np.ndarray, mask: np.ndarray | None, qps: list[int], configs: dict[str, dict],
             base: CodecConfig | None = None, check: bool = True) -> dict[str, list[dict]]:
    """RD points per named configuration over ``qps``."""
    base = base or CodecConfig()
    return {name: [rd_point(video, mask, replace(base, qp=qp, **kw), check) for qp in qps]
            for name, kw in configs.items()}


def bd_rate(rate_a, psnr_a, rate_b, psnr_b) -> dict:
    """Bjontegaard delta rate of B against A (negative: B needs fewer bits), in percent.

    log-rate is interpolated as a monotone cubic (PCHIP) in PSNR for each curve and
    integrated over the common PSNR range, which is returned with the result.
    """
    def curve(r, p):
        p, r = np.asarray(p, float), np.log(np.asarray(r, float))
        o = np.argsort(p)
        p, r = p[o], r[o]
        keep = np.concatenate([[True], np.diff(p) > 1e-9])
        return PchipInterpolator(p[keep], r[keep])

    lo = max(min(psnr_a), min(psnr_b))
    hi = min(max(psnr_a), max(psnr_b))
    if not np.isfinite([lo, hi]).all() or hi <= lo:
        return {"bd_rate_pct": None, "psnr_range_db": None}
    grid = np.linspace(lo, hi, 200)
    fa, fb = curve(rate_a, psnr_a), curve(rate_b, psnr_b)
    diff = np.trapezoid(fb(grid) - fa(grid), grid) / (hi - lo)
    return {"bd_rate_pct": float((np.exp(diff) - 1) * 100), "psnr_range_db": [float(lo), float(hi)]}


def bd_between(points: dict[str, list[dict]], a: str, b: str, min_psnr: float | None = None) -> dict:
    """:func:`bd_rate` of configuration ``b`` against ``a`` (optionally above ``min_psnr``)."""
    def rp(name):
        pts = [p for p in points[name] if np.isfinite(p["psnr_db"])]
        if min_psnr is not None:
            pts = [p for p in pts if p["psnr_db"] >= min_psnr]
        return [p["bits_per_frame"] for p in pts], [p["psnr_db"] for p in pts]

    (ra, pa), (rb, pb) = rp(a), rp(b)
    if len(pa) < 2 or len(pb) < 2:
        return {"bd_rate_pct": None, "psnr_range_db": None}
    return bd_rate(ra, pa, rb, pb)


def plot_rd(points: dict[str, list[dict]], path: str | Path, title: str = "") -> None:
    """RD curves (PSNR vs bits per pixel) to a PNG, written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FormatStrFormatter, LogLocator, NullFormatter

    fig, ax = plt.subplots(figsize=(6, 4.2))
    for name, pts in points.items():
        pts = [p for p in pts if np.isfinite(p["psnr_db"])]
        ax.plot([p["bpp"] for p in pts], [p["psnr_db"] for p in pts], "o-", label=name, ms=3)
    ax.set_xscale("log")
    # labels at 1, 2, 5 x 10^k only, plain numbers: matplotlib's default labels every minor
    # tick of a log axis spanning less than a decade, and those labels overlap
    ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(FormatStrFormatter("%g"))
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("bits per pixel (3 channels, 16 bit)")
    ax.set_ylabel("PSNR over mask, peak 65535 [dB]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)
