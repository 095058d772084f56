"""Feasibility prototype of issue 16's vectorised skeleton core: CPU per frame of the usual frame, stage by stage.

Run with ``python bench/vector_core.py`` (repository root, ``PYTHONPATH=.:test``; ``--quick`` for a
shorter run). Prints Markdown and writes ``bench/results/vector_core.md``. A measurement, not a
design: nothing here is used by the node, and ``jointfit_core``/``jointfit_ros`` are unchanged.

What is prototyped
------------------
:class:`VectorSkeleton` does, per frame, what the node's per-message path does for the *usual*
frame (every posed segment passes the outlier gate, every joint passes the joint test), with the
state of all segments and joints stacked in arrays, so that the number of numpy calls per frame
does not grow with the joints:

(a) **fill**: the (K, 4, 3) marker buffer of all K posed units from the parsed (56, 3) frame with one
    fancy index; the absurd-marker extent test; each unit's missing-marker pattern (a 4-bit code);
(b) **pose**: every unit's least-squares pose at once (Horn's quaternion method, LAPACK ``eigh``
    gufunc batched over K, as :func:`~jointfit_core.segment_pair.poses` does per joint), the
    template-side fields gathered from a (K, 16, .) table of the trackers' visible sets;
(c) **gate**: the per-unit residual test and jump test of
    :meth:`~jointfit_core.segment_tracker.SegmentTracker.shape_test` (the jump against the stacked
    shape references, aligned first where they come from another marker set, as
    :func:`~jointfit_core.gate.frame_jumps`), the turn test, and on a pass the references' update;
    the gate's limits refreshed every ``GATE_REFRESH_FRAMES`` frames from each unit's own pooled
    residual (:meth:`~jointfit_core.segment_tracker.SegmentTracker.pooled_level`, updated on a pass;
    since 2026-12-03 a segment's, not its joint's window's, so the shared mode decides as the
    current path does). A unit
    that would fail (or turn) is *flagged* for a slow path that is not implemented (counted);
(d) **joint**: all J relative poses ``[Q | t]`` in one matmul and the joint test's scores
    (:class:`~jointfit_core.joint_gate.JointTrack`), its references' update;
(e) **sums**: every joint's contribution vector (the layout of
    :class:`~jointfit_core.joint_sums.RelativePoseSums`: Z, Z Z^T, pose-noise terms, lag-1 pair,
    skin feature sums and moments, pairs at lags in seconds, movement) and the sliding window's
    add/subtract and shadow rebuild (:class:`~jointfit_core.stats.SlidingSums`) in stacked rings.
    The pairs at lags in seconds come from one shared search over the frames' times; a joint whose
    paired frame did not enter its statistics takes the per-joint search (counted). The skin
    markers' white-noise sums (``_WN``, issue 17, added after this prototype) are not prototyped:
    left zero and left out of the check;
(f) **output**: every joint's world output (position, cov, direction, cov_direction, residual,
    relative rotation and its cov; :class:`~jointfit_core.joint_world.WorldOutput`) from per-joint,
    per-visible-set tables rebuilt when an estimate is installed; the publish checks;
(g) **encode**: the J ``PoseWithCovarianceStamped`` CDR messages in one (J, bytes) buffer
    (the bytes of :func:`~jointfit_ros.conversions.pose_with_covariance_bytes` /
    :func:`~jointfit_ros.conversions.axis_pose_bytes`), then ``~/segments`` (a PoseArray of the
    segment poses, :func:`~jointfit_ros.raw.pose_array_bytes`).

Units: ``shared`` mode poses each of the S body segments once (issue 16's design: 14 segments for
12 joints), its tracker state taken from the first joint that has the segment; ``exact`` mode
poses each joint's own copy of its two segments (K = 2 J units, the current path's templates and
references), so that its numbers can be compared with the current path's.

What is measured
----------------
The stream and joints of ``bench/skeleton.py`` (full skeleton, 56 markers, 0.5 mm noise, 2 %
occluded, 100 Hz, PoseArray CDR bytes; joints: the first 1, 2, 6, 12 of ``config/full_body.yaml``).
Each joint count gets a current ``_Path`` of ``bench/skeleton.py``, warmed up on ``WARM`` frames and
solved, and a :class:`VectorSkeleton` built from it (templates, visible sets, gate and joint-test
references, windows, lag histories, solutions copied). One continuous stream; each round has two
chunks of frames. The first: the parse baseline (:meth:`MarkerParser.frame <jointfit_ros.marker_parser.MarkerParser.frame>`), then per joint count
the current path (``_Path.run``, its whole per-message path incl. ``~/segments``) and the
prototype (parse + (a)-(g), timed as one). The second, the frames that follow: the baseline and
the current paths again, and the prototypes with ``process_time`` around each stage (the stages'
split; the clock calls add ~1 us per stage). The calls per stage are counted on the 12-joint
prototype over the last ``CALL_FRAMES`` frames. Every ``SOLVE_EVERY`` frames one joint's estimate is installed in turn from the
current path (solves run in the node's worker process; the prototype's per-estimate table rebuild
is inside the timed span). CPU time is ``time.process_time``; the table gives median rounds.

Correctness (``check``): the 12-joint prototype in exact mode against the current path on the
same stream: per frame every joint's two segment poses, every output (position, cov, direction,
cov_direction, residual, rotation, rotation_cov) and its encoded bytes; every ``SOLVE_EVERY``
frames and at the end, every joint's window sums vector. Differences are reported relative to
the largest magnitude of the compared quantity.
"""

from __future__ import annotations

import argparse
import datetime as dt
import math
import struct
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine, markdown_table, save_results
from skeleton import SOLVE_EVERY, T0, WARM, _commit, _Path  # type: ignore[attr-defined]

from jointfit_core.artefact_sums import N_FEATURE_SUMS
from jointfit_core.gate import GATE_HISTORY_FRAMES, GATE_JUMP_GAP_CAP, GATE_JUMP_LOW, GATE_JUMP_MADS, _aligned
from jointfit_core.hinge_from_sums import PoseSumsAxis
from jointfit_core.joint_gate import JointResidual
from jointfit_core.joint_outliers import GATE_SIGMA_FLOOR
from jointfit_core.joint_sums import (
    _FM,
    _FS,
    _LAG,
    _MOVE,
    _MOVE_AT,
    _MOVE_GAP_MAX,
    _MOVE_TRACE_MIN,
    _SS,
    _TL,
    _W,
    _ZZ,
)
from jointfit_core.joint_sums import _WN as _WHITE
from jointfit_core.pose import skew
from jointfit_core.quaternion_fit import HORN_A, HORN_B
from jointfit_core.segment_pair import _eigh
from jointfit_core.segment_tracker import (
    _LEVEL_DECAY,
    COS_MAX_TURN,
    GATE_REFRESH_FRAMES,
    GATE_RELOCK_FRAMES,
    GATE_TURN_GAP_FRAMES,
    SegmentTracker,
)
from jointfit_core.serial import LAG_TOLERANCE, SERIAL_LAGS_S
from jointfit_core.skeleton_truth import make_skeleton, skeleton_frames
from jointfit_core.tf_tree import quaternions_from_matrices
from jointfit_ros.conversions import UNKNOWN_ROTATION_VARIANCE, axis_pose_bytes, pose_with_covariance_bytes
from jointfit_ros.inputs import MessageRouter
from jointfit_ros.params import node_config
from jointfit_ros.raw import _cdr_header, pose_array_bytes
from jointfit_ros.runner import ABSURD_RADII
from jointfit_ros.skeleton_params import skeleton_parameters

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results" / "vector_core.md"
RATE = 100.0
COUNTS = (1, 2, 6, 12)
CALL_FRAMES = 200  # frames of the calls count
TARGET_US = 150.0  # issue 16's target for the 12-joint full body (us per frame)
STAGES = ("parse", "(a) fill", "(b) pose", "(c) gate", "(d) joint", "(e) sums", "(f) output", "(g) encode")
P = 4  # markers per segment (every segment of the fake skeleton)
PATTERNS = 1 << P
_BITS = np.left_shift(1, np.arange(P))
_LAGS = np.asarray(SERIAL_LAGS_S)
N_LAGS = len(SERIAL_LAGS_S)
L_MAX = _FM.stop  # the longest sums vector (skin hinge: 1074); ball joints' rows are zero past theirs
HISTORY = 4096  # frames of the shared lag history buffer (compacted when full)
KEEP = 1024  # frames kept at a compaction (> the longest lag's reach, 3.84 s at 100 Hz)
# the table of visible sets, per unit and pattern: xc_t (12), wn (4), n, xbar (3), xx, dof, W (36), posed
_XC, _WN, _N, _XBAR, _XX, _DOF, _WU, _POSED = slice(0, 12), slice(12, 16), 16, slice(17, 20), 20, 21, slice(22, 58), 58
_TABLE_WIDTH = 59
#: The check's value-wise relative differences: of values above this share of the largest of their quantity.
VALUE_FLOOR = 1e-15


