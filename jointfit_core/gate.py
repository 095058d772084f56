"""The outlier gate's shape test: sudden changes of a segment's marker shape, not its size.

A skin-marker cluster deforms: its markers, posed in the segment's template
frame, leave the template by several times the white noise when the joint
flexes (3-marker thigh clusters: ~4 mm against 0.7 mm of noise). The
deformation is smooth, so from one frame to the next the posed markers move
little; a label swap, a ghost or a jump moves them suddenly by centimetres.
The gate therefore compares each frame's posed markers with the segment's
previous frames, not with the template:

* ``local_i = R^T (y_i - d)``, marker i in the template frame of this frame's
  pose fit (``local_i - x_i`` is its fit residual, rotated);
* the *jump* of a frame is ``max_i |local_i - ref_i|^2 / g_i`` over the
  visible markers with a recent reference, ``ref_i`` marker i in the last
  frame where the segment passed with it, ``g_i <=`` :data:`GATE_JUMP_GAP_CAP`
  frames ago (the division makes the allowed change grow like a random walk
  over a gap);
* the segment's *normal jump* is a robust high level (median plus
  :data:`GATE_JUMP_MADS` robust standard deviations, on the marker
  displacements) of the jumps of its last :data:`GATE_HISTORY_FRAMES` passed
  frames (seeded with the template frames' frame-to-frame changes). It is not the pooled
  residual ``sigma``: on skin markers that holds the deformation itself
  (2 mm on the right hip fixture's pelvis, whose markers change by 0.1-0.3
  mm from one frame to the next at 100 Hz). Without any jumps yet (a
  calibration loaded, fixed templates) it is ``6 sigma^2``, the jump of a
  rigid cluster with white noise sigma (two frames' noise in 3 coordinates);
* a frame fails when its jump exceeds ``gate^2`` times the normal jump.

Without a reference (fewer than 3 visible markers with one: the first frame
after the templates, after a reset) the residual test decides, as it did
before this module, and a failing frame becomes a provisional reference until
one passes (so a ghost in that frame cannot lock the segment out). Its level
is the segment's own pooled pose-fit residual
(:meth:`~jointfit_core.segment_tracker.SegmentTracker.pooled_level`; on skin markers: the noise
plus the cluster's deformation), read again every
:data:`~jointfit_core.segment_tracker.GATE_REFRESH_FRAMES` frames, so that a marker
back from an occlusion, with no recent reference, is judged against the
deformation the cluster normally shows, not the template frames' noise. The
limit is at least ``gate^2`` times the segment's own recent level
(:data:`GATE_RESIDUAL_RECENT`), so that the first movement after a still
stance, whose deformation the stance-filled level has not seen, is judged
against what the cluster showed a few frames before.

Templates (:func:`consistent_frames`): frames are split at sudden changes of
their inter-marker distances (above :data:`~jointfit_core.segment_tracker.TEMPLATE_DEV_FACTOR`
times the 90th percentile of the frame-to-frame changes) into smooth runs;
the longest run and the runs that continue it smoothly across the frames in
between are kept. A smoothly deforming cluster is one run; a swap or a ghost
is a run of its own.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .quaternion_fit import rotations_from_correlations

__all__ = [
    "GATE_HISTORY_FRAMES",
    "GATE_JUMP_MADS",
    "GATE_JUMP_GAP_CAP",
    "GATE_JUMP_LOW",
    "GATE_RESIDUAL_RECENT",
    "ShapeTrack",
    "consistent_frames",
    "frame_jumps",
    "gated_verdict",
    "GATE_WARN_SHARE",
    "marker_code",
    "gate_fails",
]

FloatArray = NDArray[np.float64]

#: Outlier gate: passed frames per segment whose jumps give its normal jump.
GATE_HISTORY_FRAMES = 200
#: Outlier gate: the normal jump is the median marker displacement plus this many robust
#: standard deviations (1.4826 MAD) of those jumps, squared.
GATE_JUMP_MADS = 2.0
#: Outlier gate: the allowed change of a marker grows with the frames since its reference up to
#: this many frames.
GATE_JUMP_GAP_CAP = 10
#: Outlier gate: a segment that fails the residual test fails the gate when its jump exceeds this
#: many times its normal jump (markers displaced twice as much as usual).
GATE_JUMP_LOW = 4.0
#: Outlier gate: the residual test's level follows the segment's recent frames: it is at least
#: ``gate^2`` times the median mean squared residual per degree of freedom of the segment's last
#: this many frames that passed. A skin cluster's residual grows smoothly as the joint starts to move
#: (the template frames were still): from one frame to the next it never grows ``gate^2`` times, so the
#: first movement after a still stance is not judged against the stance's noise, while a marker that
#: suddenly leaves the cluster still is (:meth:`ShapeTrack.recent_residual`).
GATE_RESIDUAL_RECENT = 3
#: Template frames: the quantile of the frame-to-frame changes that scales a sudden change.
_TEMPLATE_STEP_QUANTILE = 0.9


def marker_code(index: NDArray[np.intp]) -> int:
    """The set of markers ``index`` as a bit mask (which markers a pose fit used)."""
    return int(np.sum(np.left_shift(1, index.astype(np.int64))))


def frame_jumps(
    local: FloatArray,
    vis: NDArray[np.bool_],
    ref: FloatArray,
    at: NDArray[np.int64],
    ref_code: NDArray[np.int64],
    numbers: NDArray[np.int64],
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Jump of each frame against its recent references, and whether some visible marker has none.

    Parameters
    ----------
    local : ndarray, shape (K, P, 3)
        Posed markers in the template frame (input units).
    vis : ndarray of bool, shape (K, P)
        Markers posed in each frame (the markers of its pose fit).
    ref : ndarray, shape (K, P, 3)
        Each marker's reference for that frame (input units).
    at : ndarray of int, shape (K, P)
        The frame number of each reference (0: none).
    ref_code : ndarray of int, shape (K, P)
        The markers of the pose fit each reference comes from (:func:`marker_code`).
    numbers : ndarray of int, shape (K,)
        The frames' numbers.

    Returns
    -------
    jump : ndarray, shape (K,)
        ``max_i |local_i - ref_i|^2 / g_i`` over the visible markers with a reference at most
        :data:`GATE_JUMP_GAP_CAP` frames old (input units squared); inf where fewer than 3 have one.
        Where a reference comes from a fit of other markers (its template-frame positions
        then differ by how the fit spread the deformation), the references are first aligned
        to ``local`` by the least-squares rigid motion over those markers.
    stale : ndarray of bool, shape (K,)
        Some visible marker has no such reference (never passed, or held out or unseen for longer).
    """
    gap = numbers[:, None] - at
    fresh = vis & (at > 0) & (gap <= GATE_JUMP_GAP_CAP)
    codes = vis.astype(np.int64) @ np.left_shift(np.int64(1), np.arange(vis.shape[1], dtype=np.int64))
    other = (fresh & (ref_code != codes[:, None])).any(axis=1)
    ref = ref.copy()
    if other.any():
        ref[other] = _aligned(ref[other], local[other], fresh[other])
    diff = local - ref
    d2 = np.where(fresh, np.einsum("kpi,kpi->kp", diff, diff), 0.0) / np.where(fresh, gap, 1)
    jump: FloatArray = d2.max(axis=1, initial=0.0)
    jump[fresh.sum(axis=1) < 3] = np.inf
    stale = np.asarray((vis & ~fresh).any(axis=1), dtype=bool)
    return jump, stale


