"""Coverage (jointfit_core.coverage): 100 % exactly when the verdict's coverage tests pass, rising with the motion."""

from __future__ import annotations

import numpy as np
import pytest

from jointfit_core.coverage import joint_coverage
from jointfit_core.estimator import OnlineJoint
from jointfit_core.hinge_from_sums import PoseSumsAxis
from jointfit_core.synthetic import two_segment_motion


def _trace(kind: str, seed: int, noise: float, n: int = 600, every: int = 10) -> list[tuple[float, bool, float]]:
    """(coverage, identifiable, motion part) after every ``every`` frames of a synthetic rig (mm, 100 Hz)."""
    rng = np.random.default_rng(seed)
    motion = two_segment_motion(rng, kind=kind)
    t = np.arange(n) / 100.0
    parent, child = motion.markers_at(t)
    parent = parent + rng.normal(0.0, noise, parent.shape)
    child = child + rng.normal(0.0, noise, child.shape)
    est = OnlineJoint(kind, window=n, template_frames=20)
    out = []
    for k in range(0, n, every):
        est.update_many(parent[k : k + every], child[k : k + every], t[k : k + every])
        if not est.templates_ready or est.n_window < 3:
            continue
        try:
            sol = est.estimate()
        except ValueError:  # NotIdentifiableError: nothing to cover yet
            out.append((0.0, False, 0.0))
            continue
        sums, Wp, Wc, _, _ = est.pose_sums()
        sigma_p, sigma_c = est.noise_std
        cov = joint_coverage(sol, est.length_scale, sums, sigma_p**2 * Wp, sigma_c**2 * Wc)
        assert 0.0 <= cov.overall <= 1.0 and cov.motion is not None
        assert cov.overall == min(cov.motion, cov.estimate)
        out.append((cov.overall, sol.identifiable, cov.motion))
    return out


@pytest.mark.parametrize("kind", ["ball", "hinge"])
@pytest.mark.parametrize("seed", [1, 2])
def test_full_coverage_exactly_when_identifiable(kind: str, seed: int) -> None:
    trace = _trace(kind, seed, noise=8.0)
    ident = [i for _, i, _ in trace]
    assert not ident[0] and ident[-1], "the rig should start unidentified and end identified"
    for overall, identifiable, _ in trace:
        # identifiable => every coverage threshold met; the converse holds for these rigs (true ball or hinge)
        assert (overall == 1.0) == identifiable, trace
    first = ident.index(True)
    before = [c for c, _, _ in trace[:first]]
    assert before[-1] > before[0], f"coverage did not rise before identification: {before}"


def test_single_axis_ball_is_not_covered() -> None:
    """A ball moved as a hinge: rotation about one axis only, the second is not covered whatever the frames."""
    rng = np.random.default_rng(3)
    motion = two_segment_motion(rng, kind="hinge")
    t = np.arange(1500) / 100.0
    parent, child = motion.markers_at(t)
    est = OnlineJoint("ball", window=1500, template_frames=20)
    est.update_many(parent + rng.normal(0, 1.0, parent.shape), child + rng.normal(0, 1.0, child.shape), t)
    sol = est.estimate()
    sums, Wp, Wc, _, _ = est.pose_sums()
    sp, sc = est.noise_std
    cov = joint_coverage(sol, est.length_scale, sums, sp**2 * Wp, sc**2 * Wc)
    assert not sol.identifiable
    # both parts say so: the motion part, and the covariance, which is large along the unexcited direction
    # (the rotation axis) now that the noise's share of the normal matrix is removed (debiased_sums)
    assert cov.motion is not None and cov.motion < 0.05 and cov.estimate < 0.05 and cov.overall < 0.05, cov
    axis = np.linalg.svd(np.asarray(sums.S))[0][:, 0]  # the rotation axis, parent frame
    assert abs(float(cov.least_covered @ axis)) > 0.95, (cov.least_covered, axis)


def test_frozen_estimate_has_no_motion_part() -> None:
    rng = np.random.default_rng(4)
    motion = two_segment_motion(rng, kind="hinge")
    t = np.arange(1500) / 100.0
    parent, child = motion.markers_at(t)
    est = OnlineJoint("hinge", window=1500, template_frames=20)
    est.update_many(parent + rng.normal(0, 1.0, parent.shape), child + rng.normal(0, 1.0, child.shape), t)
    sol = est.freeze()
    assert isinstance(sol, PoseSumsAxis) and sol.identifiable
    cov = joint_coverage(sol, est.length_scale)
    assert cov.motion is None and cov.overall == cov.estimate == 1.0


def test_coverage_values_are_plain_numbers_in_diagnostics() -> None:
    """``coverage by direction (%)`` reads as a list of numbers in /diagnostics, not of numpy reprs."""
    pytest.importorskip("rclpy")
    from jointfit_ros.conversions import diagnostic_status
    from jointfit_ros.progress import coverage_values

    rng = np.random.default_rng(5)
    motion = two_segment_motion(rng, kind="ball")
    t = np.arange(1500) / 100.0
    parent, child = motion.markers_at(t)
    est = OnlineJoint("ball", window=1500, template_frames=20)
    est.update_many(parent + rng.normal(0, 1.0, parent.shape), child + rng.normal(0, 1.0, child.shape), t)
    _, values = coverage_values(est, est.estimate())
    by_direction = values["coverage by direction (%)"]
    assert len(by_direction) == 3 and all(type(v) is float for v in by_direction), by_direction
    text = {kv.key: kv.value for kv in diagnostic_status("jointfit: hip", 0, "", values).values}
    assert "np." not in text["coverage by direction (%)"], text
    assert [float(v) for v in text["coverage by direction (%)"].strip("[]").split(",")] == by_direction