# the axis messages' rotation covariance: J's entries from the quaternion (x, y, z, w) (see encode)
_PQ_I, _PQ_J = np.array([0, 2, 0, 2, 1, 0, 1, 0, 1]), np.array([1, 3, 0, 2, 2, 3, 1, 2, 3])
_PRE_A, _PRE_B = np.array([0, 2, 4, 6, 0, 7]), np.array([1, 3, 5, 3, 1, 8])
_PRE_SIGN = np.array([-1.0, 1.0, 1.0, 1.0, 1.0, -1.0])
_J_OFF = np.array([0.0, -1.0, 0.0, 1.0, 0.0, 0.0])
_J_MUL = np.array([-2.0, 2.0, -2.0, -2.0, 2.0, 2.0])
_QD = np.array([7, 2, 3])  # Q21, Q02, Q10 of vec(Q)
_QU = np.array([5, 6, 1])  # Q12, Q20, Q01
_SQ_I, _SQ_J = np.array([0, 1, 2, 0, 0, 1]), np.array([0, 1, 2, 1, 2, 2])  # q^2, q0 q1, q0 q2, q1 q2
_PAIR_I, _PAIR_J = np.triu_indices(9)
_FEAT = _FS.start  # f (9), then Q f (81), t f (27), Q^T t f (27): one outer product of (Q, t, Q^T t) with f
_FF = _FS.start + N_FEATURE_SUMS - 1
_FM0 = _FM.start  # skin hinges: f_a f_b (45), then f_a f_b Q (405)


def _feature_sums_into(z: FloatArray, c: FloatArray, ball: BoolArray) -> None:
    """:func:`~jointfit_core.artefact_sums.feature_sums` (with moments) of ``z`` (m, 3, 4) written into ``c`` (m, L_MAX).

    The same features and products in fewer numpy calls; ``ball`` (m,) rows get no moments (zeros).
    """
    m = z.shape[0]
    V = np.empty((m, 15))  # vec(Q), t, Q^T t
    V[:, :9] = z[:, :, :3].reshape(m, 9)
    V[:, 9:12] = z[:, :, 3]
    V[:, 12:] = (np.swapaxes(z[:, :, :3], 1, 2) @ z[:, :, 3:])[:, :, 0]
    Qf = V[:, :9]
    tr = np.clip((Qf[:, 0] + Qf[:, 4] + Qf[:, 8] - 1.0) * 0.5, -1.0, 1.0)
    theta = np.arccos(tr)
    sin = np.sin(theta)
    ratio = np.where(sin > 1e-9, theta / np.maximum(sin, 1e-9), 1.0)
    f = c[:, _FEAT : _FEAT + 9]
    np.multiply(0.5 * (Qf[:, _QD] - Qf[:, _QU]), ratio[:, None], out=f[:, :3])
    np.multiply(f[:, _SQ_I], f[:, _SQ_J], out=f[:, 3:])
    np.multiply(V[:, :, None], f[:, None, :], out=c[:, _FEAT + 9 : _FF].reshape(m, 15, 9))
    c[:, _FF] = (f * f).sum(axis=1)
    ff = c[:, _FM0 : _FM0 + 45]
    np.multiply(f[:, _PAIR_I], f[:, _PAIR_J], out=ff)
    np.multiply(ff[:, :, None], Qf[:, None, :], out=c[:, _FM0 + 45 : _FM0 + 450].reshape(m, 45, 9))
    if ball.any():
        c[ball, _FM0:] = 0.0