def _aligned(x: FloatArray, y: FloatArray, w: NDArray[np.bool_]) -> FloatArray:
    """``x`` (M, P, 3) moved rigidly onto ``y`` (least squares over the points ``w`` (M, P), at least 3)."""
    wf = w.astype(np.float64)
    n = np.maximum(wf.sum(axis=1), 1.0)
    xb = np.einsum("mp,mpi->mi", wf, x) / n[:, None]
    yb = np.einsum("mp,mpi->mi", wf, y) / n[:, None]
    xc = (x - xb[:, None]) * wf[..., None]
    yc = (y - yb[:, None]) * wf[..., None]
    S = np.einsum("mpi,mpj->mij", xc, yc)
    bound = 0.5 * (np.einsum("mpi,mpi->m", xc, xc) + np.einsum("mpi,mpi->m", yc, yc))
    R, _ = rotations_from_correlations(S, np.maximum(bound, np.finfo(np.float64).tiny))
    out: FloatArray = np.einsum("mij,mpj->mpi", R, x - xb[:, None]) + yb[:, None]
    return out


def gate_fails(jump: Any, stale: Any, residual_bad: Any, limit: float, low: float, jump_last: Any) -> Any:
    """Whether segments fail the gate (scalars or arrays of the same shape).

    Parameters
    ----------
    jump, stale
        :func:`frame_jumps` against the references (the frames that passed).
    residual_bad
        The residual test (against the segment's pooled residual level) failed.
    limit : float
        ``gate^2`` times the normal jump.
    low : float
        :data:`GATE_JUMP_LOW` times the normal jump.
    jump_last
        :func:`frame_jumps` against the previous frame that posed the segment, passed or not.

    Notes
    -----
    With a jump to judge (3 or more visible markers with a recent reference) a segment fails

    * when it fails the residual test and its markers moved more than usual (``low``): the
      residual test of a rigid cluster, as before the jump test, but a skin cluster that
      deforms smoothly (its residual grows, its jumps do not) passes;
    * when it jumped from its references (``limit``), unless that is a step that stays: it
      did not jump from the previous frame (held out) and passes the residual test (skin
      that slipped; a swap that lasts fails the residual test, a symmetric one the turn
      test);
    * when some visible marker has no recent reference (held out or unseen for longer than
      :data:`GATE_JUMP_GAP_CAP` frames, or never passed) and it fails the residual test.

    Without a jump to judge, the residual test alone.
    """
    jumped = (jump > limit) & ((jump_last > limit) | residual_bad)
    return np.where(np.isinf(jump), residual_bad, jumped | (residual_bad & ((jump > low) | stale)))


