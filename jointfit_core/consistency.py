"""Consistency of a joint's estimates across movement blocks: does the skin artefact dominate?

A recording (or a window) is cut into a few contiguous movement blocks, the
joint is solved on each alone, and the blocks' estimates are compared with
their covariances. Rigid markers give block estimates that scatter as their
covariances say; skin markers whose artefact is larger than the covariance
allows (or changes between movements) give estimates that disagree by more:
the verdict "skin artefact dominates" with the spread.

The functions here take the block estimates and covariances only (no sums,
no estimator): :func:`ball_consistency` and :func:`hinge_consistency`.
:mod:`jointfit_core.block_check` makes the blocks from an estimator's sums.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.stats import chi2 as chi2_dist

from .errors import InputError
from .segments import _perp_basis

__all__ = [
    "BlockConsistency",
    "ball_consistency",
    "hinge_consistency",
    "CONSISTENCY_ALPHA",
    "CONSISTENCY_BLOCKS",
    "MIN_BLOCKS",
    "ARTEFACT_VERDICT",
    "RIGID_CAUSES",
]

FloatArray = NDArray[np.float64]

#: The verdict's false-alarm probability when the blocks are independent and their covariances
#: honest: a chi-square above its ``1 - alpha`` quantile is "skin artefact dominates".
CONSISTENCY_ALPHA = 1e-3

#: How many contiguous blocks a window or recording is cut into.
CONSISTENCY_BLOCKS = 4

#: Fewer identifiable blocks than this: no verdict.
MIN_BLOCKS = 2

#: The start of the failing verdict's message.
ARTEFACT_VERDICT = "skin artefact dominates"


@dataclass(frozen=True)
class BlockConsistency:
    """The blocks' estimates against their covariances.

    Attributes
    ----------
    kind : str
        "ball" or "hinge".
    n_blocks : int
        Blocks compared (identifiable ones).
    n_skipped : int
        Blocks left out (not identifiable on their own, too few frames).
    positions : ndarray, shape (K, 3)
        Ball: each block's centre; hinge: its axis point. Parent frame, input units.
    directions : ndarray, shape (K, 3) or None
        Hinge: each block's unit axis direction (parent frame).
    frames : ndarray of int, shape (K,)
        Frames in each compared block.
    chi2 : float
        ``sum_k (x_k - x_pooled)^T C_k^-1 (x_k - x_pooled)`` (see Notes); NaN without a verdict.
    dof : int
        Its degrees of freedom (``d (K - 1)``; 0 without a verdict).
    p_value : float
        Chance of a chi-square at least this large if the covariances were honest (NaN without a verdict).
    ratio : float
        ``sqrt(chi2 / dof)``: how many times the spread is what the covariances allow (1 on average).
    spread : float
        Rms distance of the blocks' centres (hinge: of their axes, perpendicular
        to the pooled axis at the pooled point) from the pooled one, input units.
    spread_deg : float
        Hinge: rms angle of the blocks' directions from the pooled one (deg); NaN for a ball.
    consistent : bool or None
        None: no verdict (fewer than :data:`MIN_BLOCKS` identifiable blocks).
    message : str
        One line: the verdict, or why there is none.
    """

    kind: str
    n_blocks: int
    n_skipped: int
    positions: FloatArray
    directions: FloatArray | None
    frames: NDArray[np.int64]
    chi2: float
    dof: int
    p_value: float
    ratio: float
    spread: float
    spread_deg: float
    consistent: bool | None
    message: str

    @property
    def warns(self) -> bool:
        """Whether the verdict is "skin artefact dominates"."""
        return self.consistent is False

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able types (NaN as None): the verdict, the statistic and each block's estimate."""

        def num(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None

        out: dict[str, Any] = {
            "consistent": self.consistent,
            "message": self.message,
            "blocks": self.n_blocks,
            "blocks_skipped": self.n_skipped,
            "block_frames": [int(f) for f in self.frames],
            "chi2": num(self.chi2),
            "dof": self.dof,
            "p_value": num(self.p_value),
            "ratio": num(self.ratio),
            "spread": num(self.spread),
        }
        key = "block_centres_parent" if self.kind == "ball" else "block_points_parent"
        out[key] = self.positions.tolist()
        if self.directions is not None:
            out["block_directions_parent"] = self.directions.tolist()
            out["spread_deg"] = num(self.spread_deg)
        return out


def _check_stack(x: ArrayLike, name: str, shape: tuple[int, ...]) -> FloatArray:
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim != len(shape) + 1 or arr.shape[1:] != shape:
        raise InputError(f"{name}: expected shape (K, {', '.join(map(str, shape))}), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise InputError(f"{name}: expected finite numbers")
    return arr


def _frames(frames: ArrayLike | None, k: int) -> NDArray[np.int64]:
    if frames is None:
        return np.zeros(k, dtype=np.int64)
    out = np.asarray(frames, dtype=np.int64).reshape(-1)
    if out.size != k:
        raise InputError(f"frames: expected {k} block frame counts, got {out.size}")
    return out


def _pinv(C: FloatArray, rank: int) -> FloatArray:
    """Pseudo-inverses of a stack of symmetric (K, d, d) covariances keeping their ``rank`` largest eigenvalues."""
    w, V = np.linalg.eigh(0.5 * (C + np.swapaxes(C, 1, 2)))
    w, V = w[:, -rank:], V[:, :, -rank:]
    if (w <= 0.0).any():
        raise InputError("covariances: expected positive variances in the compared directions")
    out: FloatArray = np.einsum("kij,kj,klj->kil", V, 1.0 / w, V)
    return out


def _pooled(x: FloatArray, W: FloatArray) -> FloatArray:
    """Information-weighted mean of (K, d) estimates with (K, d, d) informations."""
    out: FloatArray = np.linalg.lstsq(W.sum(axis=0), np.einsum("kij,kj->i", W, x), rcond=None)[0]
    return out


def _quad(r: FloatArray, W: FloatArray) -> float:
    return float(np.einsum("ki,kij,kj->", r, W, r))


def _none(kind: str, positions: FloatArray, directions: FloatArray | None, frames: NDArray[np.int64],
          n_skipped: int, why: str) -> BlockConsistency:
    return BlockConsistency(kind, int(positions.shape[0]), n_skipped, positions, directions, frames,
                            math.nan, 0, math.nan, math.nan, math.nan, math.nan, None, why)


#: What the failing verdict adds for markers marked rigid, per joint kind: the causes there besides skin.
RIGID_CAUSES = (
    "; with attachment rigid that is markers on skin (set attachment: skin), a cluster or marker that moved on "
    "its bone during the recording (bumped, re-taped: the blocks before and after it disagree), or a joint that "
    "is not {what}"
)


def _verdict(
    k: int, chi2: float, dof: int, spread: str, alpha: float, rigid: bool, what: str
) -> tuple[bool, float, float, str]:
    p = float(chi2_dist.sf(chi2, dof))
    ratio = math.sqrt(chi2 / dof)
    numbers = f"chi2 {chi2:.3g} on {dof} dof, p {p:.2g}"
    if p >= alpha:
        return True, p, ratio, f"consistent: the {k} movement blocks' {spread}, {ratio:.2g} times their sd ({numbers})"
    return False, p, ratio, (
        f"{ARTEFACT_VERDICT}{' or a cluster moved' if rigid else ''}: the {k} movement blocks' {spread}, "
        f"{ratio:.2g} times what their covariances allow ({numbers})" + (RIGID_CAUSES.format(what=what) if rigid else "")
    )


def ball_consistency(
    centres: ArrayLike,
    covs: ArrayLike,
    *,
    frames: ArrayLike | None = None,
    n_skipped: int = 0,
    units: str = "",
    alpha: float = CONSISTENCY_ALPHA,
    rigid: bool = False,
) -> BlockConsistency:
    """Do K blocks' ball-joint centres agree within their covariances?

    Parameters
    ----------
    centres : array_like, shape (K, 3)
        Each block's centre in the parent frame, input units.
    covs : array_like, shape (K, 3, 3)
        Their covariances, input units squared.
    frames : array_like of int, shape (K,), optional
        Frames per block (reported only).
    n_skipped : int
        Blocks already left out by the caller (reported only).
    units : str
        Input units, for the message.
    alpha : float
        False-alarm probability of the verdict.
    rigid : bool
        The markers are marked rigid: the failing verdict names the causes there too (:data:`RIGID_CAUSES`).

    Returns
    -------
    BlockConsistency

    Raises
    ------
    InputError
        Shapes that do not match, non-finite numbers, a covariance that is not positive definite.

    Notes
    -----
    The pooled centre is the information-weighted mean
    ``x = (sum C_k^-1)^-1 sum C_k^-1 x_k``; the statistic
    ``chi2 = sum_k (x_k - x)^T C_k^-1 (x_k - x)`` is chi-square with
    ``3 (K - 1)`` degrees of freedom when the blocks are independent and the
    covariances honest (the homogeneity test of a weighted mean). An error
    common to all blocks (the part of a skin artefact that moves the centre
    the same way in every movement) cancels in it: the check sees the part of
    the artefact that changes between movements, and the statistic is then
    smaller than chi-square (the check is conservative) when the covariances
    hold such a common part.
    """
    x = _check_stack(centres, "centres", (3,))
    C = _check_stack(covs, "covs", (3, 3))
    if C.shape[0] != x.shape[0]:
        raise InputError(f"covs: expected {x.shape[0]} covariances, got {C.shape[0]}")
    f = _frames(frames, x.shape[0])
    k = x.shape[0]
    if k < MIN_BLOCKS:
        return _none("ball", x, None, f, n_skipped, f"no consistency check: {k} identifiable movement block(s), "
                     f"{MIN_BLOCKS} needed")
    W = _pinv(C, 3)
    r = x - _pooled(x, W)
    chi2 = _quad(r, W)
    dof = 3 * (k - 1)
    spread = float(np.sqrt(np.mean(np.sum(r**2, axis=1))))
    unit = f" {units}" if units else ""
    ok, p, ratio, msg = _verdict(k, chi2, dof, f"centres spread by {spread:.3g}{unit} rms", alpha, rigid, "a ball joint")
    return BlockConsistency("ball", k, n_skipped, x, None, f, chi2, dof, p, ratio, spread, math.nan, ok, msg)


def hinge_consistency(
    directions: ArrayLike,
    cov_directions: ArrayLike,
    points: ArrayLike,
    cov_points: ArrayLike,
    *,
    frames: ArrayLike | None = None,
    n_skipped: int = 0,
    units: str = "",
    alpha: float = CONSISTENCY_ALPHA,
    rigid: bool = False,
) -> BlockConsistency:
    """Do K blocks' hinge axes agree within their covariances?

    Parameters
    ----------
    directions : array_like, shape (K, 3)
        Each block's unit axis direction in the parent frame (signs may differ; they are aligned).
    cov_directions : array_like, shape (K, 3, 3)
        Their covariances (rank 2, perpendicular to the direction).
    points : array_like, shape (K, 3)
        A point of each block's axis (parent frame, input units).
    cov_points : array_like, shape (K, 3, 3)
        Their covariances, input units squared.
    frames, n_skipped, units, alpha, rigid
        As for :func:`ball_consistency`.

    Returns
    -------
    BlockConsistency
        ``positions`` are the blocks' axis points, ``directions`` their directions
        with the signs aligned to the first block's.

    Raises
    ------
    InputError
        Shapes that do not match, non-finite numbers, a direction that is not unit.

    Notes
    -----
    Two chi-squares of :func:`ball_consistency`'s form, each with 2 degrees of
    freedom per block: the directions in the plane perpendicular to the pooled
    direction (the mean of the sign-aligned directions, weighted by their
    information, to first order), and the axes' points projected onto that
    plane (so are their covariances: a shift along the axis is no
    disagreement; the points should be comparable along it, e.g. each the
    point nearest the parent origin). ``dof = 4 (K - 1)``. The correlation of a block's
    direction with its point is left out (each point's covariance already
    holds the direction's share along the lever to it).
    """
    u = _check_stack(directions, "directions", (3,))
    Cu = _check_stack(cov_directions, "cov_directions", (3, 3))
    p = _check_stack(points, "points", (3,))
    Cp = _check_stack(cov_points, "cov_points", (3, 3))
    k = u.shape[0]
    if not (Cu.shape[0] == p.shape[0] == Cp.shape[0] == k):
        raise InputError(f"hinge blocks: expected {k} of each, got {Cu.shape[0]}, {p.shape[0]}, {Cp.shape[0]}")
    if (np.abs(np.linalg.norm(u, axis=1) - 1.0) > 1e-6).any():
        raise InputError("directions: expected unit vectors")
    f = _frames(frames, k)
    if k < MIN_BLOCKS:
        return _none("hinge", p, u, f, n_skipped, f"no consistency check: {k} identifiable movement block(s), "
                     f"{MIN_BLOCKS} needed")
    u = u * np.where(u @ u[0] < 0.0, -1.0, 1.0)[:, None]
    u0 = u.mean(axis=0) / np.linalg.norm(u.mean(axis=0))
    B = _perp_basis(u0).T
    u_bar = u0 + B.T @ _pooled(u @ B.T, _pinv(np.einsum("ai,kij,bj->kab", B, Cu, B), 2))
    u_bar /= np.linalg.norm(u_bar)
    B = _perp_basis(u_bar).T
    Wu = _pinv(np.einsum("ai,kij,bj->kab", B, Cu, B), 2)
    ru = u @ B.T
    ru -= _pooled(ru, Wu)
    Wp = _pinv(np.einsum("ai,kij,bj->kab", B, Cp, B), 2)
    rp = p @ B.T
    rp -= _pooled(rp, Wp)
    chi2 = _quad(ru, Wu) + _quad(rp, Wp)
    dof = 4 * (k - 1)
    angles = np.degrees(np.arccos(np.clip(u @ u_bar, -1.0, 1.0)))
    spread_deg = float(np.sqrt(np.mean(angles**2)))
    spread = float(np.sqrt(np.mean(np.sum(rp**2, axis=1))))
    unit = f" {units}" if units else ""
    ok, pv, ratio, msg = _verdict(
        k, chi2, dof, f"axes spread by {spread_deg:.3g} deg and {spread:.3g}{unit} rms", alpha, rigid, "a hinge"
    )
    return BlockConsistency("hinge", k, n_skipped, p, u, f, chi2, dof, pv, ratio, spread, spread_deg, ok, msg)

