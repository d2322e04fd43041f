import numpy as np
import pytest
from _faces import face_template, random_similarity
from sklearn.decomposition import PCA as SkPCA

from facesynth.errors import FacesynthError
from facesynth.geometry import apply_affine, invert_affine, similarity_fit
from facesynth.model.pca import PCAModel
from facesynth.model.procrustes import generalised_procrustes


def _lstsq_similarity(src, dst):
    """Independent reference: a similarity is linear in (a, b, tx, ty)."""
    x, y = src[:, 0], src[:, 1]
    one, zero = np.ones_like(x), np.zeros_like(x)
    A = np.concatenate([np.stack([x, -y, one, zero], 1), np.stack([y, x, zero, one], 1)])
    a, b, tx, ty = np.linalg.lstsq(A, np.concatenate([dst[:, 0], dst[:, 1]]), rcond=None)[0]
    return np.array([[a, -b, tx], [b, a, ty]])


def test_similarity_fit_matches_least_squares(rng):
    src = rng.normal(size=(68, 2)) * 30
    dst = apply_affine(src, random_similarity(rng)) + rng.normal(size=(68, 2))
    np.testing.assert_allclose(similarity_fit(src, dst), _lstsq_similarity(src, dst), atol=1e-9)
    m = similarity_fit(src, dst)
    np.testing.assert_allclose(apply_affine(apply_affine(src, m), invert_affine(m)), src, atol=1e-9)


def test_gpa_is_invariant_to_similarity_transforms(rng):
    base = face_template().astype(np.float64)
    shapes = base + rng.normal(0, 2, (20, 68, 2))
    moved = np.stack([apply_affine(s, random_similarity(rng, angle=0.5)) for s in shapes])
    a1, m1 = generalised_procrustes(shapes)
    a2, m2 = generalised_procrustes(moved)
    np.testing.assert_allclose(np.linalg.norm(m1), 1.0)
    np.testing.assert_allclose(m1.mean(0), 0, atol=1e-12)
    # same result up to one global similarity (the gauge)
    g = similarity_fit(a2.reshape(-1, 2), a1.reshape(-1, 2))
    np.testing.assert_allclose(apply_affine(a2, g), a1, atol=1e-8)


@pytest.mark.parametrize("n, d", [(50, 20), (15, 200)])  # SVD path and Gram path
def test_pca_closed_forms(rng, n, d):
    x = rng.normal(size=(n, d)) @ rng.normal(size=(d, d)) * 0.1 + rng.normal(size=d)
    full = PCAModel.fit(x, variance=1.0)
    sk = SkPCA().fit(x)
    k = full.n_components
    np.testing.assert_allclose(full.eigenvalues, sk.explained_variance_[:k], rtol=1e-6)
    np.testing.assert_allclose(full.components @ full.components.T, np.eye(k), atol=1e-5)
    for keep in (1, 3, 7):
        m = full.truncate(keep)
        resid = x - m.reconstruct(m.project(x))
        per_sample = (resid**2).sum() / (n - 1)
        np.testing.assert_allclose(per_sample, full.eigenvalues[keep:].sum(), rtol=1e-3)


def test_pca_variance_selection_and_clamp(rng):
    x = rng.normal(size=(100, 10)) * np.arange(10, 0, -1)
    m = PCAModel.fit(x, variance=0.9)
    cum = np.cumsum(m.eigenvalues) / m.total_variance
    assert cum[-1] >= 0.9 and (m.n_components == 1 or cum[-2] < 0.9)
    b = m.project(x) * 10
    c = m.clamp(b, 3.0)
    assert (np.abs(c) <= 3 * np.sqrt(m.eigenvalues) + 1e-5).all()
    with pytest.raises(FacesynthError):
        PCAModel.fit(np.full((3, 4), np.nan))
