"""A segment's own pooled pose-fit residual, the level its outlier gate's residual test holds.

:meth:`SegmentTracker.pooled_level <jointfit_core.segment_tracker.SegmentTracker.pooled_level>`
weighs each frame's residual by its age (half-life ``GATE_LEVEL_HALF_LIFE`` frames, counted as
they arrive). These check it against the weights written out, the frame and block paths
(:meth:`add_level` one by one against :meth:`add_levels` in runs), and that a joint's limits come
from its segments alone: the same segment's level in two joints whose other segments differ.
"""

from __future__ import annotations

import itertools

import numpy as np
from numpy.typing import NDArray

from jointfit_core.estimator import OnlineJoint
from jointfit_core.segment_tracker import GATE_LEVEL_HALF_LIFE, SegmentTracker
from jointfit_core.synthetic import two_segment_motion

FloatArray = NDArray[np.float64]


def test_the_pooled_level_weighs_frames_by_their_age() -> None:
    rng = np.random.default_rng(3)
    numbers = np.cumsum(rng.integers(1, 4, size=400))  # frames that posed it, with gaps
    ss = rng.uniform(0.5, 2.0, size=numbers.size)
    dof = rng.choice([3.0, 6.0], size=numbers.size)
    tracker = SegmentTracker("child", 4, 10)
    assert tracker.pooled_level() is None
    for s, f, n in zip(ss, dof, numbers, strict=True):
        tracker.add_level(float(s), float(f), int(n))
    w = 0.5 ** ((numbers[-1] - numbers) / GATE_LEVEL_HALF_LIFE)
    expected = float(w @ ss / (w @ dof))
    level = tracker.pooled_level()
    assert level is not None
    assert abs(level - expected) <= 1e-12 * expected
    # a frame of no freedom (3 markers posing nothing to spare) does not count
    tracker.add_level(5.0, 0.0, int(numbers[-1]) + 1)
    assert tracker.pooled_level() == level


def test_runs_of_frames_pool_as_the_frames_one_by_one() -> None:
    rng = np.random.default_rng(4)
    numbers = np.cumsum(rng.integers(1, 3, size=1000)).astype(np.int64)
    ss = rng.uniform(0.5, 2.0, size=numbers.size)
    dof = rng.choice([0.0, 3.0, 6.0], size=numbers.size)
    one, runs = SegmentTracker("parent", 4, 10), SegmentTracker("parent", 4, 10)
    for s, f, n in zip(ss, dof, numbers, strict=True):
        one.add_level(float(s), float(f), int(n))
    cuts = [0, *sorted(rng.choice(np.arange(1, numbers.size), size=30, replace=False).tolist()), numbers.size]
    for lo, hi in itertools.pairwise(cuts):
        runs.add_levels(ss[lo:hi], dof[lo:hi], numbers[lo:hi])
    a, b = one.pooled_level(), runs.pooled_level()
    assert a is not None and b is not None
    assert abs(a - b) <= 1e-12 * a


def _parent_levels(child_noise: float) -> tuple[float, FloatArray]:
    """A joint's parent level and gate sigmas (mm) after a run whose child markers have ``child_noise`` (mm)."""
    motion = two_segment_motion(np.random.default_rng(11), kind="ball")
    parent, child = motion.markers_at(np.arange(1500) / 60.0)
    rng = np.random.default_rng(12)
    parent = parent + rng.normal(0.0, 0.5, parent.shape)
    child = child + rng.normal(0.0, child_noise, child.shape)
    joint = OnlineJoint("ball", window=3000)
    joint.update_many(parent, child)
    assert joint._pose is not None
    level = joint._pose.parent.pooled_level()
    assert level is not None
    return level, joint._limits.sigma(joint._pose, joint)


def test_a_segments_gate_level_does_not_depend_on_the_joints_other_segment() -> None:
    quiet, sigma_quiet = _parent_levels(0.5)
    noisy, sigma_noisy = _parent_levels(3.0)
    assert quiet == noisy  # the parent's own level: the same frames, whatever the child did
    assert sigma_quiet[0] == sigma_noisy[0]
    assert sigma_noisy[1] > 4.0 * sigma_quiet[1]  # not vacuous: the child's level is its own
    assert abs(np.sqrt(quiet) / 0.5 - 1.0) < 0.1  # and it is the parent's noise
