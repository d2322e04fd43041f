"""EPnP: the non-iterative O(n) Perspective-n-Point solution of Lepetit, Moreno-Noguer
and Fua, "EPnP: An Accurate O(n) Solution to the PnP Problem", IJCV 81(2), 2009.

Every 3D point is written as a weighted sum of four control points, ``X_i = sum_j
a_ij c_j`` (sum_j a_ij = 1). The camera-frame control points are the unknowns (12
values); each correspondence gives two linear equations, ``M x = 0`` with M (2n, 12).
x lies in the span of the N right singular vectors of M with the smallest singular
values, ``x = sum_k beta_k v_k``; the betas follow from the preserved distances between
control points. The cases N = 1, 2, 3, 4 are all solved (N = 4 and 3 by the paper's
linearisation), each refined by Gauss-Newton on the betas (paper section 3.4), and the
solution with the smallest reprojection error is kept.
"""

from __future__ import annotations

import numpy as np

_PAIRS = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))


def control_points(X: np.ndarray) -> np.ndarray:
    """Four control points (4, 3): the centroid and the centroid plus the principal axes
    scaled by the points' standard deviation along them (paper section 3.1)."""
    c0 = X.mean(axis=0)
    D = X - c0
    w, V = np.linalg.eigh(D.T @ D / len(X))
    return np.vstack([c0, c0 + (np.sqrt(np.maximum(w, 1e-300)) * V).T])


