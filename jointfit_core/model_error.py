"""Covariance inflation for model error seen in the residuals.

A covariance propagated from marker noise assumes the model holds and the
noise is white. Real recordings break both: soft tissue moves markers
relative to the bone (residuals larger than the noise predicts) and does so
smoothly (residuals correlated from frame to frame, so N frames carry far
less than N frames of information). :func:`residual_inflation` measures both
from whitened residuals and returns the factor by which a covariance must
grow to stay honest.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from .errors import InputError

__all__ = ["Inflation", "residual_inflation"]


@dataclass(frozen=True)
class Inflation:
    """How much a noise-propagated covariance must grow.

    Attributes
    ----------
    factor : float
        ``max(1, chi2_dof) * max(1, (1 + rho) / (1 - rho))``; multiply the
        covariance by it.
    chi2_dof : float
        Mean squared whitened residual per degree of freedom (1 when the
        residuals are as small as the noise model predicts).
    rho : float
        Lag-1 autocorrelation of the whitened residuals (0 for white noise).
    """

    factor: float
    chi2_dof: float
    rho: float


def residual_inflation(whitened: ArrayLike, n_params: int, *, rho_max: float = 0.999) -> Inflation:
    """Inflation factor from whitened residuals in time order.

    Parameters
    ----------
    whitened : array_like, shape (N, k)
        Residual of each frame (rows in time order) multiplied by the inverse
        square root of its predicted covariance, so that under the noise
        model each entry is standard normal and independent. Rows with NaN
        (frames not used) are skipped, and the lag-1 products are taken only
        between consecutive used rows.
    n_params : int
        Number of fitted parameters (degrees of freedom used by the fit).
    rho_max : float
        Upper bound of the autocorrelation used (keeps the factor finite).

    Returns
    -------
    Inflation

    Notes
    -----
    The variance of a least-squares estimate from N observations whose
    errors follow an AR(1) process with correlation ``rho``, and whose
    regressors vary slowly, is about ``(1 + rho) / (1 - rho)`` times the
    white-noise value; a residual scale above the predicted one multiplies
    it by ``chi2_dof``. Both factors are clipped at 1 so that white residuals
    that happen to be small never shrink the covariance below the noise
    model's.
    """
    z = np.asarray(whitened, dtype=np.float64)
    if z.ndim != 2:
        raise InputError(f"whitened: expected shape (N, k), got {z.shape}")
    ok = np.asarray(np.isfinite(z).all(axis=1), dtype=bool)
    n_used = int(ok.sum())
    dof = n_used * z.shape[1] - n_params
    if dof <= 0:
        return Inflation(factor=1.0, chi2_dof=1.0, rho=0.0)
    ss = float(np.sum(z[ok] ** 2))
    chi2_dof = ss / dof
    pairs = ok[1:] & ok[:-1]
    lag = float(np.sum(z[1:][pairs] * z[:-1][pairs]))
    rho = float(np.clip(lag / ss, -rho_max, rho_max)) if ss > 0 else 0.0
    factor = max(1.0, chi2_dof) * max(1.0, (1.0 + rho) / (1.0 - rho))
    return Inflation(factor=factor, chi2_dof=chi2_dof, rho=rho)
