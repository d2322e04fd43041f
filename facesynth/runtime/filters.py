"""The One Euro filter for landmark streams (numpy only).

G. Casiez, N. Roussel, D. Vogel, "1 Euro Filter: A Simple Speed-based Low-pass Filter
for Noisy Input in Interactive Systems", CHI 2012. An exponential smoother whose cutoff
rises with the signal's speed: ``fc = min_cutoff + beta * |dx/dt|`` (speed itself
smoothed at ``d_cutoff``), so slow jitter is removed and fast motion is not lagged.
"""

from __future__ import annotations

import numpy as np

from facesynth.errors import FacesynthError


def _alpha(cutoff: np.ndarray | float, dt: float) -> np.ndarray | float:
    tau = 1.0 / (2.0 * np.pi * cutoff)
    return 1.0 / (1.0 + tau / dt)


class OneEuroFilter:
    """Elementwise One Euro filter over arrays of a fixed shape (e.g. (68, 2) landmarks).

    Parameters
    ----------
    freq : float
        Sampling rate (Hz), e.g. the video fps.
    min_cutoff : float
        Cutoff (Hz) at zero speed: lower = smoother when still.
    beta : float
        Speed coefficient (per unit of the signal / s): higher = less lag when moving.
    d_cutoff : float
        Cutoff (Hz) of the speed estimate.
    """

    def __init__(self, freq: float, min_cutoff: float = 1.0, beta: float = 0.05, d_cutoff: float = 1.0):
        if not freq > 0 or not min_cutoff > 0 or not d_cutoff > 0 or beta < 0:
            raise FacesynthError(
                f"One Euro filter: need freq, min_cutoff, d_cutoff > 0 and beta >= 0, got "
                f"freq={freq}, min_cutoff={min_cutoff}, beta={beta}, d_cutoff={d_cutoff}"
            )
        self.freq, self.min_cutoff, self.beta, self.d_cutoff = float(freq), float(min_cutoff), float(beta), float(d_cutoff)
        self.reset()

    def reset(self) -> None:
        self._x: np.ndarray | None = None
        self._dx: np.ndarray | None = None

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Filter one sample (any shape, fixed across calls); returns float64 of that shape.

        NaN samples (no face) pass through as NaN and restart the filter afterwards.
        """
        x = np.asarray(x, np.float64)
        if not np.isfinite(x).all():
            self.reset()
            return x.copy()
        dt = 1.0 / self.freq
        if self._x is None:
            self._x, self._dx = x.copy(), np.zeros_like(x)
            return x.copy()
        dx = (x - self._x) / dt
        self._dx = self._dx + _alpha(self.d_cutoff, dt) * (dx - self._dx)
        cutoff = self.min_cutoff + self.beta * np.abs(self._dx)
        self._x = self._x + _alpha(cutoff, dt) * (x - self._x)
        return self._x.copy()


def smooth_landmarks(landmarks: np.ndarray, fps: float, min_cutoff: float = 1.0, beta: float = 0.05,
                     d_cutoff: float = 1.0) -> np.ndarray:
    """One Euro filter along time of (T, 68, 2) landmarks -> float32 (T, 68, 2) (NaN rows kept)."""
    f = OneEuroFilter(fps, min_cutoff, beta, d_cutoff)
    return np.stack([f(lm) for lm in np.asarray(landmarks)]).astype(np.float32)