class ShapeTrack:
    """One segment's shape references and its recent jumps (the gate's memory).

    Per marker: its reference (its template-frame position in the last frame where the
    segment passed with it), the frame number and the markers of the pose fit it comes from;
    the same for the previous frame that posed it, passed or not (``last``).

    Parameters
    ----------
    n_markers : int
    seed : sequence of float, optional
        Jumps to start the history with (the template frames').
    """

    def __init__(self, n_markers: int, seed: list[float] | None = None) -> None:
        self.ref = np.zeros((n_markers, 3))
        self.at = np.zeros(n_markers, dtype=np.int64)
        self.code = np.zeros(n_markers, dtype=np.int64)
        self.last = np.zeros((n_markers, 3))
        self.last_at = np.zeros(n_markers, dtype=np.int64)
        self.last_code = np.zeros(n_markers, dtype=np.int64)
        self.confirmed = False  # a frame has passed since the start
        self.history: deque[float] = deque(seed or (), maxlen=GATE_HISTORY_FRAMES)
        # mean squared residual per degree of freedom of the last frames that passed (recent_residual)
        self.residuals: deque[float] = deque(maxlen=GATE_RESIDUAL_RECENT)
        self._recent = 0.0
        # The latest write of the references (and of ``last``), as (frame number, code): every marker of
        # that code has its reference from that frame and that fit until the next write. (0, -1): not
        # known. :meth:`jump`'s shortcut for a frame of the same markers (the usual frame).
        self._ref_write = (0, -1)
        self._last_write = (0, -1)

    def normal_jump(self, sigma: float, floor: float) -> float:
        """The segment's normal jump (input units squared).

        ``(median + GATE_JUMP_MADS * 1.4826 MAD)^2`` of the square roots of its recent jumps
        (marker displacements), at least ``6 floor^2`` (``floor``: a length below which changes
        are rounding); ``6 sigma^2`` (white noise ``sigma``) while there are none (a
        calibration loaded, fixed templates). Median and MAD: frames that passed the gate
        only just (outliers a little smaller than the limit) cannot raise it unless they are
        half of the recent frames.
        """
        if not self.history:
            return 6.0 * max(sigma, floor) ** 2
        a = np.sqrt(np.fromiter(self.history, dtype=np.float64))
        med = float(np.median(a))
        spread = 1.4826 * float(np.median(np.abs(a - med)))
        return max((med + GATE_JUMP_MADS * spread) ** 2, 6.0 * floor**2)

    def jump(
        self, index: NDArray[np.intp], local: FloatArray, frame_no: int, code: int, last: bool = False
    ) -> tuple[float, bool]:
        """:func:`frame_jumps` of one frame whose markers ``index`` (fit ``code``) are posed at ``local`` (n, 3).

        ``last``: against the previous frame seen (:meth:`seen`) instead of the references.

        A frame of the markers of the latest write (:meth:`passed`, :meth:`failed`, :meth:`seen`)
        takes a shortcut: all its references come from that frame and fit, so the freshness and
        code tests are one comparison (the same numbers as the general path, tested).
        """
        written_at, written_code = self._last_write if last else self._ref_write
        if code == written_code:
            since = frame_no - written_at
            if written_at > 0 and since <= GATE_JUMP_GAP_CAP:  # all fresh, all of this fit
                if index.size < 3:
                    return np.inf, False
                change = local - (self.last if last else self.ref)[index]
                return float((np.einsum("pi,pi->p", change, change) / since).max()), False
            return np.inf, bool(index.size)  # none fresh
        ref, at, ref_code = (self.last, self.last_at, self.last_code) if last else (self.ref, self.at, self.code)
        gap = frame_no - at[index]
        fresh = (at[index] > 0) & (gap <= GATE_JUMP_GAP_CAP)
        n = np.count_nonzero(fresh)
        stale = bool(n < index.size)
        if n < 3:
            return np.inf, stale
        rows = index[fresh]
        if (ref_code[rows] != code).any():  # references from another fit: aligned first (after an occlusion)
            # frame_jumps of this one frame: the same alignment (_aligned of the whole marker set, the
            # markers without a fresh reference weighted 0) and the same jump, without the block's masks
            full = np.zeros((1, len(self.ref), 3))
            full[0, index] = local
            weight = np.zeros((1, len(self.ref)), dtype=bool)
            weight[0, rows] = True
            diff = local[fresh] - _aligned(ref[None], full, weight)[0, rows]
            return float((np.einsum("pi,pi->p", diff, diff) / gap[fresh]).max()), stale
        diff = local[fresh] - ref[rows]
        return float((np.einsum("pi,pi->p", diff, diff) / gap[fresh]).max()), stale

    def recent_residual(self) -> float:
        """The median mean squared residual per degree of freedom of the last :data:`GATE_RESIDUAL_RECENT` frames that passed (0 before any).

        Input units squared. The residual test's limit is at least ``gate^2`` times it
        (:meth:`~jointfit_core.segment_tracker.SegmentTracker.residual_bound`).
        """
        return self._recent

    def _recent_changed(self) -> None:
        """Keep :meth:`recent_residual` (the median of a few numbers, in Python: it is read per frame)."""
        vals = sorted(self.residuals)
        n = len(vals)
        self._recent = 0.0 if n == 0 else vals[n // 2] if n % 2 else 0.5 * (vals[n // 2 - 1] + vals[n // 2])

    def passed(
        self, index: NDArray[np.intp], local: FloatArray, frame_no: int, jump: float, code: int, residual: float = math.nan
    ) -> None:
        """The segment passed with markers ``index`` posed at ``local``: they become the references.

        ``residual``: the frame's mean squared pose-fit residual per degree of freedom (NaN: none,
        fewer than 3 markers' worth of freedom), for :meth:`recent_residual`.
        """
        if math.isfinite(jump):
            self.history.append(jump)
        if math.isfinite(residual):
            self.residuals.append(residual)
            self._recent_changed()
        self.ref[index] = local
        self.at[index] = frame_no
        self.code[index] = code
        self._ref_write = (frame_no, code)
        self.confirmed = True

    def failed(self, index: NDArray[np.intp], local: FloatArray, frame_no: int, code: int) -> None:
        """The segment failed: before any frame has passed, it is the provisional reference."""
        if not self.confirmed:
            self.ref[index] = local
            self.at[index] = frame_no
            self.code[index] = code
            self._ref_write = (frame_no, code)

    def seen(self, index: NDArray[np.intp], local: FloatArray, frame_no: int, code: int) -> None:
        """Markers ``index`` posed at ``local`` in frame ``frame_no``, passed or not (before the gate)."""
        self.last[index] = local
        self.last_at[index] = frame_no
        self.last_code[index] = code
        self._last_write = (frame_no, code)

    def block_references(
        self, local: FloatArray, vis: NDArray[np.bool_], numbers: NDArray[np.int64], last: bool = False
    ) -> tuple[FloatArray, NDArray[np.int64], NDArray[np.int64]]:
        """Each frame's references in a block, supposing every earlier frame of it passed with its markers.

        ``local`` (K, P, 3), ``vis`` (K, P), ``numbers`` (K,): the frames that pose the segment,
        oldest first. Returns ``ref`` (K, P, 3), ``at`` and ``code`` (K, P) for :func:`frame_jumps`.
        ``last``: the previous frames seen instead (no supposition: exact).
        """
        base, base_at, base_code = (self.last, self.last_at, self.last_code) if last else (self.ref, self.at, self.code)
        k, p = vis.shape
        codes = vis.astype(np.int64) @ np.left_shift(np.int64(1), np.arange(p, dtype=np.int64))
        latest = np.maximum.accumulate(np.where(vis, np.arange(k)[:, None], -1), axis=0)
        prev = np.empty_like(latest)
        prev[:1] = -1  # (a block in which the segment is never posed: no rows)
        prev[1:] = latest[:-1]
        inside = prev >= 0
        rows = np.maximum(prev, 0)
        ref = np.where(inside[..., None], local[rows, np.arange(p)], base[None])
        at = np.where(inside, numbers[rows], base_at[None])
        code = np.where(inside, codes[rows], base_code[None])
        return ref, at, code

    def passed_block(
        self,
        local: FloatArray,
        vis: NDArray[np.bool_],
        numbers: NDArray[np.int64],
        jumps: FloatArray,
        residuals: FloatArray,
    ) -> None:
        """:meth:`passed` and :meth:`seen` of each frame of a run (``local`` (K, P, 3), ``vis`` (K, P), ``residuals`` (K,), oldest first)."""
        if not vis.shape[0]:
            return
        self.history.extend(jumps[np.isfinite(jumps)].tolist())
        recent = residuals[np.isfinite(residuals)][-GATE_RESIDUAL_RECENT:]
        if recent.size:
            self.residuals.extend(recent.tolist())
            self._recent_changed()
        codes = vis.astype(np.int64) @ np.left_shift(np.int64(1), np.arange(vis.shape[1], dtype=np.int64))
        seen = vis.any(axis=0)
        latest = vis.shape[0] - 1 - np.argmax(vis[::-1], axis=0)
        self.ref[seen] = self.last[seen] = local[latest[seen], np.flatnonzero(seen)]
        self.at[seen] = self.last_at[seen] = numbers[latest[seen]]
        self.code[seen] = self.last_code[seen] = codes[latest[seen]]
        self._ref_write = self._last_write = (0, -1)  # markers from different frames: no shortcut
        self.confirmed = True


def consistent_frames(distances: FloatArray, factor: float) -> NDArray[np.bool_]:
    """Template candidates to keep: the longest smooth run of inter-marker distances and its smooth continuations.

    Parameters
    ----------
    distances : ndarray, shape (N, P, P)
        Inter-marker distances of the candidate frames, in their order (input units).
    factor : float
        A change from one frame to the next above ``factor`` times the 90th percentile of those
        changes is sudden (a swap, a ghost, a jump); across ``g`` frames left out, ``factor
        sqrt(g)`` times.

    Returns
    -------
    ndarray of bool, shape (N,)
    """
    n = distances.shape[0]
    flat = distances.reshape(n, -1)
    if n < 2:
        return np.ones(n, dtype=bool)
    step = np.abs(np.diff(flat, axis=0)).max(axis=1)
    limit = factor * float(np.quantile(step, _TEMPLATE_STEP_QUANTILE)) + 1e-12 * float(flat.max())
    run = np.concatenate([[0], np.cumsum(step > limit)])
    sizes = np.bincount(run)
    main = int(np.argmax(sizes))
    keep = run == main
    starts = np.searchsorted(run, np.arange(sizes.size))
    ends = starts + sizes - 1

    def joins(a: int, b: int) -> bool:
        return float(np.abs(flat[b] - flat[a]).max()) <= limit * np.sqrt(abs(b - a))

    edge = int(ends[main])
    for r in range(main + 1, sizes.size):
        if joins(edge, int(starts[r])):
            keep[run == r] = True
            edge = int(ends[r])
    edge = int(starts[main])
    for r in range(main - 1, -1, -1):
        if joins(int(ends[r]), edge):
            keep[run == r] = True
            edge = int(starts[r])
    return keep


class BlockJumps:
    """One segment's jumps over the frames of a block that pose it, supposing each passes (the block path).

    The block path (:meth:`OnlineJoint.update_many <jointfit_core.estimator.OnlineJoint.update_many>`)
    judges runs of frames at once: each frame's references are those of the frames before it in the
    block as if they passed with all their markers. A frame taken one by one that did not
    (:meth:`recheck`) changes the references of the frames up to each of its markers' next sighting,
    which are judged again.

    Parameters
    ----------
    track : ShapeTrack
        The segment's references before the block.
    local : ndarray, shape (K, P, 3)
        The posed markers in the template frame, frames oldest first.
    vis : ndarray of bool, shape (K, P)
    numbers : ndarray of int, shape (K,)
    residual_bad : ndarray of bool, shape (K,)
        The residual test of each frame, against the pooled level only: at least as strict as
        the frame path's (:meth:`~jointfit_core.segment_tracker.SegmentTracker.residual_bound`),
        so the frames that may fail are a superset.
    residuals : ndarray, shape (K,)
        Each frame's mean squared residual per degree of freedom (NaN: none), for
        :meth:`ShapeTrack.recent_residual` of the frames that pass in bulk and moved as usual
        (no stale marker, jump within ``limit``).
    limit, low : float
        ``gate^2`` and :data:`GATE_JUMP_LOW` times the normal jump (input units squared).
    """

    def __init__(
        self,
        track: ShapeTrack,
        local: FloatArray,
        vis: NDArray[np.bool_],
        numbers: NDArray[np.int64],
        residual_bad: NDArray[np.bool_],
        residuals: FloatArray,
        limit: float,
        low: float,
    ) -> None:
        self.track, self.local, self.vis, self.numbers = track, local, vis, numbers
        self.residual_bad, self.residuals, self.limit, self.low = residual_bad, residuals, limit, low
        self.jump, self.stale = frame_jumps(local, vis, *track.block_references(local, vis, numbers), numbers)
        # the jump from the previous frame matters only where the jump exceeds the limit
        self.jump_last = np.full(self.jump.shape, np.inf)
        if (self.jump > 0.9 * limit).any():
            self.jump_last = frame_jumps(local, vis, *track.block_references(local, vis, numbers, last=True), numbers)[0]

    def fails(self, margin: float, part: slice = slice(None)) -> NDArray[np.bool_]:
        """Frames (positions in ``part``) that may fail, with the limit lowered by ``margin`` (a fraction)."""
        out: NDArray[np.bool_] = gate_fails(
            self.jump[part], self.stale[part], self.residual_bad[part], (1.0 - margin) * self.limit,
            (1.0 - margin) * self.low, self.jump_last[part] * (1.0 + margin),
        )
        return out

    def passed(self, lo: int, hi: int) -> None:
        """Frames ``lo:hi`` passed in bulk: their markers become the references, their jumps the history."""
        usual = ~self.stale[lo:hi] & (self.jump[lo:hi] <= self.limit)  # as SegmentTracker.shape_test's
        self.track.passed_block(
            self.local[lo:hi], self.vis[lo:hi], self.numbers[lo:hi], self.jump[lo:hi],
            np.where(usual, self.residuals[lo:hi], np.nan),
        )

    def recheck(self, i: int, margin: float, relabelled: bool = False) -> NDArray[np.intp]:
        """Frame ``i`` went one by one: the later frames (positions) that may now fail (none if it passed whole).

        ``relabelled``: the gate put the frame's labels right, so its references are not the
        markers as the block saw them, even where it passed with all of them.
        """
        vis = self.vis[i]
        if not relabelled and (self.track.at[vis] == self.numbers[i]).all():
            return np.zeros(0, dtype=np.intp)  # its markers are the references, as supposed
        later = self.vis[i + 1 :]
        if not later.shape[0]:
            return np.zeros(0, dtype=np.intp)
        nxt = np.where(later.any(axis=0), np.argmax(later, axis=0), later.shape[0] - 1)
        part = slice(i + 1, i + 2 + int((nxt if relabelled else nxt[vis]).max()))
        loc, vis_p, num = self.local[part], self.vis[part], self.numbers[part]
        self.jump[part], self.stale[part] = frame_jumps(loc, vis_p, *self.track.block_references(loc, vis_p, num), num)
        if relabelled:  # the frame seen is the relabelled one too (the jump from the previous frame)
            last = self.track.block_references(loc, vis_p, num, last=True)
            self.jump_last[part] = frame_jumps(loc, vis_p, *last, num)[0]
        out: NDArray[np.intp] = i + 1 + np.flatnonzero(self.fails(margin, part))
        return out


#: Above this share of a segment's frames rejected by the outlier gate, the verdict says so
#: (``jointfit fit`` exits 3, ``/diagnostics`` warns): the estimate then rests on the frames the
#: gate kept, which may not be all the motion.
GATE_WARN_SHARE = 0.10


def gated_verdict(gated: tuple[int, int], frames: int, names: tuple[str, str], joint_gated: int = 0) -> str:
    """Empty, or what the outlier gate did to the segments above :data:`GATE_WARN_SHARE` of the frames.

    Parameters
    ----------
    gated : (int, int)
        Frames in which the parent and the child failed the gate
        (:attr:`OnlineJoint.gated_frames <jointfit_core.estimator.OnlineJoint.gated_frames>`).
    frames : int
        Frames the estimator took (:attr:`OnlineJoint.n_frames_seen
        <jointfit_core.estimator.OnlineJoint.n_frames_seen>`).
    names : (str, str)
        How to name the parent and the child (their role and markers).
    joint_gated : int
        Frames the joint-consistency test rejected (:mod:`jointfit_core.joint_gate`).
    """
    if frames <= 0:
        return ""
    parts = [
        f"the outlier gate rejected {100.0 * n / frames:.0f} % of the {name} frames ({n} of {frames})"
        for n, name in zip(gated, names, strict=True)
        if n > GATE_WARN_SHARE * frames
    ]
    if joint_gated > GATE_WARN_SHARE * frames:
        parts.append(
            f"the joint test rejected {100.0 * joint_gated / frames:.0f} % of the frames ({joint_gated} of {frames}: "
            "both segments posed, the joint broken suddenly)"
        )
    if not parts:
        return ""
    return (
        "; ".join(parts)
        + ": the estimate rests on the frames it kept; look for swapped labels, ghosts or jumps in those markers "
        "(the figure marks the frames), and compare with outlier_gate 0"
    )
