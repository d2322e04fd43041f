"""Temporal smoothing of head pose: the One Euro filter (Casiez, Roussel & Vogel, "1 Euro
Filter: A Simple Speed-based Low-pass Filter for Noisy Input in Interactive Systems",
CHI 2012) on translation and, on the rotation group, on the geodesic increment.

The cutoff frequency grows with the (smoothed) speed, ``f_c = min_cutoff + beta |v|``:
slow jitter is filtered hard, fast real motion passes with little lag. Rotation: the
increment ``r = log(R_hat_prev^T R)`` (axis-angle, rad) is scaled by the low-pass factor
alpha and applied, ``R_hat = R_hat_prev exp(alpha r)``, which stays a rotation and has no
quaternion sign ambiguity.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation


def _alpha(cutoff_hz: float, dt: float) -> float:
    tau = 1.0 / (2 * math.pi * cutoff_hz)
    return 1.0 / (1.0 + tau / dt)


class OneEuro:
    """One Euro filter on a vector signal (speed = norm of the derivative)."""

    def __init__(self, min_cutoff: float = 1.0, beta: float = 0.0, d_cutoff: float = 1.0):
        self.min_cutoff, self.beta, self.d_cutoff = min_cutoff, beta, d_cutoff
        self.x = self.dx = self.t = None

    def step(self, increment: np.ndarray, t: float) -> float:
        """Low-pass factor alpha for a raw increment (value - previous estimate) at time t (s)."""
        dt = max(t - self.t, 1e-6)
        self.t = t
        speed = np.asarray(increment, float) / dt
        a_d = _alpha(self.d_cutoff, dt)
        self.dx = a_d * speed + (1 - a_d) * self.dx
        return _alpha(self.min_cutoff + self.beta * float(np.linalg.norm(self.dx)), dt)

    def __call__(self, x: np.ndarray, t: float) -> np.ndarray:
        x = np.asarray(x, float)
        if self.x is None:
            self.x, self.dx, self.t = x.copy(), np.zeros_like(x), t
            return x.copy()
        a = self.step(x - self.x, t)
        self.x = a * x + (1 - a) * self.x
        return self.x.copy()


class PoseFilter:
    """One Euro smoothing of a pose sequence (R (3, 3), t (3,)), called once per frame
    in time order: ``R_s, t_s = f(R, t, time_s)``.

    ``min_cutoff`` (Hz) sets the smoothing at rest; ``beta_t`` (per cm/s) and ``beta_r``
    (per rad/s) how fast the cutoff opens with speed.
    """

    def __init__(self, min_cutoff: float = 1.0, beta_t: float = 0.05, beta_r: float = 0.5, d_cutoff: float = 1.0):
        self.trans = OneEuro(min_cutoff, beta_t, d_cutoff)
        self.rot = OneEuro(min_cutoff, beta_r, d_cutoff)
        self.R: np.ndarray | None = None

    def __call__(self, R: np.ndarray, t: np.ndarray, time_s: float) -> tuple[np.ndarray, np.ndarray]:
        t_s = self.trans(t, time_s)
        if self.R is None:
            self.R = np.asarray(R, float).copy()
            self.rot(np.zeros(3), time_s)
            return self.R.copy(), t_s
        r = Rotation.from_matrix(self.R.T @ R).as_rotvec()
        a = self.rot.step(r, time_s)
        self.R = self.R @ Rotation.from_rotvec(a * r).as_matrix()
        return self.R.copy(), t_s
