"""The two segments of a joint, posed together: their trackers, the frame's marker buffer and the pose fits.

:class:`SegmentPair` holds what an online joint
(:class:`~jointfit_core.estimator.OnlineJoint`) needs to pose its parent and
child in a frame or a block of frames: the two
:class:`~jointfit_core.segment_tracker.SegmentTracker` (templates, visibility
caches, the gate's memory), the marker buffer a frame is copied into, and per
missing-marker pattern a :class:`PairSet` (both visible sets stacked for one
batched pose fit, Stoddart et al. eq. 4). :func:`poses` fits both segments of
one frame (Horn's quaternion method, one batched ``eigh``); :func:`poses_many`
fits any number of segments of a block at once.

Issue 16 moves this per segment and shares it across the joints of a skeleton;
today each joint owns one pair.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import InputError
from .quaternion_fit import HORN_A, HORN_B, rotations_from_correlations
from .segment_tracker import COS_MAX_TURN, SegmentTracker, VisibleSet, cos_turn

__all__ = ["GateVerdict", "PairSet", "SegmentPair", "pair_set", "poses", "poses_many", "relative_poses"]

FloatArray = NDArray[np.float64]


try:  # the gufunc behind np.linalg.eigh, without its Python-level checks (~3 us per call here)
    from numpy.linalg import _umath_linalg

    _eigh: Any = _umath_linalg.eigh_lo
except (ImportError, AttributeError):  # pragma: no cover - other numpy versions
    _eigh = np.linalg.eigh


@dataclass(frozen=True, eq=False)
class PairSet:
    """Both segments' visible sets of one frame, stacked for the batched pose fit (cached)."""

    parent: VisibleSet | None
    child: VisibleSet | None
    xc_t: FloatArray  # (2, 3, Pmax) centred template points, zero columns for missing or padding
    wn: FloatArray  # (2, Pmax) visible / n
    n: FloatArray  # (2,)
    xbar: FloatArray  # (2, 3)
    xx: FloatArray  # (2,)
    W_flat: FloatArray  # (72,) unit W_p and W_c, raveled (zeros when a segment is not posed)
    dof: FloatArray  # (2,)
    slot: int  # its row in the stacked table of pair sets (SegmentPair.table)


def pair_set(parent: VisibleSet | None, child: VisibleSet | None, p_max: int, slot: int) -> PairSet:
    """Stack both segments' visible sets (None: that segment cannot be posed) for :func:`poses`.

    ``p_max``: the larger marker count (the rows of the frame buffer); ``slot``: the pair set's row
    in :meth:`SegmentPair.table`. A segment that cannot be posed has zero columns and weights, ``n``
    1 and zero ``W`` and dof.
    """
    xc = np.zeros((2, p_max, 3))
    wn = np.zeros((2, p_max))
    n = np.ones(2)
    xbar = np.zeros((2, 3))
    xx = np.zeros(2)
    W = np.zeros((2, 36))
    dof = np.zeros(2)
    for k, vs in enumerate((parent, child)):  # two segments
        if vs is None:
            continue
        xc[k, : vs.xc.shape[0]] = vs.xc
        wn[k, vs.index] = 1.0 / vs.n
        n[k] = vs.n
        xbar[k] = vs.xbar
        xx[k] = vs.xx
        W[k] = vs.W_unit.ravel()
        dof[k] = vs.dof
    return PairSet(parent, child, np.ascontiguousarray(np.swapaxes(xc, 1, 2)), wn, n, xbar, xx, W.ravel(), dof, slot)


