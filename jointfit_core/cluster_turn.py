"""How well a marker cluster's pose is determined about its weakest axis: clusters of markers nearly on a line.

Pure numpy. A rigid fit of a cluster whose markers lie nearly on a line turns
it about that line by a large, random angle in every frame: the pose's
rotation covariance is ``sigma^2 J^-1`` with ``J = sum_i (|x_i|^2 I - x_i x_i^T)``
the cluster's inertia about its centroid (the linearised covariance of the
pose fit, Stoddart et al. 1999 eq. 8), and along the line ``J`` holds only the
markers' small distances from it. The joint's covariance is linear in those
rotations; past a few degrees it under-states the error.

Measured (a ball joint, 2400 frames at 60 Hz, 0.3 mm noise, a 3-marker child
cluster 150 mm long with its middle marker ``h`` off the line, 4 seeds; mean
e/3 per seed, 1 = honest):

======  ===================  ==================
h (mm)  weakest turn sd      mean e/3
======  ===================  ==================
15      1.4 deg              0.71-0.88
8       2.6 deg              0.67-1.04
4       5.3 deg              0.62-1.46
2       10.5 deg             0.94-2.48
1       21 deg               0.36-4.46
======  ===================  ==================
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["TURN_SD_MAX_DEG", "weakest_turn_sd_deg"]

FloatArray = NDArray[np.float64]

#: Above this turn sd per frame (deg) about a cluster's weakest axis, the joint's covariance under-states
#: (mean e/3 up to 1.5 at 5 deg, 2.5 at 10, 4.5 at 21: the module notes).
TURN_SD_MAX_DEG = 5.0


def weakest_turn_sd_deg(template: ArrayLike, sigma: float) -> float:
    """The sd (deg) of a frame's rotation of the cluster about its least determined axis.

    Parameters
    ----------
    template : array_like, shape (P, 3)
        The cluster's markers (input units).
    sigma : float
        Marker noise sd per coordinate (input units).

    Returns
    -------
    float
        ``degrees(sigma / sqrt(lambda_min(J)))``, ``J`` the inertia of the
        centred template; ``inf`` for markers exactly on a line.

    Notes
    -----
    Unchanged by rotating or translating the template and by the marker
    order; scaling the template and ``sigma`` alike leaves it unchanged.
    """
    x = np.asarray(template, dtype=np.float64)
    x = x - x.mean(axis=0)
    J = np.sum(x * x) * np.eye(3) - x.T @ x
    lam = float(np.linalg.eigvalsh(J)[0])
    if lam <= 0.0:
        return float("inf")
    return float(np.rad2deg(sigma / np.sqrt(lam)))
