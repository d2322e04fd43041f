"""Small deterministic 68-point face shapes and smooth images for unit tests."""

import numpy as np


def face_template(width: float = 100.0, cx: float = 80.0, cy: float = 90.0) -> np.ndarray:
    """A plausible (68, 2) iBUG face, (x, y) pixels, built from arcs and ellipses."""
    s = width / 2
    t = np.linspace(np.pi, 0, 17)
    jaw = np.stack([np.cos(t) * s, np.sin(t) * s * 1.1 + 0.05 * s], -1)[::-1] * [-1, 1]
    jaw = jaw[::-1]
    bx = np.linspace(-0.85, -0.15, 5) * s
    brow_r = np.stack([bx, -0.55 * s - 0.15 * s * np.sin(np.linspace(0, np.pi, 5))], -1)
    brow_l = brow_r[::-1] * [-1, 1]
    nose_bridge = np.stack([np.zeros(4), np.linspace(-0.35, 0.1, 4) * s], -1)
    nose_base = np.stack([np.linspace(-0.2, 0.2, 5) * s, np.full(5, 0.2 * s) + 0.03 * s * np.cos(np.linspace(-1.2, 1.2, 5))], -1)

    def eye(cx_):
        a = np.linspace(np.pi, -np.pi, 7)[:6]
        return np.stack([cx_ + 0.18 * s * np.cos(a), -0.3 * s - 0.07 * s * np.sin(a)], -1)

    a = np.linspace(np.pi, -np.pi, 13)[:12]
    mouth_o = np.stack([0.4 * s * np.cos(a), 0.5 * s - 0.15 * s * np.sin(a)], -1)
    a = np.linspace(np.pi, -np.pi, 9)[:8]
    mouth_i = np.stack([0.3 * s * np.cos(a), 0.5 * s - 0.05 * s * np.sin(a)], -1)
    pts = np.concatenate([jaw, brow_r, brow_l, nose_bridge, nose_base, eye(-0.45 * s), eye(0.45 * s), mouth_o, mouth_i])
    assert pts.shape == (68, 2)
    return (pts + [cx, cy]).astype(np.float32)


def smooth_image(h: int, w: int, seed: int = 0) -> np.ndarray:
    """float32 (H, W, 3) in [0, 1]: a sum of low-frequency sinusoids (band-limited)."""
    rng = np.random.default_rng(seed)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    img = np.zeros((h, w, 3), np.float32)
    for c in range(3):
        for _ in range(4):
            fx, fy = rng.uniform(0.01, 0.06, 2)
            ph = rng.uniform(0, 2 * np.pi)
            img[..., c] += np.sin(fx * xs + fy * ys + ph)
    return (0.5 + 0.12 * img).clip(0, 1)


def random_similarity(rng, scale=(0.8, 1.2), angle=0.2, shift=10.0) -> np.ndarray:
    a = rng.uniform(-angle, angle)
    s = rng.uniform(*scale)
    return np.array([[s * np.cos(a), -s * np.sin(a), rng.uniform(-shift, shift)],
                     [s * np.sin(a), s * np.cos(a), rng.uniform(-shift, shift)]])


def face_sequence_arrays(n: int = 12, seed: int = 0, size: int = 180):
    """(frames uint8 (n, size, size, 3), landmarks (n, 68, 2)) with small expression changes."""
    rng = np.random.default_rng(seed)
    base = face_template()
    lms, frames = [], []
    for i in range(n):
        lm = base.copy()
        lm[48:68, 1] += np.where(lm[48:68, 1] > base[48:68, 1].mean(), 1, -0.3) * rng.uniform(0, 6)  # jaw/mouth
        lm[17:27, 1] -= rng.uniform(0, 4)  # brows
        lm += rng.normal(0, 0.3, lm.shape)
        lms.append(lm + rng.uniform(-3, 3, 2))
        frames.append((smooth_image(size, size, seed + i) * 255).astype(np.uint8))
    return np.stack(frames), np.stack(lms).astype(np.float32)
