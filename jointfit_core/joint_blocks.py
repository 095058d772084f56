"""An online joint's block path: many frames at once, ending in the state of one frame at a time.

:func:`update_many` is :meth:`OnlineJoint.update_many
<jointfit_core.estimator.OnlineJoint.update_many>`: for offline fits of whole
recordings (``jointfit fit``, :mod:`jointfit_ros.bag_blocks`), where the
per-frame world outputs are not needed, it leaves the joint as
:meth:`~jointfit_core.estimator.OnlineJoint.update` of each frame in turn
would. On a frame's path it stands where ``update`` does: it checks the whole
block first (:func:`check_block`), numbers the frames and drops those whose
stamps do not increase, groups them by missing-marker pattern (the
:class:`~jointfit_core.segment_pair.SegmentPair`'s pair sets), poses them all at
once (:func:`~jointfit_core.segment_pair.poses_many`) and pushes their
contributions into the joint's window
(:meth:`~jointfit_core.joint_sums.RelativePoseSums.add_block`). With the
outlier gate on, the block is cut where the gate's limits are read again
(:data:`~jointfit_core.segment_tracker.GATE_REFRESH_FRAMES`), and the frames the
gate might fail (a superset) go one by one through the joint's own per-frame
step (``OnlineJoint._add``) between bulk pushes of the frames around them
(:func:`_gated_block`).

The functions take the joint and read and write its state (its
:class:`~jointfit_core.frame_clock.FrameClock`'s frame numbers and stamps,
counters, the sums' version); what the block and the frame paths share (the
clock, the gate's limits, :class:`~jointfit_core.joint_outliers.GateLimits`,
the per-frame step) stays the joint's.
"""

from __future__ import annotations

import heapq
import itertools
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .checks import as_real_array
from .errors import InputError
from .frame_queue import PosedBlock
from .gate import BlockJumps
from .pose import MIN_POSE_MARKERS
from .segment_pair import poses_many, relative_poses
from .segment_tracker import COS_MAX_TURN, GATE_REFRESH_FRAMES, GATE_TURN_GAP_FRAMES, cos_turn
from .serial import NOMINAL_RATE_HZ
from .stats import WindowSpec

if TYPE_CHECKING:
    from .estimator import OnlineJoint

__all__ = ["update_many", "check_block"]

FloatArray = NDArray[np.float64]

#: Batched turn tests flag a frame as a candidate this much above the threshold: the batched poses
#: (:func:`~jointfit_core.segment_pair.poses_many`) and the cosine differ from the per-frame ones by rounding.
_COS_MARGIN = 1e-9
#: Batched residual tests flag a frame as a candidate this fraction below the gate (rounding).
_SS_MARGIN = 1e-6


def update_many(joint: OnlineJoint, parent: ArrayLike, child: ArrayLike, stamps: ArrayLike | None = None) -> None:
    """Add a block of frames to ``joint``: the state of its ``update`` of each frame in turn, without the outputs.

    :meth:`OnlineJoint.update_many <jointfit_core.estimator.OnlineJoint.update_many>`
    (parameters and errors there); once the templates are fixed, the frames of
    the block are posed, turned into contributions and added to the window in a
    few vectorised steps instead of one Python call each.

    Parameters
    ----------
    joint : OnlineJoint
        The joint the frames are added to (changed in place).
    parent, child : array_like, shape (N, Pa, 3) and (N, Pc, 3)
        World marker positions of the two segments, frame after frame
        (input units), NaN for a missing marker.
    stamps : array_like, shape (N,), optional
        Seconds.

    Raises
    ------
    InputError
        The block is malformed (:func:`check_block`); nothing is added.

    Notes
    -----
    Equivalence with ``update`` of each frame: the templates, ``dropped``,
    ``n_frames_seen``, the window's stamps and frames, and the lag-pair state
    end up the same; the sums equal to rounding (~1e-13 relative: the poses
    come from a vectorised eigen-solve, see
    :func:`~jointfit_core.segment_pair.poses_many`).

    * Frames while the templates are being built (and the replay of the
      frames kept meanwhile) go through ``update`` itself.
    * Stamps: frame k is accepted when its stamp exceeds the running
      maximum of the earlier stamps (the last accepted stamp is that
      maximum, since a dropped stamp never exceeds it).
    * Visibility: frames are grouped by their missing-marker pattern;
      each pattern's cached pair set (the same cache as ``update``)
      says whether each segment can be posed (drops counted per frame).
    * Poses (:func:`~jointfit_core.segment_pair.poses_many`) and contributions are computed for the
      frames that enter the statistics with the per-frame operations on
      stacked arrays. The outlier gate's candidates (a superset of the
      frames it fails) go through the joint's per-frame step one by one
      (:func:`_gated_block`). A frame carries its lag pair when the accepted
      frame before it (the previous block's last one for the first) entered
      the statistics.
    * The window takes the block with
      :meth:`~jointfit_core.stats.SlidingSums.push_many`: the same frames
      leave the window as when pushed one by one.

    While frozen, frames are counted and dropped as ``update`` does
    and nothing enters the statistics.
    """
    try:
        _update_many(joint, parent, child, stamps)
    finally:
        joint.frame_poses = None  # a block gives no frame's poses


