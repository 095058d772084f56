"""One segment's tracker: its template, its visibility caches and its outlier gate's memory.

A joint between two moving segments (:class:`~jointfit_core.estimator.OnlineJoint`)
holds one :class:`SegmentTracker` per segment. The tracker owns what belongs
to the segment alone:

* the **template** (its markers in its local frame), built from the first
  fully visible, mutually consistent frames (:meth:`SegmentTracker.add_template_frame`);
* the **visibility caches**: per set of visible markers, the template-side
  quantities of the pose fit and its unit-noise covariance
  (:meth:`SegmentTracker.visible_set`, Stoddart et al. eq. 4);
* the **outlier gate's memory and per-segment tests**: the shape references
  and recent jumps (:class:`~jointfit_core.gate.ShapeTrack`), the turn
  reference (its last pose that passed), the residual and jump limits set
  by its joint (:meth:`SegmentTracker.set_limits`), the turn test, the
  relabelling of a swap and the leave-out refits.

The joint decides, per frame, which of its segments to test and what to do
with the result (its statistics, counters and outputs).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .gate import GATE_JUMP_LOW, ShapeTrack, consistent_frames, gate_fails, marker_code
from .pose import COLLINEAR_RTOL, MIN_POSE_MARKERS, kabsch, pose_covariance_local
from .segments import POSE_VAR_RATIO_MAX

__all__ = [
    "GATE_LEVEL_HALF_LIFE",
    "GATE_MAX_TURN_DEG",
    "GATE_REFRESH_FRAMES",
    "GATE_RELOCK_FRAMES",
    "GATE_TURN_GAP_FRAMES",
    "TEMPLATE_DEV_FACTOR",
    "SegmentTracker",
    "VisibleSet",
    "cos_turn",
    "kabsch",
    "shape_ok",
]

FloatArray = NDArray[np.float64]

#: Frames offered for a template before a marker missing from most of them is named (:meth:`SegmentTracker.rarely_seen`).
RARELY_SEEN_MIN_FRAMES = 100
#: Share of those frames a marker is missing from to be named.
RARELY_SEEN_SHARE = 0.9

#: Template building: a candidate frame is discarded when its inter-marker distances changed from the
#: frame before by more than this many times the usual (90th percentile) change, and did not come
#: back (:func:`~jointfit_core.gate.consistent_frames`).
TEMPLATE_DEV_FACTOR = 5.0

#: Outlier gate: the largest turn (deg) of a segment between the last frame in the statistics and
#: the current one. A label swap in a nearly symmetric cluster (two markers about equidistant from
#: the others) fits within the noise turned over by ~180 deg; so does a symmetric subset left after
#: a swap. 30 deg per frame is 3000 deg/s at 100 Hz: far beyond any limb.
GATE_MAX_TURN_DEG = 30.0

#: Outlier gate: the turn test applies while its reference is at most this many frames old (frames
#: that arrived, including those dropped for their stamp): after a longer gap (occlusion) the
#: segment may really have turned, and the test starts afresh.
GATE_TURN_GAP_FRAMES = 10

#: Outlier gate: after this many frames in a row held out by the turn test, the test starts afresh
#: (the reference itself may be the wrong one). Swaps that last longer get into the statistics.
GATE_RELOCK_FRAMES = 500

#: Outlier gate: its limits (residual level and normal jump of each segment, :meth:`SegmentTracker.set_limits`)
#: are read again every this many frames (counted as they arrive, whether or not anything is solved): a skin
#: cluster's deformation grows and shrinks with the joint angles, and limits frozen at the template frames'
#: noise would hold a deforming cluster's markers out for good.
GATE_REFRESH_FRAMES = 50

#: Outlier gate: the half-life (frames, counted as they arrive) of each segment's own pooled pose-fit
#: residual, the level its residual test holds (:meth:`SegmentTracker.pooled_level`). The segment's,
#: not its joint's window: two joints that share a segment (the hip's and the knee's thigh) then judge
#: its markers against the same level and gate them alike, whatever frames each joint's statistics
#: took. 2000 frames: 200 new frames weigh 7 % of the level, as in a full 3000-frame window (30 s at 100 Hz).
GATE_LEVEL_HALF_LIFE = 2000

#: Per-frame decay of :meth:`SegmentTracker.pooled_level`'s sums.
_LEVEL_DECAY = 0.5 ** (1.0 / GATE_LEVEL_HALF_LIFE)

#: ``cos(GATE_MAX_TURN_DEG)``: a turn test fails below it.
COS_MAX_TURN = float(np.cos(np.deg2rad(GATE_MAX_TURN_DEG)))


def cos_turn(R: FloatArray, Q: FloatArray) -> FloatArray:
    """Cosine of the angle between rotations ``R`` and ``Q`` (..., 3, 3): ``(tr(R Q^T) - 1) / 2``, shape (...)."""
    return (np.einsum("...ij,...ij->...", R, Q) - 1.0) / 2.0


def shape_ok(points: FloatArray) -> bool:
    """At least 3 points, not collinear (second singular value above COLLINEAR_RTOL of the first)."""
    pts = points - points.mean(axis=0)
    lam = np.linalg.eigvalsh(pts.T @ pts)
    return bool(points.shape[0] >= MIN_POSE_MARKERS and lam[2] > 0 and lam[1] > COLLINEAR_RTOL**2 * lam[2])


@dataclass(frozen=True, eq=False)
class VisibleSet:
    """Template-side quantities of one set of visible markers (cached per visibility pattern)."""

    index: NDArray[np.intp]  # visible markers
    n: float
    xbar: FloatArray  # (3,) centroid of the visible template points
    xc: FloatArray  # (P, 3) centred visible template points, zero rows where not visible
    xx: float  # sum |xc|^2
    W_unit: FloatArray  # (6, 6) local pose covariance at unit noise
    dof: float  # 3 n - 6
    code: int = 0  # the visible markers as a bit mask (the outlier gate's shape references)


class SegmentTracker:
    """Template, visibility caches and outlier-gate memory of one segment.

    Parameters
    ----------
    name : str
        The segment's name in counters (``"parent"``, ``"child"``).
    n_markers : int
    template_frames : int
        Fully visible frames averaged into the template.
    """

    def __init__(self, name: str, n_markers: int, template_frames: int) -> None:
        self.name = name
        self.n_markers = n_markers
        self.template_frames = template_frames
        self.template: FloatArray | None = None
        self.template_sigma = 0.0  # marker noise seen in the template frames (input units)
        self._frames: list[FloatArray] = []  # centred, fully visible candidate frames
        self._seen = 0
        self._offered = 0  # frames offered for the template, and in how many of them each marker was missing
        self._missing = np.zeros(n_markers, dtype=np.int64)
        self._cache: dict[bytes, VisibleSet | None] = {}
        self._full_rot = 0.0
        self.rms_radius = 0.0  # of the template (input units; 0 until it exists)
        self.min_spacing = 0.0  # least distance between two template points (input units)
        self.shape = ShapeTrack(n_markers)  # the outlier gate's shape references and recent jumps
        self.gated_frames = 0  # frames in which the segment failed the outlier gate
        #: Frames in which the gate found the segment's labels swapped and put them right
        #: (:meth:`~jointfit_core.segment_pair.SegmentPair.relabel`).
        self.relabelled_frames = 0
        # The gate's turn test: the reference pose (the last pose that passed the gate, carried along
        # through the frames held out since), whether there is one, the number of the frame that set it
        # (frames are numbered as they arrive) and the frames held out in a row since.
        self.ref_R = np.zeros((3, 3))
        self.ref_d = np.zeros(3)
        self.ref_ok = False
        self.ref_frame = 0
        self.held = 0
        #: The residual test's limit, mean squared residual per degree of freedom (input units squared).
        self.residual_limit = np.inf
        #: The jump test's limit, ``gate^2`` times the normal jump (input units squared).
        self.jump_limit = np.inf
        self._jump_low = np.inf
        self._gate2 = np.inf  # gate^2 (set_limits)
        # pooled_level: the decayed sums of squared pose-fit residuals and of degrees of freedom of the
        # frames that posed the segment, and the number of the frame they were last decayed to
        self._level_ss = 0.0
        self._level_dof = 0.0
        self._level_at = 0

    # ------------------------------------------------------------------ template and visibility

    @property
    def template_progress(self) -> int:
        """Fully visible frames collected for the template (``template_frames`` once it is built)."""
        return self.template_frames if self.template is not None else len(self._frames)

    def rarely_seen(self) -> list[int]:
        """Markers (rows) missing from at least :data:`RARELY_SEEN_SHARE` of the frames offered for the template.

        Empty once the template is built, or before :data:`RARELY_SEEN_MIN_FRAMES` frames were offered. A
        template needs frames with every marker visible: such a marker holds it (and the joint) back.
        """
        if self.template is not None or self._offered < RARELY_SEEN_MIN_FRAMES:
            return []
        return np.flatnonzero(self._missing >= RARELY_SEEN_SHARE * self._offered).tolist()

    def add_template_frame(self, y: FloatArray) -> None:
        """Use a fully visible frame ``y`` (P, 3) for the template (consistent frames aligned and averaged).

        Once ``template_frames`` candidates are collected, frames whose
        inter-marker distances (rigid invariants) change suddenly, by more
        than :data:`TEMPLATE_DEV_FACTOR` times the usual (90th percentile)
        change from one candidate to the next, and do not come back
        (:func:`~jointfit_core.gate.consistent_frames`), are discarded (a
        label swap or a ghost during the first frames would otherwise be
        built into the template) and collection goes on; after ``4 *
        template_frames`` candidates the consistent ones are used whatever
        their number. Distances that drift smoothly (a skin cluster
        deforming as the joint flexes) are consistent. The template is their
        average, each aligned (Kabsch) to the first consistent frame; the
        aligned frames' changes from one to the next seed the gate's normal
        jump (:class:`~jointfit_core.gate.ShapeTrack`).
        """
        if self.template is not None:
            return
        missing = np.isnan(y).any(axis=1)
        self._offered += 1
        self._missing += missing
        if missing.any():
            return
        x = y - y.mean(axis=0)
        if not shape_ok(x):
            return
        self._frames.append(x)
        self._seen += 1
        if len(self._frames) < self.template_frames:
            return
        X = np.stack(self._frames)
        D = np.linalg.norm(X[:, :, None, :] - X[:, None, :, :], axis=3)
        keep = consistent_frames(D, TEMPLATE_DEV_FACTOR)
        if keep.all() or self._seen >= 4 * self.template_frames:
            kept = X[keep]
            x0 = kept[0]
            aligned = np.stack([x0] + [(x - d) @ R for x in kept[1:] for R, d in [kabsch(x, x0)]])
            mean = aligned.mean(axis=0)
            dof = max(aligned.shape[0] * (3 * aligned.shape[1] - 6) - (3 * aligned.shape[1] - 6), 1)
            self.template_sigma = float(np.sqrt(np.sum((aligned - mean) ** 2) / dof))
            self._frames = []
            self.set_template(mean)
            steps = np.sum(np.diff(aligned, axis=0) ** 2, axis=2).max(axis=1, initial=0.0)
            self.shape = ShapeTrack(self.n_markers, steps.tolist())
        else:
            self._frames = [x for x, k in zip(self._frames, keep, strict=True) if k]

    def set_template(self, template: FloatArray) -> None:
        """Fix the template ``(P, 3)`` (centred here); the visibility caches start afresh."""
        x = np.asarray(template, dtype=np.float64)
        self.template = x - x.mean(axis=0)
        self._cache = {}
        gaps = np.linalg.norm(self.template[:, None] - self.template[None, :], axis=2)
        self.min_spacing = float(np.min(gaps[np.triu_indices(len(x), 1)]))
        self.rms_radius = float(np.sqrt(np.mean(np.sum(self.template**2, axis=1))))
        full = pose_covariance_local(self.template, 1.0)
        self._full_rot = float(np.linalg.eigvalsh(full[:3, :3])[-1])

    def visible_set(self, vis: NDArray[np.bool_]) -> VisibleSet | None:
        """Cached quantities of these visible markers (P,); None when they cannot pose the segment well."""
        key = vis.tobytes()
        try:
            return self._cache[key]
        except KeyError:
            pass
        assert self.template is not None
        out: VisibleSet | None = None
        xv = self.template[vis]
        if xv.shape[0] >= MIN_POSE_MARKERS and shape_ok(xv):
            W = pose_covariance_local(self.template, 1.0, vis)
            worst = float(np.linalg.eigvalsh(W[:3, :3])[-1])
            if np.isfinite(W).all() and worst <= POSE_VAR_RATIO_MAX * self._full_rot:
                xbar = xv.mean(axis=0)
                xc = np.where(vis[:, None], self.template - xbar, 0.0)
                out = VisibleSet(
                    index=np.flatnonzero(vis),
                    n=float(xv.shape[0]),
                    xbar=xbar,
                    xc=xc,
                    xx=float(np.einsum("ij,ij->", xc, xc)),
                    W_unit=W,
                    dof=3.0 * xv.shape[0] - 6.0,
                    code=marker_code(np.flatnonzero(vis)),
                )
        self._cache[key] = out
        return out

    # ------------------------------------------------------------------ the outlier gate

    def add_level(self, ss: float, dof: float, frame_no: int) -> None:
        """Pool a frame's pose-fit residual: sum of squares ``ss`` (input units squared) over ``dof`` degrees of freedom.

        Frames that posed the segment after the gate (whole or the markers it kept), numbered
        as they arrive (increasing); see :meth:`pooled_level`.
        """
        if dof <= 0.0:
            return
        w = _LEVEL_DECAY ** (frame_no - self._level_at)
        self._level_ss = self._level_ss * w + ss
        self._level_dof = self._level_dof * w + dof
        self._level_at = frame_no

    def add_levels(self, ss: FloatArray, dof: FloatArray, numbers: NDArray[np.int64]) -> None:
        """:meth:`add_level` of a run of frames: ``ss``, ``dof`` and ``numbers`` (K,), oldest first."""
        keep = dof > 0.0
        if not keep.any():
            return
        ss, dof, numbers = ss[keep], dof[keep], numbers[keep]
        last = int(numbers[-1])
        w = _LEVEL_DECAY ** (last - numbers).astype(np.float64)
        old = _LEVEL_DECAY ** (last - self._level_at)
        self._level_ss = self._level_ss * old + float(w @ ss)
        self._level_dof = self._level_dof * old + float(w @ dof)
        self._level_at = last

    def pooled_level(self) -> float | None:
        """The segment's pooled pose-fit residual, mean square per degree of freedom (input units squared), or None.

        ``sum w SS / sum w dof`` over the frames that posed it (:meth:`add_level`), each
        weighted by its age, half-life :data:`GATE_LEVEL_HALF_LIFE` frames: white noise, plus
        on skin markers the cluster's deformation. None before any such frame.
        """
        return self._level_ss / self._level_dof if self._level_dof > 0.0 else None

    def set_limits(self, residual_limit: float, normal_jump: float, gate: float) -> None:
        """The gate's limits: ``residual_limit`` = ``(gate sigma)^2`` per degree of freedom; the jump's from ``normal_jump``.

        The jump limit is ``gate^2`` times the normal jump; the low one
        :data:`~jointfit_core.gate.GATE_JUMP_LOW` times it (input units squared).
        """
        self.residual_limit = residual_limit
        self._gate2 = gate**2
        self.jump_limit = gate**2 * normal_jump
        self._jump_low = GATE_JUMP_LOW * normal_jump

    def residual_bound(self) -> float:
        """The residual test's limit now: mean squared residual per degree of freedom (input units squared).

        :attr:`residual_limit` (``gate^2`` times the segment's pooled residual level), or ``gate^2``
        times the segment's recent level (:meth:`~jointfit_core.gate.ShapeTrack.recent_residual`,
        :data:`~jointfit_core.gate.GATE_RESIDUAL_RECENT`) when that is larger: a skin cluster's
        deformation, which grows smoothly when the joint starts to move after a still stance,
        is judged against what the cluster showed a few frames before, not against the noise
        of the stance that fills the window.
        """
        recent = self.shape.recent_residual()
        return max(self.residual_limit, self._gate2 * recent) if recent > 0.0 else self.residual_limit

    @property
    def jump_limits(self) -> tuple[float, float]:
        """``(gate^2, GATE_JUMP_LOW)`` times the normal jump (input units squared)."""
        return self.jump_limit, self._jump_low

    def turn_active(self, frame_no: int) -> bool:
        """Whether the turn test applies in frame ``frame_no``.

        Not without a reference, when the reference is more than
        :data:`GATE_TURN_GAP_FRAMES` frames old, or after :data:`GATE_RELOCK_FRAMES`
        frames held out by the turn test in a row.
        """
        return self.ref_ok and self.held < GATE_RELOCK_FRAMES and frame_no - self.ref_frame <= GATE_TURN_GAP_FRAMES

    def turns(self, R: FloatArray, frame_no: int, margin: float = 0.0) -> bool:
        """Whether the pose ``R`` (3, 3) may fail the turn test in frame ``frame_no`` (cosine ``margin`` above the limit)."""
        if not self.turn_active(frame_no):
            return False
        return bool(cos_turn(R, self.ref_R) < COS_MAX_TURN + margin)

    def set_reference(self, R: FloatArray, d: FloatArray, frame_no: int) -> None:
        """The segment passed the gate in frame ``frame_no`` with pose ``R`` (3, 3), ``d`` (3,)."""
        self.ref_R[...] = R
        self.ref_d[...] = d
        self.ref_ok = True
        self.ref_frame = frame_no
        self.held = 0

    def shape_test(
        self, y: FloatArray, vs: VisibleSet, R: FloatArray, d: FloatArray, ss: float, frame_no: int, refit: bool
    ) -> tuple[FloatArray, float, bool, bool]:
        """A posed frame's markers in the template frame, its jump, whether it fails the gate and whether it moved as usual.

        ``y`` (n, 3): the visible markers ``vs``, posed ``R``, ``d`` with residual sum of
        squares ``ss``. :func:`~jointfit_core.gate.gate_fails`, scalar: the jump
        (:class:`~jointfit_core.gate.ShapeTrack`) against the jump limits, the residual
        against :meth:`residual_bound` per degree of freedom. ``refit``: the markers the
        gate kept (:meth:`leave_out`), which pass when they pass the residual test. *Moved as
        usual*: every visible marker has a recent reference and the jump is within the jump
        limit; only such a frame's residual, when it passes whole (not a refit's subset), sets
        the residual test's recent level, so that a lasting swap or ghost, or a subset the
        leave-out refit chose, cannot raise it (:meth:`residual_bound`).
        """
        local = (y - d) @ R
        jump, stale = self.shape.jump(vs.index, local, frame_no, vs.code)
        bad = bool(ss > self.residual_bound() * vs.dof and vs.dof > 0.0)
        # gate_fails, in scalars, with the jump from the previous frame only where it matters (per-frame cost)
        limit, low = self.jump_limits
        if jump == np.inf:
            fail = bad
        else:
            fail = bad and (stale or jump > low)
            if not fail and jump > limit:
                fail = self.shape.jump(vs.index, local, frame_no, vs.code, last=True)[0] > limit
        return local, jump, fail and (bad or not refit), not stale and jump <= limit

    def _fails(self, index: NDArray[np.intp], y: FloatArray, R: FloatArray, d: FloatArray, bad: bool, frame_no: int) -> bool:
        """:func:`~jointfit_core.gate.gate_fails` of markers ``index`` at ``y`` (n, 3) posed ``R``, ``d``."""
        local, code = (y - d) @ R, marker_code(index)
        jump, stale = self.shape.jump(index, local, frame_no, code)
        last = self.shape.jump(index, local, frame_no, code, last=True)[0]
        return bool(gate_fails(jump, stale, bad, *self.jump_limits, last))

    def relabelling(self, y: FloatArray, vs: VisibleSet, frame_no: int) -> NDArray[np.intp] | None:
        """The visible markers ``y`` (n, 3) as the reference's markers relabelled, or None.

        Returns the template index of each visible marker when each lies within half the
        template's smallest marker spacing of a different marker predicted by the reference
        pose: the same points under other labels (a swap). Failing that (at low frame rates
        the limb moves further than that from one frame to the next), the permutation of the
        visible markers' labels under which they pass the gate's shape test
        (:meth:`_relabelled_fit`) without turning from the reference, if any. None when
        there is none: a segment that jumped (a recording that restarts, another subject),
        or ghosts.
        """
        assert self.template is not None
        predicted = self.template @ self.ref_R.T + self.ref_d
        d2 = np.sum((y[:, None, :] - predicted[None, :, :]) ** 2, axis=2)
        nearest = np.argmin(d2, axis=1)
        close = d2[np.arange(nearest.size), nearest] < (0.5 * self.min_spacing) ** 2
        if close.all() and np.unique(nearest).size == nearest.size:
            return nearest
        return self._relabelled_fit(vs.index, y, frame_no)

    def _relabelled_fit(self, index: NDArray[np.intp], y: FloatArray, frame_no: int) -> NDArray[np.intp] | None:
        """The labels (template indices) other than ``index`` under which ``y`` (n, 3) fits unturned, or None.

        Every permutation of ``index`` (at most 5! = 120; run only for segments that turned
        by more than :data:`GATE_MAX_TURN_DEG`) is fitted; among those within
        :data:`GATE_MAX_TURN_DEG` of the reference that pass the shape and residual tests of
        :func:`~jointfit_core.gate.gate_fails`, the one of least residual.
        """
        assert self.template is not None
        if not np.isfinite(self.residual_limit):
            return None
        bound = self.residual_bound()
        dof = 3 * index.size - 6
        best: tuple[float, NDArray[np.intp]] | None = None
        for perm in itertools.permutations(range(index.size)):
            if perm == tuple(range(index.size)):
                continue
            labels = index[list(perm)]
            x = self.template[labels]
            R, d = kabsch(y, x)
            if cos_turn(R, self.ref_R) < COS_MAX_TURN:
                continue
            ss = float(np.sum((x @ R.T + d - y) ** 2))
            if self._fails(labels, y, R, d, ss > bound * dof, frame_no):
                continue
            if best is None or ss < best[0]:
                best = (ss, labels)
        return None if best is None else best[1]

    def follow(self, y: FloatArray, labels: NDArray[np.intp], frame_no: int) -> None:
        """Carry the turn reference along through a frame held out, its markers ``y`` (n, 3) relabelled.

        The reference becomes the pose of the frame's visible markers under the labels of
        :meth:`relabelling` (where the segment is, whatever the swap), so that the true labels
        pass the turn test again when the swap ends, however far the limb moved meanwhile.
        """
        assert self.template is not None
        self.ref_R, self.ref_d = kabsch(y, self.template[labels])
        self.held += 1
        self.ref_frame = frame_no

    def leave_out(self, y: FloatArray, vs: VisibleSet, active: bool, frame_no: int) -> tuple[int, ...] | None:
        """The fewest visible markers to leave out of a frame that failed the gate, or None (none will do).

        ``y`` (n, 3): the visible markers ``vs``. The subsets without one (then two) of them,
        keeping at least 3, are fitted; the best one (least residual) that passes the
        residual or the shape test, AND the turn test (when ``active``), is kept. Returns the
        positions (in ``vs.index``) left out. The turn test catches a swap in a nearly
        symmetric cluster, and one that leaves a symmetric subset (e.g. the two swapped
        markers equidistant from a third): a ~180 deg turn fits either within the noise.
        """
        assert self.template is not None
        idx = vs.index
        x = self.template[idx]
        bound = self.residual_bound()
        best: tuple[float, tuple[int, ...]] | None = None
        for n_out in (1, 2):
            if idx.size - n_out < MIN_POSE_MARKERS:
                break
            for drop in itertools.combinations(range(idx.size), n_out):
                keep = np.delete(np.arange(idx.size), drop)
                Rk, dk = kabsch(y[keep], x[keep])
                ss = float(np.sum((x[keep] @ Rk.T + dk - y[keep]) ** 2))
                # else it fits as well as ever
                if ss > bound * (3 * keep.size - 6) and self._fails(idx[keep], y[keep], Rk, dk, True, frame_no):
                    continue
                if active and cos_turn(Rk, self.ref_R) < COS_MAX_TURN:
                    continue
                if best is None or ss < best[0]:
                    best = (ss, drop)
            if best is not None:
                break  # as few markers left out as possible
        return None if best is None else best[1]
