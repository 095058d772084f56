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
        self._older: FloatArray | None = None  # (2 segments, Pmax, 3): the frame before the last
        self._newer: FloatArray | None = None  # the last frame
        self._codes: tuple[int, int, int, int] = (-1, -1, -1, -1)  # visible-marker codes: older (p, c), newer (p, c)
        self._last_paired = False  # whether the newer one was chained to the older

    def add_many(self, Y: FloatArray, wn: FloatArray, R: FloatArray, d: FloatArray, paired: BoolArray) -> FloatArray:
        """Frames entering the statistics in order: ``(ss_p, dof_p, ss_c, dof_c)`` of each, (M, 4) returned.

        ``Y`` (M, 2, Pmax, 3), ``wn`` (M, 2, Pmax), ``R`` (M, 2, 3, 3), ``d`` (M, 2, 3), ``paired`` (M,).
        """
        m = Y.shape[0]
        local = np.matmul(Y - d[:, :, None, :], R)
        vis = wn > 0.0
        paired = np.asarray(paired, dtype=bool)
        chained = np.empty(m, dtype=bool)  # the frame before each was chained to its own predecessor
        chained[0] = self._last_paired and self._older is not None
        chained[1:] = paired[:-1]
        older = local[0] if self._older is None else self._older
        newer = local[0] if self._newer is None else self._newer
        L = np.concatenate([older[None], newer[None], local])
        codes = np.array(self._codes).reshape(2, 2)  # older, newer; per segment
        row_codes = np.where(vis.any(axis=2), (vis * (np.int64(1) << np.arange(vis.shape[2]))).sum(axis=2), -1)
        C = np.concatenate([codes, row_codes])  # (M + 2, 2) visible-marker codes, -1: not posed
        d2 = L[2:] - 2.0 * L[1:-1] + L[:-2]
        n_vis = vis.sum(axis=2)  # (M, 2)
        ok = (paired & chained)[:, None] & (C[2:] >= 0) & (C[2:] == C[1:-1]) & (C[2:] == C[:-2]) & (n_vis >= MIN_WHITE_MARKERS)
        out = np.zeros((m, 4))
        out[:, 0::2] = np.where(ok, np.einsum("mkpi,mkpi,mkp->mk", d2, d2, vis), 0.0)
        out[:, 1::2] = np.where(ok, 6.0 * (3.0 * n_vis - 6.0), 0.0)
        self._older, self._newer = L[-2].copy(), L[-1].copy()
        self._codes = (int(C[-2, 0]), int(C[-2, 1]), int(C[-1, 0]), int(C[-1, 1]))
        self._last_paired = bool(paired[-1])
        return out


def white_noise_from_sums(sums: FloatArray) -> tuple[float, float]:
    """``(parent, child)`` white noise per coordinate (input units) from ``(ss_p, dof_p, ss_c, dof_c)``; NaN without triples."""
    s = np.asarray(sums, dtype=np.float64)
    return tuple(  # type: ignore[return-value]
        float(np.sqrt(max(s[k], 0.0) / s[k + 1])) if s[k + 1] > 0.0 else float("nan") for k in (0, 2)
    )