class VectorSkeleton:
    """The prototype: every unit's and joint's per-frame state in stacked arrays (see the module docstring).

    Parameters
    ----------
    path : _Path
        A warmed-up, solved current path of ``bench/skeleton.py``; its state is copied.
    shared : bool
        One unit per body segment (True) or one per joint and side (False, comparable with ``path``).
    """

    def __init__(self, path: Any, shared: bool) -> None:
        self.path = path
        self.router = MessageRouter(path.router.cfg, [])
        runners = path.runners
        self.J = len(runners)
        self.est = [r.estimator for r in runners]
        units: list[tuple[int, int]] = []  # (joint, side) whose tracker a unit copies
        index: dict[tuple[int, ...], int] = {}
        jp, jc = [], []
        rows: list[NDArray[np.intp]] = []
        for j, r in enumerate(runners):
            for side, rr in ((0, r.parent_rows), (1, r.child_rows)):
                key = tuple(int(x) for x in rr) if shared else (j, side)
                if key not in index:
                    index[key] = len(units)
                    units.append((j, side))
                    rows.append(np.asarray(rr, dtype=np.intp))
                (jp if side == 0 else jc).append(index[key])
        self.K = len(units)
        self.units = units
        self.jp, self.jc = np.array(jp), np.array(jc)
        self.rows = np.stack(rows)  # (K, P)
        self.kidx = np.arange(self.K)
        self.jidx = np.arange(self.J)
        self.trackers: list[SegmentTracker] = [self._tracker(j, s) for j, s in units]
        self._init_units()
        self._init_joints()
        self.frame_no = self.est[0]._clock.arrivals
        self.gate_block = -1
        self.flags = {"gate_slow": 0, "joint_slow": 0, "absurd_slow": 0, "aligned": 0, "jump_last": 0}
        self.last: dict[str, Any] = {}

    # ------------------------------------------------------------------ state copied from the current path

    def _tracker(self, j: int, side: int) -> SegmentTracker:
        pose = self.est[j]._pose
        assert pose is not None
        return pose.parent if side == 0 else pose.child

    def _init_units(self) -> None:
        K = self.K
        table = np.zeros((K, PATTERNS, _TABLE_WIDTH))
        for k, tr in enumerate(self.trackers):
            for code in range(PATTERNS):
                vis = (code & _BITS) > 0
                vs = tr.visible_set(vis) if vis.sum() >= 3 else None
                row = table[k, code]
                row[_N] = 1.0
                if vs is None:
                    continue
                row[_XC] = vs.xc.T.ravel()
                row[_WN] = np.where(vis, 1.0 / vs.n, 0.0)
                row[_N], row[_XBAR], row[_XX], row[_DOF] = vs.n, vs.xbar, vs.xx, vs.dof
                row[_WU] = vs.W_unit.ravel()
                row[_POSED] = 1.0
        self.table = table
        shapes = [tr.shape for tr in self.trackers]
        self.ref = np.stack([s.ref for s in shapes]).copy()
        self.at = np.stack([s.at for s in shapes]).copy()
        self.code_ref = np.stack([s.code for s in shapes]).copy()
        self.last_local = np.stack([s.last for s in shapes]).copy()
        self.last_at = np.stack([s.last_at for s in shapes]).copy()
        self.last_code = np.stack([s.last_code for s in shapes]).copy()
        self.hist = np.zeros((K, GATE_HISTORY_FRAMES))
        self.hist_n = np.zeros(K, dtype=np.int64)
        self.hist_pos = np.zeros(K, dtype=np.int64)
        for k, s in enumerate(shapes):
            h = list(s.history)
            self.hist[k, : len(h)] = h
            self.hist_n[k] = len(h)
            self.hist_pos[k] = len(h) % GATE_HISTORY_FRAMES
        self.ref_R = np.stack([tr.ref_R for tr in self.trackers]).copy()
        self.ref_ok = np.array([tr.ref_ok for tr in self.trackers])
        self.ref_frame = np.array([tr.ref_frame for tr in self.trackers], dtype=np.int64)
        self.held = np.array([tr.held for tr in self.trackers], dtype=np.int64)
        self.res_limit = np.array([tr.residual_limit for tr in self.trackers])
        self.jump_limit = np.array([tr.jump_limits[0] for tr in self.trackers])
        self.jump_low = np.array([tr.jump_limits[1] for tr in self.trackers])
        self.scale = np.array([ABSURD_RADII * self.est[j].length_scale for j, _ in self.units])[:, None]
        self.owner = np.array([j for j, _ in self.units])
        self.side = np.array([side for _, side in self.units])
        self.unit_floor = np.array([GATE_SIGMA_FLOOR * tr.rms_radius for tr in self.trackers])
        self.template_sigma = np.array([tr.template_sigma for tr in self.trackers])
        # each unit's pooled residual (SegmentTracker.add_level): decayed sums and the frame they were decayed to
        self.lvl_ss = np.array([tr._level_ss for tr in self.trackers])
        self.lvl_dof = np.array([tr._level_dof for tr in self.trackers])
        self.lvl_at = np.array([tr._level_at for tr in self.trackers], dtype=np.int64)
        self.unit_gate = np.array([self.est[j].gate for j, _ in self.units])
        self.unit_sigma = np.array([self.est[j]._sigma[side] for j, side in self.units])

    def _init_joints(self) -> None:
        J = self.J
        self.n_sums = np.array([e._stats.n_sums for e in self.est])
        windows = [e._stats.window for e in self.est]
        assert all(w is not None and w.spec.frames is not None for w in windows), "frame windows only"
        self.frames_max = np.array([w.spec.frames for w in windows])  # type: ignore[union-attr]
        cap = max(w._rec.shape[0] for w in windows)  # type: ignore[union-attr]
        self.cap = cap
        self.rec = np.zeros((J, cap, L_MAX))
        self.sums = np.zeros((J, L_MAX))
        self.shadow = np.zeros((J, L_MAX))
        self.lo = np.zeros(J, dtype=np.int64)
        self.hi = np.zeros(J, dtype=np.int64)
        self.sh_next = np.zeros(J, dtype=np.int64)
        self.sh_end = np.zeros(J, dtype=np.int64)
        for j, w in enumerate(windows):
            assert w is not None and w._rec.shape[0] == cap and w._shadow_active
            n = self.n_sums[j]
            self.rec[j, :, :n] = w._rec
            self.sums[j, :n] = w.sums
            self.shadow[j, :n] = w._shadow
            self.lo[j], self.hi[j], self.sh_next[j], self.sh_end[j] = w._lo, w._hi, w._shadow_next, w._shadow_end
        self.chained = np.array([e._stats.chained for e in self.est])
        self.z_prev = np.stack([e._stats._z_prev for e in self.est]).copy()
        self.hinge = np.array([e.kind == "hinge" for e in self.est])
        assert all(e._skin for e in self.est), "skin joints only (the stream's)"
        # the lag history: shared frame times, per joint whether the frame entered and its Z
        self.T = np.zeros(HISTORY)
        self.E = np.zeros((J, HISTORY), dtype=bool)
        self.ZH = np.zeros((J, HISTORY, 12))
        self.nT = 0
        self.last_time = np.full(J, np.nan)
        times = sorted({t for e in self.est for t in e._stats._history._t[: e._stats._history._n].tolist()})
        pos = {t: i for i, t in enumerate(times)}
        self.T[: len(times)] = times
        self.nT = len(times)
        for j, e in enumerate(self.est):
            h = e._stats._history
            for t, z in zip(h._t[: h._n].tolist(), h._z[: h._n], strict=True):
                self.E[j, pos[t]] = True
                self.ZH[j, pos[t]] = z
            self.last_time[j] = h._t[h._n - 1] if h._n else np.nan
        self._index_history()
        self.c_buf = np.zeros((J, L_MAX))
        self.c_buf[:, 0] = 1.0
        self.ball_rows = ~self.hinge
        self.hinge_rows = np.flatnonzero(self.hinge)
        self.msg_floats = np.zeros((J, 43))  # one PoseWithCovariance per joint: position, xyzw, 6 x 6 cov
        self.msg_floats[:, 6] = 1.0
        self.msg_floats[:, 7:].reshape(J, 6, 6)[:, [3, 4, 5], [3, 4, 5]] = UNKNOWN_ROTATION_VARIANCE
        self.seg_floats = np.zeros((self.K, 7))
        # the joint test
        tracks = [e._joint for e in self.est]
        self.jz_ref = np.stack([t.z_ref for t in tracks]).copy()
        self.jref_frame = np.stack([t.ref_frame for t in tracks]).copy()
        self.je_ref = np.zeros((J, 2, 6))
        self.jscores = np.zeros((J, GATE_HISTORY_FRAMES))
        self.jscores_n = np.zeros(J, dtype=np.int64)
        self.jscores_pos = np.zeros(J, dtype=np.int64)
        for j, t in enumerate(tracks):
            s = list(t.scores)
            self.jscores[j, : len(s)] = s
            self.jscores_n[j] = len(s)
            self.jscores_pos[j] = len(s) % GATE_HISTORY_FRAMES
        # solutions: the joint test's residual and the output tables (install)
        self.has_res = np.zeros(J, dtype=bool)
        self.jlimit = np.full(J, np.inf)
        self.res_a = np.zeros((J, 3))
        self.res_b = np.zeros((J, 3))
        self.res_u = np.zeros((J, 3))
        self.res_v = np.zeros((J, 3))
        self.res_len = np.zeros(J)
        self.res_bv = np.zeros((J, 3, 2))
        self.has_sol = np.zeros(J, dtype=bool)
        self.publish = np.zeros(J, dtype=bool)
        self.o_local = np.zeros((J, 3))
        self.o_other = np.zeros((J, 3))
        self.o_dir_p = np.zeros((J, 3))
        self.o_dir_c = np.zeros((J, 3))
        self.o_cov = np.zeros((J, PATTERNS, 3, 3))
        self.o_cov_dir = np.zeros((J, PATTERNS, 3, 3))
        self.o_rot = np.zeros((J, PATTERNS, 3, 3))
        self.o_s2c = np.zeros(J)
        for j in range(J):
            self.install(j, copy_joint_test=True)

    def install(self, j: int, copy_joint_test: bool = False) -> None:
        """Take joint ``j``'s current estimate from the current path (what a solve's install does).

        The joint test is armed again (its residual, its references' residuals, its limit from the
        scores kept), the output tables of all 16 parent visible sets are rebuilt, and the gate's
        limits are refreshed at the next frame. ``copy_joint_test``: take the test's residuals and
        limit as they are (the prototype's construction).
        """
        e = self.est[j]
        sol = e.solution
        if hasattr(self, "unit_sigma"):
            self.unit_sigma[self.owner == j] = np.array(e._sigma)[self.side[self.owner == j]]
        length = e.length_scale
        if sol is None or not sol.identifiable or not (math.isfinite(length) and length > 0.0):
            self.has_res[j], self.jlimit[j] = False, np.inf
        else:
            res = JointResidual.of(sol, length)
            self.has_res[j] = True
            self.res_a[j], self.res_b[j], self.res_u[j], self.res_v[j] = res.a, res.b, res.u, res.v
            self.res_len[j] = res.length if res.kind == "hinge" else 0.0
            self.res_bv[j] = np.stack([res.b, res.v], axis=1)
            self.je_ref[j] = self._residuals(self.jz_ref[j], j)
            if copy_joint_test:
                self.jlimit[j] = e._joint.limit
            else:
                n = int(self.jscores_n[j])
                if n < 20 or e.gate <= 0.0:
                    self.jlimit[j] = np.inf
                else:
                    s = self.jscores[j, :n]
                    med = float(np.median(s))
                    spread = 1.4826 * float(np.median(np.abs(s - med)))
                    self.jlimit[j] = e.gate * (med + GATE_JUMP_MADS * spread)
        self.has_sol[j] = sol is not None
        self.publish[j] = sol is not None and (sol.identifiable or self.path.runners[j].cfg.publish_unidentified)
        if sol is None:
            return
        s2 = e._sigma[0] ** 2
        if isinstance(sol, PoseSumsAxis):
            local, local_cov, other = sol.point_parent, sol.cov_point_parent, sol.point_child
            self.o_dir_p[j], self.o_dir_c[j] = sol.direction_parent, sol.direction_child
        else:
            local, local_cov, other = sol.centre_parent, sol.cov_parent, sol.centre_child
        self.o_local[j], self.o_other[j] = local, other
        W = self.table[self.jp[j], :, _WU].reshape(PATTERNS, 6, 6)
        Jm = np.concatenate([-skew(local), np.eye(3)], axis=1)
        self.o_cov[j] = local_cov + s2 * (Jm @ W @ Jm.T)
        if isinstance(sol, PoseSumsAxis):
            Nx = skew(sol.direction_parent)
            self.o_cov_dir[j] = sol.cov_direction_parent + s2 * (Nx @ W[:, :3, :3] @ Nx.T)
        self.o_rot[j] = s2 * W[:, :3, :3]
        self.o_s2c[j] = e._sigma[1] ** 2

    def _residuals(self, z: FloatArray, j: Any) -> FloatArray:
        """Joint residuals (..., 6) of relative poses ``z`` (..., 3, 4) of joints ``j`` (ball: turn part zero)."""
        Q, t = z[..., :3], z[..., 3]
        Qbv = Q @ self.res_bv[j]
        carried = Qbv[..., 0] + t - self.res_a[j]
        u = self.res_u[j]
        out = np.empty((*z.shape[:-2], 6))
        out[..., 3:] = carried - (carried * u).sum(axis=-1)[..., None] * u
        out[..., :3] = self.res_len[j][..., None] * (Qbv[..., 1] - u)
        return out

    # ------------------------------------------------------------------ the per-frame stages

    def parse(self, raw: bytes) -> tuple[int, FloatArray]:
        """The message's stamp (ns) and (56, 3) frame, as the node parses it."""
        got = self.router.parser.frame(raw)
        assert got is not None
        return got[0], got[2]

    def fill(self, frame: FloatArray) -> None:
        """(a) every unit's markers, its missing pattern, the absurd-marker extent test."""
        Y = frame[self.rows]  # (K, P, 3)
        spread = np.fmax.reduce(Y, axis=1) - np.fmin.reduce(Y, axis=1)  # (quiet NaNs: no warnings)
        if not (spread <= self.scale).all():
            self.flags["absurd_slow"] += 1
        missing = np.isnan(Y[:, :, 0])
        code = (~missing) @ _BITS
        np.copyto(Y, 0.0, where=missing[:, :, None])
        self.Y, self.missing, self.code = Y, missing, code
        self.frame_no += 1

    def pose(self) -> None:
        """(b) every unit's pose: Horn's method, one batched ``eigh``."""
        K, Y = self.K, self.Y
        G = self.table[self.kidx, self.code]  # (K, 59)
        self.G = G
        xc_t = G[:, _XC].reshape(K, 3, P)
        ybar = (G[:, None, _WN] @ Y)[:, 0]
        S = xc_t @ Y
        N = (S.reshape(K, 9) @ HORN_A.T).reshape(K, 4, 4)
        lam, V = _eigh(N)
        q = V[:, :, 3]
        self.q = q
        R = ((q[:, :, None] * q[:, None, :]).reshape(K, 16) @ HORN_B.T).reshape(K, 3, 3)
        d = ybar - (R @ G[:, _XBAR, None])[:, :, 0]
        yy = (Y * Y).sum(axis=(1, 2)) - G[:, _N] * (ybar * ybar).sum(axis=1)
        self.ss = np.maximum(yy + G[:, _XX] - 2.0 * lam[:, 3], 0.0)
        self.R, self.d = R, d
        self.posed = G[:, _POSED] > 0.0

    def _refresh_limits(self) -> None:
        """The gate's limits of the units of the joints due (per ``GATE_REFRESH_FRAMES`` frames and after an estimate).

        ``GateLimits.var``: the residual level ``(gate s)^2`` from the window's pooled pose-fit
        residual, the jump limits from the recent jumps' median and MAD (all units at once; the due
        ones take them).
        """
        block = self.frame_no // GATE_REFRESH_FRAMES
        if block == self.gate_block:
            return
        self.gate_block = block
        due = np.ones(self.K, dtype=bool)
        ss, dof = self.lvl_ss, self.lvl_dof
        fallback = np.where(self.template_sigma > 0.0, self.template_sigma, self.unit_sigma)
        sigma = np.where(dof > 0.0, np.sqrt(np.maximum(ss, 0.0) / np.where(dof > 0.0, dof, 1.0)), fallback)
        s = np.maximum(sigma, self.unit_floor)
        if (self.hist_n == GATE_HISTORY_FRAMES).all():
            a = np.sqrt(self.hist)
            med = np.median(a, axis=1)
            spread = 1.4826 * np.median(np.abs(a - med[:, None]), axis=1)
            normal = np.maximum((med + GATE_JUMP_MADS * spread) ** 2, 6.0 * self.unit_floor**2)
        else:  # (a history not yet full: unit by unit)
            normal = np.empty(self.K)
            for k in range(self.K):
                n = int(self.hist_n[k])
                if n == 0:
                    normal[k] = 6.0 * max(s[k], self.unit_floor[k]) ** 2
                    continue
                a1 = np.sqrt(self.hist[k, :n])
                m1 = float(np.median(a1))
                sp = 1.4826 * float(np.median(np.abs(a1 - m1)))
                normal[k] = max((m1 + GATE_JUMP_MADS * sp) ** 2, 6.0 * self.unit_floor[k] ** 2)
        np.copyto(self.res_limit, (self.unit_gate * s) ** 2, where=due)
        np.copyto(self.jump_limit, self.unit_gate**2 * normal, where=due)
        np.copyto(self.jump_low, GATE_JUMP_LOW * normal, where=due)

    def _jumps(self, local: FloatArray, vis: BoolArray, ref: FloatArray, at: IntArray, rcode: IntArray) -> tuple[FloatArray, BoolArray]:
        """:func:`~jointfit_core.gate.frame_jumps` of this frame's units (aligned references only where needed)."""
        gap = self.frame_no - at
        fresh = vis & (at > 0) & (gap <= GATE_JUMP_GAP_CAP)
        other = (fresh & (rcode != self.code[:, None])).any(axis=1)
        if other.any():
            self.flags["aligned"] += int(other.sum())
            ref = ref.copy()
            ref[other] = _aligned(ref[other], local[other], fresh[other])
        diff = local - ref
        d2 = np.where(fresh, np.einsum("kpi,kpi->kp", diff, diff) / np.where(fresh, gap, 1), 0.0)
        jump = d2.max(axis=1)
        jump[fresh.sum(axis=1) < 3] = np.inf
        return jump, (vis & ~fresh).any(axis=1)

    def gate(self) -> None:
        """(c) the outlier gate's tests of every posed unit; on a pass, its references move on."""
        self._refresh_limits()
        R, posed = self.R, self.posed
        local = (self.Y - self.d[:, None, :]) @ R
        vis = ~self.missing & posed[:, None]
        jump, stale = self._jumps(local, vis, self.ref, self.at, self.code_ref)
        bad = (self.ss > self.res_limit * self.G[:, _DOF]) & (self.G[:, _DOF] > 0.0)
        inf = np.isinf(jump)
        fail = np.where(inf, bad, bad & (stale | (jump > self.jump_low)))
        check_last = ~fail & ~inf & (jump > self.jump_limit)
        if check_last.any():  # the jump from the previous frame seen decides (rare)
            self.flags["jump_last"] += int(check_last.sum())
            last = self._jumps(local, vis, self.last_local, self.last_at, self.last_code)[0]
            fail |= check_last & (last > self.jump_limit)
        active = self.ref_ok & (self.held < GATE_RELOCK_FRAMES) & (self.frame_no - self.ref_frame <= GATE_TURN_GAP_FRAMES)
        cos = (np.einsum("kij,kij->k", R, self.ref_R) - 1.0) / 2.0
        slow = posed & (fail | (active & (cos < COS_MAX_TURN)))
        self.slow_units = slow
        if slow.any():
            self.flags["gate_slow"] += int(slow.sum())
        ok = posed & ~slow
        # passed: turn and shape references, jump history; seen: the previous frame's markers
        np.copyto(self.ref_R, R, where=ok[:, None, None])
        self.ref_ok |= ok
        np.copyto(self.ref_frame, self.frame_no, where=ok)
        np.copyto(self.held, 0, where=ok)
        take = vis & ok[:, None]
        np.copyto(self.ref, local, where=take[:, :, None])
        np.copyto(self.at, self.frame_no, where=take)
        code = self.code[:, None]
        np.copyto(self.code_ref, code, where=take)
        np.copyto(self.last_local, local, where=vis[:, :, None])  # (vis: posed units' visible markers)
        np.copyto(self.last_at, self.frame_no, where=vis)
        np.copyto(self.last_code, code, where=vis)
        pool = np.flatnonzero(ok & (self.G[:, _DOF] > 0.0))  # SegmentTracker.add_level of the units that passed
        w = _LEVEL_DECAY ** (self.frame_no - self.lvl_at[pool]).astype(np.float64)
        self.lvl_ss[pool] = self.lvl_ss[pool] * w + self.ss[pool]
        self.lvl_dof[pool] = self.lvl_dof[pool] * w + self.G[pool, _DOF]
        self.lvl_at[pool] = self.frame_no
        keep = np.flatnonzero(ok & ~inf)
        self.hist[keep, self.hist_pos[keep]] = jump[keep]
        self.hist_pos[keep] = (self.hist_pos[keep] + 1) % GATE_HISTORY_FRAMES
        self.hist_n[keep] = np.minimum(self.hist_n[keep] + 1, GATE_HISTORY_FRAMES)

    def joint(self) -> None:
        """(d) all relative poses ``[Q | t]`` in one matmul; the joint test's scores and references."""
        R, d, jp, jc = self.R, self.d, self.jp, self.jc
        self.Rp, self.Rc, self.dp, self.dc = Rp, Rc, dp, dc = R[jp], R[jc], d[jp], d[jc]
        self.Rp_t = Rp_t = np.swapaxes(Rp, 1, 2)
        z = np.empty((self.J, 3, 4))
        np.matmul(Rp_t, Rc, out=z[:, :, :3])
        np.matmul(Rp_t, (dc - dp)[:, :, None], out=z[:, :, 3:])
        self.z = z
        both = self.posed[jp] & self.posed[jc]
        slow = self.slow_units[jp] | self.slow_units[jc]
        test = both & self.has_res & ~slow
        e = self._residuals(z, self.jidx)
        gap = self.frame_no - self.jref_frame  # (J, 2)
        ok = (self.jref_frame > 0) & (gap <= GATE_JUMP_GAP_CAP)
        de = e[:, None] - self.je_ref
        dist = np.sqrt((de * de).sum(axis=2))
        score = np.where(ok, dist / np.sqrt(np.maximum(gap - np.arange(2), 1)), np.inf).min(axis=1)
        fails = test & np.isfinite(score) & (score > self.jlimit)  # (no reference: passes)
        if fails.any():
            self.flags["joint_slow"] += int(fails.sum())
        passed = test & ~fails
        self.enter = both & ~slow & ~fails
        # pass_one of the joints tested
        if passed.all():
            self.jz_ref[:, 1], self.jref_frame[:, 1], self.je_ref[:, 1] = self.jz_ref[:, 0], self.jref_frame[:, 0], self.je_ref[:, 0]
            self.jz_ref[:, 0], self.jref_frame[:, 0], self.je_ref[:, 0] = z, self.frame_no, e
        else:
            self.jz_ref[passed, 1], self.jref_frame[passed, 1], self.je_ref[passed, 1] = (
                self.jz_ref[passed, 0], self.jref_frame[passed, 0], self.je_ref[passed, 0])  # fmt: skip
            self.jz_ref[passed, 0], self.jref_frame[passed, 0], self.je_ref[passed, 0] = z[passed], self.frame_no, e[passed]
        keep = np.flatnonzero(passed & np.isfinite(score))
        self.jscores[keep, self.jscores_pos[keep]] = score[keep]
        self.jscores_pos[keep] = (self.jscores_pos[keep] + 1) % GATE_HISTORY_FRAMES
        self.jscores_n[keep] = np.minimum(self.jscores_n[keep] + 1, GATE_HISTORY_FRAMES)

    def _lag_rows(self, time: float, je: Any) -> tuple[IntArray, BoolArray]:
        """Per entering joint and lag, the history row paired with this frame (the nearest frame it entered) and whether taken.

        :meth:`LagHistory.contributions <jointfit_core.serial.LagHistory.contributions>`'s pairing
        over each joint's own frames, vectorised: ``rank[j, i]`` counts the frames joint ``j``
        entered up to row ``i`` and ``rows_of[j, r]`` is the row of its ``r``-th, so the frames
        before and after a target are two gathers.
        """
        n = self.nT
        target = time - _LAGS  # (L,)
        le = np.searchsorted(self.T[:n], target, side="right") - 1  # the last row at or before each target
        r = np.where(le >= 0, self.rank[self.jidx[je][:, None], np.maximum(le, 0)], 0)  # (m, L) entered up to there
        tot = self.tot[je][:, None]
        a = np.maximum(r - 1, 0)
        b = np.minimum(a + 1, np.maximum(tot - 1, 0))
        rows_j = self.jidx[je][:, None]
        ra = self.rows_of[rows_j, a]
        rb = self.rows_of[rows_j, b]
        later = (a + 1 < tot) & (np.abs(self.T[rb] - target) < np.abs(self.T[ra] - target))
        rows = np.where(later, rb, ra)
        gap = time - self.T[rows]
        return rows, np.abs(gap - _LAGS) <= LAG_TOLERANCE * _LAGS

    def sums_update(self, time: float) -> None:
        """(e) every entering joint's contribution vector and its window's add, subtract and shadow rebuild."""
        enter = self.enter
        every = bool(enter.all())
        je: Any = slice(None) if every else np.flatnonzero(enter)
        if self.nT == HISTORY:
            self._compact_history()
        z = self.z[je]
        m = z.shape[0]
        zf = z.reshape(m, 12)
        c = self.c_buf[:m]
        c[:, 1:13] = zf
        np.multiply(zf[:, :, None], zf[:, None, :], out=c[:, _ZZ].reshape(m, 12, 12))
        G = self.G
        jp, jc = self.jp[je], self.jc[je]
        c[:, _W] = np.concatenate([G[jp, _WU], G[jc, _WU]], axis=1)
        c[:, _SS : _SS + 4] = np.stack([self.ss[jp], G[jp, _DOF], self.ss[jc], G[jc, _DOF]], axis=1)
        ch = self.chained[je]
        zp = self.z_prev[je]
        lag1 = c[:, _LAG : _LAG + 29]
        if ch.all():
            lag1[:, 0] = 1.0
            np.add(z, zp, out=lag1[:, 1:13].reshape(m, 3, 4))
            np.matmul(np.swapaxes(z, 1, 2), zp, out=lag1[:, 13:29].reshape(m, 4, 4))
        else:
            lag1[:, 0] = ch
            lag1[:, 1:13] = np.where(ch[:, None], (z + zp).reshape(m, 12), 0.0)
            lag1[:, 13:29] = np.where(ch[:, None], (np.swapaxes(z, 1, 2) @ zp).reshape(m, 16), 0.0)
        _feature_sums_into(z, c, self.ball_rows[je])
        # the pairs at lags in seconds
        rows, ok = self._lag_rows(time, je)
        has = self.tot[je] > 0
        tl = c[:, _TL]
        tl[:, 0] = has
        tl[:, 1] = np.where(has, time - self.last_time[je], 0.0)
        prev = self.ZH[self.jidx[je][:, None], rows].reshape(m, N_LAGS, 3, 4)
        blocks = tl[:, 2:].reshape(m, N_LAGS, 30)
        okh = ok & has[:, None]
        blocks[:, :, 0] = okh
        blocks[:, :, 1:13] = (prev + z[:, None]).reshape(m, N_LAGS, 12)
        blocks[:, :, 13:29] = (np.swapaxes(z, 1, 2)[:, None] @ prev).reshape(m, N_LAGS, 16)
        blocks[:, :, 29] = time - self.T[rows]
        if not okh.all():
            blocks[~okh] = 0.0
        c[:, _TL] = tl
        node = tl[:, _MOVE_AT : _MOVE_AT + 30]
        moved = (node[:, 0] > 0.0) & (node[:, 13] + node[:, 18] + node[:, 23] < _MOVE_TRACE_MIN)
        c[:, _MOVE] = np.where(moved, np.minimum(tl[:, 1], _MOVE_GAP_MAX), 0.0)
        self.c = c
        self._push(je, c, every)
        # the lag history and the lag-1 chain
        n = self.nT
        self.T[n] = time
        self.E[:, n] = enter
        self.ZH[je, n] = zf
        self.rank[:, n] = (self.rank[:, n - 1] if n else 0) + enter
        tot = self.tot[je]
        self.rows_of[self.jidx[je], tot] = n
        self.tot[je] = tot + 1
        self.nT = n + 1
        self.last_time[je] = time
        self.z_prev[je] = z
        self.chained = enter.copy()

    def _index_history(self) -> None:
        """``rank``, ``rows_of`` and ``tot`` of the lag history (at the start and after a compaction)."""
        n = self.nT
        self.rank = np.zeros((self.J, HISTORY), dtype=np.int64)
        self.rank[:, :n] = np.cumsum(self.E[:, :n], axis=1)
        self.rows_of = np.zeros((self.J, HISTORY), dtype=np.int64)
        self.tot = self.E[:, :n].sum(axis=1)
        for j in range(self.J):
            own = np.flatnonzero(self.E[j, :n])
            self.rows_of[j, : own.size] = own

    def _compact_history(self) -> None:
        keep = slice(self.nT - KEEP, self.nT)
        self.T[:KEEP] = self.T[keep].copy()
        self.E[:, :KEEP] = self.E[:, keep].copy()
        self.ZH[:, :KEEP] = self.ZH[:, keep].copy()
        self.nT = KEEP
        self._index_history()

    def _push(self, je: Any, c: FloatArray, every: bool) -> None:
        """``RingWindowSums._push_contrib`` (:mod:`jointfit_core.ring_sums`) of the joints ``je``, stacked."""
        cap = self.cap
        lo, hi = self.lo[je].copy(), self.hi[je].copy()  # (copies: je may be a slice, and lo, hi are updated below)
        leave = hi - lo >= self.frames_max[je]
        rows = self.jidx[je]
        sums = self.sums[je] if not every else self.sums
        shadow = self.shadow[je] if not every else self.shadow
        sums += c
        shadow += c
        new_lo = lo + leave
        nxt = np.maximum(self.sh_next[je], new_lo)
        if leave.any():
            old = self.rec[rows, lo % cap]
            np.subtract(sums, old, out=sums, where=leave[:, None])
            inside = leave & ((lo < self.sh_next[je]) | (lo >= self.sh_end[je]))
            np.subtract(shadow, old, out=shadow, where=inside[:, None])
        more = nxt < self.sh_end[je]
        np.add(shadow, self.rec[rows, nxt % cap], out=shadow, where=more[:, None])
        nxt = nxt + more
        self.rec[rows, hi % cap] = c
        self.lo[je], self.hi[je] = new_lo, hi + 1
        done = nxt >= self.sh_end[je]
        if done.any():  # the rebuilt sums replace the live ones; a new rebuild starts
            sums[done] = shadow[done]
            shadow[done] = 0.0
            nxt[done] = new_lo[done]
            self.sh_end[rows[done]] = hi[done] + 1
        if not every:
            self.sums[je], self.shadow[je] = sums, shadow
        self.sh_next[je] = nxt

    def outputs(self) -> None:
        """(f) every joint's world output of this frame, and which go out."""
        jp, jc = self.jp, self.jc
        Rp, Rc, dp, dc, Rp_t = self.Rp, self.Rc, self.dp, self.dc, self.Rp_t
        cp = self.code[jp]
        position = (Rp @ self.o_local[:, :, None])[:, :, 0] + dp
        cov = Rp @ self.o_cov[self.jidx, cp] @ Rp_t
        direction = (Rp @ self.o_dir_p[:, :, None])[:, :, 0]
        cov_dir = Rp @ self.o_cov_dir[self.jidx, cp] @ Rp_t
        diff = position - ((Rc @ self.o_other[:, :, None])[:, :, 0] + dc)
        axis_c = (Rc @ self.o_dir_c[:, :, None])[:, :, 0]
        diff = diff - axis_c * np.einsum("ji,ji->j", diff, axis_c)[:, None]
        posed_c = self.posed[jc]
        residual = np.where(posed_c, np.sqrt(np.einsum("ji,ji->j", diff, diff)), np.nan)
        Q = Rp_t @ Rc
        Wc = self.G[jc, _WU].reshape(self.J, 6, 6)[:, :3, :3]
        Q_cov = self.o_rot[self.jidx, cp] + self.o_s2c[:, None, None] * (Q @ Wc @ np.swapaxes(Q, 1, 2))
        sane = np.isfinite(position).all(axis=1) & np.isfinite(cov).all(axis=(1, 2)) & np.isfinite(cov_dir).all(axis=(1, 2))
        self.out_mask = self.posed[jp] & self.has_sol & self.publish & sane & ~(self.slow_units[jp] | self.slow_units[jc])
        self.out = (position, cov, direction, cov_dir, residual, Q, Q_cov)

    def encode(self, stamp_ns: int) -> list[bytes]:
        """(g) the joints' output messages in one (J, bytes) buffer, then ``~/segments`` (PoseArray of the units' poses)."""
        position, cov, direction, cov_dir, _, _, _ = self.out
        header = _cdr_header(stamp_ns, "world", "<")
        header += bytes((-(len(header) - 4)) % 8)
        F = self.msg_floats
        F[:, :3] = position
        c6 = F[:, 7:].reshape(self.J, 6, 6)
        c6[:, :3, :3] = cov
        h = self.hinge_rows
        if h.size:
            u = direction[h] / np.sqrt((direction[h] * direction[h]).sum(axis=1))[:, None]
            dx, dy, dz = u.T
            w = np.where(dz >= 0.0, 1.0 + dz, (dx * dx + dy * dy) / (1.0 - dz))
            q = np.stack([-dy, dx, np.zeros_like(dx), w], axis=1)
            q /= np.sqrt((q * q).sum(axis=1))[:, None]
            q /= np.sqrt((q * q).sum(axis=1))[:, None]
            # J = [-R[:, 1], R[:, 0]] of the quaternion's rotation R (conversions._axis_parts), as its entries
            # -2 (xy - zw), -(1 - 2 (xx + zz)), -2 (yz + xw); 1 - 2 (yy + zz), 2 (xy + zw), 2 (xz - yw)
            pq = q[:, _PQ_I] * q[:, _PQ_J]  # xy, zw, xx, zz, yz, xw, yy, xz, yw
            pre = pq[:, _PRE_A] + _PRE_SIGN * pq[:, _PRE_B]
            Jt = (_J_OFF + _J_MUL * pre).reshape(-1, 2, 3)  # J^T
            rot = Jt @ cov_dir[h] @ np.swapaxes(Jt, 1, 2)
            c6[h, 3:5, 3:5] = 0.5 * (rot + np.swapaxes(rot, 1, 2))
            F[h, 3:7] = q
        width = len(header) + 43 * 8
        buf = np.empty((self.J, width), dtype=np.uint8)
        buf[:, : len(header)] = np.frombuffer(header, dtype=np.uint8)
        buf[:, len(header) :] = F.view(np.uint8)
        blob = buf.tobytes()
        msgs = [blob[j * width : (j + 1) * width] for j in np.flatnonzero(self.out_mask).tolist()]
        # ~/segments: Horn's quaternion is the pose's (x, y, z, w after its scalar, w >= 0)
        S = self.seg_floats
        S[:, :3] = np.where(self.posed[:, None], self.d, np.nan)
        S[:, 3:] = self.q[:, [1, 2, 3, 0]] * np.where(self.q[:, :1] < 0.0, -1.0, 1.0)
        S[~self.posed, 3:] = 0.0
        head = _cdr_header(T0, "world", "<")
        head += bytes((-(len(head) - 4)) % 4)
        head += struct.pack("<I", self.K)
        head += bytes((-(len(head) - 4)) % 8)
        self.segments_bytes = bytes(head) + S.tobytes()
        return msgs

    def step(self, raw: bytes) -> list[bytes]:
        """One message through (a)-(g)."""
        stamp_ns, frame = self.parse(raw)
        self.fill(frame)
        self.pose()
        self.gate()
        self.joint()
        self.sums_update(stamp_ns * 1e-9)
        self.outputs()
        return self.encode(stamp_ns)

    def step_timed(self, raw: bytes, acc: FloatArray) -> list[bytes]:
        """:meth:`step` with ``process_time`` after each stage, added to ``acc`` (8,) in seconds."""
        c0 = time.process_time()
        stamp_ns, frame = self.parse(raw)
        c1 = time.process_time()
        self.fill(frame)
        c2 = time.process_time()
        self.pose()
        c3 = time.process_time()
        self.gate()
        c4 = time.process_time()
        self.joint()
        c5 = time.process_time()
        self.sums_update(stamp_ns * 1e-9)
        c6 = time.process_time()
        self.outputs()
        c7 = time.process_time()
        msgs = self.encode(stamp_ns)
        c8 = time.process_time()
        acc += np.diff([c0, c1, c2, c3, c4, c5, c6, c7, c8])
        return msgs

    def run(self, messages: Sequence[bytes], turn: list[int], acc: FloatArray | None = None) -> float:
        """CPU seconds of ``messages``; every ``SOLVE_EVERY`` an estimate installed from the current path (joint ``turn[0]`` in turn)."""
        total = 0.0
        for start in range(0, len(messages), SOLVE_EVERY):
            c0 = time.process_time()
            self.install(turn[0])
            for raw in messages[start : start + SOLVE_EVERY]:
                if acc is None:
                    self.step(raw)
                else:
                    self.step_timed(raw, acc)
            total += time.process_time() - c0
            turn[0] = (turn[0] + 1) % self.J
        return total


