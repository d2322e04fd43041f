"""The embedded default subject: a **synthetic** face video whose appearance depends on shape.

This is not a real person and not a photorealistic renderer. It is a deterministic
cartoon-like face, generated from a seed, built so that the learning problems of
facesynth (shape -> appearance mapping, after Cootes-style shape/appearance models) are
well posed and testable without any data download:

* landmarks follow four expression controls (``jaw_open``, ``smile``, ``brow_raise``,
  ``eye_close``; see :mod:`facesynth.data.synthetic_shape`) plus a slight head motion
  (small similarity transform: translation, roll, scale);
* the image is a function of those landmarks only (plus sensor noise): the renderer
  recovers the controls from the landmarks (:func:`estimate_pose_and_controls`) and
  draws shape-dependent detail -- forehead wrinkles that deepen as the brows rise,
  nasolabial folds and cheek shading with smiles, a dark mouth interior and teeth as
  the jaw opens, eyelids that cover the eyes as they close;
* lighting is constant (a fixed light direction; the shading moves with the head);
  mild Gaussian sensor noise (``noise_sigma`` grey levels) is added per frame.

Rendering is vectorised numpy/OpenCV: anti-aliased filled polygons (sub-pixel,
``cv2.LINE_AA``) from the landmarks, smooth shading and wrinkle line patterns computed
per pixel in face coordinates, on bounding boxes only. 300 frames at 256 x 256 take about
3 s of CPU time.
"""

from __future__ import annotations

import numpy as np

from facesynth.data.frames import ArrayFrames
from facesynth.data.sequence import FaceSequence, validate_landmarks
from facesynth.data.synthetic_draw import Alpha, DrawFrame, Shaded, bbox, bezier, blend
from facesynth.data.synthetic_shape import (
    CONTROL_NAMES,
    MEAN_SHAPE,
    estimate_pose_and_controls,
    pose_matrices,
    shapes_from_controls,
    smooth_controls,
    smooth_head_motion,
)
from facesynth.errors import FacesynthError
from facesynth.geometry import apply_affine, invert_affine
from facesynth.landmarks import BROWS, INNER_LIPS, JAW, LEFT_BROW, LEFT_EYE, OUTER_LIPS, RIGHT_BROW, RIGHT_EYE

__all__ = ["CONTROL_NAMES", "make_synthetic_sequence", "render_faces", "synthetic_landmarks"]

_SKIN = np.array([0.87, 0.68, 0.56], np.float32)
_HAIR = np.array([0.22, 0.14, 0.09], np.float32)
_BROW = np.array([0.26, 0.17, 0.11], np.float32)
_LIP = np.array([0.74, 0.40, 0.39], np.float32)
_MOUTH = np.array([0.20, 0.05, 0.07], np.float32)
_TEETH = np.array([0.86, 0.84, 0.78], np.float32)  # in the mouth's shade
_SCLERA = np.array([0.93, 0.91, 0.88], np.float32)
_IRIS = np.array([0.36, 0.24, 0.13], np.float32)
_LIGHT = np.array([-0.35, -0.45, 0.82], np.float32) / np.linalg.norm([-0.35, -0.45, 0.82])


def _render_one(L: np.ndarray, c: np.ndarray, f: DrawFrame, background: np.ndarray) -> np.ndarray:
    """Draw one face. L: (68, 2) landmarks in face units; c: (K,) controls in [0, 1]."""
    jaw_open, smile, brow, eye_close = c
    img = background.copy()
    lam = _lighting(f)
    shade = (0.5 + 0.55 * lam)[..., None]
    face_a, fringe = _draw_head(img, L, f, lam, shade)
    _draw_creases(img, L, f, smile, brow, face_a, fringe)
    _draw_nose(img, L, f, face_a)
    _draw_eyes(img, L, f, shade)
    _draw_brows(img, L, f)
    _draw_mouth(img, L, f, shade, jaw_open)
    return img


