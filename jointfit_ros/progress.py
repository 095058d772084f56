"""A joint's progress for ``/diagnostics``: coverage of the motion and the "done" signal.

Pure Python and numpy (no rclpy). :func:`coverage_values` gives the
diagnostic values of :func:`jointfit_core.coverage.joint_coverage` (per cent);
:func:`done_check` says whether an estimate meets its ``target_sd``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from jointfit_core.axis_sign import direction_sd_deg
from jointfit_core.coverage import joint_coverage
from jointfit_core.errors import InputError
from jointfit_core.estimator import OnlineJoint
from jointfit_core.hinge_from_sums import PoseSumsAxis
from jointfit_core.segments import PoseSumsCentre

__all__ = ["coverage_values", "done_check", "estimate_sd"]


def _percent(fraction: float) -> float:
    # float(): a numpy float's round() stays numpy, whose repr in a list ("[np.float64(100.0), ...]")
    # is what the diagnostic value showed
    return round(100.0 * float(fraction), 1)


def coverage_values(est: OnlineJoint, sol: PoseSumsCentre | PoseSumsAxis) -> tuple[float, dict[str, Any]]:
    """The coverage (per cent) and its diagnostic values.

    Parameters
    ----------
    est : OnlineJoint
        The estimator (its window's sums give the motion part, unless frozen).
    sol : PoseSumsCentre or PoseSumsAxis
        Its latest estimate.

    Returns
    -------
    coverage : float
        Per cent, 0-100 (100: every coverage threshold of the verdict is met).
    values : dict of str to object
        ``coverage (%)``, ``coverage: motion (%)`` (not when frozen), and for a
        ball ``coverage by direction (%)`` with ``least covered direction
        (parent frame)``, for a hinge ``coverage: direction (%)`` and
        ``coverage: point (%)``.
    """
    sums = Wp = Wc = None
    if not est.frozen and est.n_window >= 3:
        try:
            sums, Wp_unit, Wc_unit, _, _ = est.pose_sums()
            sigma_p, sigma_c = est.noise_std
            Wp, Wc = sigma_p**2 * Wp_unit, sigma_c**2 * Wc_unit
        except InputError:
            sums = None
    cov = joint_coverage(sol, est.length_scale, sums, Wp, Wc, skin="skin" in est.attachment)
    values: dict[str, Any] = {"coverage (%)": _percent(cov.overall)}
    if cov.motion is not None:
        values["coverage: motion (%)"] = _percent(cov.motion)
    if isinstance(sol, PoseSumsCentre):
        values["coverage by direction (%)"] = [_percent(f) for f in cov.by_direction]
        values["least covered direction (parent frame)"] = np.round(cov.least_covered, 3).tolist()
    else:
        values["coverage: direction (%)"] = _percent(float(cov.by_direction[0]))
        values["coverage: point (%)"] = _percent(float(cov.by_direction[1]))
    return _percent(cov.overall), values


def estimate_sd(sol: PoseSumsCentre | PoseSumsAxis) -> tuple[float, str]:
    """The sd ``target_sd`` is compared with, and its name: the centre's largest (input units) or the direction's (deg)."""
    if isinstance(sol, PoseSumsCentre):
        lam = np.linalg.eigvalsh(sol.cov_parent)[-1] if np.isfinite(sol.cov_parent).all() else np.inf
        return float(np.sqrt(max(float(lam), 0.0))), "centre sd"
    return direction_sd_deg(sol.cov_direction_parent), "direction sd"


def done_check(sol: PoseSumsCentre | PoseSumsAxis, target_sd: float, units: str) -> tuple[bool, str]:
    """Whether an identifiable estimate with no warning is done: its sd at most ``target_sd``.

    Parameters
    ----------
    sol : PoseSumsCentre or PoseSumsAxis
    target_sd : float
        Input units (ball) or degrees (hinge); 0: no done signal.
    units : str
        The input length unit, for the text.

    Returns
    -------
    done : bool
    text : str
        E.g. ``done: centre sd 0.8 mm <= target 1 mm``, or ``centre sd 2.1 mm, target 1 mm``;
        empty without a target.
    """
    if not target_sd > 0.0:
        return False, ""
    sd, name = estimate_sd(sol)
    unit = units if isinstance(sol, PoseSumsCentre) else "deg"
    if sol.identifiable and sd <= target_sd:
        return True, f"done: {name} {sd:.3g} {unit} <= target {target_sd:g} {unit}"
    return False, f"{name} {sd:.3g} {unit}, target {target_sd:g} {unit}"
