"""The rectangular parametric domain of the EIP: ``[0, 1]^2`` with three elliptic holes
(the two eyes and the mouth), the slit c' joining the eye holes along their centre row, the
slit d' from c's midpoint straight down to the mouth hole, and the seam from the mouth hole
straight down to the rim. It is meshed as a regular grid (right triangles: non-negative
cotangent weights) whose lines carry the slits, so the slits are mesh edges; the grid
nodes on a hole's outline are moved onto the ellipse.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from facesynth.errors import FacesynthError


@dataclass(frozen=True)
class Domain:
    """Elliptic holes ``(cu, cv, ru, rv)`` (centre and semi-axes in [0, 1], v up) and the
    number of grid cells per side.

    The eye holes share their centre row; the mouth hole is centred under the midpoint of
    c'. Centres are snapped to grid nodes. Smooth holes matter: at a sharp hole corner the
    integral curves fan out and the triangles beside it fold. The defaults follow the
    proportions of a face: hole perimeters about a tenth (eyes) and a sixth (mouth) of the rim's.
    """

    eye_r: tuple[float, float, float, float] = (0.30, 0.63, 0.085, 0.035)
    eye_l: tuple[float, float, float, float] = (0.70, 0.63, 0.085, 0.035)
    mouth: tuple[float, float, float, float] = (0.50, 0.27, 0.145, 0.04)
    grid: int = 128

    def holes(self) -> dict[str, tuple[float, float, float, float]]:
        n = self.grid
        out = {}
        for k in ("eye_r", "eye_l", "mouth"):
            cu, cv, ru, rv = getattr(self, k)
            out[k] = (round(cu * n) / n, round(cv * n) / n, ru, rv)
        er, el, mo = out["eye_r"], out["eye_l"], out["mouth"]
        mid = (er[0] + el[0]) / 2
        ok = (er[1] == el[1] and round(mid * n) == mid * n and abs(mo[0] - mid) < 1e-12
              and er[0] + er[2] < el[0] - el[2] and mo[1] + mo[3] < er[1] - er[3] and mo[1] - mo[3] > 0
              and er[0] - er[2] > 0 and el[0] + el[2] < 1 and er[1] + er[3] < 1
              and min(h[3] for h in out.values()) * n >= 3)
        if not ok:
            raise FacesynthError(f"Domain: holes {out} on a {n}-grid must be inside the square, the eyes on one "
                                 "row with a gap whose midpoint is a grid node, the mouth below and centred under "
                                 "it, every semi-axis at least 3 cells")
        return out

    def mesh(self):
        """Grid mesh of the domain (cells whose centre is in a hole removed, hole outline
        nodes moved radially onto the ellipse): ``V`` (n, 3) with z = 0, ``F``, ``loops``,
        ``c``, ``d``, ``seam``."""
        from facesynth.mesh.laplacian import drop_ears, ordered_boundary_loops

        n = self.grid
        holes = self.holes()
        ii, jj = np.meshgrid(np.arange(n), np.arange(n))
        ii, jj = ii.ravel(), jj.ravel()
        inside = np.zeros(len(ii), bool)
        for cu, cv, ru, rv in holes.values():
            inside |= ((ii + 0.5) / n - cu) ** 2 / ru**2 + ((jj + 0.5) / n - cv) ** 2 / rv**2 < 1
        ii, jj = ii[~inside], jj[~inside]
        a, b = jj * (n + 1) + ii, jj * (n + 1) + ii + 1
        c, d = (jj + 1) * (n + 1) + ii + 1, (jj + 1) * (n + 1) + ii
        F = drop_ears(np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]))
        used = np.unique(F)
        remap = np.full((n + 1) ** 2, -1, np.int64)
        remap[used] = np.arange(len(used))
        g = np.arange(n + 1) / n
        U, W = np.meshgrid(g, g)
        V = np.stack([U.ravel(), W.ravel(), np.zeros(U.size)], 1)[used]
        F = remap[F]
        loops = {}
        for lp in ordered_boundary_loops(F):
            ctr = V[lp, :2].mean(0)
            name = next((k for k, (cu, cv, ru, rv) in holes.items()
                         if (ctr[0] - cu) ** 2 / ru**2 + (ctr[1] - cv) ** 2 / rv**2 < 1), "outer")
            loops[name] = lp
            if name != "outer":
                cu, cv, ru, rv = holes[name]
                q = np.sqrt((V[lp, 0] - cu) ** 2 / ru**2 + (V[lp, 1] - cv) ** 2 / rv**2)
                V[lp, 0] = cu + (V[lp, 0] - cu) / q
                V[lp, 1] = cv + (V[lp, 1] - cv) / q
        # radial snapping can fold a thin triangle next to an outline: move the inner grid
        # node beside it into its one-ring's kernel
        fixed = np.zeros(len(V), bool)
        fixed[np.concatenate(list(loops.values()))] = True
        V[:, :2], _ = untangle(V[:, :2], F, fixed)
        er, el, mo = holes["eye_r"], holes["eye_l"], holes["mouth"]
        row = np.isclose(V[:, 1], er[1])
        c = np.nonzero(row & (V[:, 0] >= er[0] + er[2] - 1e-12) & (V[:, 0] <= el[0] - el[2] + 1e-12))[0]
        c = c[np.argsort(V[c, 0])]
        col = np.isclose(V[:, 0], mo[0])
        d = np.nonzero(col & (V[:, 1] <= er[1] + 1e-12) & (V[:, 1] >= mo[1] + mo[3] - 1e-12))[0]
        d = d[np.argsort(-V[d, 1])]
        seam = np.nonzero(col & (V[:, 1] <= mo[1] - mo[3] + 1e-12))[0]
        seam = seam[np.argsort(-V[seam, 1])]
        return V, F, loops, c, d, seam

    def coordinates(self):
        """The domain's :class:`~facesynth.mesh.eip.AnnulusCoords` (computed once per Domain)."""
        return _coordinates(self)

    def rim_point(self, tau: np.ndarray, ref) -> np.ndarray:
        """Points (k, 2) on the rim whose integral-curve label is ``tau`` (k,) (periodic 8)."""
        p = ref.V[ref.outer, :2]
        s = _rim_arclength(p)
        t = ref.tau[ref.outer]
        o = np.argsort(t)
        t, s = t[o], s[o]
        s = np.unwrap(s * (np.pi / 2)) / (np.pi / 2)
        tt = np.concatenate([t - 8, t, t + 8])
        ss = np.concatenate([s - 4 * np.sign(s[-1] - s[0]), s, s + 4 * np.sign(s[-1] - s[0])])
        return _rim_xy(np.mod(np.interp(np.mod(tau - t[0], 8) + t[0], tt, ss), 4.0))