def _lighting(f: DrawFrame) -> np.ndarray:
    """(H, W) Lambertian term of a head-sized ellipsoid under a fixed light (normal rotated
    with the head roll); 0.5 outside the head."""
    U, V, h = f.U, f.V, f.head
    Uh, Vh = U[h], V[h]
    nx, ny = Uh / 0.52, (Vh - 0.42) / 0.78
    nz = np.sqrt(np.clip(1.0 - nx**2 - ny**2, 0.02, 1.0))
    ca, sa = np.cos(f.angle), np.sin(f.angle)
    lam = np.full(U.shape, 0.5, np.float32)
    lam[h] = np.clip((ca * nx - sa * ny) * _LIGHT[0] + (sa * nx + ca * ny) * _LIGHT[1] + nz * _LIGHT[2], 0, 1)

    return lam


def _draw_head(img: np.ndarray, L: np.ndarray, f: DrawFrame, lam: np.ndarray, shade: np.ndarray):
    """Hair, ears, neck, the face (jaw contour closed by a forehead arc) and the fringe;
    (face alpha, fringe alpha), (H, W) each."""
    U, V, h = f.U, f.V, f.head
    Uh, Vh = U[h], V[h]
    skin = Shaded(_SKIN, shade)
    # hair behind the head, ears, neck
    r_hair = np.sqrt((Uh / 0.6) ** 2 + ((Vh - 0.3) / 0.62) ** 2)
    hair_a = np.zeros_like(U)
    hair_a[h] = np.clip((1.0 - r_hair) * 0.6 * f.ppu, 0, 1) * np.clip((0.62 - Vh) * f.ppu * 0.2, 0, 1)
    hair_col = Shaded(_HAIR, (0.8 + 0.4 * lam)[..., None])
    blend(img, Alpha(hair_a, f.box([[-0.6, -0.32], [0.6, -0.32], [-0.6, 0.62], [0.6, 0.62]], 0.01)), hair_col)
    for sgn in (-1, 1):
        ear = np.array([[sgn * 0.44, 0.36], [sgn * 0.53, 0.32], [sgn * 0.55, 0.45], [sgn * 0.5, 0.6], [sgn * 0.45, 0.62]])
        blend(img, f.poly(ear), _SKIN * 0.8)
    neck = np.array([[-0.25, 0.8], [0.25, 0.8], [0.3, 1.8], [-0.3, 1.8]])
    blend(img, f.poly(neck), _SKIN * 0.68)

    # face: jaw contour closed by a forehead arc
    y0 = 0.5 * (L[0, 1] + L[16, 1])
    th = np.linspace(0, np.pi, 24)
    arc = np.stack([0.46 * np.cos(th) * (L[16, 0] - L[0, 0]) / 0.9, y0 - 0.5 * np.sin(th)], 1)
    face = f.poly(np.concatenate([L[list(JAW)], arc[1:-1]]))
    face_a = face.a
    blend(img, face, skin)
    # hairline fringe over the upper forehead
    fringe = np.zeros_like(U)
    fringe[h] = np.clip((-0.06 - Vh - 0.05 * np.cos(Uh * 9.0) + 0.35 * Uh**2) * f.ppu * 0.5, 0, 1) * face_a[h]
    blend(img, Alpha(fringe, face.s), hair_col)

    return face_a, fringe


def _draw_creases(img: np.ndarray, L: np.ndarray, f: DrawFrame, smile, brow, face_a: np.ndarray, fringe: np.ndarray) -> None:
    """Cheeks, forehead wrinkles and nasolabial folds, growing with the smile and the brow raise."""
    U, V = f.U, f.V
    # cheeks: raised, brighter apples and a shadow below them with smiles
    for sgn in (-1, 1):
        f.shade_blob(img, -(0.03 + 0.10 * smile), sgn * 0.21, 0.57 - 0.035 * smile, 0.07, mask=face_a)
        if smile > 0.01:
            f.shade_blob(img, 0.20 * smile, sgn * 0.25, 0.72, 0.05, 0.04, mask=face_a)

    # forehead wrinkles: horizontal line pattern, contrast grows with brow raise
    top = L[list(BROWS), 1].min()
    if brow > 0.005:
        s = f.box([[-0.3, top - 0.2], [0.3, top - 0.2], [-0.3, top], [0.3, top]], 0.01)
        Us, Vs = U[s], V[s]
        win = np.exp(-((Us / 0.27) ** 4)) * face_a[s] * (1 - fringe[s])
        wr = np.zeros_like(Us)
        for k in range(4):
            vk = top - 0.045 - 0.034 * k + 0.25 * Us**2 + 0.004 * np.sin(Us * 23.0 + 1.7 * k)
            wr += np.exp(-(((Vs - vk) / 0.0075) ** 2)) - 0.3 * np.exp(-(((Vs - vk + 0.012) / 0.008) ** 2))
        img[s] *= 1.0 - (0.45 * brow**1.3 * win * wr)[..., None]

    # nasolabial folds: curves from the nose wings past the mouth corners
    for nose_i, corner_i, sgn in ((31, 48, -1), (35, 54, 1)):
        p0 = L[nose_i] + [sgn * 0.03, -0.02]
        p2 = L[corner_i] + [sgn * 0.03, 0.07]
        p1 = 0.5 * (p0 + p2) + [sgn * 0.045, -0.01]
        fold = f.line(bezier(p0, p1, p2), 0.010, blur=0.006)
        img[fold.s] *= 1.0 - ((0.04 + 0.30 * smile) * fold.a[fold.s])[..., None]



