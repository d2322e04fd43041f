"""Expression-invariant parameterisation (EIP; Xia et al. 2012, sec. IV, Algorithm 1).

A segmented face with four boundaries (outer rim, two eyes, mouth; see
:mod:`facesynth.mesh.segment`) is mapped to a rectangle with three holes
(:class:`Domain`) so that the eyes and mouth land on the holes
for every expression:

1. geodesic ``c`` joins the eye loops and ``d`` joins c's midpoint to the mouth loop (shortest
   edge paths, so that the mesh can be cut along them; through the midline landmarks when
   they are given, see :func:`face_cuts`);
2. a harmonic function ``f`` is 0 on the outer rim and 1 on the inner boundary (eyes, mouth,
   c and d); the same is solved on the domain, whose c' and d' are straight slits;
3. the inner boundaries correspond by arc length, piece by piece (mouth, d, c, eye, c, eye,
   c, d), which gives every inner point a feature-aligned label ``tau`` in [0, 8);
4. the integral curves of grad f run from the inner to the outer boundary; the curve through
   a point is labelled by the ``tau`` where it starts. The integral curves are the level
   lines of the stream function ``g`` (the harmonic conjugate, ``grad g = n x grad f``),
   found by sparse least squares on the mesh cut open along c, d and a seam, so the label of
   every vertex is a 1-D lookup ``tau(g)`` rather than a curve traced per vertex (the tests
   trace gradient curves in the domain and check that g stays constant along them);
5. a mesh vertex with coordinates ``(tau, f)`` maps to the domain point with the same
   ``(tau, f)`` (point location in the domain's ``(tau, f)`` triangulation).

Boundary vertices are placed exactly: inner ones on the hole outlines and slits by ``tau``,
outer ones on the rectangle's rim. Where the mesh's hole outline has a sharper corner than
the domain's ellipse (the lip corners) a few triangles can fold; :func:`untangle` moves their
free vertices into the kernels of their one-rings (reported as ``untangled``). ``f`` uses
libigl's intrinsic Delaunay cotangent Laplacian (non-negative weights, hence a discrete
maximum principle and no spurious critical points on obtuse scan triangles); libigl also cuts
the mesh (``cut_mesh``) and gives the gradient operator. :func:`harmonic_disk` is the plain
harmonic map to a disk (HM) for comparison.

The domain (the second half of this module): the rectangular parametric domain of the EIP: ``[0, 1]^2`` with three elliptic holes
(the two eyes and the mouth), the slit c' joining the eye holes along their centre row, the
slit d' from c's midpoint straight down to the mouth hole, and the seam from the mouth hole
straight down to the rim. It is meshed as a regular grid (right triangles: non-negative
cotangent weights) whose lines carry the slits, so the slits are mesh edges; the grid
nodes on a hole's outline are moved onto the ellipse.

One module for the method and its domain: each half calls the other (the domain's
``(tau, f)`` coordinates are computed by the method's steps 2-4), hence its length.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve
from scipy.spatial import cKDTree

from facesynth.errors import FacesynthError, MissingExtraError
from facesynth.landmarks import NOSE_BRIDGE
from facesynth.mesh.laplacian import cotangent_laplacian, face_normals, ordered_boundary_loops
from facesynth.mesh.paths import edge_graph, shortest_path

FEATURES = ("eye_r", "eye_l", "mouth")
# midline landmarks the cuts c and d pass through: nose bridge top, nose tip, subnasale, upper-lip top
MIDLINE = (NOSE_BRIDGE[0], NOSE_BRIDGE[-1], 33, 51)


def _igl():
    try:
        import igl
    except ImportError:
        raise MissingExtraError("scan", "libigl") from None
    return igl


@dataclass
class AnnulusCoords:
    """Per cut-vertex coordinates of a face cut open along c, d and the seam.

    Attributes
    ----------
    V, F : the cut mesh; src : (Vc,) original vertex of each cut vertex.
    tau : (Vc,) feature-aligned label of the integral curve through the vertex, unwrapped to
        ``[tau_seam, tau_seam + 8]``; f : (Vc,) harmonic coordinate (0 outer, 1 inner).
    inner, outer : ordered cut-vertex runs of the inner and outer boundaries.
    eye_order : the eye met first after the mouth along the inner boundary.
    """

    V: np.ndarray
    F: np.ndarray
    src: np.ndarray
    tau: np.ndarray
    f: np.ndarray
    inner: np.ndarray
    outer: np.ndarray
    eye_order: str
    g: np.ndarray


def _edge_set(path: np.ndarray, closed: bool = False) -> set[tuple[int, int]]:
    p = np.asarray(path)
    q = np.roll(p, -1) if closed else p[1:]
    p = p if closed else p[:-1]
    return {(min(a, b), max(a, b)) for a, b in zip(p.tolist(), q.tolist(), strict=True)}


def harmonic_levels(V: np.ndarray, F: np.ndarray, zero: np.ndarray, one: np.ndarray) -> np.ndarray:
    """Harmonic f (V,) with f = 0 on ``zero`` and 1 on ``one`` (intrinsic Delaunay cotangent Laplacian)."""
    L = _igl().intrinsic_delaunay_cotmatrix(V, F)[0].tocsr()
    n = len(V)
    fixed = np.zeros(n, bool)
    fixed[zero] = fixed[one] = True
    val = np.zeros(n)
    val[one] = 1.0
    free = np.nonzero(~fixed)[0]
    out = val.copy()
    out[free] = spsolve(L[free][:, free].tocsc(), -(L[free][:, fixed] @ val[fixed]))
    return out


def stream_function(V: np.ndarray, F: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Least-squares g (V,) with grad g = n x grad f per triangle (area-weighted), g[0] = 0.

    On a mesh cut to a disk g is single-valued and its level lines are the integral curves
    of grad f."""
    G = _igl().grad(V, F).tocsr()
    m = len(F)
    gf = (G @ f).reshape(3, m).T
    r = np.cross(face_normals(V, F), gf)
    area = 0.5 * np.linalg.norm(face_normals(V, F, unit=False), axis=1)
    W = sp.diags(np.tile(area, 3))
    A = (G.T @ W @ G).tocsr()
    b = G.T @ (W @ r.T.ravel())
    g = np.zeros(len(V))
    g[1:] = spsolve(A[1:, 1:].tocsc(), b[1:])
    return g


