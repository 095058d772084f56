"""residual_inflation: chi-square and autocorrelation factors."""

from __future__ import annotations

import numpy as np
import pytest

from jointfit_core.errors import InputError
from jointfit_core.model_error import residual_inflation


def test_white_residuals_give_no_inflation() -> None:
    z = np.random.default_rng(0).normal(size=(5000, 3))
    inf = residual_inflation(z, 6)
    assert inf.chi2_dof == pytest.approx(1.0, abs=0.05)
    assert abs(inf.rho) < 0.05
    assert inf.factor < 1.12


def test_scaled_and_correlated_residuals() -> None:
    rng = np.random.default_rng(1)
    n, rho = 20000, 0.9
    e = np.empty((n, 3))
    e[0] = rng.normal(size=3)
    for t in range(1, n):  # AR(1) with unit marginal variance
        e[t] = rho * e[t - 1] + np.sqrt(1 - rho**2) * rng.normal(size=3)
    inf = residual_inflation(2.0 * e, 6)
    assert inf.chi2_dof == pytest.approx(4.0, rel=0.1)
    assert inf.rho == pytest.approx(rho, abs=0.02)
    assert inf.factor == pytest.approx(4.0 * 19.0, rel=0.25)


def test_nan_rows_skipped_and_shape_checked() -> None:
    z = np.random.default_rng(2).normal(size=(100, 3))
    z[::7] = np.nan
    assert np.isfinite(residual_inflation(z, 3).factor)
    assert residual_inflation(np.full((2, 3), np.nan), 3).factor == 1.0
    with pytest.raises(InputError, match=r"\(N, k\)"):
        residual_inflation(np.zeros(5), 1)