def _draw_nose(img: np.ndarray, L: np.ndarray, f: DrawFrame, face_a: np.ndarray) -> None:
    # nose: side shadows, tip highlight, nostrils, shadow below
    for sgn in (-1, 1):
        f.shade_blob(img, 0.08, sgn * 0.045, 0.42, 0.02, 0.09, mask=face_a)
    f.shade_blob(img, -0.08, L[30, 0], L[30, 1] + 0.01, 0.025)
    t = np.linspace(0, 2 * np.pi, 20)
    for a_i, b_i in ((31, 32), (34, 35)):
        m_ = 0.5 * (L[a_i] + L[b_i]) + [0, -0.012]
        nos = m_ + np.stack([0.022 * np.cos(t), 0.011 * np.sin(t)], 1)
        blend(img, f.poly(nos), np.array([0.30, 0.15, 0.13], np.float32), 0.85)
    f.shade_blob(img, 0.12, L[33, 0], L[33, 1] + 0.035, 0.05, 0.015)
    ala = bezier(L[31] + [-0.02, -0.035], L[33] + [0.0, 0.02], L[35] + [0.02, -0.035])
    blend(img, f.line(ala, 0.008, blur=0.004), _SKIN * 0.5, 0.25)



def _draw_eyes(img: np.ndarray, L: np.ndarray, f: DrawFrame, shade: np.ndarray) -> None:
    U, V = f.U, f.V
    # eyes: sclera, iris clipped by the lids, upper-lid skin, lashes, crease
    for idx in (np.array(RIGHT_EYE), np.array(LEFT_EYE)):
        e = L[idx]
        eye = f.poly(e)
        blend(img, eye, _SCLERA)
        s = f.box(e, 0.01)
        ea = eye.a[s]
        w = e[3, 0] - e[0, 0]
        ctr = np.array([0.5 * (e[0, 0] + e[3, 0]), 0.5 * (e[0, 1] + e[3, 1]) + 0.002])
        r = np.hypot(U[s] - ctr[0], V[s] - ctr[1]) * f.ppu
        rad = 0.23 * abs(w) * f.ppu
        sub = img[s]
        iris_a = (np.clip(rad - r + 0.5, 0, 1) * ea)[..., None]
        sub += iris_a * (_IRIS * (0.7 + 0.5 * np.clip(r / rad, 0, 1))[..., None] - sub)
        sub += (np.clip(0.45 * rad - r + 0.5, 0, 1) * ea)[..., None] * (np.array([0.04, 0.03, 0.03], np.float32) - sub)
        hl = 0.9 * np.exp(-0.5 * ((U[s] - ctr[0] + 0.012) ** 2 + (V[s] - ctr[1] + 0.012) ** 2) / 0.006**2) * ea
        sub += hl[..., None] * (1.0 - sub)
        # upper lid skin: between the (fixed) crease and the moving lid margin
        crease = MEAN_SHAPE[idx[[3, 2, 1, 0]]] + np.array([[0.0, -0.028], [0.0, -0.035], [0.0, -0.035], [0.0, -0.028]])
        crease[:, 0] += L[idx[0], 0] - MEAN_SHAPE[idx[0], 0]
        crease[:, 1] += L[idx[0], 1] - MEAN_SHAPE[idx[0], 1]
        blend(img, f.poly(np.concatenate([e[:4], crease])), Shaded(_SKIN * 0.86, shade))
        blend(img, f.line(crease, 0.006, blur=0.004), _SKIN * 0.55, 0.35)
        blend(img, f.line(e[:4], 0.014), np.array([0.12, 0.08, 0.07], np.float32), 0.95)
        blend(img, f.line(e[[3, 4, 5, 0]], 0.006), np.array([0.45, 0.3, 0.28], np.float32), 0.35)