# --------------------------------------------------------------------------- correctness


def _stream(frames: int) -> list[bytes]:
    sk = make_skeleton("full", seed=0)
    t = np.arange(frames) / RATE
    data = skeleton_frames(sk, t, np.random.default_rng(0), 0.0005, 0.02)
    return [pose_array_bytes(T0 + round(tk * 1e9), "world", f) for tk, f in zip(t, data, strict=True)]


class _Diff:
    """Largest difference per quantity, relative to the largest magnitude of the reference's values."""

    def __init__(self) -> None:
        self.diff: dict[str, float] = {}
        self.scale: dict[str, float] = {}
        self.count: dict[str, int] = {}
        self.own: dict[str, float] = {}

    def add(self, name: str, ref: Any, new: Any) -> None:
        a, b = np.asarray(ref, dtype=np.float64), np.asarray(new, dtype=np.float64)
        both = np.isfinite(a) & np.isfinite(b)
        if not np.array_equal(np.isfinite(a), np.isfinite(b)):
            self.diff[name] = np.inf
        d = float(np.max(np.abs(a - b), where=both, initial=0.0))
        top = float(np.max(np.abs(a), where=both, initial=0.0))
        self.diff[name] = max(self.diff.get(name, 0.0), d)
        self.scale[name] = max(self.scale.get(name, 0.0), top)
        # each value's own relative difference (values above 1e-9 of the largest: exact zeros and rounding-level
        # entries, e.g. sums that cancel, have none)
        big = both & (np.abs(a) > VALUE_FLOOR * top)
        own = float(np.max(np.abs(a - b) / np.where(big, np.abs(a), 1.0), where=big, initial=0.0))
        self.own[name] = max(self.own.get(name, 0.0), own)
        self.count[name] = self.count.get(name, 0) + 1

    def table(self) -> str:
        """The differences as a Markdown table."""
        header = ["quantity", "comparisons", "largest difference", "largest value", "relative to it", "largest value-wise relative"]
        return markdown_table(header, self.rows(), "lrrrrr")

    def rows(self) -> list[list[str]]:
        return [[k, f"{self.count[k]}", f"{self.diff[k]:.2g}", f"{self.scale[k]:.3g}",
                 f"{self.diff[k] / self.scale[k] if self.scale[k] else 0.0:.2g}", f"{self.own[k]:.2g}"]
                for k in self.diff]  # fmt: skip