def barycentric(X: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Weights alpha (N, 4) with ``X = alpha @ C`` and rows summing to 1."""
    B = (C[1:] - C[0]).T
    a = np.linalg.solve(B, (X - C[0]).T).T
    return np.column_stack([1.0 - a.sum(axis=1), a])


def _build_m(alpha: np.ndarray, x: np.ndarray, K: np.ndarray) -> np.ndarray:
    fu, fv, uc, vc = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    n = len(alpha)
    M = np.zeros((2 * n, 12))
    for j in range(4):
        M[0::2, 3 * j] = alpha[:, j] * fu
        M[0::2, 3 * j + 1] = alpha[:, j] * K[0, 1]
        M[0::2, 3 * j + 2] = alpha[:, j] * (uc - x[:, 0])
        M[1::2, 3 * j + 1] = alpha[:, j] * fv
        M[1::2, 3 * j + 2] = alpha[:, j] * (vc - x[:, 1])
    return M


def _l6x10(V: np.ndarray) -> np.ndarray:
    """L (6, 10) with ``L @ b = ||c_a - c_b||^2`` for the six control-point pairs, where
    b = [b11, b12, b22, b13, b23, b33, b14, b24, b34, b44] and ``b_kl = beta_k beta_l``."""
    L = np.zeros((6, 10))
    for r, (a, b) in enumerate(_PAIRS):
        d = [V[k].reshape(4, 3)[a] - V[k].reshape(4, 3)[b] for k in range(4)]
        L[r] = [
            d[0] @ d[0], 2 * d[0] @ d[1], d[1] @ d[1], 2 * d[0] @ d[2], 2 * d[1] @ d[2],
            d[2] @ d[2], 2 * d[0] @ d[3], 2 * d[1] @ d[3], 2 * d[2] @ d[3], d[3] @ d[3],
        ]
    return L


def _b_vector(beta: np.ndarray) -> np.ndarray:
    b1, b2, b3, b4 = beta
    return np.array([b1 * b1, b1 * b2, b2 * b2, b1 * b3, b2 * b3, b3 * b3, b1 * b4, b2 * b4, b3 * b4, b4 * b4])


def _gauss_newton(L: np.ndarray, rho: np.ndarray, beta: np.ndarray, iters: int = 5) -> np.ndarray:
    """Refine the four betas minimising ``sum (L b(beta) - rho)^2`` (paper eq. 15)."""
    beta = beta.astype(float).copy()
    for _ in range(iters):
        b1, b2, b3, b4 = beta
        J = np.column_stack([
            2 * b1 * L[:, 0] + b2 * L[:, 1] + b3 * L[:, 3] + b4 * L[:, 6],
            b1 * L[:, 1] + 2 * b2 * L[:, 2] + b3 * L[:, 4] + b4 * L[:, 7],
            b1 * L[:, 3] + b2 * L[:, 4] + 2 * b3 * L[:, 5] + b4 * L[:, 8],
            b1 * L[:, 6] + b2 * L[:, 7] + b3 * L[:, 8] + 2 * b4 * L[:, 9],
        ])
        r = rho - L @ _b_vector(beta)
        try:
            beta += np.linalg.solve(J.T @ J, J.T @ r)
        except np.linalg.LinAlgError:
            beta += np.linalg.lstsq(J, r, rcond=None)[0]
    return beta


def _betas_n1(V: np.ndarray, Cw: np.ndarray) -> np.ndarray:
    v = V[0].reshape(4, 3)
    num = sum(np.linalg.norm(v[a] - v[b]) * np.linalg.norm(Cw[a] - Cw[b]) for a, b in _PAIRS)
    den = sum(np.linalg.norm(v[a] - v[b]) ** 2 for a, b in _PAIRS)
    return np.array([num / den, 0.0, 0.0, 0.0])


def _beta12(b: np.ndarray) -> tuple[float, float]:
    """beta1, beta2 from (b11, b12, b22, ...) with the sign rule of the authors' reference
    code (and OpenCV): the sign of b12 sets the sign of beta1, whatever the sign of b11."""
    if b[0] < 0:
        b1, b2 = np.sqrt(-b[0]), (np.sqrt(-b[2]) if b[2] < 0 else 0.0)
    else:
        b1, b2 = np.sqrt(b[0]), (np.sqrt(b[2]) if b[2] > 0 else 0.0)
    return (-b1 if b[1] < 0 else b1), b2


def _betas_n2(L: np.ndarray, rho: np.ndarray) -> np.ndarray:
    b = np.linalg.lstsq(L[:, [0, 1, 2]], rho, rcond=None)[0]  # b11, b12, b22
    b1, b2 = _beta12(b)
    return np.array([b1, b2, 0.0, 0.0])


def _betas_n3(L: np.ndarray, rho: np.ndarray) -> np.ndarray:
    b = np.linalg.lstsq(L[:, [0, 1, 2, 3, 4]], rho, rcond=None)[0]  # b11, b12, b22, b13, b23
    b1, b2 = _beta12(b)
    return np.array([b1, b2, b[3] / b1 if b1 != 0 else 0.0, 0.0])


def _betas_n4(L: np.ndarray, rho: np.ndarray) -> np.ndarray:
    b = np.linalg.lstsq(L[:, [0, 1, 3, 6]], rho, rcond=None)[0]  # b11, b12, b13, b14
    s = -1.0 if b[0] < 0 else 1.0
    b1 = np.sqrt(abs(b[0]))
    return np.array([b1, s * b[1] / b1, s * b[2] / b1, s * b[3] / b1]) if b1 > 0 else np.zeros(4)


def absolute_orientation(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R and translation t minimising ``sum ||R A_i + t - B_i||^2`` (Kabsch/Horn,
    no scale); A, B (N, 3)."""
    ca, cb = A.mean(axis=0), B.mean(axis=0)
    U, _, Vt = np.linalg.svd((B - cb).T @ (A - ca))
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ S @ Vt
    return R, cb - R @ ca


def _pose_from_betas(beta, V, alpha, X):
    """R, t aligning the world points to the camera-frame points given by the betas.

    When the best orthogonal map is a reflection (noisy, nearly planar points whose depth
    came out mirrored), the camera z row is negated, as in the authors' reference code:
    this undoes the depth reversal instead of forcing the nearest proper rotation."""
    cc = sum(beta[k] * V[k] for k in range(4)).reshape(4, 3)
    Xc = alpha @ cc
    if np.median(Xc[:, 2]) < 0:  # the sign of the null-space combination is free
        Xc = -Xc
    ca, cb = X.mean(axis=0), Xc.mean(axis=0)
    U, _, Vt = np.linalg.svd((Xc - cb).T @ (X - ca))
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R[2] = -R[2]
    return R, cb - R @ ca


def _reprojection(R, t, K, X, x) -> float:
    Xc = X @ R.T + t
    p = Xc @ K.T
    return float(np.linalg.norm(p[:, :2] / p[:, 2:3] - x, axis=1).mean())


def epnp(X: np.ndarray, x: np.ndarray, K: np.ndarray, return_all: bool = False):
    """EPnP pose (R (3, 3), t (3,)) with ``x ~ K (R X + t)``.

    Parameters
    ----------
    X : (N, 3) world points, N >= 4; x : (N, 2) pixels; K : (3, 3) intrinsics.
    return_all : also return ``{N: (R, t, reprojection_error)}`` for N = 1..4.
    """
    X = np.asarray(X, float)
    x = np.asarray(x, float)
    K = np.asarray(K, float)
    Cw = control_points(X)
    alpha = barycentric(X, Cw)
    M = _build_m(alpha, x, K)
    _, vecs = np.linalg.eigh(M.T @ M)
    V = vecs[:, :4].T  # V[0]: smallest eigenvalue
    L = _l6x10(V)
    rho = np.array([np.sum((Cw[a] - Cw[b]) ** 2) for a, b in _PAIRS])
    inits = {1: _betas_n1(V, Cw), 2: _betas_n2(L, rho), 3: _betas_n3(L, rho), 4: _betas_n4(L, rho)}
    results = {}
    for n, beta0 in inits.items():
        beta = _gauss_newton(L, rho, beta0)
        R, t = _pose_from_betas(beta, V, alpha, X)
        results[n] = (R, t, _reprojection(R, t, K, X, x))
    best = min(results, key=lambda k: results[k][2])
    R, t, _ = results[best]
    return (R, t, results) if return_all else (R, t)
