"""Each segment's white marker noise, online: sums of the second differences of its pose-fit residuals.

On skin markers the pose fit's pooled residual holds the cluster's deformation as well as the
marker noise (on a thigh with 20 mm of artefact, 11-12 mm read for 0.6-0.8 mm of noise), and a
noise level read that way over-corrects the estimate's second-order bias by the square of that
ratio (issue 17, item 1). :class:`SecondDifferences` keeps, frame after frame, what
:func:`jointfit_core.artefact.white_noise_std` computes over a whole recording: per segment, the
sum of squared second differences of the local residuals over three consecutive frames with the
same visible markers, and its degrees of freedom. They go into the joint's sliding window with the
frame (:class:`~jointfit_core.joint_sums.RelativePoseSums`, layout ``_WN``), so that a window's
white noise is ``sqrt(ss / dof)`` (:func:`white_noise_from_sums`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["MIN_WHITE_MARKERS", "SecondDifferences", "white_noise_from_sums"]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: A frame triple counts for a segment when it shows at least this many markers (as
#: :func:`jointfit_core.artefact.white_noise_std`): with 3, the residual has 3 dof, all of them
#: easily taken by a deformation.
MIN_WHITE_MARKERS = 4


class SecondDifferences:
    """The last two frames of a joint's statistics, and what each new frame adds to its white-noise sums.

    Notes
    -----
    The local residual of a posed segment, ``e_t = R_t^T (y_t - d_t) - x`` (template ``x``), is the
    marker noise projected off the cluster's small rigid motions (``3 P - 6`` dimensions), plus the
    cluster's deformation, plus the template's error (the same in every frame). Its second
    difference ``e_t - 2 e_{t-1} + e_{t-2}`` cancels the template and damps a deformation of
    frequency ``f`` by ``(2 pi f / rate)^2``, while white noise gains the variance factor
    ``1 + 4 + 1 = 6``; so a frame adds ``ss = sum |Delta^2 e|^2`` and ``dof = 6 (3 P - 6)`` per
    segment whose visible markers (at least :data:`MIN_WHITE_MARKERS`) are the same in the three
    frames, when the three are chained (each frame's lag pair is the one before it: nothing that
    reached the joint between them was left out of the statistics, as for the lag-1 pairs of
    :class:`~jointfit_core.joint_sums.RelativePoseSums`); otherwise it adds zeros. The template
    cancels, so ``R^T (y - d)`` stands for ``e``.
    """

    def __init__(self) -> None:
        self._local: FloatArray | None = None  # (2 frames, 2 segments, Pmax, 3): older, newer
        self._vis: BoolArray | None = None  # (2, 2, Pmax)
        self._last_paired = False  # whether the newer one was chained to the older

    def add_one(self, Y: FloatArray, wn: FloatArray, R: FloatArray, d: FloatArray, paired: bool, out: FloatArray) -> None:
        """One frame entering the statistics: write ``(ss_p, dof_p, ss_c, dof_c)`` into ``out`` (4,).

        ``Y`` (2, Pmax, 3): both segments' markers (input units; missing rows anything);
        ``wn`` (2, Pmax): the pair set's weights, positive for the markers the pose used;
        ``R`` (2, 3, 3), ``d`` (2, 3): the poses; ``paired``: whether the frame is chained to the
        last frame this saw.
        """
        local = np.matmul(Y - d[:, None, :], R)  # rows R^T (y - d)
        vis = wn > 0.0
        prev, pvis = self._local, self._vis
        if prev is None or pvis is None:
            self._local = np.stack([local, local])
            self._vis = np.stack([vis, vis])
            out[:] = 0.0
        else:
            if paired and self._last_paired:
                d2 = local - 2.0 * prev[1] + prev[0]
                n_vis = vis.sum(axis=1)
                ok = (vis == pvis[0]).all(axis=1) & (vis == pvis[1]).all(axis=1) & (n_vis >= MIN_WHITE_MARKERS)
                out[0::2] = np.where(ok, np.einsum("kpi,kpi,kp->k", d2, d2, vis), 0.0)
                out[1::2] = np.where(ok, 6.0 * (3.0 * n_vis - 6.0), 0.0)
            else:
                out[:] = 0.0
            prev[0] = prev[1]
            prev[1] = local
            pvis[0] = pvis[1]
            pvis[1] = vis
        self._last_paired = bool(paired)

    def add_many(self, Y: FloatArray, wn: FloatArray, R: FloatArray, d: FloatArray, paired: BoolArray) -> FloatArray:
        """Frames entering the statistics in order: :meth:`add_one` of each, (M, 4) returned.

        ``Y`` (M, 2, Pmax, 3), ``wn`` (M, 2, Pmax), ``R`` (M, 2, 3, 3), ``d`` (M, 2, 3), ``paired`` (M,).
        """
        m = Y.shape[0]
        local = np.matmul(Y - d[:, :, None, :], R)
        vis = wn > 0.0
        paired = np.asarray(paired, dtype=bool)
        chained = np.empty(m, dtype=bool)  # the frame before each was chained to its own predecessor
        chained[0] = self._last_paired and self._local is not None
        chained[1:] = paired[:-1]
        if self._local is None or self._vis is None:
            self._local = np.stack([local[0], local[0]])
            self._vis = np.stack([vis[0], vis[0]])
        L = np.concatenate([self._local, local])
        V = np.concatenate([self._vis, vis])
        d2 = L[2:] - 2.0 * L[1:-1] + L[:-2]
        n_vis = vis.sum(axis=2)  # (M, 2)
        ok = (
            (paired & chained)[:, None]
            & (V[2:] == V[1:-1]).all(axis=2)
            & (V[2:] == V[:-2]).all(axis=2)
            & (n_vis >= MIN_WHITE_MARKERS)
        )
        out = np.zeros((m, 4))
        out[:, 0::2] = np.where(ok, np.einsum("mkpi,mkpi,mkp->mk", d2, d2, vis), 0.0)
        out[:, 1::2] = np.where(ok, 6.0 * (3.0 * n_vis - 6.0), 0.0)
        self._local = L[-2:].copy()
        self._vis = V[-2:].copy()
        self._last_paired = bool(paired[-1])
        return out


def white_noise_from_sums(sums: FloatArray) -> tuple[float, float]:
    """``(parent, child)`` white noise per coordinate (input units) from ``(ss_p, dof_p, ss_c, dof_c)``; NaN without triples."""
    s = np.asarray(sums, dtype=np.float64)
    return tuple(  # type: ignore[return-value]
        float(np.sqrt(max(s[k], 0.0) / s[k + 1])) if s[k + 1] > 0.0 else float("nan") for k in (0, 2)
    )