def cut_along(V: np.ndarray, F: np.ndarray, cut_edges: set[tuple[int, int]]):
    """libigl ``cut_mesh`` along undirected edges -> (Vc, Fc, src)."""
    C = np.zeros(F.shape, bool)
    for k in range(3):
        a, b = F[:, k], F[:, (k + 1) % 3]
        C[:, k] = [(min(x, y), max(x, y)) in cut_edges for x, y in zip(a.tolist(), b.tolist(), strict=True)]
    Vc, Fc, src = _igl().cut_mesh(np.ascontiguousarray(V, np.float64), np.ascontiguousarray(F, np.int64), C)
    return np.asarray(Vc), np.asarray(Fc, np.int64), np.asarray(src, np.int64)


def annulus_coordinates(V: np.ndarray, F: np.ndarray, loops: dict[str, np.ndarray], c: np.ndarray,
                        d: np.ndarray, seam: np.ndarray) -> AnnulusCoords:
    """Steps 2-4 of the module docstring on one surface (a face mesh or the domain).

    ``loops``: ordered ``outer``, ``eye_r``, ``eye_l``, ``mouth``; ``c`` (eye_r -> eye_l),
    ``d`` (c's midpoint -> mouth) and ``seam`` (mouth -> outer) are vertex paths.
    """
    inner_ids = np.unique(np.concatenate([loops["eye_r"], loops["eye_l"], loops["mouth"], c, d]))
    f = harmonic_levels(V, F, loops["outer"], inner_ids)
    Vc, Fc, src = cut_along(V, F, _edge_set(c) | _edge_set(d) | _edge_set(seam))
    bl = ordered_boundary_loops(Fc)
    if len(bl) != 1:
        raise FacesynthError(f"parameterisation: cutting along c, d and the seam left {len(bl)} boundaries, "
                             "expected a disk (are the four loops the only boundaries?)")
    ring = bl[0]
    fc = f[src]
    on_inner = np.isin(src[ring], inner_ids)
    # rotate the disk boundary so that it starts with the first inner vertex after an outer/seam one
    k0 = int(np.nonzero(on_inner & ~np.roll(on_inner, 1))[0][0])
    ring = np.roll(ring, -k0)
    on_inner = np.roll(on_inner, -k0)
    n_in = int(np.argmin(on_inner)) if not on_inner.all() else len(ring)
    if on_inner[n_in:].any():
        raise FacesynthError("parameterisation: the inner boundary is not one run (does a cut touch the rim?)")
    inner = ring[:n_in]
    types = _edge_types(src[inner], loops, c, d)
    tau_in, eye_order = _tau_along(Vc[inner], types, src[inner] == d[0])
    # outer run: the f = 0 vertices in boundary order
    rest = ring[n_in:]
    outer = rest[np.isin(src[rest], loops["outer"])]
    g = stream_function(Vc, Fc, fc)
    if g[inner[-1]] < g[inner[0]]:
        g = -g
    g_in = np.maximum.accumulate(g[inner])
    period = g_in[-1] - g_in[0]
    # periodic extension: just beside the seam, curves start on the inner boundary's far end
    tau = np.interp(g, np.concatenate([g_in[:-1] - period, g_in, g_in[1:] + period]),
                    np.concatenate([tau_in[:-1] - 8.0, tau_in, tau_in[1:] + 8.0]))
    tau[inner] = tau_in
    # along the rim the labels must run monotonically (they do in the continuum: grad f is
    # never tangent to the rim); a jagged rim can break that at a few vertices
    to = tau[outer]
    tau[outer] = np.minimum.accumulate(to) if to[-1] < to[0] else np.maximum.accumulate(to)
    return AnnulusCoords(Vc, Fc, src, tau, fc, inner, outer, eye_order, g)


