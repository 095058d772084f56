"""The joint-consistency test: frames whose two segments broke the joint suddenly.

The outlier gate of :mod:`jointfit_core.gate` looks at one segment at a time,
at the shape of its markers. A corruption that moves a segment's markers
*rigidly* leaves its shape unchanged and passes it: a ghost on a 3-marker
cluster that moves one marker about the line through the other two (the
cluster turns about that line; a 3-marker cluster has no other shape than its
three distances), a rigid-body pose that glitches, a cluster that slips as a
whole. Each such frame still breaks the joint: a ball joint's centre, carried
by the two segments' poses, no longer coincides; a hinge's axis, carried by
both, no longer lines up. This test looks there, once the joint has an
identifiable estimate.

For a frame with both segments posed, the *joint residual* ``e`` in the parent
template frame is, with ``[Q | t]`` the child's pose relative to the parent's
(:func:`joint_residuals`):

* ball: ``e = Q c_c + t - c_p`` (3,): the child's centre carried into the
  parent frame minus the parent's;
* hinge: ``e = [L (Q a_c - a_p), P (Q p_c + t - p_p)]`` (6,) with ``P`` the
  projection across the axis ``a_p`` and ``L`` the templates' length scale
  (a turn of the axis in length units at the clusters).

Skin artefact and estimation error make ``e`` drift with the joint's motion,
smoothly; marker noise moves it by about the lever arm times the clusters'
rotation noise in every frame; a corruption changes it suddenly, by about the
lever arm times the corruption's turn, or its shift. The test therefore
scores the change of ``e`` from the joint's last passed frame,
``score = |e_k - e_ref| / sqrt(g)`` (input units; ``g`` frames apart, as the
segment gate lets a change grow over a gap; against the frame before the last
passed one, ``g - 1``: the frame skipped over does not widen the allowance;
not divided while the frames since the reference failed: they were held out
because the joint stepped, not drifted, and a step that stays must not pass
by the allowance growing, as a 30-frame rigid glitch did from its 18th frame;
then a frame back within :data:`JOINT_STEP_RMS` times the estimate's rms
residual of the reference passes). It is not divided by the turn
between the two frames: at mocap rates a ghost turns a cluster by far more
than the limb turns in one frame, and would be allowed what such a turn
allows. The joint's *normal score* is a robust high level (median plus
:data:`~jointfit_core.gate.GATE_JUMP_MADS` robust standard deviations) of
the scores of its last :data:`~jointfit_core.gate.GATE_HISTORY_FRAMES`
passed frames, fixed when an estimate is installed (and, while frozen, when
it has :data:`JOINT_GATE_MIN_SCORES` scores). A frame fails when its score
exceeds ``gate`` times the normal score: it enters no statistics and gives
no per-frame output (``joint_gated`` in the counters). Without a recent
reference (none yet, or more than :data:`~jointfit_core.gate.GATE_JUMP_GAP_CAP`
frames ago) the frame passes and becomes the reference; after
:data:`JOINT_GATE_RELOCK_FRAMES` failures in a row the new state is taken
(a new subject, a calibration from another session) and the test starts
afresh.

**A joint that broke for good.** When the failures last until the
references expire (more than :data:`~jointfit_core.gate.GATE_JUMP_GAP_CAP`
frames ago: the frame would pass unscored), each frame is compared with the
expired reference, ``|e_k - e_ref|`` (not divided by the gap: the frames
between failed, the joint stepped rather than drifted). Within the limit, or
:data:`JOINT_STEP_RMS` times the estimate's rms residual, the joint came back:
the frame passes. Above it, the frame is held out too, until
:data:`JOINT_BREAK_FRAMES` frames after the reference; a frame still off then
means the two segments' relative pose changed for good (a tracker that swapped
the two thighs' labels, a cluster moved on its bone): it passes as the new
reference and :attr:`JointTrack.broke` is set, as it is at a relock. The frames
before belong to another joint: the estimator forgets its window and estimate
(frozen: holds its outputs until the calibration is judged again). Before
(2026-12-06), the first frame past the expired references passed and became the
reference: with the left and right thigh clusters' labels swapped at 20 s, the
knees were published 300-360 mm off at mean e/k 13-580, the skin left knee with
status OK; and a skin thigh posed from 3 markers for 14 frames (55 mm of joint
residual) entered the window for its last frames.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .gate import GATE_HISTORY_FRAMES, GATE_JUMP_GAP_CAP, GATE_JUMP_MADS
from .hinge_from_sums import PoseSumsAxis
from .segments import PoseSumsCentre

__all__ = [
    "JOINT_BREAK_FRAMES",
    "JOINT_BREAK_S",
    "JOINT_GATE_MIN_SCORES",
    "JOINT_GATE_RELOCK_FRAMES",
    "JOINT_STEP_RMS",
    "JointResidual",
    "JointTrack",
    "joint_residuals",
]

FloatArray = NDArray[np.float64]

#: Joint test: passed frames' scores needed before it is armed.
JOINT_GATE_MIN_SCORES = 20
#: Joint test: failures in a row after which the new state is taken as the reference.
JOINT_GATE_RELOCK_FRAMES = 25
#: Joint test: frames after its last passed frame that a joint still off it is held out before it is taken to
#: have broken for good (a skin cluster posed from 3 markers for 14 frames stepped the hip's joint residual by
#: 55 mm, then came back).
JOINT_BREAK_FRAMES = 100
#: ... and more than this many seconds after its first failure, so that a faster stream is not called broken
#: sooner: at 1 kHz, a parent plate mis-tracked 80 mm for 0.3 s (held out at 100 Hz) was a joint broken for
#: good, its window restarted on the wrong state and the WARN kept. (Under JOINT_BREAK_FRAMES' 1 s at 100 Hz, so
#: that at 100 Hz and below the frame count decides, as before.)
JOINT_BREAK_S = 0.9
#: Joint test: while frames fail, a frame whose joint residual is within this many times the estimate's rms
#: residual of the last passed frame's has come back (a step within the joint's usual scatter is no break):
#: standing still, the normal frame-to-frame change (and so the limit) is tiny, and the real hip's 1.2 mm
#: shift at the end of its trial held 13 frames out against a 0.76 mm limit, where its rms residual is 9.5 mm.
JOINT_STEP_RMS = 3.0


@dataclass(frozen=True)
class JointResidual:
    """What :func:`joint_residuals` needs of an estimate (parent and child template frames, input units).

    ``kind`` "ball": ``a = c_p``, ``b = c_c``; "hinge": ``a = p_p``, ``b = p_c``, and the
    directions ``u = a_p``, ``v = a_c`` with the length scale ``length``.
    """

    kind: str
    a: FloatArray
    b: FloatArray
    u: FloatArray
    v: FloatArray
    length: float

    @classmethod
    def of(cls, solution: PoseSumsCentre | PoseSumsAxis, length: float) -> JointResidual:
        """The residual of ``solution`` with templates of length scale ``length`` (input units)."""
        if isinstance(solution, PoseSumsAxis):
            u = np.asarray(solution.direction_parent, dtype=np.float64)
            v = np.asarray(solution.direction_child, dtype=np.float64)
            return cls("hinge", np.asarray(solution.point_parent, float), np.asarray(solution.point_child, float),
                       u, v, float(length))
        zero = np.zeros(3)
        return cls("ball", np.asarray(solution.centre_parent, float), np.asarray(solution.centre_child, float),
                   zero, zero, float(length))


def joint_residuals(z: FloatArray, res: JointResidual) -> FloatArray:
    """Joint residuals of relative poses ``z`` (K, 3, 4) = ``[Q | t]``: (K, 3) ball, (K, 6) hinge (input units).

    See the module notes for the definitions.
    """
    Q, t = z[:, :, :3], z[:, :, 3]
    carried = Q @ res.b + t - res.a
    if res.kind == "ball":
        out: FloatArray = carried
        return out
    u = res.u
    across = carried - np.multiply.outer(carried @ u, u)  # (np.outer's products, without its Python wrapper)
    turn = res.length * (Q @ res.v - u)
    return np.concatenate([turn, across], axis=1)


class JointTrack:
    """The joint test's state: the two last passed frames, the recent scores and the armed limit.

    A frame is scored against the last passed frame and the one before it, and keeps the lower
    score: a corruption the test missed (it passed, and became the reference) then does not
    lock the clean frames after it out.

    Parameters
    ----------
    gate : float
        A frame fails when its score exceeds ``gate`` times the normal score (0: off).
    """

    def __init__(self, gate: float) -> None:
        self.gate = float(gate)
        self.scores: deque[float] = deque(maxlen=GATE_HISTORY_FRAMES)
        self.residual: JointResidual | None = None
        self.limit = np.inf  # score limit (input units); inf: not armed
        self.z_ref = np.zeros((2, 3, 4))  # the last passed frame's relative pose, and the one's before it
        self.ref_frame = np.zeros(2, dtype=np.int64)  # their frame numbers; 0: none
        self.e_ref = np.zeros((2, 3))  # their joint residuals under the current residual
        self.fails_in_row = 0
        self.step_floor = 0.0  # JOINT_STEP_RMS times the armed estimate's rms residual (input units)
        #: The joint broke for good at the last frame passed (a relock, or failures until the references
        #: expired and the frame still off them, see the module notes); the estimator clears it.
        self.broke = False
        self._failing_since = math.nan  # the time of the first of the failures in a row (check_one)

    @property
    def armed(self) -> bool:
        """Whether the test applies (an identifiable estimate and enough scores)."""
        return bool(np.isfinite(self.limit))

    def arm(self, solution: PoseSumsCentre | PoseSumsAxis | None, length: float) -> None:
        """Fix the residual of ``solution`` and the limit from the scores so far (unarmed without both)."""
        if solution is None or not solution.identifiable or not np.isfinite(length) or length <= 0.0:
            self.residual, self.limit = None, np.inf
            return
        self.residual = JointResidual.of(solution, length)
        self.e_ref = joint_residuals(self.z_ref, self.residual)
        self.limit = self._limit()
        rms = float(solution.rms)
        self.step_floor = JOINT_STEP_RMS * rms if np.isfinite(rms) else 0.0

    def _limit(self) -> float:
        """``gate`` times the normal score of the scores kept (inf with too few, or the gate off)."""
        if len(self.scores) < JOINT_GATE_MIN_SCORES or self.gate <= 0.0:
            return float(np.inf)
        s = np.fromiter(self.scores, dtype=np.float64)
        med = float(np.median(s))
        spread = 1.4826 * float(np.median(np.abs(s - med)))
        return self.gate * (med + GATE_JUMP_MADS * spread)

    def scores_of(self, z: FloatArray, numbers: NDArray[np.int64]) -> FloatArray:
        """Scores of frames ``z`` (K, 3, 4) numbered ``numbers`` (K,), as if each frame before passed.

        Each row against the two frames before it (rows 0 and 1 against the references);
        NaN where neither is within :data:`~jointfit_core.gate.GATE_JUMP_GAP_CAP` frames, or
        there is no residual.
        """
        k = z.shape[0]
        if self.residual is None or k == 0:
            return np.full(k, np.nan)
        # (K + 2, m): the older reference first (their residuals as kept, the same numbers as score_one's)
        e = np.concatenate([self.e_ref[::-1], joint_residuals(z, self.residual)])
        nn = np.concatenate([self.ref_frame[::-1], numbers])
        best = np.full(k, np.inf)
        for back in (1, 2):
            gap = nn[2:] - nn[2 - back : nn.size - back]
            ok = (gap <= GATE_JUMP_GAP_CAP) & (nn[2 - back : nn.size - back] > 0)
            # the allowance grows with the frames since the reference, not counting one skipped over
            jump = np.linalg.norm(e[2:] - e[2 - back : nn.size - back], axis=1) / np.sqrt(np.maximum(gap - back + 1, 1))
            best = np.where(ok, np.minimum(best, jump), best)
        out: FloatArray = np.where(np.isfinite(best), best, np.nan)
        return out

    def score_one(self, z: FloatArray, number: int) -> tuple[float, FloatArray | None]:
        """:meth:`scores_of` of one frame ``z`` (3, 4) (the per-frame path), and its residual (None without one)."""
        res = self.residual
        if res is None:
            return float("nan"), None
        e = joint_residuals(z[None], res)[0]
        best = float("inf")
        failing = self.fails_in_row > 0  # the frames since failed: the joint did not drift there, no gap allowance
        for back in (0, 1):
            at = int(self.ref_frame[back])
            gap = number - at
            if at > 0 and gap <= GATE_JUMP_GAP_CAP:
                d = e - self.e_ref[back]
                best = min(best, math.sqrt(float(d @ d)) / (1.0 if failing else math.sqrt(max(gap - back, 1))))
        if failing and best < float("inf") and self.armed:  # back within the joint's usual scatter: passes
            best *= self.limit / max(self.limit, self.step_floor)
        return (best if best < float("inf") else float("nan")), e

    def pass_one(self, z: FloatArray, number: int, score: float, e: FloatArray | None, frozen: bool) -> None:
        """:meth:`passed` of one frame ``z`` (3, 4), with its :meth:`score_one`."""
        if score == score:  # not NaN
            self.scores.append(score)
        self.z_ref[1], self.ref_frame[1], self.e_ref[1] = self.z_ref[0], self.ref_frame[0], self.e_ref[0]
        self.z_ref[0], self.ref_frame[0] = z, number
        if e is not None:
            self.e_ref[0] = e
        self.fails_in_row = 0
        if frozen and not self.armed and self.residual is not None:
            self.limit = self._limit()

    @property
    def latest(self) -> tuple[FloatArray, FloatArray]:
        """The last passed frame's relative pose ``[Q | t]`` (3, 4) and its joint residual under :attr:`residual`."""
        return self.z_ref[0], self.e_ref[0]

    def check_one(self, R: FloatArray, d: FloatArray, number: int, frozen: bool, time: float = math.nan) -> bool:
        """The test of one frame (the per-frame path): whether it passes (then it is kept as :meth:`pass_one` keeps it).

        Parameters
        ----------
        R, d : ndarray, shapes (2, 3, 3) and (2, 3)
            The frame's parent and child poses (template frame to world, input units).
        number : int
            Its frame number.
        frozen : bool
            Whether the joint is frozen (:meth:`pass_one`).
        time : float, optional
            Its time (s; the stamp): a joint still off is broken for good only :data:`JOINT_BREAK_S` after
            its first failure too (NaN: frames only).
        """
        z = np.empty((3, 4))  # the child's pose relative to the parent's, [Q | t]
        Rp_t = R[0].T
        np.matmul(Rp_t, R[1], out=z[:, :3])
        np.matmul(Rp_t, d[1] - d[0], out=z[:, 3])
        score, e = self.score_one(z, number)
        if score != score and self.fails_in_row and e is not None and self._still_off(e):
            # the references expired while it failed, and it is still off them: held out until it comes back, or
            # until it has stayed off for JOINT_BREAK_FRAMES frames and JOINT_BREAK_S seconds (then it broke for
            # good: the new state is taken)
            if number - int(self.ref_frame[0]) <= JOINT_BREAK_FRAMES or time - self._failing_since <= JOINT_BREAK_S:
                self.fails_in_row += 1
                return False
            self.broke = True
        elif self.fails(score):
            if self.fails_in_row == 1:
                self._failing_since = time
            return False
        if self.fails_in_row:  # back after failures: its score is no frame-to-frame change for the normal score
            score = float("nan")
        self.pass_one(z, number, score, e, frozen)
        return True

    def _still_off(self, e: FloatArray) -> bool:
        """Whether a frame's joint residual ``e`` is still off the last passed frame's by more than one frame may change.

        Not divided by the gap: the frames between failed, so the joint did not drift there, it stepped; a
        step that went back (a glitch) leaves only the drift of the gap, well within one frame's limit.
        """
        d = e - self.e_ref[0]
        step = math.sqrt(float(d @ d))
        return bool(self.armed and self.ref_frame[0] > 0 and step > max(self.limit, self.step_floor))

    def fails(self, score: float) -> bool:
        """Whether a frame of ``score`` (:meth:`scores_of`) fails (and counts the failures in a row)."""
        if not (self.armed and score > self.limit):  # NaN: no reference, passes
            return False
        self.fails_in_row += 1
        if self.fails_in_row > JOINT_GATE_RELOCK_FRAMES:
            self.fails_in_row = 0
            self.broke = True
            self.scores.clear()
            self.limit = np.inf  # re-armed by the next estimate (or, frozen, by enough scores)
            return False
        return True

    def passed(self, z: FloatArray, numbers: NDArray[np.int64], scores: FloatArray, frozen: bool) -> None:
        """Frames ``z`` (K, 3, 4) numbered ``numbers`` passed with ``scores`` (:meth:`scores_of`): keep them.

        The last two become the references. While ``frozen`` (no estimates to arm the test at),
        the test is armed as soon as there are enough scores.
        """
        k = z.shape[0]
        if k == 0:
            return
        self.scores.extend(scores[np.isfinite(scores)].tolist())
        if k == 1:
            self.z_ref[1], self.ref_frame[1] = self.z_ref[0], self.ref_frame[0]
            self.z_ref[0], self.ref_frame[0] = z[0], numbers[0]
        else:
            self.z_ref[:] = z[::-1][:2]
            self.ref_frame[:] = numbers[::-1][:2]
        if self.residual is not None:
            self.e_ref = joint_residuals(self.z_ref, self.residual)
        self.fails_in_row = 0
        if frozen and not self.armed and self.residual is not None:
            self.limit = self._limit()