def _rim_arclength(p: np.ndarray) -> np.ndarray:
    """Counter-clockwise arc length from (0, 0) along the unit square's rim of points on it."""
    u, v = p[:, 0], p[:, 1]
    eps = 1e-9
    return np.where(v < eps, u, np.where(u > 1 - eps, 1 + v, np.where(v > 1 - eps, 3 - u, 4 - v)))


def _rim_xy(s: np.ndarray) -> np.ndarray:
    side, r = np.floor(s).astype(int) % 4, s - np.floor(s)
    u = np.choose(side, [r, np.ones_like(r), 1 - r, np.zeros_like(r)])
    v = np.choose(side, [np.zeros_like(r), r, np.ones_like(r), 1 - r])
    return np.stack([u, v], 1)


@lru_cache(maxsize=4)
def _coordinates(dom: Domain):
    from facesynth.mesh.eip import annulus_coordinates

    V, F, loops, c, d, seam = dom.mesh()
    return annulus_coordinates(V, F, loops, c, d, seam)


def locate(ref, tau: np.ndarray, f: np.ndarray, k: int = 24) -> np.ndarray:
    """Domain points (n, 2) with coordinates ``(tau, f)``: point location in the domain's
    ``(tau, f)`` triangulation (three periodic copies in tau), then barycentric
    interpolation of the domain positions. A point in no candidate triangle takes the
    nearest one's clamped barycentrics."""
    T = np.concatenate([ref.F + s * len(ref.V) for s in range(3)])
    P = np.concatenate([np.stack([ref.tau + sh, ref.f * 8.0], 1) for sh in (-8.0, 0.0, 8.0)])
    X = np.tile(ref.V[:, :2], (3, 1))
    tree = cKDTree(P[T].mean(axis=1))
    q = np.stack([tau, f * 8.0], 1)
    _, cand = tree.query(q, k=k)
    tri = P[T[cand]]  # (n, k, 3, 2)
    v0, v1, v2 = tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :], q[:, None, :] - tri[..., 0, :]
    den = v0[..., 0] * v1[..., 1] - v1[..., 0] * v0[..., 1]
    den = np.where(np.abs(den) < 1e-300, 1e-300, den)
    l1 = (v2[..., 0] * v1[..., 1] - v1[..., 0] * v2[..., 1]) / den
    l2 = (v0[..., 0] * v2[..., 1] - v2[..., 0] * v0[..., 1]) / den
    lam = np.stack([1 - l1 - l2, l1, l2], -1)
    best = np.argmax(lam.min(-1), axis=1)
    rows = np.arange(len(q))
    w = np.clip(lam[rows, best], 0, None)
    w /= w.sum(1, keepdims=True)
    return np.einsum("nk,nkc->nc", w, X[T[cand[rows, best]]])