def _update_many(joint: OnlineJoint, parent: ArrayLike, child: ArrayLike, stamps: ArrayLike | None) -> None:
    """:func:`update_many`: the template frames one by one, the rest in parts cut where the gate's limits are read again."""
    yp, yc, st = check_block(parent, child, stamps, joint.n_markers, joint.spec)
    n = yp.shape[0]
    k = 0
    while k < n and not joint.templates_ready:
        joint.update(yp[k], yc[k], None if st is None else float(st[k]))
        k += 1
    # the gate's limits are refreshed every GATE_REFRESH_FRAMES frames (see GateLimits.var): blocks are cut there
    # so that each part is judged with the limits its frames one by one would meet
    cuts = [k]
    if joint.gate > 0.0:
        first = joint._clock.arrivals + 1  # the number of frame k
        cuts += range(k + ((-first) % GATE_REFRESH_FRAMES or GATE_REFRESH_FRAMES), n, GATE_REFRESH_FRAMES)
    cuts.append(n)
    for lo, hi in itertools.pairwise(cuts):
        if lo < hi:
            _update_block(joint, yp[lo:hi], yc[lo:hi], None if st is None else st[lo:hi])


def check_block(
    parent: ArrayLike, child: ArrayLike, stamps: ArrayLike | None, n_markers: tuple[int, int] | None, spec: WindowSpec
) -> tuple[FloatArray, FloatArray, FloatArray | None]:
    """The checks :meth:`~jointfit_core.estimator.OnlineJoint.update` makes per frame, on a whole block.

    Parameters
    ----------
    parent, child : array_like, shape (N, Pa, 3) and (N, Pc, 3)
        World marker positions (input units), NaN for a missing marker.
    stamps : array_like, shape (N,), optional
        Seconds.
    n_markers : (int, int) or None
        The joint's marker counts (None: not known yet, at least
        :data:`~jointfit_core.pose.MIN_POSE_MARKERS` each).
    spec : WindowSpec
        The joint's window (whether it needs stamps).

    Returns
    -------
    yp, yc : ndarray, shape (N, Pa, 3) and (N, Pc, 3)
        float64 copies or views of the markers.
    st : ndarray, shape (N,), or None
        The stamps (s).

    Raises
    ------
    InputError
        See :meth:`~jointfit_core.estimator.OnlineJoint.update_many`.
    """
    blocks = []
    for name, value, k in (("parent", parent, 0), ("child", child, 1)):
        arr = as_real_array(value, name=name, expected="shape (N, P, 3)")
        if arr.ndim != 3 or arr.shape[2] != 3:
            raise InputError(f"{name}: expected shape (N, P, 3), got shape {arr.shape}")
        if n_markers is not None and arr.shape[1] != n_markers[k]:
            raise InputError(f"{name}: expected {n_markers[k]} markers, got {arr.shape[1]}")
        if np.isinf(arr).any():
            raise InputError(f"{name}: contains inf; use NaN for missing markers")
        blocks.append(arr)
    yp, yc = blocks
    n = yp.shape[0]
    if yc.shape[0] != n:
        raise InputError(f"parent, child: expected the same number of frames, got {n} and {yc.shape[0]}")
    if n and n_markers is None and min(yp.shape[1], yc.shape[1]) < MIN_POSE_MARKERS:
        raise InputError(
            f"parent, child: expected at least {MIN_POSE_MARKERS} markers per segment, got "
            f"{yp.shape[1]} and {yc.shape[1]}"
        )
    st: FloatArray | None = None
    if stamps is not None:
        st = as_real_array(stamps, name="stamps", expected=f"shape ({n},)")
        if st.shape != (n,):
            raise InputError(f"stamps: expected shape ({n},), got shape {st.shape}")
        if not np.isfinite(st).all():
            raise InputError("stamp: expected finite numbers of seconds, got a non-finite stamp")
    elif n and spec.needs_stamps:
        raise InputError(f"stamp: the window ({spec.describe()}) needs a stamp with every frame")
    return yp, yc, st


