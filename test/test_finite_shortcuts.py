"""The per-frame finiteness shortcuts (a sum of Python floats) give the verdicts of ``np.isfinite(...).all()``.

:func:`jointfit_ros.runner.output_sane` and :func:`jointfit_ros.conversions.pose_with_covariance_bytes`
test finiteness by the sum of the entries, with the exact test where that sum overflows from
finite entries: NaN and infinities anywhere are refused, huge finite values are not.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from jointfit_core.estimator import JointOutput
from jointfit_ros.conversions import ConversionError, pose_with_covariance, pose_with_covariance_bytes
from jointfit_ros.runner import output_sane


def _hinge(position: np.ndarray, cov: np.ndarray, direction: np.ndarray, cov_direction: np.ndarray) -> JointOutput:
    return JointOutput("hinge", position, cov, direction, cov_direction, float("nan"))


def _reference(out: JointOutput, limit: float) -> bool:
    """output_sane as it was written before the shortcut (``np.isfinite(a).all()`` of each array)."""
    arrays = [out.position, out.cov] + ([out.direction, out.cov_direction] if out.direction is not None else [])
    if not all(a is not None and np.isfinite(a).all() for a in arrays):
        return False
    limit = limit if math.isfinite(limit) else 1e9
    return bool(np.abs(out.position).max() <= limit and np.diag(out.cov).max() <= limit**2)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, 1e308, -1e308, 2e9, 0.0])
@pytest.mark.parametrize("where", ["position", "cov", "direction", "cov_direction"])
@pytest.mark.parametrize("limit", [math.inf, 10.0])
def test_output_sane_matches_the_exact_test(bad: float, where: str, limit: float) -> None:
    parts = {"position": np.array([0.1, -0.2, 0.3]), "cov": np.eye(3) * 1e-6, "direction": np.array([0.0, 0.0, 1.0]),
             "cov_direction": np.diag([1e-4, 1e-4, 0.0])}  # fmt: skip
    arr = parts[where].copy()
    arr.flat[1] = bad
    arr.flat[0] = bad if where == "cov_direction" else arr.flat[0]  # two huge entries: their sum overflows
    parts[where] = arr
    out = _hinge(**parts)
    assert output_sane(out, limit) == _reference(out, limit)


def test_output_sane_huge_finite_direction_covariance_is_finite() -> None:
    """Entries whose sum overflows are still finite (the shortcut falls back to the exact test)."""
    out = _hinge(np.zeros(3), np.eye(3), np.array([0.0, 0.0, 1.0]), np.full((3, 3), 1e308))
    assert output_sane(out, math.inf)


@pytest.mark.parametrize("bad", [np.nan, np.inf, 1e308])
def test_pose_bytes_refuse_exactly_what_the_message_refuses(bad: float) -> None:
    cov = np.eye(3)
    cov[0, 1] = cov[1, 0] = bad
    cov[2, 2] = bad
    try:
        pose_with_covariance(5, "world", np.zeros(3), cov)
    except ConversionError:
        with pytest.raises(ConversionError):
            pose_with_covariance_bytes(5, "world", np.zeros(3), cov)
    else:
        assert len(pose_with_covariance_bytes(5, "world", np.zeros(3), cov)) > 0
