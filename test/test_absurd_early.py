"""A finite absurd value (1e160, 1e299 from a driver) before the templates exist, or in a rigid-body pose.

Before the fix, such a marker among the template frames overflowed the templates' shape test: a
LinAlgError left the frame callback (counted as an unexpected error in the node, ERROR) and the
hip never had an estimate again ("no estimate: W_parent_local ..."); such a pose position entered
the window's sums as inf and the joint was not identifiable until that frame left the window.
Now both are absurd values: treated as missing (dropped for a pose) and counted.
"""

from __future__ import annotations

import numpy as np
import pytest
from bagtools import pose_stamped_bytes
from helpers import fake_rig_values

from jointfit_core.synthetic import two_segment_motion
from jointfit_ros.fake_mocap import frame_at, make_rigs, truth_in_template_frame
from jointfit_ros.inputs import MessageRouter
from jointfit_ros.params import node_config
from jointfit_ros.raw import pose_array_bytes
from jointfit_ros.runner import JointRunner

T0 = 10**12  # ns


@pytest.mark.parametrize("huge", [1e160, 1e299])
def test_an_absurd_marker_among_the_template_frames_is_missing(huge: float) -> None:
    cfg = node_config(fake_rig_values())
    rigs = make_rigs(3)
    rng = np.random.default_rng(3)
    runners = [JointRunner(j, cfg) for j in cfg.joints]
    router = MessageRouter(cfg, runners)
    for k in range(1500):
        frame = frame_at(rigs, k / 100.0, rng, 0.5, 0.0) / 1000.0
        if k in (5, 6, 7):  # the templates (20 frames) are being built
            frame[1, 0] = huge  # PELV2 (hip parent)
            frame[9, 1] = huge  # FEMUR2 (knee parent)
        router.markers(pose_array_bytes(T0 + k * 10_000_000, "world", frame))  # raises before the fix
        router.after_outputs()
    for r in runners:
        assert r.counters["absurd_markers"] == 3, (r.cfg.name, r.counters)
        assert r.estimate(force=True), (r.cfg.name, r.last_error)
        sol = r.estimator.solution
        assert sol is not None and sol.identifiable
        template = r.estimator.templates[0]
        assert template is not None
        point, axis = truth_in_template_frame(rigs[r.cfg.name], template * 1000.0)
        found = sol.centre_parent if r.cfg.type == "ball" else sol.point_parent
        err = found * 1000.0 - point
        if axis is not None:  # a hinge: the distance from the true axis
            err = err - axis * float(err @ axis)
        assert np.linalg.norm(err) < 5.0, (r.cfg.name, found * 1000.0, point)  # mm (sd ~0.2 mm)


@pytest.mark.parametrize("huge", [1e160, 1e299])
def test_an_absurd_pose_position_is_dropped(huge: float) -> None:
    cfg = node_config({
        "joints": ["hip"], "hip.type": "ball", "hip.parent_pose_topic": "/p", "hip.child_pose_topic": "/c",
        "hip.pose_translation_sd": 0.0003, "hip.pose_rotation_sd_deg": 0.1, "hip.attachment": "rigid",
    })
    rig = two_segment_motion(np.random.default_rng(1), kind="ball")
    rng = np.random.default_rng(2)
    runner = JointRunner(cfg.joints[0], cfg)
    router = MessageRouter(cfg, [runner])
    for k in range(2000):
        R_p, d_p, R_c, d_c = rig.poses_at(k / 100.0)
        stamp = T0 + k * 10_000_000
        d = d_p[0] / 1000.0 + rng.normal(0.0, 3e-4, 3)
        if k in (1000, 1001, 1002):
            d = d + huge
        router.pose("/p", pose_stamped_bytes(stamp, "world", R_p[0], d))
        router.pose("/c", pose_stamped_bytes(stamp, "world", R_c[0], d_c[0] / 1000.0 + rng.normal(0.0, 3e-4, 3)))
    assert runner.counters["absurd_markers"] == 3, runner.counters
    assert runner.estimate(force=True), runner.last_error
    sol = runner.estimator.solution
    assert sol is not None and sol.identifiable and np.isfinite(sol.cov_parent).all()
    assert np.linalg.norm(sol.centre_parent * 1000.0 - rig.centre_parent) < 1.0  # mm (sd ~0.05 mm)