def _update_block(joint: OnlineJoint, yp: FloatArray, yc: FloatArray, st: FloatArray | None) -> None:
    """:func:`update_many` once the templates are fixed: frames ``yp`` (M, Pa, 3), ``yc`` (M, Pc, 3) checked, stamps ``st`` (M,) s or None."""
    pose = joint._pose
    assert pose is not None and joint.n_markers is not None
    clock = joint._clock
    numbers = clock.arrivals + 1 + np.arange(yp.shape[0], dtype=np.int64)
    clock.arrivals += yp.shape[0]
    if st is not None:
        before = np.empty_like(st)
        before[0] = -np.inf if clock.last_stamp is None else clock.last_stamp
        np.maximum.accumulate(st[:-1], out=before[1:])
        np.maximum(before[1:], before[0], out=before[1:])
        accepted = st > before
        n_late = int(st.size - np.count_nonzero(accepted))
        if n_late:
            joint.dropped["stamp_not_increasing"] = joint.dropped.get("stamp_not_increasing", 0) + n_late
            yp, yc, st, numbers = yp[accepted], yc[accepted], st[accepted], numbers[accepted]
        if st.size:
            clock.last_stamp = float(st[-1])
    m = yp.shape[0]
    if m == 0:
        return
    joint.n_frames_seen += m
    pa, pc = joint.n_markers
    p_max = max(pa, pc)
    Y = np.zeros((m, 2, p_max, 3))
    Y[:, 0, :pa] = yp
    Y[:, 1, :pc] = yc
    # (m, 2, Pmax): a marker with any non-finite coordinate; padding rows are zeros: present
    missing = ~(np.isfinite(Y[..., 0]) & np.isfinite(Y[..., 1]) & np.isfinite(Y[..., 2]))
    Y[missing] = 0.0
    flat = missing.reshape(m, 2 * p_max)
    if 2 * p_max <= 63:
        codes = flat @ (np.int64(1) << np.arange(2 * p_max, dtype=np.int64))
        _, first, inverse = np.unique(codes, return_index=True, return_inverse=True)
    else:
        _, first, inverse = np.unique(flat, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(m)
    sets = [pose.pair(missing[i]) for i in first]
    parent_ok = np.array([ps.parent is not None for ps in sets])[inverse]
    child_ok = np.array([ps.child is not None for ps in sets])[inverse]
    slots = np.array([ps.slot for ps in sets])[inverse]  # each frame's pair set, as its row in SegmentPair.table
    for reason, ok in (("parent_not_posed", parent_ok), ("child_not_posed", child_ok)):
        bad = int(m - np.count_nonzero(ok))
        if bad:
            joint.dropped[reason] = joint.dropped.get(reason, 0) + bad
    gate_var = joint._limits.var(clock.arrivals, pose, joint)
    if gate_var is not None:
        _gated_block(joint, Y, missing, slots, parent_ok, child_ok, st, gate_var, numbers)
        return
    if joint.gate > 0.0:  # no level yet (fixed templates): frame by frame, the segments start their levels
        for f in range(m):
            pose.Y[...] = Y[f]
            counted = (not bool(parent_ok[f]), not bool(child_ok[f]))
            joint._add(missing[f], None if st is None else float(st[f]), int(numbers[f]), counted)
        return
    entered = parent_ok & child_ok
    if joint._frozen:
        entered[:] = False
    rows = np.flatnonzero(entered)
    if rows.size:
        # a lag pair when the accepted frame before entered the statistics
        before_in = np.empty(m, dtype=bool)
        before_in[0] = joint._stats.chained
        before_in[1:] = entered[:-1]
        _push_block(joint, Y[rows], slots[rows], before_in[rows], st, rows, numbers)
    joint._stats.chained = bool(entered[-1])


def _gated_block(
    joint: OnlineJoint,
    Y: FloatArray,
    missing: NDArray[np.bool_],
    slots: NDArray[np.intp],
    parent_ok: NDArray[np.bool_],
    child_ok: NDArray[np.bool_],
    st: FloatArray | None,
    gate_var: FloatArray,
    numbers: NDArray[np.int64],
) -> None:
    """:func:`_update_block` with the outlier gate: runs of passing frames in bulk, the others one by one.

    Every frame that ``update`` might gate goes through the joint's ``_add``
    (marker removal, refit, turn-test references), exactly as
    ``update`` would take it, between the bulk pushes of the frames
    before and after it. The candidates are a superset of the frames the
    gate fails, which is safe: a frame that passes enters the sums the
    same way (to rounding) either way.

    * Frames with one segment posed pass the gate in bulk too: they enter
      no sums, and a pass only moves that segment's turn reference (set
      after each run: per segment, its pose in the run's last frame that
      posed it). While frozen, every frame with a segment posed goes one
      by one.
    * Residual: the comparison of ``_add``, per posed segment, with a
      small margin: the batched poses equal the per-frame ones to
      rounding only.
    * Turn (:data:`~jointfit_core.segment_tracker.GATE_MAX_TURN_DEG`): per segment, against its pose in
      the previous frame that posed it, assuming that frame passed; with
      a small margin. After each frame taken one by one, each segment's
      next frame that poses it is tested again against the references as
      they then are.
    """
    pose = joint._pose
    assert pose is not None
    m = Y.shape[0]
    entered = parent_ok & child_ok
    if joint._frozen:
        posed_ok = np.zeros((0, 2), dtype=bool)
        rows = np.zeros(0, dtype=np.intp)
        sequential = parent_ok | child_ok
        entered = np.zeros(m, dtype=bool)
    else:
        rows = np.flatnonzero(parent_ok | child_ok)
        posed_ok = np.stack([parent_ok[rows], child_ok[rows]], axis=1)  # (K, 2)
        sequential = np.zeros(m, dtype=bool)
    R = np.zeros((rows.size, 2, 3, 3))
    d = np.zeros((rows.size, 2, 3))
    ss = np.zeros((rows.size, 2))
    # the posed segments, row after row: positions in ``rows`` and sides (0 parent, 1 child)
    posed = np.flatnonzero(posed_ok.ravel())
    at, side = np.divmod(posed, 2)
    # per segment: rows (positions in ``rows``) that pose it, oldest first
    seg_rows = [at[side == k] for k in range(2)]
    shapes: list[BlockJumps] = []  # per segment, the jumps of the rows that pose it
    seg_levels: list[tuple[FloatArray, FloatArray, NDArray[np.int64]]] = []
    if rows.size:
        fields = pose.table()
        seg = 2 * slots[rows][at] + side  # each posed segment's row in the fields, (slot, side) flattened
        Y_seg = Y.reshape(2 * m, *Y.shape[2:])[2 * rows[at] + side]
        Rs, ds, sss = poses_many(Y_seg, *pose.pose_fields(seg))
        R.reshape(-1, 3, 3)[posed] = Rs
        d.reshape(-1, 3)[posed] = ds
        ss.reshape(-1)[posed] = sss
        dof = fields[5].reshape(-1)[seg]
        # per segment, its rows' residuals, degrees of freedom and frame numbers (its pooled level)
        seg_levels = [(sss[side == k], dof[side == k], numbers[rows[seg_rows[k]]]) for k in range(2)]
        candidate = np.zeros(rows.size, dtype=bool)
        residual_bad = (sss > (1.0 - _SS_MARGIN) * gate_var[side] * dof) & (dof > 0.0)
        levels = np.divide(sss, dof, out=np.full(sss.shape, np.nan), where=dof > 0.0)  # per degree of freedom
        local = np.einsum("kpi,kij->kpj", Y_seg - ds[:, None, :], Rs)  # R^T (y - d) of every marker
        vis = fields[1].reshape(-1, Y.shape[2])[seg] > 0.0
        for k, segment in enumerate((pose.parent, pose.child)):
            sel, p = side == k, segment.n_markers
            bj = BlockJumps(
                segment.shape, local[sel, :p], vis[sel, :p], numbers[rows[seg_rows[k]]], residual_bad[sel],
                levels[sel], *segment.jump_limits,
            )
            candidate[seg_rows[k][bj.fails(_SS_MARGIN)]] = True
            shapes.append(bj)
        for k in range(2):
            pos = seg_rows[k]
            if not pos.size:
                continue
            Rk = Rs[side == k]
            close = np.diff(numbers[rows[pos]]) <= GATE_TURN_GAP_FRAMES
            candidate[pos[1:]] |= close & (cos_turn(Rk[1:], Rk[:-1]) < COS_MAX_TURN + _COS_MARGIN)
            candidate[pos[0]] |= pose.tracker(k).turns(Rk[0], int(numbers[rows[pos[0]]]), _COS_MARGIN)
        if joint._joint.armed:  # the joint test, each frame against the one before it (a superset)
            both = np.flatnonzero(posed_ok.all(axis=1))
            score = joint._joint.scores_of(relative_poses(R[both], d[both]), numbers[rows[both]])
            candidate[both[_joint_candidates(joint, score)]] = True
        sequential[rows[candidate]] = True
    queue = np.flatnonzero(sequential).tolist()  # a heap: frames to take one by one, oldest first
    queued = set(queue)
    start = 0
    while True:
        f = heapq.heappop(queue) if queue else m
        run = np.flatnonzero(entered[start:f]) + start
        if run.size:
            before_in = np.empty(run.size, dtype=bool)
            before_in[0] = joint._stats.chained if run[0] == start else False
            before_in[1:] = np.diff(run) == 1
            if run[0] > start:
                before_in[0] = bool(entered[run[0] - 1])
            pos = np.searchsorted(rows, run)  # the run's rows among the posed ones
            if joint._joint.residual is not None:
                z = relative_poses(R[pos], d[pos])
                joint._joint.passed(z, numbers[run], joint._joint.scores_of(z, numbers[run]), False)
            _push_block(joint, Y[run], slots[run], before_in, st, run, numbers, (R[pos], d[pos], ss[pos]))
        if start < f:
            joint._stats.chained = bool(entered[f - 1])
            lo, hi = np.searchsorted(rows, (start, f))
            for k in range(2):
                seg = seg_rows[k]
                i = int(np.searchsorted(seg, hi)) - 1  # the run's last row that poses segment k
                if i >= 0 and seg[i] >= lo:
                    pose.tracker(k).set_reference(R[seg[i], k], d[seg[i], k], int(numbers[rows[seg[i]]]))
                if shapes:
                    a = int(np.searchsorted(seg, lo))
                    shapes[k].passed(a, i + 1)
                    ss_k, dof_k, num_k = seg_levels[k]
                    pose.tracker(k).add_levels(ss_k[a : i + 1], dof_k[a : i + 1], num_k[a : i + 1])
        if f == m:
            break
        pose.Y[...] = Y[f]
        counted = (not bool(parent_ok[f]), not bool(child_ok[f]))
        relabels = joint.relabelled_frames
        joint._add(missing[f], None if st is None else float(st[f]), int(numbers[f]), counted)
        relabelled = [a != b for a, b in zip(relabels, joint.relabelled_frames, strict=True)]  # frame f's labels put right
        after = int(np.searchsorted(rows, f, side="right"))
        for k in range(2):
            seg = seg_rows[k]
            i = int(np.searchsorted(seg, after))  # the next row that poses segment k
            if i < seg.size:
                g = int(rows[seg[i]])
                if g not in queued and pose.tracker(k).turns(R[seg[i], k], int(numbers[g]), _COS_MARGIN):
                    heapq.heappush(queue, g)
                    queued.add(g)
            if shapes and i > 0 and seg[i - 1] == after - 1:  # frame f posed segment k
                for j in shapes[k].recheck(i - 1, _SS_MARGIN, relabelled[k]).tolist():
                    g = int(rows[seg[j]])
                    if g not in queued:
                        heapq.heappush(queue, g)
                        queued.add(g)
        if joint._joint.armed:  # the next two frames with both segments posed, against the joint's references now
            nxt = f + 1 + np.flatnonzero(entered[f + 1 :])[:2]
            if nxt.size:
                at_rows = np.searchsorted(rows, nxt)
                score = joint._joint.scores_of(relative_poses(R[at_rows], d[at_rows]), numbers[nxt])
                for g in nxt[_joint_candidates(joint, score)].tolist():
                    if g not in queued:
                        heapq.heappush(queue, g)
                        queued.add(g)
        start = f + 1


def _joint_candidates(joint: OnlineJoint, score: FloatArray) -> NDArray[np.bool_]:
    """Frames the joint test might fail, or find the joint broken at, by their :meth:`JointTrack.scores_of`.

    Over the limit (with a margin); every frame while the test is failing frames (it scores them
    without the gap's allowance, and against an expired reference: ``JointTrack.broke``).
    """
    track = joint._joint
    out: NDArray[np.bool_] = score > (1.0 - _SS_MARGIN) * track.limit
    if track.fails_in_row:  # scored without the gap's allowance, or against the expired reference, one by one
        out[:] = True
    return out


def _push_block(
    joint: OnlineJoint,
    Y: FloatArray,
    which: NDArray[np.intp],
    paired: NDArray[np.bool_],
    st: FloatArray | None,
    rows: NDArray[np.intp],
    numbers: NDArray[np.int64],
    poses: tuple[FloatArray, FloatArray, FloatArray] | None = None,
) -> None:
    """Pose the frames that enter the statistics (``Y`` (M, 2, Pmax, 3), pair sets of slots ``which``) and push them.

    ``rows``: their indices in the block; ``numbers``: the block's frame numbers (the times of
    frames without stamps). ``poses``: their ``(R, d, ss)`` from :func:`~jointfit_core.segment_pair.poses_many` when already computed.
    """
    pose = joint._pose
    assert pose is not None
    m = Y.shape[0]
    if poses is None:
        seg = (2 * which[:, None] + np.arange(2)).ravel()
        R, d, ss = poses_many(Y.reshape(2 * m, *Y.shape[2:]), *pose.pose_fields(seg))
        poses = (R.reshape(m, 2, 3, 3), d.reshape(m, 2, 3), ss.reshape(m, 2))
    R, d, ss = poses
    stamps = None if st is None else st[rows]
    times = stamps if stamps is not None else numbers[rows] / NOMINAL_RATE_HZ
    table = pose.table()
    joint._stats.add_block(
        PosedBlock(R, d, ss, table[6], table[5], which, paired, stamps, np.asarray(times, dtype=np.float64), Y, table[1])
    )
    joint._version += 1
