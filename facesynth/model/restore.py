"""A per-subject restoration filter: one small convolution on the rendered face crop that
gives back the detail the render path itself blurs (``model.restore=true``).

The render samples the frame into the reference frame and warps it back (bilinear both ways),
then the paste scales the crop into the frame (bilinear again): even the frame's own texture
comes back softer than the real frame (``rewarp`` keeps 0.50-0.66 of its gradient energy at
128 px). The filter ``K`` (k x k, one kernel for every colour channel) is fitted by least
squares on training frames so that the frame's own texture, rendered, filtered and pasted,
matches the real frame over the face::

    min_K  sum_frames sum_face px | paste(K * render(texture)) - frame |^2 + lam |K - delta|^2

Paste (an affine warp with bilinear interpolation) is linear, so each kernel tap contributes
the pasted, shifted crop as one column of the least-squares design, and the normal equations
are summed frame by frame (:data:`FIT_FRAMES` evenly spaced training frames, a seeded subset
of :data:`FIT_PIXELS` face pixels each). The kernel size (1 = none, 3, 5, 7) and ``lam`` (ridge towards no
filter) are chosen by two-fold blocked cross-validation over the training frames (the first
half against the second and back); the winner is refitted on all of them. Outside the face
the crop is zero, so before filtering, the pixels within the kernel's reach of the face are
filled with the mean of the face pixels around them (a normalised box filter), and the
result is cut back to the face: the convolution never reads black.

At render time :class:`Restore` runs inside the warp (:class:`facesynth.model.warp.ToTarget`),
so the evaluation, the torch synthesiser and the exported face-only graph (three depthwise Conv
nodes over row strips: the fill's box sums along x and along y, and the filter) all show the
filtered face.

**The mean first.** The filter is linear, so on a texture ``T = mean + v`` it adds ``D(mean) +
D(v)`` (``D = K - delta``). ``D(mean)`` is the same for every frame: the mean texture's own detail
given back, which is always where the warp puts it; ``D(v)`` also sharpens what the regressor got
wrong. A point ``t`` on the filter's path (:func:`path_parts`) applies the mean's part at
``min(t, 1)`` and the variation's at ``max(t - 1, 0)``: ``t = 2`` is the filter as fitted, ``t = 1``
the mean's part alone, which is a constant added to the texture before the warp
(:func:`mean_offset`, ``FaceModel.restore_offset``: no filter in the graph). The variation's part
is the crop's filter at that strength (the mean's part it also applies is taken off the offset).
On 17 shared clips at ``reference_width=auto`` the mean's part alone keeps 87 % of the face's
LPIPS gain at a third of the filter's own PSNR cost on the clips that lose most
(docs/studies/example-detail.md).

The filter, its fit, its PSNR curve and guard, and its path all read the same least-squares
design (:func:`_designs`), hence its length.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

SIZES = (3, 5, 7)
RIDGE = (1e-4, 1e-3, 1e-2)  # lam, as a fraction of the design's mean diagonal energy
FIT_FRAMES = 32  # evenly spaced training frames
FIT_PIXELS = 12000  # face pixels per frame (a seeded random subset; all when fewer)


# the image's rows are cut into this many strips (each with the kernel's reach of rows either side)
# that become channels of one depthwise Conv: ONNX Runtime runs a Conv 16 channels wide (its
# blocked NCHWc layout), so a one-channel Conv pays for 16; as channels, 3 x 16 strips fill them
STRIPS = 16


@functools.lru_cache(maxsize=32)
def _strip_rows(h: int, halo: int) -> tuple[np.ndarray, np.ndarray]:
    """For strips of ``sh`` = ceil(h / STRIPS) rows of an image ``h`` rows tall, with ``halo`` rows
    either side: int64 (STRIPS * (sh + 2 halo),) the source row of each strip row (``h`` beyond the
    image: the zero row appended to it), and float32 (STRIPS, sh + 2 halo, 1): 1 where that row
    lies inside the image, else 0."""
    sh = -(-h // STRIPS)
    rows = np.arange(STRIPS)[:, None] * sh + np.arange(sh + 2 * halo)[None] - halo
    inside = (rows >= 0) & (rows < h)
    return np.where(inside, rows, h).reshape(-1).astype(np.int64), inside[..., None].astype(np.float32)


class Restore(nn.Module):
    """``forward(img (B, C, H, W), mask (B, 1, H, W) in {0, 1})`` -> the face filtered by the
    (k, k) ``kernel`` (the same for every channel; a correlation, zero beyond the image), zero
    outside ``mask``.

    The image's rows are cut into :data:`STRIPS` strips with the kernel's reach either side (one
    row gather), the strips stacked as channels, and the fill's box sums (a 1 x k, then a k x 1
    box) and the filter are depthwise Convs over them (every channel the same kernel): in ONNX
    Runtime a Conv of fewer than 16 channels costs as much as one of 16, and 3 x 16 strips use
    what a one-channel Conv wastes (on a 300 px crop 5x faster than three one-channel Convs)."""

    def __init__(self, kernel: np.ndarray):
        super().__init__()
        k = np.asarray(kernel, np.float32)
        self.radius = k.shape[0] // 2
        self.register_buffer("kernel", torch.from_numpy(k.copy())[None, None])
        self.register_buffer("box", torch.ones(1, 1, 2 * self.radius + 1, 2 * self.radius + 1))

    def _filled_strips(self, img: torch.Tensor, mask: torch.Tensor, extra: int) -> torch.Tensor:
        """(B, C, STRIPS, sh + 2 extra, W): :meth:`fill`'s image in strips of ``sh`` rows with
        ``extra`` rows of the image either side (0 beyond the image)."""
        c, h, w = (int(v) for v in img.shape[1:])  # Python ints: constants of an exported graph
        r = self.radius
        rows, inside = _strip_rows(int(h), r + extra)
        x = F.pad(torch.cat([img, mask], 1), (0, 0, 0, 1))  # (B, C + 1, H + 1, W), a zero row last
        n, tall = STRIPS, len(rows) // STRIPS  # strips, rows per strip with the halo
        s = torch.index_select(x, 2, torch.from_numpy(rows)).reshape(-1, (c + 1) * n, tall, w)
        m = (c + 1) * n  # the box sums separably: along x, then along y
        sums = F.conv2d(s, self.box[:, :, :1].expand(m, -1, -1, -1), padding=(0, r), groups=m)
        sums = F.conv2d(sums, self.box[:, :, :, :1].expand(m, -1, -1, -1), groups=m)
        sums = sums.reshape(-1, c + 1, n, tall - 2 * r, w)  # num (C), den (1)
        inner = s.reshape(-1, c + 1, n, tall, w)[:, :, :, r:tall - r]
        valid = torch.from_numpy(np.ascontiguousarray(inside[:, r:tall - r]))  # 1 inside the image
        return inner[:, :c] + (valid - inner[:, c:]) * sums[:, :c] / torch.clamp(sums[:, c:], min=1.0)

    def fill(self, img: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """``img`` with the pixels outside ``mask`` within the kernel's reach set to the mean of
        the face pixels in their box (0 where there are none)."""
        c, h, w = (int(v) for v in img.shape[1:])  # Python ints: constants of an exported graph
        return self._filled_strips(img, mask, 0).reshape(-1, c, STRIPS * (-(-int(h) // STRIPS)), w)[:, :, :h]

    def forward(self, img: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        c, h, w = (int(v) for v in img.shape[1:])  # Python ints: constants of an exported graph
        r, n = self.radius, STRIPS
        sh = -(-int(h) // n)
        x = self._filled_strips(img, mask, r)  # (B, C, n, sh + 2r, W)
        y = F.conv2d(x.reshape(-1, c * n, sh + 2 * r, w), self.kernel.expand(c * n, -1, -1, -1), padding=(0, r),
                     groups=c * n)
        y = y.reshape(-1, c, n * sh, w)[:, :, :h]
        return torch.clamp(y, 0.0, 1.0) * mask


def _taps(size: int, full: int) -> np.ndarray:
    """Indices (into the (full, full) taps, raster order) of the centred (size, size) ones."""
    off = (full - size) // 2
    idx = np.arange(full * full).reshape(full, full)
    return idx[off : off + size, off : off + size].reshape(-1)


def _designs(model, seq, rows: np.ndarray, textures: np.ndarray, feather: float = 2.0, full: int = max(SIZES),
             seed_offset: int = 0):
    """Per frame of ``rows`` (textures rendered with ``model``, which must hold no kernel): the
    least-squares design ``(a (pixels * C, full * full), b (pixels * C,))``: column t is the
    rendered crop (filled, :meth:`Restore.fill`) shifted by tap t and pasted into the frame, over
    a seeded subset of :data:`FIT_PIXELS` face pixels; ``b`` is the real frame there, in [0, 1].
    Yields ``(index into rows, a, b)``; frames without face pixels are skipped."""
    for j, (a,), b in _design_sets(model, seq, rows, [textures], feather, full, seed_offset):
        yield j, a, b


def _design_sets(model, seq, rows: np.ndarray, sets: list[np.ndarray], feather: float = 2.0, full: int = max(SIZES),
                 seed_offset: int = 0):
    """:func:`_designs` of several texture sets of the same ``rows`` on the same pixels, each frame
    read once: yields ``(index into rows, [a of each set], b)``."""
    r = full // 2
    rows = np.asarray(rows)
    lm = seq.landmarks[rows][:, : model.mean_shape.shape[0]]
    rendered = [model.render(textures, lm) for textures in sets]
    _, masks, places = rendered[0]  # the mask and placement follow the landmarks alone
    n_taps = full * full
    fill = Restore(np.zeros((full, full), np.float32))
    for j, frame in enumerate(seq.iter_frames(rows)):
        msk = torch.from_numpy(masks[j])[None, None]
        h, w = frame.shape[:2]
        alpha = cv2.warpAffine(masks[j], places[j], (w, h), flags=cv2.INTER_LINEAR) > 0.999
        region = cv2.erode(alpha.astype(np.uint8), np.ones((2 * int(np.ceil(feather)) + 1,) * 2, np.uint8)) > 0
        ys, xs = np.nonzero(region)
        if len(ys) == 0:
            continue
        y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
        place = places[j].copy()
        place[0, 2] -= x0
        place[1, 2] -= y0
        sy, sx = np.nonzero(region[y0:y1, x0:x1])
        if len(sy) > FIT_PIXELS:
            keep = np.sort(np.random.default_rng(j + seed_offset).choice(len(sy), FIT_PIXELS, replace=False))
            sy, sx = sy[keep], sx[keep]
        designs = []
        for crops, _, _ in rendered:
            x = fill.fill(torch.from_numpy(crops[j]).permute(2, 0, 1)[None], msk)[0].permute(1, 2, 0).numpy()
            xp = cv2.copyMakeBorder(x, r, r, r, r, cv2.BORDER_CONSTANT, value=0)
            hh, ww = x.shape[:2]
            cols = []
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):  # conv2d is a correlation: tap (dy, dx) reads x[p + (dy, dx)]
                    shifted = np.ascontiguousarray(xp[r + dy : r + dy + hh, r + dx : r + dx + ww])
                    cols.append(cv2.warpAffine(shifted, place, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR)[sy, sx])
            designs.append(np.stack(cols, -1).reshape(-1, n_taps).astype(np.float64))  # (pixels * 3, taps)
        b = frame[y0:y1, x0:x1][sy, sx].reshape(-1).astype(np.float64) / 255.0
        yield j, designs, b


def fit_restoration(model, seq, rows: np.ndarray, textures: np.ndarray, feather: float = 2.0) -> tuple[np.ndarray | None, dict]:
    """(kernel or None, report) for a face model ``model`` (without a kernel) fitted on ``rows``
    of ``seq`` whose sampled textures are ``textures`` (len(rows), C * M); None when no filter
    beats none in cross-validation. report: the chosen ``size`` and ``ridge``, the frames used,
    and the held-out RMS (0-255) per size of the best ridge."""
    full = max(SIZES)
    pick = np.unique(np.linspace(0, len(rows) - 1, min(FIT_FRAMES, len(rows))).round().astype(int))
    n_taps = full * full
    folds = [np.zeros((n_taps, n_taps)), np.zeros((n_taps, n_taps))]
    rhs = [np.zeros(n_taps), np.zeros(n_taps)]
    energy = [0.0, 0.0]
    count = [0, 0]
    for j, a, b in _designs(model, seq, np.asarray(rows)[pick], textures[pick], feather, full):
        f = 0 if j < len(pick) / 2 else 1
        folds[f] += a.T @ a
        rhs[f] += a.T @ b
        energy[f] += float(b @ b)
        count[f] += len(b)
    centre = n_taps // 2
    scale = float(np.mean(np.diag(folds[0] + folds[1]))) / max(sum(count), 1)

    def solve(ata, atb, n, taps, lam):
        a_, b_ = ata[np.ix_(taps, taps)], atb[taps]
        delta = (taps == centre).astype(np.float64)
        return np.linalg.solve(a_ + lam * n * scale * np.eye(len(taps)), b_ + lam * n * scale * delta)

    def sse(ata, atb, bb, taps, k):
        return float(k @ ata[np.ix_(taps, taps)] @ k - 2 * k @ atb[taps] + bb)

    none = sum(sse(folds[f], rhs[f], energy[f], np.array([centre]), np.ones(1)) for f in (0, 1))
    best = (none, 1, 0.0)
    held_out = {"1": float(255 * np.sqrt(none / max(sum(count), 1)))}
    for size in SIZES:
        taps = _taps(size, full)
        best_size = None
        for lam in RIDGE:
            err = 0.0
            for f in (0, 1):
                k = solve(folds[f], rhs[f], count[f], taps, lam)
                err += sse(folds[1 - f], rhs[1 - f], energy[1 - f], taps, k)
            best_size = err if best_size is None else min(best_size, err)
            if err < best[0]:
                best = (err, size, lam)
        held_out[str(size)] = float(255 * np.sqrt(best_size / max(sum(count), 1)))
    _, size, lam = best
    report = {"size": size, "ridge": lam, "frames": int(len(pick)), "held_out_rms": held_out}
    if size == 1:
        return None, report
    taps = _taps(size, full)
    k = solve(folds[0] + folds[1], rhs[0] + rhs[1], sum(count), taps, lam)
    return k.reshape(size, size).astype(np.float32), report


GUARD_DB = 0.05  # the PSNR (dB) the restoration may cost on held-out predictions (choose_strength)
STRENGTHS = np.linspace(0.0, 1.0, 41)  # the strengths choose_strength tries


def _identity(size: int) -> np.ndarray:
    """float64 (size, size): the kernel that leaves an image as it is (``delta``)."""
    delta = np.zeros((size, size))
    delta[size // 2, size // 2] = 1.0
    return delta


def with_strength(kernel: np.ndarray, strength: float) -> np.ndarray:
    """``delta + strength * (kernel - delta)``: 0 = no filter, 1 = ``kernel``."""
    k = np.asarray(kernel, np.float64)
    delta = _identity(k.shape[0])
    return (delta + float(strength) * (k - delta)).astype(np.float32)


def strength_curve(model, seq, rows: np.ndarray, textures: np.ndarray, kernel: np.ndarray,
                   strengths: np.ndarray = STRENGTHS, feather: float = 2.0) -> np.ndarray:
    """The PSNR change (dB, mean over the frames of ``rows``) of the pasted face against the real
    frame when ``textures`` (e.g. a regressor's held-out predictions of those frames) are rendered
    through ``with_strength(kernel, s)`` instead of no filter, for every ``s`` of ``strengths``.
    ``model`` must hold no kernel. The error is quadratic in ``s`` per frame:
    ``|e0 + s d|^2`` with ``e0 = render - frame`` and ``d = (kernel - delta) * render``."""
    k = np.asarray(kernel, np.float64)
    full = k.shape[0]
    delta = _identity(full).reshape(-1)
    step = k.reshape(-1) - delta
    strengths = np.asarray(strengths, np.float64)
    change = []
    for _, a, b in _designs(model, seq, rows, textures, feather, full):
        e0 = a @ delta - b
        d = a @ step
        sse0 = float(e0 @ e0)
        sse = sse0 + 2 * strengths * float(e0 @ d) + strengths**2 * float(d @ d)
        change.append(-10 * np.log10(np.maximum(sse, 1e-20) / max(sse0, 1e-20)))
    return np.mean(change, 0) if change else np.zeros_like(strengths)


def choose_strength(curve: np.ndarray, strengths: np.ndarray = STRENGTHS, guard_db: float = GUARD_DB) -> float:
    """The largest strength (or path point) of ``strengths`` whose PSNR change on ``curve`` (dB, as
    from :func:`strength_curve` or :func:`path_curve`) is no worse than ``-guard_db`` (0 when none is)."""
    ok = np.asarray(curve) >= -float(guard_db)
    return float(np.max(np.asarray(strengths)[ok])) if ok.any() else 0.0


def mean_offset(model, kernel: np.ndarray) -> np.ndarray:
    """float32 (C * M,): ``D(mean)``, the filter's change to ``model``'s mean texture in the reference
    frame (filled and filtered as :class:`Restore` does a crop, clipped to [0, 1] as it is) minus the
    mean: what the filter adds to every frame's face at the mean's full strength."""
    samp = model.sampler()
    c = model.n_channels
    mean = torch.from_numpy(np.asarray(model.appearance_pca.mean, np.float32)).reshape(1, c, -1)
    with torch.no_grad():
        img = samp.to_image(mean, 0.0)
        mask = samp.to_image(torch.ones(1, 1, mean.shape[2]), 0.0)
        out = Restore(kernel)(img, mask).reshape(1, c, -1)[:, :, samp.mask_index]
    return (out - mean).reshape(-1).numpy().astype(np.float32)


PATH_POINTS = np.linspace(0.0, 2.0, 81)  # the points of the filter's path the guard tries (path_parts)


def path_parts(t: float) -> tuple[float, float]:
    """``(mean, variation)``: the strengths of the filter's parts at point ``t`` of its path (0..2):
    the mean's part first (``t`` <= 1), then the variation's."""
    t = float(np.clip(t, 0.0, 2.0))
    return min(t, 1.0), max(t - 1.0, 0.0)


def apply_path(model, kernel: np.ndarray, t: float) -> None:
    """Set ``model``'s filter (in place) to point ``t`` of the path of the full ``kernel``: the crop's
    filter at the variation's strength (None at 0) and, for the rest of the mean's part, the
    constant texture offset ``(mean - variation) D(mean)`` (None at 0)."""
    m, v = path_parts(t)
    model.restore_kernel = None if v <= 0 else with_strength(kernel, v)
    model.restore_offset = None if m - v <= 0 else ((m - v) * mean_offset(model, kernel)).astype(np.float32)


def path_curve(model, seq, rows: np.ndarray, textures: np.ndarray, kernel: np.ndarray,
               points: np.ndarray = PATH_POINTS, feather: float = 2.0) -> np.ndarray:
    """:func:`strength_curve` along the filter's path (:func:`path_parts`): the PSNR change (dB, mean
    over the frames of ``rows``) at each of ``points`` against no filter. Per frame the error is
    ``e0 + m dm + v dv`` with ``dm = (kernel - delta) * render(mean)`` and ``dv = (kernel - delta) *
    (render(texture) - render(mean))``, so its square is a quadratic form in (m, v). ``model`` must hold
    no filter."""
    k = np.asarray(kernel, np.float64)
    delta = _identity(k.shape[0]).reshape(-1)
    step = k.reshape(-1) - delta
    parts = np.array([path_parts(t) for t in np.asarray(points, np.float64)])  # (T, 2)
    m, v = parts[:, 0], parts[:, 1]
    rows = np.asarray(rows)
    mean = np.repeat(np.asarray(model.appearance_pca.mean, np.float32)[None], len(textures), 0)
    change = []
    for _, (a, am), b in _design_sets(model, seq, rows, [textures, mean], feather, k.shape[0]):
        e0, dm = a @ delta - b, am @ step
        dv = a @ step - dm
        sse0 = float(e0 @ e0)
        sse = (sse0 + 2 * m * float(e0 @ dm) + 2 * v * float(e0 @ dv) + m**2 * float(dm @ dm)
               + 2 * m * v * float(dm @ dv) + v**2 * float(dv @ dv))
        change.append(-10 * np.log10(np.maximum(sse, 1e-20) / max(sse0, 1e-20)))
    return np.mean(change, 0) if change else np.zeros(len(parts))


def fit_size(n_rows: int, n_val: int) -> int:
    """How many leading rows of ``n_rows`` a validation fit sees: those before the last ``n_val``
    (the validation slice) and a gap as long (no gap when the rows are too few for one)."""
    return n_rows - 2 * n_val if n_rows - 2 * n_val >= n_val else n_rows - n_val


def validation_predictions(fit, seq, rows: np.ndarray, n_val: int) -> tuple[int, np.ndarray, np.ndarray]:
    """``(before, val, pred)``: the validation slice ``val`` (the last ``n_val`` of ``rows``) and its
    textures ``pred`` (n_val, C * M) predicted by ``fit(np.arange(before))``, a synthesiser fitted on
    the first ``before`` rows: those before a gap of ``n_val`` rows (none when the rows are too few
    for one), so that the slice's frames lie beyond the fit's as the test frames lie beyond the
    training frames (see :func:`guard_restoration`)."""
    rows = np.asarray(rows)
    before = fit_size(len(rows), n_val)
    syn = fit(np.arange(before))
    val = rows[len(rows) - n_val :]
    with torch.no_grad():
        pred = syn.texture(torch.from_numpy(seq.landmarks[val])).reshape(n_val, -1).numpy()
    return before, val, pred


VALIDATION_SLICES = 4  # the guards' validation slices (slice_stops)


def slice_stops(n_rows: int, n_val: int, slices: int = VALIDATION_SLICES) -> list[int]:
    """Where the guards' validation slices end (row counts, earliest first): the last ``slices``
    blocks of ``n_val`` rows, each kept only when the rows before it and a gap as long number at
    least ``n_val`` (the last one always: without a gap when the rows are too few for one). One
    slice misjudges clips whose cost changes along the video: on vrt_face5 the filter at full
    strength gains 0.50 dB on the last slice, loses 0.60 dB on the first and 0.56 dB on the test
    frames (``bench/studies/width_guard.py`` shows the same for the reference width)."""
    stops = [n_rows - k * n_val for k in range(slices - 1, 0, -1)]
    return [stop for stop in stops if stop - 2 * n_val >= n_val] + [n_rows]


def full_kernel(model) -> np.ndarray | None:
    """The filter as fitted (``meta['restore']['kernel']``), whatever point of its path ``model`` is
    at; models without it (trained before the path) hold the kernel they apply."""
    k = model.meta.get("restore", {}).get("kernel") if isinstance(model.meta, dict) else None
    return np.asarray(k, np.float32) if k is not None else model.restore_kernel


def guard_restoration(fit, model, seq, rows: np.ndarray, n_val: int, guard_db: float = GUARD_DB) -> dict:
    """Move ``model``'s restoration filter (in place) to the farthest point of its path
    (:func:`path_parts`: the mean's part, then the variation's, up to ``1 + model.config.restore_variation``)
    whose PSNR cost is at most ``guard_db`` on every validation slice (:func:`slice_stops`: blocks of
    ``n_val`` at the end of ``rows``), each slice's textures predicted by ``fit(indices into rows)``: a
    synthesiser fitted on the rows before it and before a gap of ``n_val`` rows (what the filter
    will filter at run time, predictions of frames that lie beyond the training frames, not the
    frames' own textures; without the gap the slice's frames are too near the fit's, and the cost
    is underestimated: 0.16 against the test segment's 0.35 dB on lp_d13). Returns the report:
    ``path`` (the point), ``mean_strength`` and ``strength`` (the variation's) there,
    ``psnr_change_db`` at it, ``psnr_change_full_db`` at the path's end and ``curve_db`` (the change
    at :data:`PATH_POINTS` up to the end), each the worst slice's, and per slice (``slices``) its
    ``val_rows`` [start, stop), ``fit_frames`` and ``psnr_change_db`` at the point."""
    kernel = full_kernel(model)
    end = 1.0 + float(getattr(model.config, "restore_variation", 1.0))
    points = PATH_POINTS[PATH_POINTS <= end + 1e-9]
    rows = np.asarray(rows)
    curves, slices = [], []
    kept = model.restore_kernel, model.restore_offset
    model.restore_kernel, model.restore_offset = None, None
    try:
        for stop in slice_stops(len(rows), n_val):
            before, val, pred = validation_predictions(fit, seq, rows[:stop], n_val)
            curves.append(path_curve(model, seq, val, pred, kernel, points))
            slices.append({"val_rows": [stop - n_val, stop], "fit_frames": int(before)})
    finally:
        model.restore_kernel, model.restore_offset = kept
    curve = np.min(curves, 0)  # the worst slice at every point
    t = choose_strength(curve, points, guard_db)
    apply_path(model, kernel, t)
    at = int(np.flatnonzero(points == t)[0])
    for sl, c in zip(slices, curves, strict=True):
        sl["psnr_change_db"] = float(c[at])
    m, v = path_parts(t)
    return {"path": t, "mean_strength": m, "strength": v, "guard_db": float(guard_db), "val_frames": int(n_val),
            "fit_frames": slices[-1]["fit_frames"], "psnr_change_db": float(curve[at]), "psnr_change_full_db": float(curve[-1]),
            "curve_db": [round(float(c), 4) for c in curve], "slices": slices}