def check(frames: int, shared: bool = False) -> tuple[_Diff, dict[str, int], int, int]:
    """The 12-joint prototype (exact mode, or ``shared``: one unit per segment) against the current path on the same messages (see the module docstring)."""
    messages = _stream(WARM + frames)
    sk = make_skeleton("full", seed=0)
    cfg = node_config(skeleton_parameters(sk, sk.joints[:12]))
    path = _Path(cfg, messages[:WARM])
    vec = VectorSkeleton(path, shared=shared)
    diff = _Diff()
    names = [r.cfg.name for r in path.runners]
    bytes_same = bytes_total = 0
    for f, raw in enumerate(messages[WARM:]):
        routed = path.router.markers(raw)
        path.router.after_outputs()
        msgs = vec.step(raw)
        for j, e in enumerate(vec.est):
            fp = e.frame_poses
            if fp is not None:
                for side, k in ((0, vec.jp[j]), (1, vec.jc[j])):
                    if fp[2][side]:
                        diff.add("pose R", fp[0][side], vec.R[k])
                        diff.add("pose d", fp[1][side], vec.d[k])
        posed = vec.posed
        qs = np.zeros((vec.K, 4))
        qs[posed] = quaternions_from_matrices(vec.R[posed])
        ref_seg = pose_array_bytes(T0, "world", np.where(posed[:, None], vec.d, np.nan), orientations=qs)
        if ref_seg[: -56 * vec.K] != vec.segments_bytes[: -56 * vec.K]:
            raise RuntimeError(f"frame {f}: ~/segments headers differ")
        diff.add("~/segments floats", np.frombuffer(ref_seg[-56 * vec.K :], "<f8"),
                 np.frombuffer(vec.segments_bytes[-56 * vec.K :], "<f8"))  # fmt: skip
        got = {names[j]: i for i, j in enumerate(np.flatnonzero(vec.out_mask).tolist())}
        if sorted(got) != sorted(r.runner.cfg.name for r in routed):
            raise RuntimeError(f"frame {f}: outputs of {sorted(got)} against {sorted(r.runner.cfg.name for r in routed)}")
        position, cov, direction, cov_dir, residual, Q, Q_cov = vec.out
        for r in routed:
            j, o = names.index(r.runner.cfg.name), r.output
            diff.add("position", o.position, position[j])
            diff.add("cov", o.cov, cov[j])
            diff.add("residual", o.residual, residual[j])
            if o.rotation is not None:
                diff.add("rotation", o.rotation, Q[j])
                diff.add("rotation_cov", o.rotation_cov, Q_cov[j])
            if o.direction is None:
                ref = pose_with_covariance_bytes(r.stamp_ns, r.frame_id, o.position, o.cov)
            else:
                diff.add("direction", o.direction, direction[j])
                diff.add("cov_direction", o.cov_direction, cov_dir[j])
                ref = axis_pose_bytes(r.stamp_ns, r.frame_id, o.position, o.direction, o.cov, o.cov_direction)
            new = msgs[got[names[j]]]
            bytes_total += 1
            bytes_same += ref == new
            floats_ref = np.frombuffer(ref[-344:], dtype="<f8")
            floats_new = np.frombuffer(new[-344:], dtype="<f8")
            if ref[:-344] != new[:-344]:
                raise RuntimeError(f"frame {f}, {names[j]}: message headers differ")
            diff.add("message floats", floats_ref, floats_new)
        if (f + 1) % SOLVE_EVERY == 0 or f + 1 == frames:
            for j, e in enumerate(vec.est):
                sums = e.sums_vector()
                assert sums is not None
                # (the white-noise sums, _WN, came after the prototype (issue 17): not prototyped, left zero)
                keep = np.r_[: _WHITE.start, _WHITE.stop : sums.size]
                diff.add("window sums", sums[keep], vec.sums[j, keep])
                stats = e._stats
                diff.add("lag history Z", stats._history._z[stats._history._n - 1], vec.ZH[j, np.flatnonzero(vec.E[j, : vec.nT])[-1]])
            for k, tr in enumerate(vec.trackers):
                diff.add("gate limits", [tr.residual_limit, *tr.jump_limits], [vec.res_limit[k], vec.jump_limit[k], vec.jump_low[k]])
        if (f + 1) % SOLVE_EVERY == 0:
            path.runners[path.turn].estimate(force=True)
            vec.install(path.turn)
            path.turn = (path.turn + 1) % len(path.runners)
    for e in vec.est:
        if e.gated_frames != (0, 0) or e.joint_gated_frames:
            print(f"note: the current path gated frames: {e.gated_frames}, {e.joint_gated_frames}", file=sys.stderr)
    return diff, vec.flags, bytes_same, bytes_total


