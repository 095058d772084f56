"""A marker knocked on its cluster after freezing: the frozen joint withholds its outputs and says why.

Before, the outlier gate let the lasting step through (by design: skin that slipped) and the
frozen joint published outputs off by the move times the lever arm with its frozen covariance:
on the live node a 5 mm move put the hip 38 mm off with an sd of 2.3 mm (9.5 sd), status OK
"frozen" (the hunt of 2026-12-03, D1).
"""

from __future__ import annotations

import numpy as np
import pytest

from jointfit_core.calibration_fit import MISFIT_FRAMES, CalibrationFit
from jointfit_core.estimator import OnlineJoint
from jointfit_core.synthetic import markers_from_poses, two_segment_motion

RATE = 100.0
NOISE = 0.5


def _stream(seed: int, knock_mm: float, attachment: str = "rigid") -> tuple[list[float], int, int]:
    """Estimate 12 s, freeze, then 8 s with the parent's marker 0 moved by ``knock_mm`` on its cluster after 2 s.

    Returns the per-frame errors over the published sd of the frozen outputs after the knock (world centre,
    e/3), the outputs withheld for the misfit, and the frames after the knock.
    """
    rng = np.random.default_rng(seed)
    motion = two_segment_motion(rng)
    t = np.arange(round(20.0 * RATE)) / RATE
    poses = motion.poses_at(t)
    knocked = motion.template_parent.copy()
    knocked[0] += knock_mm * np.array([0.6, 0.8, 0.0])
    yp, yc = markers_from_poses(poses, motion.template_parent, motion.template_child)
    yp_k, _ = markers_from_poses(poses, knocked, motion.template_child)
    start = round(14.0 * RATE)
    yp[start:] = yp_k[start:]
    yp += rng.normal(0.0, NOISE, yp.shape)
    yc += rng.normal(0.0, NOISE, yc.shape)
    est = OnlineJoint("ball", window=round(12.0 * RATE), attachment=attachment)
    freeze_at = round(12.0 * RATE)
    truth = motion.centre_world_at(t)
    e: list[float] = []
    for k in range(t.size):
        out = est.update(yp[k], yc[k], float(t[k]))
        if k == freeze_at:
            est.freeze()
        if k >= start and out is not None:
            delta = out.position - truth[k]
            e.append(float(delta @ np.linalg.solve(out.cov, delta)) / 3.0)
    return e, est.dropped.get("markers_off_calibration", 0), t.size - start


def test_a_knocked_marker_withholds_the_frozen_outputs_and_says_why() -> None:
    e, withheld, after = _stream(1, 5.0)
    assert withheld >= after - 2 * MISFIT_FRAMES  # from within ~50 frames of the knock on
    assert max(e) < 25.0, max(e)  # the few outputs before it was seen were published, not far off (e/3 25: 5 sd)


def test_without_a_knock_the_frozen_outputs_go_on_and_are_honest() -> None:
    for seed in (1, 2, 3):
        e, withheld, after = _stream(seed, 0.0)
        assert withheld == 0 and len(e) == after
        assert float(np.mean(e)) < 2.0, (seed, float(np.mean(e)))


def test_skin_deformation_within_its_calibration_does_not_withhold() -> None:
    """Skin: the calibration's noise holds the cluster's deformation; a frozen skin joint is judged at 3x it."""
    e, withheld, _ = _stream(4, 0.0, attachment="skin")
    assert withheld == 0 and e


@pytest.mark.parametrize("ratio", [1.5, 2.5])
def test_the_level_is_judged_after_its_frames(ratio: float) -> None:
    fit = CalibrationFit(("rigid", "rigid"))
    for _ in range(MISFIT_FRAMES - 1):
        fit.add(0, 6.0 * (ratio * 0.5) ** 2, 6.0, 0.5)
    assert fit.problem == ""  # not yet judged
    fit.add(0, 6.0 * (ratio * 0.5) ** 2, 6.0, 0.5)
    assert bool(fit.problem) == (ratio > 2.0)
    fit.add(1, 1.0, 6.0, 0.0)  # no noise to judge against (virtual markers): ignored
    fit.restart()
    assert fit.problem == ""