def poses(Y: FloatArray, ps: PairSet) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Least-squares poses of both segments (Horn's quaternion method, one batched ``eigh``).

    Parameters
    ----------
    Y : ndarray, shape (2, Pmax, 3)
        Measured world points of the parent and the child, zero where missing or padding
        (the residual sum of squares relies on the zeros).
    ps : _PairSet

    Returns
    -------
    R : ndarray, shape (2, 3, 3)
    d : ndarray, shape (2, 3)
        ``world = R @ local + d``.
    ss : ndarray, shape (2,)
        Residual sums of squares ``|y - R x - d|^2`` over the visible markers,
        ``|y - ybar|^2 + |x_c|^2 - 2 lambda_max``.
    """
    ybar = (ps.wn[:, None, :] @ Y)[:, 0]
    S = ps.xc_t @ Y  # centred x: no need to centre y
    N = (S.reshape(2, 9) @ HORN_A.T).reshape(2, 4, 4)
    lam, V = _eigh(N)
    q = V[:, :, 3]
    R = ((q[:, :, None] * q[:, None, :]).reshape(2, 16) @ HORN_B.T).reshape(2, 3, 3)
    d = ybar - (R @ ps.xbar[:, :, None])[:, :, 0]
    yy = (Y * Y).sum(axis=(1, 2)) - ps.n * (ybar * ybar).sum(axis=1)  # Y is zero where not visible
    ss = np.maximum(yy + ps.xx - 2.0 * lam[:, 3], 0.0)
    return R, d, ss


def relative_poses(R: FloatArray, d: FloatArray) -> FloatArray:
    """``[Q | t] = R_p^T [R_c | d_c - d_p]`` (K, 3, 4) of poses ``R`` (K, 2, 3, 3), ``d`` (K, 2, 3)."""
    Rp_t = np.swapaxes(R[:, 0], 1, 2)
    z = np.empty((R.shape[0], 3, 4))
    np.matmul(Rp_t, R[:, 1], out=z[:, :, :3])
    z[:, :, 3] = np.einsum("kij,kj->ki", Rp_t, d[:, 1] - d[:, 0])
    return z


def poses_many(
    Y: FloatArray, xc_t: FloatArray, wn: FloatArray, n: FloatArray, xbar: FloatArray, xx: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`poses` of K posed segments at once (any frames, either side), with the largest eigenpair found without LAPACK.

    Parameters
    ----------
    Y : ndarray, shape (K, Pmax, 3)
        Measured points of each segment, zero where missing or padding.
    xc_t, wn, n, xbar, xx : ndarray, shapes (K, 3, Pmax), (K, Pmax), (K,), (K, 3), (K,)
        That segment's fields of the frame's :class:`PairSet` (one row of each).

    Returns
    -------
    R : ndarray, shape (K, 3, 3)
    d : ndarray, shape (K, 3)
    ss : ndarray, shape (K,)

    Notes
    -----
    The same steps as :func:`poses` on stacked arrays, except the eigen-solve:
    :func:`~jointfit_core.quaternion_fit.largest_eigenpair` (Newton on Horn's
    characteristic polynomial, eigenvector from the adjugate) instead of LAPACK's
    full ``eigh``, eight times faster on blocks. The poses equal the per-frame
    path's to ~1e-13 (rotation entries) and the residuals to ~1e-14 of the
    point spread; each segment's result does not depend on the block it is in.
    Only segments that can be posed belong here (an empty set has no largest
    eigenvalue to find).
    """
    ybar = np.einsum("kp,kpi->ki", wn, Y)
    S = xc_t @ Y
    yy = np.einsum("kpi,kpi->k", Y, Y) - n * np.einsum("ki,ki->k", ybar, ybar)
    R, lam = rotations_from_correlations(S, 0.5 * (yy + xx))
    d = ybar - np.einsum("kij,kj->ki", R, xbar)
    ss = np.maximum(yy + xx - 2.0 * lam, 0.0)
    return R, d, ss


@dataclass(frozen=True, eq=False)
class GateVerdict:
    """Why a posed frame failed the outlier gate, and what to do after its refit (:meth:`SegmentPair.judge`)."""

    failed: tuple[bool, bool]  # per segment (parent, child): it failed a shape or a turn test
    active: tuple[bool, bool]  # per segment: its turn test applied (a recent reference)
    local: list[FloatArray | None]  # per segment: its markers in the template frame, before the gate
    follow: list[tuple[int, FloatArray, NDArray[np.intp]]]  # (segment, its markers, the relabelling) of swaps


class SegmentPair:
    """A joint's parent and child trackers with the buffers and caches of their pose fits.

    Parameters
    ----------
    n_parent, n_child : int
        Marker counts of the two segments (>= 3 each).
    template_frames : int
        Fully visible frames averaged into each template.

    Attributes
    ----------
    parent, child : SegmentTracker
    n_markers : (int, int)
    Y : ndarray, shape (2, Pmax, 3)
        The frame being posed: parent and child markers (input units), rows past a segment's
        count zero; missing markers NaN until the pose fit zeroes them.
    none_missing : ndarray of bool, shape (2, Pmax)
        The all-present mask (compared by identity on the per-frame path).
    missing : ndarray of bool, shape (2, Pmax)
        The missing-marker mask of the frame :meth:`fast_fill` copied in.
    """

    def __init__(self, n_parent: int, n_child: int, template_frames: int) -> None:
        self.n_markers = (n_parent, n_child)
        self.parent = SegmentTracker("parent", n_parent, template_frames)
        self.child = SegmentTracker("child", n_child, template_frames)
        self.Y = np.zeros((2, max(n_parent, n_child), 3))
        self.none_missing: NDArray[np.bool_] = np.zeros((2, max(n_parent, n_child)), dtype=bool)
        self.missing = self.none_missing
        self._pairs: dict[bytes, PairSet] = {}
        self._table: tuple[FloatArray, ...] = ()

    def table(self) -> tuple[FloatArray, ...]:
        """Every cached pair set's ``xc_t, wn, n, xbar, xx, dof, W_flat`` stacked, row ``ps.slot``, for gathers by frame.

        Then the first five side by side per segment, ``(2 slots, 5 Pmax + 5)``, row ``2 slot + side``
        (:meth:`pose_fields`).

        Rebuilt only when pair sets were added (a new visibility pattern), not per block.
        """
        if not self._table or self._table[0].shape[0] != len(self._pairs):
            sets = list(self._pairs.values())
            names = ("xc_t", "wn", "n", "xbar", "xx", "dof", "W_flat")
            table = [np.stack([getattr(ps, name) for ps in sets]) for name in names]
            # the pose fit's fields side by side, one row per (slot, side): one gather per block
            rows = 2 * len(sets)
            table.append(np.concatenate([f.reshape(rows, -1) for f in table[:5]], axis=1))
            self._table = tuple(table)
        return self._table

    def pose_fields(self, seg: NDArray[np.intp]) -> tuple[FloatArray, ...]:
        """:func:`poses_many`'s ``xc_t, wn, n, xbar, xx`` of the segments at rows ``seg`` (``2 slot + side``) of the table."""
        g = self.table()[7][seg]
        p = self.Y.shape[1]
        return g[:, : 3 * p].reshape(-1, 3, p), g[:, 3 * p : 4 * p], g[:, 4 * p], g[:, 4 * p + 1 : 4 * p + 4], g[:, 4 * p + 4]

    def fast_fill(self, parent: ArrayLike, child: ArrayLike) -> bool:
        """Copy a well-shaped frame straight into the pose buffer; False to take the checked path.

        Steady-state fast path: one finiteness test for both segments instead of two frame checks.
        Leaves ``self.missing`` set. Raises InputError for infinite values.
        """
        if not (isinstance(parent, np.ndarray) and isinstance(child, np.ndarray)):
            return False
        if parent.shape != (self.n_markers[0], 3) or child.shape != (self.n_markers[1], 3):
            return False
        Y = self.Y
        Y[0, : self.n_markers[0]] = parent
        Y[1, : self.n_markers[1]] = child
        finite = np.isfinite(Y)
        if finite.all():
            self.missing = self.none_missing
            return True
        if np.isinf(Y).any():
            raise InputError("parent, child: contain inf; use NaN for missing markers")
        self.missing = np.asarray(~finite.all(axis=2), dtype=bool)
        return True

    def fill(self, yp: FloatArray, yc: FloatArray) -> NDArray[np.bool_]:
        """Copy checked frames into the pose buffer; return the missing-marker mask (2, Pmax)."""
        Y = self.Y
        Y[0, : yp.shape[0]] = yp
        Y[1, : yc.shape[0]] = yc
        missing: NDArray[np.bool_] = np.isnan(Y[:, :, 0])
        return missing

    def pair(self, missing: NDArray[np.bool_]) -> PairSet:
        """Cached pair set for the missing-marker mask (2, Pmax) of ``self.Y`` (padding rows count as present)."""
        key = missing.tobytes()
        ps = self._pairs.get(key)
        if ps is None:
            pa, pc = self.parent.n_markers, self.child.n_markers
            ps = pair_set(
                self.parent.visible_set(~missing[0, :pa]),
                self.child.visible_set(~missing[1, :pc]),
                max(pa, pc),
                len(self._pairs),
            )
            self._pairs[key] = ps
        return ps

    def tracker(self, k: int) -> SegmentTracker:
        """Segment ``k``'s tracker (0 parent, 1 child; the templates' segments exist)."""
        return self.parent if k == 0 else self.child

    def shape_tests(
        self, ps: PairSet, R: FloatArray, d: FloatArray, ss: FloatArray, frame_no: int, refit: tuple[bool, bool]
    ) -> tuple[list[FloatArray | None], list[float], list[bool], list[bool]]:
        """Per segment of a posed frame: its markers in the template frame, its jump, whether it fails the gate and whether it moved as usual.

        :meth:`~jointfit_core.segment_tracker.SegmentTracker.shape_test` of each posed segment.
        """
        local: list[FloatArray | None] = [None, None]
        jumps = [np.inf, np.inf]
        fails = [False, False]
        usual = [False, False]
        Y = self.Y
        for k, vs in enumerate((ps.parent, ps.child)):
            if vs is not None:
                seg = self.tracker(k)
                n = vs.index.size
                y = Y[k, :n] if n == seg.n_markers else Y[k, vs.index]  # all visible: its rows as they are
                local[k], jumps[k], fails[k], usual[k] = seg.shape_test(y, vs, R[k], d[k], float(ss[k]), frame_no, refit[k])
        return local, jumps, fails, usual

    def seen(self, ps: PairSet, local: list[FloatArray | None], frame_no: int) -> None:
        """Keep each posed segment's markers of this frame (before the gate) for the next frame's test."""
        for k, (vs, lk) in enumerate(((ps.parent, local[0]), (ps.child, local[1]))):
            if vs is not None and lk is not None:
                self.tracker(k).shape.seen(vs.index, lk, frame_no, vs.code)

    def judge(
        self, ps: PairSet, R: FloatArray, d: FloatArray, ss: FloatArray, frame_no: int, refit: tuple[bool, bool]
    ) -> GateVerdict | None:
        """The outlier gate's per-segment tests of a posed frame: None when it passes (references moved on).

        Parameters
        ----------
        ps : PairSet
            The frame's visible sets; :attr:`Y` holds its markers (zeros where missing).
        R, d, ss : ndarray, shapes (2, 3, 3), (2, 3), (2,)
            Both segments' poses and pose-fit residual sums of squares (:func:`poses`).
        frame_no : int
            The frame's number (the turn test's clock).
        refit : (bool, bool)
            Per segment, whether the gate left its markers out earlier in this frame (this call is
            a refit of them). A segment judged on all its markers is judged as if alone, whatever
            the other did: two joints that share it then judge it alike. The frame's markers before
            the gate are kept for the next frame's test by the first call only (neither set).

        Returns
        -------
        GateVerdict or None
            A segment fails when its markers jumped or its residual is too large
            (:meth:`~jointfit_core.segment_tracker.SegmentTracker.shape_test`), or when it turned by
            more than :data:`~jointfit_core.segment_tracker.GATE_MAX_TURN_DEG` from its reference
            while its turn test is active and the turn is a relabelling or comes with a failed
            shape test (a rigid turn without either: the segment jumped, its reference starts
            afresh). On a pass, each posed segment's turn and shape references move to this frame,
            and its residual joins its pooled level
            (:meth:`~jointfit_core.segment_tracker.SegmentTracker.add_level`).
        """
        local, jumps, fails, usual = self.shape_tests(ps, R, d, ss, frame_no, refit)
        active = (self.parent.turn_active(frame_no), self.child.turn_active(frame_no))
        turned = [False, False]
        labels: list[NDArray[np.intp] | None] = [None, None]
        for k, vs in enumerate((ps.parent, ps.child)):
            if not active[k] or vs is None:
                continue
            seg = self.tracker(k)
            cos = float(cos_turn(R[k], seg.ref_R))
            if not (fails[k] or cos < COS_MAX_TURN):
                continue
            # (here: a refit clears the markers it leaves out)
            labels[k] = seg.relabelling(self.Y[k, vs.index], vs, frame_no)
            # a rigid turn that is not a relabelling: the segment jumped (the recording
            # restarts, another subject): no swap to hold out, the reference starts afresh
            turned[k] = cos < COS_MAX_TURN and (fails[k] or labels[k] is not None)
        if fails[0] or fails[1] or turned[0] or turned[1]:
            failed = (fails[0] or turned[0], fails[1] or turned[1])
            follow = [
                (k, self.Y[k, vs.index].copy(), lab)
                for k, (vs, lab) in enumerate(((ps.parent, labels[0]), (ps.child, labels[1])))
                if failed[k] and vs is not None and lab is not None
            ]
            return GateVerdict(failed, active, local, follow)
        for k, vs in enumerate((ps.parent, ps.child)):
            lk = local[k]
            if vs is not None and lk is not None:
                seg = self.tracker(k)
                seg.set_reference(R[k], d[k], frame_no)
                # the residual test's recent level: frames that passed whole (not a refit's chosen subset)
                # and moved as usual
                level = float(ss[k]) / vs.dof if usual[k] and not refit[k] and vs.dof > 0.0 else math.nan
                seg.shape.passed(vs.index, lk, frame_no, jumps[k], vs.code, level)
                seg.add_level(float(ss[k]), vs.dof, frame_no)
        if not (refit[0] or refit[1]):
            self.seen(ps, local, frame_no)
        return None

    def relabel(
        self, missing: NDArray[np.bool_], ps: PairSet, verdict: GateVerdict, allowed: tuple[bool, bool]
    ) -> tuple[NDArray[np.bool_], list[int]] | None:
        """The frame with the swapped labels of its failing segments put right, or None (no swap to put right).

        A segment that failed with its visible markers found to be its reference's markers under
        other labels (:meth:`~jointfit_core.segment_tracker.SegmentTracker.relabelling`: each
        within half the template's smallest marker spacing of a different marker's predicted
        place, or the permutation that passes the shape test unturned) has its rows of :attr:`Y`
        moved to those labels. Returns the new missing-marker mask (2, Pmax) and the segments
        relabelled; each tracker counts the frame (:attr:`~jointfit_core.segment_tracker.SegmentTracker.relabelled_frames`).
        The frame is then judged again as it now stands, and held out as usual if it still fails.

        ``allowed``: per segment, whether its labels may be put right: markers, not the virtual
        markers of a pose stream (a regular tetrahedron, which a turn of one of its symmetries
        maps onto itself: "putting right" a pose that glitched would make up a rotation).
        """
        out: NDArray[np.bool_] | None = None
        fixed: list[int] = []
        for k, y, labels in verdict.follow:
            vs = ps.parent if k == 0 else ps.child
            if vs is None or not allowed[k] or np.array_equal(labels, vs.index):
                continue
            seg = self.tracker(k)
            if out is None:
                out = missing.copy()
            self.Y[k, : seg.n_markers] = 0.0
            self.Y[k, labels] = y
            out[k, : seg.n_markers] = True
            out[k, labels] = False
            seg.relabelled_frames += 1
            fixed.append(k)
        return None if out is None else (out, fixed)

    def hold_out(
        self, missing: NDArray[np.bool_], ps: PairSet, verdict: GateVerdict, frame_no: int
    ) -> tuple[NDArray[np.bool_], list[tuple[int, int | None]]]:
        """The missing-marker mask after the gate, and per failing segment how many markers it lost.

        A failing segment keeps the subset of its markers that
        :meth:`~jointfit_core.segment_tracker.SegmentTracker.leave_out` finds; without one it loses
        all its markers (not posed). Returns the new mask (2, Pmax) and ``(segment, markers left
        out, or None for all)`` per failing segment; each such segment counts a gated frame.
        """
        out = missing.copy()
        held: list[tuple[int, int | None]] = []
        for k, vs in enumerate((ps.parent, ps.child)):
            seg = self.tracker(k)
            if not verdict.failed[k] or vs is None or seg.template is None:
                continue
            drop = seg.leave_out(self.Y[k, vs.index], vs, verdict.active[k], frame_no)
            seg.gated_frames += 1
            if drop is None:
                out[k, : seg.n_markers] = True
                held.append((k, None))
            else:
                out[k, vs.index[list(drop)]] = True
                held.append((k, len(drop)))
        return out, held

    def after_refit(self, ps: PairSet, verdict: GateVerdict, frame_no: int, refit: tuple[bool, bool]) -> None:
        """After the refit of a frame that failed: references follow a swap, the failed shapes are kept provisionally.

        A segment held out whose markers are its reference's relabelled (a swap): its turn
        reference follows the limb through the swap (unless the refit set it in this frame).
        """
        for k, y, lab in verdict.follow:
            if self.tracker(k).ref_frame != frame_no:
                self.tracker(k).follow(y, lab, frame_no)
        for k, vs in enumerate((ps.parent, ps.child)):
            lk = verdict.local[k]
            if verdict.failed[k] and vs is not None and lk is not None:
                self.tracker(k).shape.failed(vs.index, lk, frame_no, vs.code)  # provisional reference
        if not (refit[0] or refit[1]):
            self.seen(ps, verdict.local, frame_no)