# --------------------------------------------------------------------------- timing

_STAGE_OF = {"parse": 0, "fill": 1, "pose": 2, "gate": 3, "joint": 4, "sums_update": 5, "outputs": 6, "encode": 7}


def calls_per_stage(vec: VectorSkeleton, messages: Sequence[bytes]) -> FloatArray:
    """Python and C function calls per frame in each stage (``sys.setprofile``; numpy operators such as ``a + b`` are not calls)."""
    counts = np.zeros(len(STAGES))
    stage = [0]

    def hook(frame: Any, event: str, arg: Any) -> None:
        if event == "call":
            back = frame.f_back
            if back is not None and back.f_code.co_name == "step" and frame.f_code.co_name in _STAGE_OF:
                stage[0] = _STAGE_OF[frame.f_code.co_name]
            counts[stage[0]] += 1
        elif event == "c_call":
            counts[stage[0]] += 1

    for raw in messages:
        sys.setprofile(hook)
        try:
            vec.step(raw)
        finally:
            sys.setprofile(None)
    out: FloatArray = counts / len(messages)
    return out



def call_costs(n: int = 20000) -> dict[str, float]:
    """CPU us of one numpy call of the prototype's kinds on its array sizes (J = 12, K = 14), this run."""
    a, b, out = np.ones(3), np.ones(3), np.empty(3)
    A, B = np.ones((14, 3, 3)), np.ones((14, 3, 3))
    C, D = np.ones((12, 1070)), np.ones((12, 1070))
    idx = np.arange(12)
    M = np.random.default_rng(0).normal(size=(14, 4, 4))
    N4 = M + np.swapaxes(M, 1, 2)  # (Horn's matrices are symmetric 4 x 4)
    cases = {
        "ufunc, 3 values, out=": lambda: np.add(a, b, out=out),
        "matmul (14, 3, 3)": lambda: A @ B,
        "einsum (14, 3, 3) -> (14,)": lambda: np.einsum("kij,kij->k", A, B),
        "fancy gather (12 of 14, 3, 3)": lambda: A[idx],
        "ufunc (12, 1070) in place": lambda: np.add(C, D, out=C),
        "eigh (14, 4, 4)": lambda: _eigh(N4),
    }
    costs = {}
    for name, fn in cases.items():
        c0 = time.process_time()
        for _ in range(n):
            fn()
        costs[name] = 1e6 * (time.process_time() - c0) / n
    return costs