def _edge_types(ids: np.ndarray, loops, c, d) -> list[str]:
    """Curve name of each edge (ids[k], ids[k+1]) along the inner run."""
    sets = {name: _edge_set(loops[name], closed=True) for name in FEATURES}
    sets["c"], sets["d"] = _edge_set(c), _edge_set(d)
    out = []
    for a, b in zip(ids[:-1].tolist(), ids[1:].tolist(), strict=True):
        e = (min(a, b), max(a, b))
        name = next((k for k, s in sets.items() if e in s), None)
        if name is None:
            raise FacesynthError("parameterisation: an inner-boundary edge is on no loop or cut")
        out.append(name)
    return out


def _tau_along(P: np.ndarray, types: list[str], is_mid: np.ndarray) -> tuple[np.ndarray, str]:
    """Unwrapped tau along the inner run (which starts and ends inside the mouth loop).

    Each of the 8 pieces is parameterised by arc length; the far side of c, which passes
    c's midpoint ``is_mid`` (where d starts), by arc length on each half, so that both sides
    of c give every vertex of c the same point of the slit c'."""
    runs = [[types[0], 0, 1]]
    for k, t in enumerate(types[1:], 1):
        if t == runs[-1][0]:
            runs[-1][2] = k + 1
        else:
            runs.append([t, k, k + 1])
    names = [r[0] for r in runs]
    pattern = ["mouth", "d", "c", "eye", "c", "eye", "c", "d", "mouth"]
    if [("eye" if n.startswith("eye") else n) for n in names] != pattern or names[3] == names[5]:
        raise FacesynthError(f"parameterisation: unexpected inner boundary order {names}")
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    tau = np.empty(len(P))
    # mouth: the tail run (index 8) then the head run (index 0), one segment [0, 1)
    a0, a1 = runs[0][1], runs[0][2]
    b0, b1 = runs[8][1], runs[8][2]
    mouth_len = (arc[a1] - arc[a0]) + (arc[b1] - arc[b0])
    tail = arc[b1] - arc[b0]
    tau[a0:a1 + 1] = (tail + arc[a0:a1 + 1] - arc[a0]) / mouth_len
    for k in range(1, 8):
        s0, s1 = runs[k][1], runs[k][2]
        mid = np.nonzero(is_mid[s0 + 1:s1])[0]
        if names[k] == "c" and len(mid):
            sm = s0 + 1 + int(mid[0])
            tau[s0:sm + 1] = k + 0.5 * (arc[s0:sm + 1] - arc[s0]) / (arc[sm] - arc[s0])
            tau[sm:s1 + 1] = k + 0.5 + 0.5 * (arc[sm:s1 + 1] - arc[sm]) / (arc[s1] - arc[sm])
        else:
            tau[s0:s1 + 1] = k + (arc[s0:s1 + 1] - arc[s0]) / (arc[s1] - arc[s0])
    tau[b0:b1 + 1] = 8.0 + (arc[b0:b1 + 1] - arc[b0]) / mouth_len
    return tau, names[3]


