"""How far a joint is from the marker clusters that locate it, in cluster sizes (issue 17, item 6).

A cluster that turns on its bone by a small angle ``theta`` moves the joint it carries by about
``theta`` times the lever, the distance from the cluster to the joint. Part of that motion is
invisible: a cluster turning with the joint is exactly a joint at a shifted place and leaves no
residual (:mod:`jointfit_core.artefact`), so a thigh cluster turning 2 % of the hip rotation at a
250 mm lever biases the hip centre by ~5 mm whatever the residuals say. The cluster's size sets
how well its turns are read at all (a pose's rotation noise is the marker noise over the cluster's
radius). The ratio of the two, the lever over the cluster's rms radius, is then what a lab can
change to make the estimate less sensitive to the artefact (a larger cluster, or one nearer the
joint): jointfit reports it per segment in ``/diagnostics`` and ``summary.json``.

Typical values: a hip centre 200-300 mm from a thigh cluster of 50-100 mm rms radius gives 2-6 (the real right-hip
trial of the tests: 2.64);
from a pelvis cluster of ASIS/PSIS markers (~100 mm radius) 1-1.5.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .checks import as_real_array
from .errors import InputError

__all__ = ["lever_ratio", "lever_ratios", "rms_radius"]

FloatArray = NDArray[np.float64]


def rms_radius(points: FloatArray) -> float:
    """Rms distance of points ``(P, 3)`` from their centroid (input units): a cluster's size."""
    return float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1))))


def lever_ratio(template: ArrayLike, point: ArrayLike, direction: ArrayLike | None = None) -> float:
    """A cluster's distance to the joint over its rms radius.

    Parameters
    ----------
    template : array_like, shape (P, 3)
        The cluster's markers in its segment's frame (input units).
    point : array_like, shape (3,)
        The joint centre (ball) or a point of the axis (hinge) in that frame.
    direction : array_like, shape (3,), optional
        The hinge axis direction in that frame (unit or not): the lever is then the distance from
        the cluster's centroid to the axis line.

    Returns
    -------
    float
        ``|lever| / sqrt(mean |x - xbar|^2)``; NaN when the template has no extent.

    Raises
    ------
    InputError
        Wrong shapes or non-finite values.
    """
    x = as_real_array(template, name="template", expected="(P, 3) marker positions")
    p = as_real_array(point, name="point", expected="a (3,) point")
    if x.ndim != 2 or x.shape[1] != 3 or x.shape[0] < 1 or p.shape != (3,):
        raise InputError(f"template, point: expected shapes (P, 3) and (3,), got {x.shape} and {p.shape}")
    if not (np.isfinite(x).all() and np.isfinite(p).all()):
        raise InputError("template, point: expected finite values")
    xbar = x.mean(axis=0)
    lever = xbar - p
    if direction is not None:
        n = as_real_array(direction, name="direction", expected="a (3,) direction")
        norm = float(np.linalg.norm(n)) if n.shape == (3,) else 0.0
        if not (np.isfinite(norm) and norm > 0.0):
            raise InputError(f"direction: expected a non-zero finite (3,) vector, got {n!r}")
        n = n / norm
        lever = lever - n * float(n @ lever)
    radius = rms_radius(x)
    return float(np.linalg.norm(lever)) / radius if radius > 0.0 else float("nan")


def lever_ratios(
    templates: tuple[ArrayLike, ArrayLike],
    points: tuple[ArrayLike, ArrayLike],
    directions: tuple[ArrayLike, ArrayLike] | None = None,
) -> tuple[float, float]:
    """:func:`lever_ratio` of the parent and the child cluster (each in its own frame).

    ``points``: the centre (ball) or axis point (hinge) in each segment's frame; ``directions``:
    the hinge axis in each (None for a ball joint).
    """
    dirs: tuple[ArrayLike | None, ArrayLike | None] = (None, None) if directions is None else directions
    return (
        lever_ratio(templates[0], points[0], dirs[0]),
        lever_ratio(templates[1], points[1], dirs[1]),
    )
