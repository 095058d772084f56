"""A calibration reused in a later session after a whole cluster was taken off and put back elsewhere.

A plate re-strapped a few cm or degrees away on the same bone (or another subject's, the other side's
calibration with plates of the same shape) keeps its shape, so the pose fits' residual check of
:mod:`jointfit_core.calibration_fit` cannot see it; the saved joint, fixed in the old template frame, is
then off. Before (hunt-calib B1), a hip whose pelvis plate was put back 20 mm away was published 20 mm off
with an sd of 1.9 mm (e/3 41, 11 sd) and a knee whose thigh plate turned 5 deg 4 mm off with e/2 136,
both "frozen", OK, every frame. The joint itself shows it: the parent- and the child-carried joint no
longer meet.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers import output_index
from scipy.spatial.transform import Rotation

from jointfit_core.calibration_fit import JOINT_MISFIT_FRAMES, JOINT_MISFIT_RATIO
from jointfit_core.estimator import OnlineJoint
from jointfit_core.synthetic import TwoSegmentMotion, two_segment_motion

RATE = 100.0
NOISE = 0.5  # mm


def _frames(motion: TwoSegmentMotion, t: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    yp, yc = motion.markers_at(t)
    return (yp + rng.normal(0.0, NOISE, yp.shape)) * 1e-3, (yc + rng.normal(0.0, NOISE, yc.shape)) * 1e-3


def _calibrated(motion: TwoSegmentMotion) -> dict:
    t = np.arange(round(30.0 * RATE)) / RATE
    yp, yc = _frames(motion, t, 1)
    est = OnlineJoint(motion.kind, window=3000, attachment="rigid")
    for k in range(t.size):
        est.update(yp[k], yc[k], float(t[k]))
    est.estimate()
    est.freeze()
    return est.to_dict()


def _moved(motion: TwoSegmentMotion, shift_mm: tuple[float, float, float], turn_deg: float) -> TwoSegmentMotion:
    """The parent's cluster put back elsewhere on its bone: the same shape, turned about its centroid and shifted."""
    x = motion.template_parent
    c = x.mean(axis=0)
    R = Rotation.from_rotvec(np.deg2rad(turn_deg) * np.array([0.0, 1.0, 0.0])).as_matrix()
    return dataclasses.replace(motion, template_parent=(x - c) @ R.T + c + np.asarray(shift_mm))


def _session(
    saved: dict, motion: TwoSegmentMotion, truth: TwoSegmentMotion, held: bool = False, child_hidden: int = 0
) -> tuple[list[float], OnlineJoint]:
    """A later 10 s session with the saved calibration: e/k of every published output (k = 3 ball, 2 hinge point).

    ``held``: as the node loads a calibration file (:meth:`OnlineJoint.hold_until_judged`).
    ``child_hidden``: the child's markers are all occluded in the first that many frames.
    """
    t = 200.0 + np.arange(round(10.0 * RATE)) / RATE
    yp, yc = _frames(motion, t, 7)
    yc[:child_hidden] = np.nan
    centre = truth.centre_world_at(t) * 1e-3
    est = OnlineJoint.from_dict(saved)
    if held:
        est.hold_until_judged()
    e: list[float] = []
    for k in range(t.size):
        out = est.update(yp[k], yc[k], float(t[k]))
        if out is None:
            continue
        e.append(output_index(out, centre[k], truth.kind))
    return e, est


@pytest.mark.parametrize(("kind", "shift", "turn"), [("ball", (20.0, 0.0, 0.0), 0.0), ("ball", (0.0, 0.0, 0.0), 5.0),
                                                     ("hinge", (0.0, 0.0, 0.0), 5.0)])
def test_a_cluster_put_back_elsewhere_withholds_the_outputs_and_says_why(kind: str, shift: tuple, turn: float) -> None:
    motion = two_segment_motion(np.random.default_rng(3), kind=kind, offset=(2500.0, 3000.0, 900.0))
    saved = _calibrated(motion)
    e, est = _session(saved, _moved(motion, shift, turn), motion)
    assert len(e) <= JOINT_MISFIT_FRAMES + 5, (len(e), float(np.median(e)))  # withheld within ~1 s
    assert est.dropped.get("markers_off_calibration", 0) > 800
    assert "no longer fits the joint" in est.calibration_problem


@pytest.mark.parametrize("kind", ["ball", "hinge"])
@pytest.mark.parametrize("axis", [0, 1, 2])
def test_a_cluster_put_back_a_few_mm_away_publishes_nothing_confidently_wrong(kind: str, axis: int) -> None:
    """A rigid parent plate re-strapped 3 mm away: outputs either withheld or within their covariance.

    Before 2026-12-07 the joint residual's mean was judged against its whole per-frame scatter (the frames'
    pose noise at the joint, ~4 mm here), which a mean of 100 frames does not have: 3 mm (ball) and 3 mm
    (hinge) moves read 0.4-2.2 against a limit of 4, and were published at mean e/k 6-48 with status OK.
    """
    motion = two_segment_motion(np.random.default_rng(3), kind=kind, offset=(2500.0, 3000.0, 900.0))
    saved = _calibrated(motion)
    shift = [0.0, 0.0, 0.0]
    shift[axis] = 3.0
    e, est = _session(saved, _moved(motion, tuple(shift), 0.0), motion, held=True)
    if est.calibration_problem:
        assert "no longer fits the joint" in est.calibration_problem
        assert len(e) <= 50, len(e)  # withheld from the first judgement on, or nearly
    else:
        assert len(e) == 1000 - (JOINT_MISFIT_FRAMES - 1) and float(np.mean(e)) < 3.0, float(np.mean(e))


