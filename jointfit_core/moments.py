"""Per-marker sufficient statistics of marker positions.

The Gamage-Lasenby centre and axis (and their noise estimates and covariances)
need, per marker, only the weight sum and the first four moments of its
positions. :class:`MarkerMoments` holds these raw sums about a reference point
near the data (so that lab coordinates far from the origin lose no precision);
:func:`central_moments` turns them into the per-marker central moments the
estimators use. The batch fits build the sums from a whole array; the online
estimators add and subtract frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .checks import check_markers, valid_mask

__all__ = [
    "MarkerMoments",
    "CentralMoments",
    "moments_from_markers",
    "central_moments",
    "frame_moments",
    "shift_sums",
]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class MarkerMoments:
    """Raw weighted sums of marker positions about a reference point.

    With ``y = v - ref`` the marker position relative to ``ref`` and ``w`` the
    weight of a sample (1 for a plain window, a decay factor under exponential
    forgetting, 0 when the marker is missing), for each marker p:

    Attributes
    ----------
    ref : ndarray, shape (3,)
        Reference point, input units.
    w : ndarray, shape (P,)
        Sum of weights (the sample count for unit weights).
    w2 : ndarray, shape (P,)
        Sum of squared weights (equal to ``w`` for unit weights); gives the
        effective degrees of freedom ``w - w2 / w``.
    s1 : ndarray, shape (P, 3)
        Sum of ``w y``.
    s2 : ndarray, shape (P, 3, 3)
        Sum of ``w y y^T``.
    s3 : ndarray, shape (P, 3)
        Sum of ``w |y|^2 y``.
    s4 : ndarray, shape (P,)
        Sum of ``w |y|^4``.
    n_frames : float
        Sum of the weights of frames with at least one valid marker.
    """

    ref: FloatArray
    w: FloatArray
    w2: FloatArray
    s1: FloatArray
    s2: FloatArray
    s3: FloatArray
    s4: FloatArray
    n_frames: float

    @property
    def n_markers(self) -> int:
        """Number of markers P."""
        return int(self.w.shape[0])


@dataclass(frozen=True, eq=False)
class CentralMoments:
    """Per-marker central moments (about each marker's own mean).

    With ``x = v - mean_p`` for marker p:

    Attributes
    ----------
    used : ndarray of bool, shape (P,)
        Markers with positive degrees of freedom (at least two samples).
    n : ndarray, shape (P,)
        Weight sums.
    dof : ndarray, shape (P,)
        Effective degrees of freedom ``n - w2 / n`` (``n - 1`` for unit weights).
    mean : ndarray, shape (P, 3)
        Marker means, relative to ``ref`` of the raw sums.
    m2 : ndarray, shape (P, 3, 3)
        Sum of ``w x x^T`` (scatter matrix).
    m3 : ndarray, shape (P, 3)
        Sum of ``w |x|^2 x``.
    m4 : ndarray, shape (P,)
        Sum of ``w |x|^4``.
    """

    used: NDArray[np.bool_]
    n: FloatArray
    dof: FloatArray
    mean: FloatArray
    m2: FloatArray
    m3: FloatArray
    m4: FloatArray


def frame_moments(
    frames: FloatArray, ref: FloatArray, weights: FloatArray | None = None
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Weighted sums of a block of frames about ``ref``.

    Parameters
    ----------
    frames : ndarray, shape (N, P, 3)
        Marker positions, NaN for missing (already checked).
    ref : ndarray, shape (3,)
        Reference point.
    weights : ndarray, shape (N,), optional
        Weight of each frame (default 1).

    Returns
    -------
    w, w2 : ndarray, shape (P,)
    s1 : ndarray, shape (P, 3)
    s2 : ndarray, shape (P, 3, 3)
    s3 : ndarray, shape (P, 3)
    s4 : ndarray, shape (P,)
        As in :class:`MarkerMoments`, summed over the block.
    """
    valid = valid_mask(frames)
    fw = np.ones(frames.shape[0]) if weights is None else np.asarray(weights, dtype=np.float64)
    wk = valid * fw[:, None]  # (N, P)
    y = np.where(valid[..., None], frames - ref, 0.0)
    yy = np.einsum("npi,npi->np", y, y)
    wy = wk[..., None] * y
    w = wk.sum(axis=0)
    w2 = (wk * wk).sum(axis=0)
    s1 = wy.sum(axis=0)
    s2 = np.einsum("npi,npj->pij", wy, y)
    s3 = np.einsum("np,npi->pi", yy, wy)
    s4 = np.einsum("np,np->p", wk, yy * yy)
    return w, w2, s1, s2, s3, s4


def moments_from_markers(markers: ArrayLike, ref: ArrayLike | None = None) -> MarkerMoments:
    """Sufficient statistics of a marker array.

    Parameters
    ----------
    markers : array_like, shape (N, P, 3)
        Marker positions (any unit), NaN for missing.
    ref : array_like, shape (3,), optional
        Reference point; default the mean of all valid samples.

    Returns
    -------
    MarkerMoments
    """
    arr = check_markers(markers)
    ref_arr = np.nanmean(arr.reshape(-1, 3), axis=0) if ref is None else np.asarray(ref, dtype=np.float64)
    w, w2, s1, s2, s3, s4 = frame_moments(arr, ref_arr)
    n_frames = float(valid_mask(arr).any(axis=1).sum())
    return MarkerMoments(ref=ref_arr, w=w, w2=w2, s1=s1, s2=s2, s3=s3, s4=s4, n_frames=n_frames)


def shift_sums(
    w: FloatArray, s1: FloatArray, s2: FloatArray, s3: FloatArray, s4: FloatArray, d: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Raw sums about a point moved by ``d``: the sums of ``y - d`` from those of ``y``.

    Parameters
    ----------
    w : ndarray, shape (P,)
    s1, s2, s3, s4 : ndarray, shapes (P, 3), (P, 3, 3), (P, 3), (P,)
        Sums as in :class:`MarkerMoments`.
    d : ndarray, shape (P, 3) or (3,)
        Shift of the reference point, per marker or common.

    Returns
    -------
    s1, s2, s3, s4
        The sums of ``w (y - d)``, ``w (y - d)(y - d)^T``, ``w |y - d|^2 (y - d)``
        and ``w |y - d|^4``.

    Notes
    -----
    Expanding the powers of ``y - d``:

    * ``s1' = s1 - w d``
    * ``s2' = s2 - s1 d^T - d s1^T + w d d^T``
    * ``s3' = s3 - tr(s2) d - 2 s2 d + 2 (s1.d) d + |d|^2 s1 - w |d|^2 d``
    * ``s4' = s4 + 4 d^T s2 d - 4 s3.d + 2 |d|^2 tr(s2) - 4 |d|^2 (s1.d) + w |d|^4``

    The loss of precision grows with ``|d| / spread``.
    """
    dd = np.broadcast_to(d, s1.shape)
    tr2 = np.einsum("pii->p", s2)
    d2 = np.einsum("pi,pi->p", dd, dd)
    s1d = np.einsum("pi,pi->p", s1, dd)
    s2d = np.einsum("pij,pj->pi", s2, dd)
    n1 = s1 - w[:, None] * dd
    n2 = s2 - np.einsum("pi,pj->pij", s1, dd) - np.einsum("pi,pj->pij", dd, s1)
    n2 = n2 + w[:, None, None] * np.einsum("pi,pj->pij", dd, dd)
    n2 = 0.5 * (n2 + np.swapaxes(n2, 1, 2))
    n3 = s3 - tr2[:, None] * dd - 2.0 * s2d + (2.0 * s1d)[:, None] * dd + d2[:, None] * s1
    n3 = n3 - (w * d2)[:, None] * dd
    n4 = s4 + 4.0 * np.einsum("pi,pi->p", dd, s2d) - 4.0 * np.einsum("pi,pi->p", s3, dd)
    n4 = n4 + 2.0 * d2 * tr2 - 4.0 * d2 * s1d + w * d2 * d2
    return n1, n2, n3, n4


def central_moments(mom: MarkerMoments) -> CentralMoments:
    """Convert raw sums about ``ref`` to per-marker central moments.

    Notes
    -----
    :func:`shift_sums` with ``d = mu = s1 / n``, each marker about its own
    mean. The loss of precision grows with ``|mu| / spread``, which is why
    the sums are kept about a reference point near the data.
    """
    n = mom.w
    with np.errstate(divide="ignore", invalid="ignore"):
        dof = np.where(n > 0, n - np.divide(mom.w2, n, out=np.zeros_like(n), where=n > 0), 0.0)
        used = dof > 1e-9 * np.maximum(n, 1.0)
        safe_n = np.where(used, n, 1.0)
        mu = np.where(used[:, None], mom.s1 / safe_n[:, None], 0.0)
    _, m2, m3, m4 = shift_sums(n, mom.s1, mom.s2, mom.s3, mom.s4, mu)
    m2 = np.where(used[:, None, None], m2, 0.0)
    m3 = np.where(used[:, None], m3, 0.0)
    m4 = np.where(used, np.maximum(m4, 0.0), 0.0)
    return CentralMoments(used=used, n=n, dof=np.where(used, dof, 0.0), mean=mu, m2=m2, m3=m3, m4=m4)