def _baseline(router: MessageRouter, messages: Sequence[bytes]) -> float:
    c0 = time.process_time()
    for raw in messages:
        router.parser.frame(raw)
    return time.process_time() - c0


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="2 rounds of 500 frames, a 300-frame check")
    p.add_argument("--frames", type=int, default=1000, help="timed frames per round (default 1000)")
    p.add_argument("--rounds", type=int, default=3, help="rounds (default 3)")
    p.add_argument("--check-frames", type=int, default=3000,
                   help="frames of the correctness check (default 3000: the 30 s windows fill and slide)")  # fmt: skip
    p.add_argument("--out", type=Path, default=RESULTS)
    opts = p.parse_args(argv)
    per_round, rounds, check_frames = (500, 2, 300) if opts.quick else (opts.frames, opts.rounds, opts.check_frames)
    started = dt.datetime.now().astimezone()
    commit = _commit()
    host = machine()
    diff, flags_check, bytes_same, bytes_total = check(check_frames)
    diff_sh, flags_sh, same_sh, total_sh = check(check_frames, shared=True)
    # one continuous stream: per round a chunk timed whole and a chunk timed stage by stage (every path and
    # prototype sees every frame, in order), then the frames of the calls count
    messages = _stream(WARM + 2 * per_round * rounds + CALL_FRAMES)
    warm = messages[:WARM]
    sk = make_skeleton("full", seed=0)
    configs = {k: node_config(skeleton_parameters(sk, sk.joints[:k])) for k in COUNTS}
    paths = {k: _Path(cfg, warm) for k, cfg in configs.items()}
    vecs = {k: VectorSkeleton(paths[k], shared=True) for k in COUNTS}
    exact12 = VectorSkeleton(_Path(configs[12], warm), shared=False)
    router = MessageRouter(configs[1], [])
    turns = {k: [0] for k in COUNTS}
    turn_exact = [0]
    base: list[float] = []
    cur: dict[int, list[float]] = {k: [] for k in COUNTS}
    vec_cpu: dict[int, list[float]] = {k: [] for k in COUNTS}
    ex_cpu: list[float] = []
    stage: dict[int, list[FloatArray]] = {k: [] for k in COUNTS}
    for r in range(rounds):
        start = WARM + 2 * r * per_round
        whole, staged = messages[start : start + per_round], messages[start + per_round : start + 2 * per_round]
        base.append(_baseline(router, whole) / per_round)
        for k in COUNTS:
            cur[k].append(paths[k].run(whole) / per_round)
            vec_cpu[k].append(vecs[k].run(whole, turns[k]) / per_round)
        ex_cpu.append(exact12.run(whole, turn_exact) / per_round)
        base.append(_baseline(router, staged) / per_round)
        for k in COUNTS:
            cur[k].append(paths[k].run(staged) / per_round)
            acc = np.zeros(len(STAGES))
            vecs[k].run(staged, turns[k], acc)
            stage[k].append(acc / per_round)
        exact12.run(staged, turn_exact)
    flags = {k: dict(vecs[k].flags) for k in COUNTS}  # (before the calls count)
    calls = calls_per_stage(vecs[12], messages[-CALL_FRAMES:])
    costs = call_costs()
    small = [us for name, us in costs.items() if not name.startswith("eigh")]
    lo_cost, hi_cost = min(small), max(small)
    base_us = 1e6 * float(np.median(base))
    med_cur = {k: 1e6 * float(np.median(cur[k])) for k in COUNTS}
    med_vec = {k: 1e6 * float(np.median(vec_cpu[k])) for k in COUNTS}
    med_stage = {k: 1e6 * np.median(np.stack(stage[k]), axis=0) for k in COUNTS}
    header = ["joints", "units (K)", "current path (us)", "prototype (us)", "x faster", "prototype / baseline",
              *(f"{s} (us)" for s in STAGES), "sum of stages (us)"]  # fmt: skip
    rows = [
        [f"{k}", f"{vecs[k].K}", f"{med_cur[k]:.0f}", f"{med_vec[k]:.0f}", f"{med_cur[k] / med_vec[k]:.1f}",
         f"{med_vec[k] / base_us:.1f}", *(f"{x:.0f}" for x in med_stage[k]), f"{med_stage[k].sum():.0f}"]
        for k in COUNTS
    ]  # fmt: skip
    rows.append(["12: calls per frame", "", "", "", "", "", *(f"{x:.0f}" for x in calls), f"{calls.sum():.0f}"])
    slope, intercept = np.polyfit(np.array(COUNTS, dtype=float), [med_vec[k] for k in COUNTS], 1)
    ex_us = 1e6 * float(np.median(ex_cpu))
    total_frames = per_round * rounds * 2
    flag_text = "; ".join(f"{k} joints: " + ", ".join(f"{n} {v}" for n, v in flags[k].items()) for k in COUNTS)
    text = "\n".join([
        "# Feasibility of issue 16's vectorised core: CPU per frame, stage by stage (prototype)",
        "",
        f"Command: `python bench/vector_core.py{' ' + ' '.join(sys.argv[1:]) if sys.argv[1:] else ''}`; commit {commit}; "
        f"{started:%Y-%m-%d %H:%M %Z}.",
        f"Machine: {host}.",
        "",
        f"Stream: `bench/skeleton.py`'s (full skeleton, 56 markers, 0.5 mm noise, 2 % occluded, 100 Hz), {rounds} "
        f"round(s) of {per_round} frames after {WARM} warm-up frames; median round. Baseline (parse alone, "
        f"`MarkerParser.frame`, same run): **{base_us:.0f} us per frame**. Prototype: `bench/vector_core.py` "
        "`VectorSkeleton`, one unit per body segment (shared mode), timed whole on the first chunk of each "
        "round and stage by stage (process_time around each stage: ~1 us each) on the second; current path and "
        "baseline: median over both chunks of every round.",
        "",
        markdown_table(header, rows),
        "",
        f"Prototype slope over 1, 2, 6, 12 joints: {slope:.1f} us per joint, intercept {intercept:.0f} us. "
        f"12 joints with one unit per joint and side (exact mode, K = 24): {ex_us:.0f} us.",
        "",
        "CPU of one numpy call on this machine, this run (us): "
        + "; ".join(f"{name}: {us:.2f}" for name, us in costs.items()) + ".",
        "",
        f"Budget: issue 16's {TARGET_US:.0f} us for 12 joints, less the parse baseline ({base_us:.0f} us), leaves "
        f"{TARGET_US - base_us:.0f} us: {(TARGET_US - base_us) / hi_cost:.0f}-{(TARGET_US - base_us) / lo_cost:.0f} "
        f"numpy calls at {lo_cost:.1f}-{hi_cost:.1f} us each (the kinds above but eigh), against "
        f"{calls.sum() - calls[0]:.0f} calls per frame past the parse in the prototype (operators such as `a + b` "
        f"not counted). The prototype with 1 joint (2 segments) costs {med_vec[1]:.0f} us, "
        f"{100.0 * med_vec[1] / med_vec[12]:.0f} % of its 12-joint cost: the per-frame cost is the number of calls, "
        "not the joints.",
        "",
        f"Slow-path flags over the {total_frames} frames per joint count (not implemented; counted): {flag_text}. "
        "`gate_slow`: units that would fail the outlier gate or its turn test; `joint_slow`: joints failing the "
        "joint test; `absurd_slow`: frames whose extent test did not settle; `aligned`: units whose jump needed references aligned (vectorised, done); "
        "`jump_last`: units whose jump needed the previous frame's (vectorised, done).",
        "",
        f"## Correctness: exact mode against the current path, 12 joints, {check_frames} frames",
        "",
        "Largest absolute difference over all frames and joints, and relative to the largest magnitude of the "
        f"current path's values. Encoded messages: {bytes_same} of {bytes_total} byte-identical (headers all "
        f"identical; the float fields compared below). Flags during the check: {flags_check}.",
        "",
        diff.table(),
        "",
        f"## Correctness: shared mode (one unit per body segment, the issue's design) against the current path, 12 joints, {check_frames} frames",
        "",
        "The current path still holds one copy of a shared segment per joint; since 2026-12-03 the copies judge it "
        "against the segment's own level and decide alike (`test/test_shared_segment_gate.py`), so one unit per "
        f"segment must give the same. Encoded messages: {same_sh} of {total_sh} byte-identical. Flags during the "
        f"check: {flags_sh}.",
        "",
        diff_sh.table(),
        "",
    ])  # fmt: skip
    print(text)
    save_results(opts.out, text)
    print(f"wrote {opts.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
