"""Shared helpers for the tests: random rigid transforms and validation indices."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation


def random_rigid(rng: np.random.Generator, scale: float = 1000.0) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A random rotation matrix and a translation of about ``scale``."""
    return Rotation.random(random_state=rng).as_matrix(), rng.normal(0.0, scale, 3)


def transform(markers: NDArray[np.float64], rot: NDArray[np.float64], trans: NDArray[np.float64]) -> NDArray[np.float64]:
    """Apply ``x -> R x + t`` to every marker (NaN stays NaN)."""
    return np.einsum("ij,npj->npi", rot, markers) + trans


def mahalanobis(err: NDArray[np.float64], cov: NDArray[np.float64]) -> float:
    """``err^T cov^+ err`` divided by the rank of ``cov`` (Stoddart's v^2)."""
    pinv = np.linalg.pinv(cov, rcond=1e-10, hermitian=True)
    rank = int(np.linalg.matrix_rank(cov, tol=1e-10 * np.abs(np.linalg.eigvalsh(cov)).max(), hermitian=True))
    return float(err @ pinv @ err) / rank


def mc_band(values: list[float], low: float = 0.8, high: float = 1.25) -> None:
    """Assert the mean validation index squared lies in the calibration band."""
    mean = float(np.mean(values))
    assert low <= mean <= high, f"mean e/rank = {mean:.3f} outside [{low}, {high}] over {len(values)} trials"
