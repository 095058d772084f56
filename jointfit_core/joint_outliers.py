"""An online joint's outlier gate: the limits its segments are judged against, and what follows a failure.

:class:`GateLimits` is what :class:`~jointfit_core.estimator.OnlineJoint`
asks, once per frame, whether its gate is on and how far a segment may stray
(:meth:`GateLimits.var`); the frame path (the joint's ``_add``) and the block
path (:func:`~jointfit_core.joint_blocks.update_many`) both ask it, so that
they judge alike. The limits are the segments' own (each segment's pooled
pose-fit residual, :meth:`GateLimits.sigma`), not the joint's estimate, so
that joints sharing a segment judge it alike; they are read again every
:data:`~jointfit_core.segment_tracker.GATE_REFRESH_FRAMES` frames, counted as
they arrive. Judging a frame against them is the segments'
(:meth:`~jointfit_core.segment_pair.SegmentPair.judge`); :func:`after_failure`
is the joint's frame path once a segment has failed: a swap's labels put right,
else the failing markers held out (counted in the joint's ``dropped`` and
``gate_log``), and the frame posed again. Like
:mod:`jointfit_core.joint_blocks`, it takes the joint and reads and writes its
state.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from .segment_tracker import GATE_REFRESH_FRAMES

if TYPE_CHECKING:
    from .estimator import OnlineJoint
    from .joint_estimate import JointEstimate
    from .joint_world import JointOutput
    from .segment_pair import GateVerdict, PairSet, SegmentPair

__all__ = ["GATE_SIGMA_FLOOR", "GateLimits", "after_failure"]

FloatArray = NDArray[np.float64]

#: Outlier gate: the noise sigma it assumes is at least this fraction of the templates' rms radius
#: (noise-free or rounding-level data would otherwise fail it in every frame).
GATE_SIGMA_FLOOR = 1e-6


class GateLimits:
    """The outlier gate's limits of a joint's parent and child, cached between refreshes.

    Parameters
    ----------
    gate : float
        The joint's gate (>= 0; 0: off): the limits are ``gate`` times each
        segment's noise level and ``gate^2`` times its normal jump.
    noise_std : (float or None, float or None)
        The joint's fixed marker noise of the parent and the child (input
        units; None: read from the segment's residuals).
    """

    def __init__(self, gate: float, noise_std: tuple[float | None, float | None]) -> None:
        self.gate = gate
        self.noise_std = noise_std
        self._key: tuple[float, int] | None = None
        self._var: FloatArray | None = None

    def var(self, arrivals: int, pair: SegmentPair, estimate: JointEstimate) -> FloatArray | None:
        """Per segment (2,), ``(gate * sigma)^2``: the largest mean squared residual per degree of freedom accepted.

        ``sigma``: :meth:`sigma`. None while the gate is off or there is no noise level
        (fixed templates before any frame posed the segments). Sets the segments'
        limits with it (:meth:`~jointfit_core.segment_tracker.SegmentTracker.set_limits`:
        the residual's, and ``gate^2`` times each segment's normal jump,
        :class:`~jointfit_core.gate.ShapeTrack`). Cached: both are read again every
        :data:`~jointfit_core.segment_tracker.GATE_REFRESH_FRAMES` frames, counted as they
        arrive (per-frame cost; the update and block paths then judge alike,
        :func:`~jointfit_core.joint_blocks.update_many` cutting its blocks there), and not
        with the joint's estimates: the limits are the segments' own, so that joints sharing a
        segment judge it alike.

        Parameters
        ----------
        arrivals : int
            Frames that have arrived at the joint so far (the refresh clock).
        pair : SegmentPair
            The joint's two segments (their levels are read, their limits set).
        estimate : JointEstimate
            The joint: its latest estimate's noise is the last fallback of :meth:`sigma`.

        Returns
        -------
        ndarray, shape (2,), or None
            Squared input units.
        """
        key = (self.gate, arrivals // GATE_REFRESH_FRAMES)
        if key != self._key:
            self._key = key
            sigma = self.sigma(pair, estimate)
            if self.gate <= 0.0 or min(sigma) <= 0.0:
                self._var = None
            else:
                segs = (pair.parent, pair.child)
                # noise-free data: sigmas of rounding would gate every frame
                floor = GATE_SIGMA_FLOOR * np.array([seg.rms_radius for seg in segs])
                s = np.maximum(sigma, floor)
                self._var = np.square(self.gate * s)
                for seg, sk, var, fk in zip(segs, s, self._var, floor, strict=True):
                    seg.set_limits(float(var), seg.shape.normal_jump(float(sk), float(fk)), self.gate)
        return self._var

    def sigma(self, pair: SegmentPair, estimate: JointEstimate) -> FloatArray:
        """Per segment (2,), the residual level the gate's residual test holds (input units).

        Each segment's own pooled pose-fit residual
        (:meth:`~jointfit_core.segment_tracker.SegmentTracker.pooled_level`: white noise, plus
        on skin markers the cluster's deformation, over the frames that posed it, whatever the
        other segment did); before a segment has any: the noise seen while building its
        template, else the latest estimate's noise (``estimate``'s, a calibration loaded). A
        fixed ``noise_std`` is used as given.
        """
        sigma = np.zeros(2)
        for k, seg in enumerate((pair.parent, pair.child)):
            level = seg.pooled_level()
            fixed = self.noise_std[k]
            if fixed is not None:
                sigma[k] = float(fixed)
            elif level is not None:
                sigma[k] = math.sqrt(max(level, 0.0))
            elif seg.template_sigma > 0.0:
                sigma[k] = seg.template_sigma
            elif estimate.solution is not None:
                sigma[k] = estimate.noise_std[k]
        return sigma


def after_failure(
    joint: OnlineJoint,
    missing: NDArray[np.bool_],
    ps: PairSet,
    verdict: GateVerdict,
    stamp: float | None,
    frame_no: int,
    refit: tuple[bool, bool],
    relabelled: bool,
) -> JointOutput | None:
    """The joint's frame step after a segment failed the gate: labels put right or markers held out, then again.

    A swap (the failing segment's markers are its reference's under other labels,
    :meth:`~jointfit_core.segment_pair.SegmentPair.relabel`; not for fixed templates,
    a pose stream's virtual markers, whose labels cannot swap, nor twice in a frame)
    is put right, logged, and the frame judged again with all its markers; otherwise
    the failing markers are held out (:func:`_held_out`) and the frame posed and
    judged again without them.

    Parameters
    ----------
    joint : OnlineJoint
        The joint whose ``_add`` judged the frame (its marker buffer holds it).
    missing : ndarray of bool, shape (2, Pmax)
        The frame's missing markers, as judged.
    ps : PairSet
        Its visible sets.
    verdict : GateVerdict
        What failed (:meth:`~jointfit_core.segment_pair.SegmentPair.judge`).
    stamp : float or None
        The frame's stamp (s).
    frame_no : int
        Its number (1-based, as the frames arrived).
    refit, relabelled : (bool, bool), bool
        As the joint's ``_add`` was called: per segment, whether this is already a
        refit after the gate; whether the labels were already put right.

    Returns
    -------
    JointOutput or None
        The frame's output, as the joint's ``_add`` returns it.
    """
    pose = joint._pose
    assert pose is not None
    # (fixed templates: a pose stream's virtual markers, whose labels cannot swap)
    markers = (joint._templates_arg[0] is None, joint._templates_arg[1] is None)
    fix = None if relabelled or refit[0] or refit[1] else pose.relabel(missing, ps, verdict, markers)
    if fix is not None:  # a swap put right: the frame judged again with all its markers
        if joint.gate_log is not None:
            joint.gate_log.extend((frame_no, k, np.nan if stamp is None else stamp) for k in fix[1])
        return joint._add(fix[0], stamp, frame_no, (ps.parent is None, ps.child is None), relabelled=True)
    gated = _held_out(joint, pose, missing, ps, verdict, frame_no, stamp)
    again = (refit[0] or verdict.failed[0], refit[1] or verdict.failed[1])
    out = joint._add(gated, stamp, frame_no, (ps.parent is None, ps.child is None), again)
    pose.after_refit(ps, verdict, frame_no, refit)
    return out


def _held_out(
    joint: OnlineJoint,
    pose: SegmentPair,
    missing: NDArray[np.bool_],
    ps: PairSet,
    verdict: GateVerdict,
    frame_no: int,
    stamp: float | None,
) -> NDArray[np.bool_]:
    """The missing-marker mask (2, Pmax) after the gate (:meth:`~jointfit_core.segment_pair.SegmentPair.hold_out`), counted.

    A failing segment's left-out markers are counted as ``<segment>_gated_markers``; a segment
    that loses all its markers (not posed) as ``<segment>_gated``; each failing segment's frame
    goes to the joint's ``gate_log``.
    """
    out, held = pose.hold_out(missing, ps, verdict, frame_no)
    for k, dropped in held:
        if joint.gate_log is not None:
            joint.gate_log.append((frame_no, k, np.nan if stamp is None else stamp))
        name = pose.tracker(k).name
        if dropped is None:
            joint._drop(f"{name}_gated")
        else:
            joint.dropped[f"{name}_gated_markers"] = joint.dropped.get(f"{name}_gated_markers", 0) + dropped
    return out
