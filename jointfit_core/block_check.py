"""The consistency check on an online estimator's window or a whole recording: blocks of sums, solved apart.

The estimator's sums are exactly additive over frames, so a movement block's
sums are the sum of its frames' contributions (a window that keeps its
frames: :meth:`OnlineJoint.window_contributions
<jointfit_core.estimator.OnlineJoint.window_contributions>`) or the
difference of two snapshots of a window that forgets nothing (``jointfit
fit``: :meth:`OnlineJoint.sums_vector
<jointfit_core.estimator.OnlineJoint.sums_vector>` taken along the
recording). Each block is solved as the whole window is
(:func:`~jointfit_core.estimator.solve_window`: the same noise, serial and
soft-tissue covariance parts) and the blocks are compared by
:mod:`jointfit_core.consistency`. Nothing here runs per frame.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from .consistency import CONSISTENCY_BLOCKS, BlockConsistency, ball_consistency, hinge_consistency
from .errors import JointfitError
from .estimator import OnlineJoint, solve_window
from .hinge_from_sums import PoseSumsAxis
from .segments import PoseSumsCentre

__all__ = ["block_bounds", "blocks_consistency", "window_consistency", "snapshots_consistency",
           "MIN_BLOCK_FRAMES", "MIN_BLOCK_S"]

FloatArray = NDArray[np.float64]

#: A block holds at least this many frames ...
MIN_BLOCK_FRAMES = 30
#: ... and, when the frames are stamped, spans at least this many seconds (a movement or two).
MIN_BLOCK_S = 1.0


#: Verdicts of a block that moved enough to be solved but whose sd is large: compared (its weight is small).
_WIDE_ONLY = ("centre poorly determined", "axis direction poorly determined", "axis position poorly determined")


def _comparable(sol: PoseSumsCentre | PoseSumsAxis) -> bool:
    """A block estimate enters the comparison: identifiable, or only too uncertain (not degenerate motion)."""
    if isinstance(sol, PoseSumsCentre):
        covs, ranks = [sol.cov_parent], [3]
    else:
        covs, ranks = [sol.cov_direction_parent, sol.cov_point_parent], [2, 2]
    for c, rank in zip(covs, ranks, strict=True):
        if not np.isfinite(c).all() or np.linalg.eigvalsh(c)[-rank] <= 0.0:
            return False  # no variance in a compared direction: no weight to give it
    return sol.identifiable or sol.reason.startswith(_WIDE_ONLY)


def block_bounds(
    n_frames: int,
    n_blocks: int = CONSISTENCY_BLOCKS,
    stamps: FloatArray | None = None,
    *,
    min_frames: int = MIN_BLOCK_FRAMES,
    min_seconds: float = MIN_BLOCK_S,
) -> list[tuple[int, int]]:
    """Contiguous, about equal blocks ``[start, stop)`` of ``n_frames`` frames, as many as fit (at most ``n_blocks``).

    Parameters
    ----------
    n_frames : int
    n_blocks : int
        Blocks wanted.
    stamps : ndarray, shape (n_frames,), optional
        Seconds; NaN or None: unstamped (only ``min_frames`` applies).
    min_frames : int
        Fewest frames in a block.
    min_seconds : float
        Shortest block (stamped frames), seconds.

    Returns
    -------
    list of (int, int)
        Fewer than 2 when the frames do not fill two blocks.
    """
    k = min(int(n_blocks), int(n_frames) // max(int(min_frames), 1))
    if stamps is not None and stamps.size == n_frames and n_frames > 1 and np.isfinite(stamps[[0, -1]]).all():
        duration = float(stamps[-1] - stamps[0]) * n_frames / (n_frames - 1)
        k = min(k, int(duration / min_seconds)) if min_seconds > 0 else k
    if k < 1:
        return []
    edges = np.rint(np.linspace(0, n_frames, k + 1)).astype(int)
    return [(int(a), int(b)) for a, b in itertools.pairwise(edges)]


def blocks_consistency(est: OnlineJoint, block_sums: Sequence[FloatArray], *, units: str = "") -> BlockConsistency:
    """Solve each block's sums with ``est``'s settings and compare the estimates.

    Parameters
    ----------
    est : OnlineJoint
        Whose settings (noise, attachment, templates' radii, hinge sign) the blocks are solved with.
    block_sums : sequence of ndarray, shape (n_sums,)
        Each block's sums (the estimator's layout).
    units : str
        Input units, for the message.

    Returns
    -------
    BlockConsistency
        Blocks that cannot be solved, or whose motion alone cannot determine
        the joint (no rotation, a single axis for a ball, not a hinge), are
        skipped (``n_skipped``); blocks that are only too uncertain to be
        identifiable by the ``SD_REL_MAX`` / ``AXIS_SD_MAX_DEG`` rules are
        compared with their (large) covariances. The covariances compared are
        the published ones (with the soft-tissue part for skin markers).
    """
    sols: list[PoseSumsCentre | PoseSumsAxis] = []
    skipped = 0
    for s in block_sums:
        try:
            sol = solve_window(est.request_for(s)).solution
        except JointfitError:
            skipped += 1
            continue
        if _comparable(sol):
            sols.append(sol)
        else:
            skipped += 1
    frames = [int(s.n_frames) for s in sols]
    balls = [s for s in sols if isinstance(s, PoseSumsCentre)]
    if est.kind == "ball":
        return ball_consistency(
            np.array([s.centre_parent for s in balls]).reshape(-1, 3),
            np.array([s.cov_parent for s in balls]).reshape(-1, 3, 3),
            frames=frames, n_skipped=skipped, units=units, rigid="skin" not in est.attachment,
        )
    axes = [s for s in sols if isinstance(s, PoseSumsAxis)]
    return hinge_consistency(
        np.array([s.direction_parent for s in axes]).reshape(-1, 3),
        np.array([s.cov_direction_parent for s in axes]).reshape(-1, 3, 3),
        np.array([s.point_parent for s in axes]).reshape(-1, 3),
        np.array([s.cov_point_parent for s in axes]).reshape(-1, 3, 3),
        frames=frames, n_skipped=skipped, units=units, rigid="skin" not in est.attachment,
    )


def window_consistency(
    est: OnlineJoint, *, n_blocks: int = CONSISTENCY_BLOCKS, units: str = ""
) -> BlockConsistency | None:
    """The check on the estimator's current window, cut into ``n_blocks`` contiguous blocks.

    Returns
    -------
    BlockConsistency or None
        None when the window keeps no frames (exponential forgetting) or none entered.
    """
    window = est.window_contributions()
    if window is None:
        return None
    rows, stamps = window
    bounds = block_bounds(rows.shape[0], n_blocks, stamps)
    return blocks_consistency(est, [rows[a:b].sum(axis=0) for a, b in bounds], units=units)


def snapshots_consistency(
    est: OnlineJoint,
    snapshots: Sequence[FloatArray],
    *,
    n_blocks: int = CONSISTENCY_BLOCKS,
    rate_hz: float = 0.0,
    units: str = "",
) -> BlockConsistency:
    """The check on a window that forgets nothing, from snapshots of its sums taken along the recording.

    Parameters
    ----------
    est : OnlineJoint
        The estimator (settings; its current sums close the last block).
    snapshots : sequence of ndarray, shape (n_sums,)
        :meth:`OnlineJoint.sums_vector` at increasing points of the recording
        (e.g. the convergence checkpoints), cumulative: no forgetting.
    n_blocks : int
        Blocks wanted.
    rate_hz : float
        Frame rate (0: unknown): a block spans at least :data:`MIN_BLOCK_S` seconds of frames.
    units : str
        Input units, for the message.

    Returns
    -------
    BlockConsistency
        Block boundaries are the snapshots nearest ``1/K, 2/K, ...`` of the
        frames, with ``K`` at most ``n_blocks`` and small enough that blocks
        hold :data:`MIN_BLOCK_FRAMES` frames (and :data:`MIN_BLOCK_S` seconds).
    """
    final = est.sums_vector()
    if final is None:
        return blocks_consistency(est, [], units=units)
    cum = [np.zeros_like(final), *(np.asarray(s, dtype=np.float64) for s in snapshots), final]
    n = np.array([c[0] for c in cum])
    min_frames = max(MIN_BLOCK_FRAMES, math.ceil(MIN_BLOCK_S * rate_hz)) if rate_hz > 0 else MIN_BLOCK_FRAMES
    k = min(int(n_blocks), int(n[-1]) // min_frames)
    edges = [0]
    for j in range(1, k):
        idx = int(np.argmin(np.abs(n - n[-1] * j / k)))
        if edges[-1] < idx < len(cum) - 1:
            edges.append(idx)
    edges.append(len(cum) - 1)
    sums = [cum[b] - cum[a] for a, b in itertools.pairwise(edges)]
    return blocks_consistency(est, sums if len(sums) >= 2 else [], units=units)