def _path_via(V, F, points, blocked_base) -> np.ndarray:
    """Shortest edge path through ``points`` (each a vertex or an array of candidate
    vertices: the first and last may be loops), legs not crossing earlier legs."""
    path: list[int] = []
    cur = np.atleast_1d(points[0])
    for nxt in points[1:]:
        nxt = np.atleast_1d(nxt)
        blocked = np.setdiff1d(np.concatenate([blocked_base, np.asarray(path[:-1], np.int64)]), np.r_[cur, nxt])
        leg = shortest_path(edge_graph(V, F, blocked=blocked), cur, nxt)
        path = path[:-1] + leg.tolist() if path else leg.tolist()
        cur = leg[-1:]
    return np.asarray(path, np.int64)


def face_cuts(V: np.ndarray, F: np.ndarray, loops: dict[str, np.ndarray], landmarks: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 1: c (eye_r loop -> eye_l loop), d (c's midpoint -> mouth loop) and the seam
    (mouth loop -> outer rim, leaving the mouth on the far side from d) as edge paths.

    With ``landmarks`` (68,) local vertex ids, the paths run through the midline landmarks
    so that they are the same on every frame and the face stays left-right symmetric: c
    through the nose bridge (iBUG 28, its midpoint), d through the nose tip, subnasale and
    upper-lip top (iBUG 31, 34, 52). Without them d may go round either side of the nose.
    """
    boundary = np.concatenate([loops[k] for k in ("outer", *FEATURES)])
    eyes = np.concatenate([loops["eye_r"], loops["eye_l"]])
    mids = None if landmarks is None else np.asarray(landmarks)[list(MIDLINE)]
    use = mids is not None and (mids >= 0).all() and not np.isin(mids, boundary).any()
    if use:
        c = _path_via(V, F, [loops["eye_r"], mids[0], loops["eye_l"]], np.setdiff1d(boundary, eyes))
        m = int(np.nonzero(c == mids[0])[0][0])
    else:
        g = edge_graph(V, F, blocked=np.setdiff1d(boundary, eyes))
        c = shortest_path(g, loops["eye_r"], loops["eye_l"])
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(V[c], axis=0), axis=1))])
        m = int(np.argmin(np.abs(arc - arc[-1] / 2)))
    if m in (0, len(c) - 1):
        raise FacesynthError("parameterisation: the eye loops touch (no vertex between them)")
    blocked = np.setdiff1d(np.concatenate([np.delete(c, m), loops["outer"], eyes]), loops["mouth"])
    stops = [c[m], *(mids[1:] if use else []), loops["mouth"]]
    d = _path_via(V, F, stops, blocked)
    # the seam leaves the mouth at the vertex farthest (along the loop) from d's end
    mouth = loops["mouth"]
    k_end = int(np.nonzero(mouth == d[-1])[0][0])
    start = mouth[(k_end + len(mouth) // 2) % len(mouth)]
    blocked = np.concatenate([c, d, eyes, np.setdiff1d(mouth, [start])])
    seam = shortest_path(edge_graph(V, F, blocked=blocked), start, loops["outer"])
    return c, d, seam


@dataclass
class EIPResult:
    """Per-vertex parametric coordinates of a face in the rectangular domain.

    uv : float64 (V, 2) in [0, 1]^2 (v up, as OBJ UVs); f, tau : (V,); c, d, seam : paths;
    flipped : number of triangles with non-positive signed area in uv.
    untangled : vertices moved by :func:`untangle`.
    """

    uv: np.ndarray
    f: np.ndarray
    tau: np.ndarray
    c: np.ndarray
    d: np.ndarray
    seam: np.ndarray
    flipped: int
    untangled: int = 0


def parameterise(V: np.ndarray, F: np.ndarray, loops: dict[str, np.ndarray], landmarks: np.ndarray | None = None,
                 domain: Domain | None = None) -> EIPResult:
    """EIP of a face with loops ``outer``, ``eye_r``, ``eye_l``, ``mouth`` (see the module
    docstring); ``landmarks`` (68,) local vertex ids (-1: absent) steer the cuts (:func:`face_cuts`).

    Returns
    -------
    EIPResult with ``uv`` (V, 2) in [0, 1]^2.
    """
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    missing = [k for k in ("outer", *FEATURES) if k not in loops]
    if missing:
        raise FacesynthError(f"parameterisation: the face has no {missing} loop (segment it with remove_features)")
    dom = domain or Domain()
    c, d, seam = face_cuts(V, F, loops, landmarks)
    mesh = annulus_coordinates(V, F, loops, c, d, seam)
    ref = dom.coordinates()
    if ref.eye_order != mesh.eye_order:
        raise FacesynthError("parameterisation: the mesh is oriented against the domain (faces' normals must "
                             "point towards the viewer, +z)")
    uv_cut = np.empty((len(mesh.V), 2))
    t = mesh.tau  # unwrapped like the domain's (both start at the seam inside the mouth segment)
    ti, xi = ref.tau[ref.inner], ref.V[ref.inner, :2]
    ti, xi = np.concatenate([ti[:-1] - 8.0, ti, ti[1:] + 8.0]), np.concatenate([xi[:-1], xi, xi[1:]])
    inner = np.zeros(len(mesh.V), bool)
    inner[mesh.inner] = True
    outer = np.zeros(len(mesh.V), bool)
    outer[mesh.outer] = True
    for k in range(2):
        uv_cut[inner, k] = np.interp(t[inner], ti, xi[:, k])
    uv_cut[outer] = dom.rim_point(t[outer], ref)
    rim = uv_cut[mesh.outer]
    for corner in ((0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)):
        rim[np.argmin(np.linalg.norm(rim - corner, axis=1))] = corner
    uv_cut[mesh.outer] = rim
    rest = ~(inner | outer)
    uv_cut[rest] = locate(ref, t[rest], mesh.f[rest])
    uv = np.zeros((len(V), 2))
    cnt = np.bincount(mesh.src, minlength=len(V))
    np.add.at(uv, mesh.src, uv_cut)
    uv /= np.maximum(cnt, 1)[:, None]
    fixed = np.zeros(len(V), bool)
    fixed[mesh.src[inner | outer]] = True
    uv, moved = untangle(uv, F, fixed)
    tau = np.zeros(len(V))
    tau[mesh.src] = np.mod(mesh.tau, 8.0)
    f = np.zeros(len(V))
    f[mesh.src] = mesh.f
    return EIPResult(uv, f, tau, c, d, seam, int((signed_areas(uv, F) <= 0).sum()), moved)


def harmonic_disk(V: np.ndarray, F: np.ndarray, outer: np.ndarray, start: int | None = None) -> np.ndarray:
    """HM: harmonic map (cotangent Laplacian) with the ordered ``outer`` loop on the circle
    inscribed in [0, 1]^2 by arc length from ``start`` (a vertex of the loop; default its
    first); other boundaries free. Returns (V, 2)."""
    V = np.asarray(V, np.float64)
    outer = np.asarray(outer, np.int64)
    if start is not None:
        outer = np.roll(outer, -int(np.nonzero(outer == start)[0][0]))
    seg = np.linalg.norm(V[np.roll(outer, -1)] - V[outer], axis=1)
    th = -np.pi / 2 + 2 * np.pi * np.concatenate([[0.0], np.cumsum(seg)[:-1]]) / seg.sum()
    L = cotangent_laplacian(V, F)
    free = np.setdiff1d(np.arange(len(V)), outer)
    uv = np.zeros((len(V), 2))
    uv[outer] = 0.5 + 0.5 * np.stack([np.cos(th), np.sin(th)], 1)
    A = L[free][:, free].tocsc()
    B = L[free][:, outer]
    for k in range(2):
        uv[free, k] = spsolve(A, -(B @ uv[outer, k]))
    return uv


# ---------------------------------------------------------------------------------------------- the domain


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