def _draw_brows(img: np.ndarray, L: np.ndarray, f: DrawFrame) -> None:
    # brows: tapered filled bands around the brow points
    for idx in (np.array(RIGHT_BROW), np.array(LEFT_BROW)):
        b = L[idx]
        thick = np.linspace(0.010, 0.019, 5) if idx[0] == 17 else np.linspace(0.019, 0.010, 5)
        off = np.stack([0 * thick, thick], 1)
        blend(img, f.poly(np.concatenate([b - off, (b + off)[::-1]])), _BROW, 0.92)



def _draw_mouth(img: np.ndarray, L: np.ndarray, f: DrawFrame, shade: np.ndarray, jaw_open) -> None:
    U, V = f.U, f.V
    # mouth: lips, dark interior, upper and lower teeth, lip line
    blend(img, f.poly(L[list(OUTER_LIPS)]), Shaded(_LIP, shade))
    upper = np.concatenate([L[48:55], L[[64, 63, 62, 61, 60]]])
    blend(img, f.poly(upper), Shaded(_LIP * 0.85, shade))
    inner = f.poly(L[list(INNER_LIPS)])
    blend(img, inner, _MOUTH)
    if jaw_open > 0.005 and (s := bbox(inner.a)) is not None:
        Us, Vs, ia, sub = U[s], V[s], inner.a[s], img[s]
        y_up = np.interp(Us, L[60:65, 0], L[60:65, 1])
        y_lo = np.interp(Us, L[[60, 67, 66, 65, 64], 0], L[[60, 67, 66, 65, 64], 1])
        half = 0.5 * (L[64, 0] - L[60, 0]) + 1e-6
        du = np.abs(Us - 0.5 * (L[60, 0] + L[64, 0])) / half  # 0 at the centre, 1 at the corners
        gap = np.maximum(y_lo - y_up, 0.0)
        t_up = np.clip((np.minimum(0.03, 0.3 * gap) - (Vs - y_up)) * f.ppu, 0, 1) * np.clip((0.7 - du) * 6.0, 0, 1) * ia
        gaps = 1.0 - 0.3 * np.exp(-((((Us - L[62, 0]) / 0.034) % 1.0 - 0.5) / 0.07) ** 2)
        tone = (1.0 - 0.45 * du**2)[..., None]
        sub += t_up[..., None] * (_TEETH * tone * gaps[..., None] - sub)
        t_lo = np.clip((np.minimum(0.016, 0.15 * gap) - (y_lo - Vs)) * f.ppu, 0, 1) * np.clip((0.5 - du) * 6.0, 0, 1) * ia * (1 - t_up)
        sub += t_lo[..., None] * (_TEETH * 0.8 * tone - sub)
    blend(img, f.line(L[60:65], 0.009), np.array([0.33, 0.12, 0.12], np.float32), 0.6)


def render_faces(landmarks: np.ndarray, size: int = 256, seed: int = 0, noise_sigma: float = 2.0) -> np.ndarray:
    """Render the synthetic subject for any landmarks of its shape model.

    Parameters
    ----------
    landmarks : np.ndarray
        (T, 68, 2) or (68, 2) image landmarks (x, y pixels, 0-based iBUG), as produced
        by :func:`synthetic_landmarks`. Pose and expression are recovered from them, so
        the image is a deterministic function of the landmarks (plus noise). Other
        shapes (e.g. noisy landmarks) are projected on the model by least squares:
        similarity from the rigid points, controls clipped to [0, 1].
    size : int
        Image side in pixels (square images).
    seed : int
        Seed of the sensor noise.
    noise_sigma : float
        Standard deviation of the additive Gaussian noise, in grey levels (0 = none).

    Returns
    -------
    np.ndarray
        uint8 (T, size, size, 3) RGB frames.
    """
    lm = validate_landmarks(landmarks, "synthetic landmarks")
    m, controls = estimate_pose_and_controls(lm)
    local = apply_affine(lm.astype(np.float64), invert_affine(m))
    controls = np.clip(controls, 0.0, 1.0)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    grid = np.stack([xx, yy])
    g = np.linspace(0.0, 1.0, size, dtype=np.float32)[:, None, None]
    background = (np.array([0.58, 0.64, 0.70], np.float32) * (1.05 - 0.2 * g)) * np.ones((1, size, 1), np.float32)
    rng = np.random.default_rng([seed, 7919])
    out = np.empty((len(lm), size, size, 3), np.uint8)
    for t in range(len(lm)):
        img = _render_one(local[t], controls[t], DrawFrame(size, m[t], grid), background)
        img *= 255.0
        if noise_sigma > 0:
            img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(noise_sigma)
        np.clip(img + 0.5, 0, 255, out=img)
        out[t] = img.astype(np.uint8)
    return out


