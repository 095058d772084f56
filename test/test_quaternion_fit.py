"""The vectorised largest eigenpair of Horn's matrix against LAPACK's eigh.

``OnlineJoint.update_many`` poses blocks of frames with it; the per-frame
path uses ``numpy.linalg.eigh``. They must agree to rounding, for any noise,
for 3 to 6 markers, in lab coordinates, and on degenerate input (handed back
to eigh); a frame's result must not depend on the block it is in.
"""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from jointfit_core.quaternion_fit import HORN_A, adjugate, determinant, largest_eigenpair

FloatArray = NDArray[np.float64]


def _horn(x: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """N, S and the bound of clusters x (local) and y (world), shapes (M, P, 3)."""
    xc = x - x.mean(axis=1, keepdims=True)
    yc = y - y.mean(axis=1, keepdims=True)
    S = np.einsum("mpi,mpj->mij", xc, yc)
    N = (S.reshape(-1, 9) @ HORN_A.T).reshape(-1, 4, 4)
    return N, S, 0.5 * (np.einsum("mpi,mpi->m", xc, xc) + np.einsum("mpi,mpi->m", yc, yc))


def _clusters(rng: np.random.Generator, m: int, p: int, noise: float) -> tuple[FloatArray, FloatArray]:
    x = rng.normal(0.0, 60.0, (m, p, 3))
    R = Rotation.random(m, random_state=rng).as_matrix()
    y = np.einsum("mij,mpj->mpi", R, x) + np.array([1500.0, -800.0, 1000.0]) + rng.normal(0.0, noise, (m, p, 3))
    return x, y


def _check(N: FloatArray, lam: FloatArray, q: FloatArray, bound: FloatArray) -> None:
    w, v = np.linalg.eigh(N)
    assert np.all(np.abs(lam - w[:, 3]) <= 1e-13 * bound)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, rtol=0, atol=1e-14)
    # the same eigenvector up to sign; the rotation depends on q q^T
    np.testing.assert_allclose(q[:, :, None] * q[:, None, :], v[:, :, 3, None] * v[:, None, :, 3], rtol=0, atol=1e-11)


def test_minors_formulas() -> None:
    A = np.random.default_rng(0).normal(size=(200, 4, 4))
    np.testing.assert_allclose(determinant(A), np.linalg.det(A), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(adjugate(A), np.linalg.det(A)[:, None, None] * np.linalg.inv(A), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("markers", [3, 4, 6])
@pytest.mark.parametrize("noise", [0.0, 0.5, 5.0, 80.0])
def test_agrees_with_eigh(markers: int, noise: float) -> None:
    rng = np.random.default_rng(markers * 10 + int(noise))
    N, S, bound = _horn(*_clusters(rng, 3000, markers, noise))
    lam, q = largest_eigenpair(N, S, bound)
    _check(N, lam, q, bound)


def test_degenerate_rows_go_to_eigh() -> None:
    """A zero matrix (no points), and a largest eigenvalue that is double (markers on a line)."""
    rng = np.random.default_rng(3)
    x, y = _clusters(rng, 6, 4, 0.5)
    t = rng.normal(size=(4, 1))
    x[4] = t * np.array([1.0, 2.0, 3.0])  # collinear: Horn's N has a double largest eigenvalue
    y[4] = t * np.array([3.0, 1.0, 2.0]) + 100.0
    N, S, bound = _horn(x, y)
    N[5], S[5], bound[5] = 0.0, 0.0, 0.0
    lam, q = largest_eigenpair(N, S, bound)
    w = np.linalg.eigvalsh(N)
    np.testing.assert_allclose(lam, w[:, 3], rtol=0, atol=1e-12 * float(bound.max()))
    assert np.all(np.isfinite(q)) and np.allclose(np.linalg.norm(q, axis=1), 1.0)
    _check(N[:4], lam[:4], q[:4], bound[:4])
    # the collinear row: any unit vector of the double eigenspace is a valid answer
    assert np.linalg.norm(N[4] @ q[4] - lam[4] * q[4]) < 1e-9 * bound[4]


def test_a_row_does_not_depend_on_its_block() -> None:
    rng = np.random.default_rng(4)
    N, S, bound = _horn(*_clusters(rng, 500, 4, 2.0))
    lam, q = largest_eigenpair(N, S, bound)
    for lo, hi in ((0, 1), (17, 18), (100, 333), (0, 500)):
        lam_b, q_b = largest_eigenpair(N[lo:hi], S[lo:hi], bound[lo:hi])
        np.testing.assert_array_equal(lam_b, lam[lo:hi])
        np.testing.assert_array_equal(q_b, q[lo:hi])


def test_few_and_many_pairs_give_the_same_rotations() -> None:
    """Up to EIGH_BELOW pairs are solved with eigh, more with the closed form: the same rotations."""
    from jointfit_core.quaternion_fit import EIGH_BELOW, rotations_from_correlations

    rng = np.random.default_rng(16)
    x = rng.normal(size=(EIGH_BELOW + 5, 4, 3))
    x -= x.mean(axis=1, keepdims=True)
    R_true = Rotation.random(x.shape[0], random_state=rng).as_matrix()
    y = np.einsum("mij,mpj->mpi", R_true, x) + rng.normal(0.0, 0.001, x.shape)
    S = np.einsum("mpi,mpj->mij", x, y)
    bound = 0.5 * (np.einsum("mpi,mpi->m", x, x) + np.einsum("mpi,mpi->m", y, y))
    many, lam_many = rotations_from_correlations(S, bound)
    few = [rotations_from_correlations(S[k : k + 1], bound[k : k + 1]) for k in range(x.shape[0])]
    np.testing.assert_allclose(np.concatenate([f[0] for f in few]), many, atol=1e-12)
    np.testing.assert_allclose(np.concatenate([f[1] for f in few]), lam_many, rtol=1e-12)
    np.testing.assert_allclose(many, R_true, atol=0.02)
