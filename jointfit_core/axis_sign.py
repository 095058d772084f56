"""Which way a hinge axis points: a sign convention from named markers, chosen only when it is unambiguous.

A hinge axis has no natural sign. Users name it by markers ("from the
medial toward the lateral epicondyle"). :func:`hinge_sign` turns such a
convention and one frame's markers into +1 (keep the estimate's direction),
-1 (flip it) or 0 (undecided, with the reason), without depending on where
the marker clusters sit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["SignChoice", "hinge_sign", "direction_sd_deg", "SIGN_SD_MAX_DEG", "MIN_ALONG_RATIO"]

FloatArray = NDArray[np.float64]

#: The sign is chosen only from an estimate whose direction sd (deg, largest) is below this.
SIGN_SD_MAX_DEG = 5.0
#: Two markers fix the sign only when their line has at least this share of its length along the axis.
MIN_ALONG_RATIO = 0.25


@dataclass(frozen=True)
class SignChoice:
    """The outcome of :func:`hinge_sign`.

    Attributes
    ----------
    sign : float
        +1 (the direction already follows the convention), -1 (flip it), 0 (undecided).
    final : bool
        Whether the decision holds for good: a sign, or a convention that can
        never be honoured (an ambiguous single marker). False: try again on a
        later frame (a marker missing in this one).
    reason : str
        Why undecided (empty when decided).
    """

    sign: float
    final: bool
    reason: str


def direction_sd_deg(cov_direction: ArrayLike) -> float:
    """Largest standard deviation (deg) of a unit direction from its (3, 3) covariance (rad^2); inf if not finite."""
    cov = np.asarray(cov_direction, dtype=np.float64)
    if not np.isfinite(cov).all():
        return float("inf")
    return float(np.degrees(np.sqrt(max(float(np.linalg.eigvalsh(cov)[-1]), 0.0))))


def hinge_sign(
    point: ArrayLike,
    direction: ArrayLike,
    toward: ArrayLike,
    from_marker: ArrayLike | None = None,
    cluster: ArrayLike | None = None,
    names: tuple[str, str] = ("", ""),
) -> SignChoice:
    """Sign that makes a hinge direction follow a marker convention in one frame.

    Parameters
    ----------
    point, direction : array_like, shape (3,)
        A point of the axis and its unit direction (world frame, input units).
    toward : array_like, shape (3,)
        The marker the axis should point toward (NaN when missing).
    from_marker : array_like, shape (3,), optional
        The marker it should point away from: the sign is then that of
        ``direction . (toward - from)``, whatever the clusters' positions.
    cluster : array_like, shape (P, 3), optional
        The markers of both segments (NaN rows ignored), for the one-marker
        form: there the marker's side is measured from the axis point nearest
        the clusters' centroid, and the convention is unambiguous only when
        the marker lies farther along the axis from that point than every
        cluster marker (a marker on the far side of the limb). A marker within
        the clusters' extent along the axis (a lateral epicondyle beside a
        lateral thigh cluster) can lie on either side of it for small changes
        of the set-up, so it decides nothing: the result is final and 0.
    names : (str, str)
        The toward and from markers' names, for the reasons.

    Returns
    -------
    SignChoice
    """
    d = np.asarray(direction, dtype=np.float64)
    m = np.asarray(toward, dtype=np.float64)
    if not np.isfinite(m).all():
        return SignChoice(0.0, False, f"marker {names[0]} not visible")
    if from_marker is not None:
        f = np.asarray(from_marker, dtype=np.float64)
        if not np.isfinite(f).all():
            return SignChoice(0.0, False, f"marker {names[1]} not visible")
        line = m - f
        along = float(d @ line)
        length = float(np.linalg.norm(line))
        if not abs(along) >= MIN_ALONG_RATIO * length or length == 0.0:
            return SignChoice(
                0.0,
                True,
                f"the line from {names[1]} to {names[0]} is nearly perpendicular to the axis "
                f"({np.degrees(np.arccos(min(abs(along) / max(length, 1e-300), 1.0))):.0f} deg from it): "
                "name two markers on either side of the joint along the axis",
            )
        return SignChoice(1.0 if along > 0.0 else -1.0, True, "")
    pts = np.asarray(cluster, dtype=np.float64).reshape(-1, 3) if cluster is not None else np.zeros((0, 3))
    pts = pts[np.isfinite(pts).all(axis=1)]
    p = np.asarray(point, dtype=np.float64)
    if pts.shape[0]:
        p = p + d * float(d @ (pts.mean(axis=0) - p))
    s = float(d @ (m - p))
    extent = float(np.abs((pts - p) @ d).max()) if pts.shape[0] else 0.0
    if not abs(s) > extent:
        return SignChoice(
            0.0,
            True,
            f"axis_toward_marker {names[0]} is ambiguous: it lies {abs(s):.3g} along the axis from the clusters' "
            f"centre, within their extent ({extent:.3g}), so its side depends on where the clusters sit; "
            "name axis_from_marker too (a marker on the other side of the joint, e.g. the medial epicondyle)",
        )
    return SignChoice(1.0 if s > 0.0 else -1.0, True, "")