@pytest.mark.parametrize("kind", ["ball", "hinge"])
def test_the_same_markers_in_a_later_session_publish_honestly(kind: str) -> None:
    motion = two_segment_motion(np.random.default_rng(3), kind=kind, offset=(2500.0, 3000.0, 900.0))
    saved = _calibrated(motion)
    e, est = _session(saved, motion, motion)
    assert est.calibration_problem == "" and len(e) >= 990
    assert float(np.mean(e)) < 2.0
    # far inside the limit; since 2026-12-07 the statistic is on the outputs' own scale (honest: 0.01-0.3)
    assert est._fit.joint_ratio < JOINT_MISFIT_RATIO["rigid"] / 5


@pytest.mark.parametrize(("kind", "shift", "turn"), [("ball", (20.0, 0.0, 0.0), 0.0), ("hinge", (0.0, 0.0, 0.0), 5.0)])
def test_a_loaded_calibration_publishes_nothing_before_it_is_judged(kind: str, shift: tuple, turn: float) -> None:
    """As the node loads a file: the first second is held too, so a moved cluster publishes nothing at all.

    Without the hold the first JOINT_MISFIT_FRAMES frames went out (the hip 20 mm off at an sd of 1.9 mm).
    """
    motion = two_segment_motion(np.random.default_rng(3), kind=kind, offset=(2500.0, 3000.0, 900.0))
    saved = _calibrated(motion)
    e, est = _session(saved, _moved(motion, shift, turn), motion, held=True)
    assert e == [], (len(e), float(np.median(e)))
    assert est.dropped.get("calibration_being_checked") == JOINT_MISFIT_FRAMES - 1
    assert "no longer fits the joint" in est.calibration_problem
    e_same, est_same = _session(saved, motion, motion, held=True)
    assert len(e_same) == 1000 - (JOINT_MISFIT_FRAMES - 1) and est_same.calibration_problem == ""


@pytest.mark.parametrize("hidden", [30, 300])
def test_a_loaded_calibration_is_held_until_the_joint_itself_is_judged(hidden: int) -> None:
    """Frames where only the parent is posed cannot judge the joint: the hold lasts until 100 frames with both posed.

    Before (hunt-calib2 A), the hold counted frames with either segment posed: with the child hidden for the first
    0.3 s (3 s), a hip whose pelvis plate was put back 20 mm away was published 30 (300) times, 20 mm off at
    e/3 ~550, with no warning, before the joint residual was first judged.
    """
    motion = two_segment_motion(np.random.default_rng(3), kind="ball", offset=(2500.0, 3000.0, 900.0))
    saved = _calibrated(motion)
    e, est = _session(saved, _moved(motion, (20.0, 0.0, 0.0), 0.0), motion, held=True, child_hidden=hidden)
    assert e == [], (len(e), float(np.median(e)))
    assert est.dropped.get("calibration_being_checked") == hidden + JOINT_MISFIT_FRAMES - 1
    assert "no longer fits the joint" in est.calibration_problem
    e_same, est_same = _session(saved, motion, motion, held=True, child_hidden=hidden)
    assert len(e_same) == 1000 - hidden - (JOINT_MISFIT_FRAMES - 1) and est_same.calibration_problem == ""
    assert float(np.mean(e_same)) < 2.0


@pytest.mark.parametrize(("kind", "thaw_at"), [("ball", 300), ("hinge", 300), ("hinge", 50)])
def test_thawing_a_calibration_that_does_not_fit_estimates_anew_without_publishing_it(kind: str, thaw_at: int) -> None:
    """``~/freeze false`` after a loaded calibration was withheld (or while it is still being checked).

    The joint estimates anew from the live markers, so its outputs must come from that new estimate only.
    Before (hunt-calib2 B), the withheld calibration was published again from the thaw until the first solve
    of the new window: the node's knee whose thigh plate had been put back elsewhere went out about 20 mm off
    at e/2 ~200 for 0.1 s, status OK "estimating".
    """
    motion = two_segment_motion(np.random.default_rng(3), kind=kind, offset=(2500.0, 3000.0, 900.0))
    saved = _calibrated(motion)
    moved = _moved(motion, (20.0, 0.0, 0.0), 5.0)
    t = 200.0 + np.arange(round(20.0 * RATE)) / RATE
    yp, yc = _frames(moved, t, 7)
    centre = motion.centre_world_at(t) * 1e-3
    est = OnlineJoint.from_dict(saved)
    est.hold_until_judged()
    e: list[tuple[int, float]] = []
    for k in range(t.size):
        if k == thaw_at:
            assert est.calibration_problem
            est.thaw()
        out = est.update(yp[k], yc[k], float(t[k]))
        if k > thaw_at and k % 10 == 0:
            try:
                est.estimate()
            except ValueError:
                pass
        if out is None:
            continue
        e.append((k, output_index(out, centre[k], kind)))
    assert e and all(k > thaw_at + 10 for k, _ in e), e[:3]  # nothing before the new window's first solve
    assert max(v for _, v in e) < 25.0 and float(np.mean([v for _, v in e])) < 2.0
