"""Two rigidly marked segments that are not joined are not estimated as a joint.

Before (2026-12-06) a joint configured between the wrong segments (the pelvis and a shank, the
right thigh and the left shank) on rigid markers was identifiable, published with a covariance of
a millimetre or two, 93-283 mm of joint residual behind it. Known truth: the rigid lower body.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from skeleton_runs import run_stream

from jointfit_core.joint_fit_check import NOT_A_JOINT_RATIO, expected_residual_rms
from jointfit_core.segments import PoseSumsCentre
from jointfit_core.skeleton_truth import make_skeleton, skeleton_frames
from jointfit_core.window_solve import unpack_pose_sums
from jointfit_ros.params import node_config, params_from_file

ROOT = Path(__file__).resolve().parents[1]
WRONG = {"pelvis_to_shank": ("ball", "pelvis", "r_shank"), "thigh_to_other_shank": ("hinge", "r_thigh", "l_shank")}


@pytest.fixture(scope="module")
def runners() -> dict[str, object]:
    values = params_from_file(ROOT / "config" / "lower_body.yaml")
    values["joints"] = [*values["joints"], *WRONG]
    for name, (kind, parent, child) in WRONG.items():
        values.update({f"{name}.type": kind, f"{name}.parent": parent, f"{name}.child": child, f"{name}.window": 3000})
    for joint in values["joints"]:
        values[f"{joint}.attachment"] = "rigid"
    sk = make_skeleton("lower", seed=0)
    t = np.arange(1500) / 100.0
    frames = skeleton_frames(sk, t, np.random.default_rng(0), 0.0005, 0.02)
    out = {}
    for r in run_stream(node_config(values), t, frames, estimate_period=0.5):
        assert r.estimate(force=True), r.last_error
        out[r.cfg.name] = r
    return out


def _ratio(runner: object) -> float:
    est = runner.estimator  # type: ignore[attr-defined]
    sol = est.solution
    sums = est.sums_vector()
    _, Wp, Wc, _, _ = unpack_pose_sums(sums)
    sp, sc = est.noise_std
    points = (sol.centre_parent, sol.centre_child) if isinstance(sol, PoseSumsCentre) else (sol.point_parent, sol.point_child)
    return float(sol.rms) / expected_residual_rms(sp**2 * Wp, sc**2 * Wc, *points)


def test_joints_read_the_residual_their_pose_noise_gives(runners: dict[str, object]) -> None:
    for name in ("r_hip", "r_knee", "r_ankle", "l_hip", "l_knee", "l_ankle"):
        sol = runners[name].estimator.solution  # type: ignore[attr-defined]
        assert sol.identifiable, (name, sol.reason)
        assert 0.9 < _ratio(runners[name]) < 1.15, (name, _ratio(runners[name]))


def test_segments_that_are_not_joined_are_not_identifiable(runners: dict[str, object]) -> None:
    for name in WRONG:
        r = runners[name]
        sol = r.estimator.solution  # type: ignore[attr-defined]
        assert not sol.identifiable and "do not turn about" in sol.reason, (name, sol.reason)
        assert _ratio(r) > 2.0 * NOT_A_JOINT_RATIO, _ratio(r)
        status = r.status()  # type: ignore[attr-defined]
        assert "not identifiable (no per-frame output until it is)" in status.message and "attachment: skin" in status.message