def synthetic_landmarks(controls: np.ndarray, pose: np.ndarray | None = None, size: int = 256) -> np.ndarray:
    """Image landmarks (T, 68, 2) float32 of the synthetic subject.

    Parameters
    ----------
    controls : np.ndarray
        (T, K) expression controls in [0, 1], columns in ``CONTROL_NAMES`` order.
    pose : np.ndarray, optional
        (T, 4) head motion (dx, dy as fractions of ``size``, roll in degrees, log scale);
        zeros (frontal, centred) by default.
    size : int
        Image side in pixels.
    """
    controls = np.atleast_2d(np.asarray(controls, dtype=np.float64))
    if controls.shape[1] != len(CONTROL_NAMES):
        raise FacesynthError(f"controls must have shape (T, {len(CONTROL_NAMES)}) ({', '.join(CONTROL_NAMES)}), got {controls.shape}")
    pose = np.zeros((len(controls), 4)) if pose is None else np.atleast_2d(pose)
    return apply_affine(shapes_from_controls(controls), pose_matrices(pose, size)).astype(np.float32)


def make_synthetic_sequence(
    n_frames: int = 300,
    size: int = 256,
    seed: int = 0,
    fps: float = 30.0,
    noise_sigma: float = 2.0,
    head_motion: bool = True,
) -> FaceSequence:
    """Generate the embedded default subject: a synthetic face video with 68 landmarks.

    Deterministic in ``seed``: controls, head motion and noise all come from it.

    Parameters
    ----------
    n_frames : int
        Number of frames T.
    size : int
        Square frame side in pixels (>= 64).
    seed : int
    fps : float
        Frame rate; sets the time scale of the random expression signals.
    noise_sigma : float
        Sensor noise (grey levels).
    head_motion : bool
        Whether to add the slight random similarity head motion.

    Returns
    -------
    FaceSequence
        ``landmarks`` float32 (T, 68, 2); ``frames`` an in-memory ``ArrayFrames``
        uint8 (T, size, size, 3); ``meta['controls']`` float32 (T, K) with
        ``meta['control_names']``; ``meta['head_pose']`` (T, 4) with
        ``meta['head_pose_names']``; ``meta['synthetic'] = True``.
    """
    if n_frames < 1:
        raise FacesynthError(f"n_frames must be >= 1, got {n_frames}")
    if size < 64:
        raise FacesynthError(f"size must be >= 64 pixels, got {size}")
    rng = np.random.default_rng(seed)
    controls = smooth_controls(n_frames, rng, fps)
    pose = smooth_head_motion(n_frames, rng, fps) if head_motion else np.zeros((n_frames, 4))
    lm = synthetic_landmarks(controls, pose, size)
    frames = render_faces(lm, size, seed=seed, noise_sigma=noise_sigma)
    meta = {
        "synthetic": True,
        "description": "facesynth synthetic subject (not a real person): appearance is a function of the 68 landmarks",
        "seed": int(seed),
        "controls": controls.astype(np.float32),
        "control_names": list(CONTROL_NAMES),
        "head_pose": pose.astype(np.float32),
        "head_pose_names": ["dx_frac", "dy_frac", "roll_deg", "log_scale"],
        "noise_sigma": float(noise_sigma),
    }
    return FaceSequence.from_arrays(lm, ArrayFrames(frames), where="synthetic", name=f"synthetic_s{seed}", fps=fps, meta=meta)