def signed_areas(uv: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Signed area (F,) of each triangle in the plane (positive: counter-clockwise)."""
    a, b, c = uv[F[:, 0]], uv[F[:, 1]], uv[F[:, 2]]
    return 0.5 * ((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1]))


def untangle(uv: np.ndarray, F: np.ndarray, fixed: np.ndarray, rounds: int = 30) -> tuple[np.ndarray, int]:
    """Local repair of folded triangles. Each free vertex of a flipped triangle moves into the
    kernel of its one-ring: a 3-variable linear program (scipy HiGHS) maximises the smallest
    signed area of its triangles (linear in its position), capped at the one-ring's mean
    area; rounds repeat (Gauss-Seidel) until nothing is flipped. Needed where the mesh's hole
    outline has a sharper corner than the domain's (the lip corners), where the integral
    curves fan out across a few triangles. Returns the new uv (V, 2) and the number of
    vertices moved."""
    from scipy.optimize import linprog

    uv = uv.copy()
    vf = sp.csr_matrix((np.ones(F.size), (F.ravel(), np.repeat(np.arange(len(F)), 3))), shape=(len(uv), len(F)))
    moved = set()
    for _ in range(rounds):
        bad = signed_areas(uv, F) <= 0
        if not bad.any():
            break
        for v in np.unique(F[bad]):
            if fixed[v]:
                continue
            tris = F[vf[v].indices]
            k = np.argmax(tris == v, axis=1)  # rotate so that v comes first
            b = uv[tris[np.arange(len(tris)), (k + 1) % 3]]
            c = uv[tris[np.arange(len(tris)), (k + 2) % 3]]
            # 2 area(x) = b x c + x_x (b_y - c_y) + x_y (c_x - b_x) >= t
            A = np.stack([-(b[:, 1] - c[:, 1]), -(c[:, 0] - b[:, 0]), np.ones(len(b))], 1)
            rhs = b[:, 0] * c[:, 1] - c[:, 0] * b[:, 1]
            cap = float(np.abs(signed_areas(uv, tris)).mean()) * 2
            res = linprog([0, 0, -1], A_ub=A, b_ub=rhs, bounds=[(None, None), (None, None), (None, cap)],
                          method="highs")
            if res.status == 0 and res.x[2] > 0:
                uv[v] = res.x[:2]
                moved.add(int(v))
    return uv, len(moved)
