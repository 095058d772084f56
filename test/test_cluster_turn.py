"""A cluster whose markers lie nearly on a line: each frame's pose turns about it, the covariance under-states.

Known truth: the rigid two-segment rig with a 3-marker child 150 mm long whose middle marker is
``h`` mm off the line (the measured calibration is in :mod:`jointfit_core.cluster_turn`).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jointfit_core.cluster_turn import TURN_SD_MAX_DEG, weakest_turn_sd_deg
from jointfit_core.synthetic import two_segment_motion
from jointfit_ros.inputs import MessageRouter
from jointfit_ros.joint_diagnostics import OK, WARN
from jointfit_ros.params import node_config
from jointfit_ros.raw import pose_array_bytes
from jointfit_ros.runner import JointRunner

NOISE_MM = 0.3


def _line(h: float) -> np.ndarray:
    x = np.array([[-75.0, 0.0, 0.0], [0.0, h, 0.0], [75.0, 0.0, 0.0]])
    return x - x.mean(axis=0)


def test_the_turn_sd_is_the_linearised_rotation_sd_and_ignores_pose_order_and_units() -> None:
    x = _line(1.0)
    # about the line, the inertia is the middle marker's h^2 less the centroid's share: 2/3 h^2
    assert weakest_turn_sd_deg(x, NOISE_MM) == pytest.approx(np.rad2deg(NOISE_MM / np.sqrt(2.0 / 3.0)), rel=1e-9)
    R = Rotation.from_rotvec([0.4, -1.2, 2.0]).as_matrix()
    moved = x[[2, 0, 1]] @ R.T + np.array([300.0, -40.0, 1000.0])
    assert weakest_turn_sd_deg(moved / 1000.0, NOISE_MM / 1000.0) == pytest.approx(weakest_turn_sd_deg(x, NOISE_MM))
    assert weakest_turn_sd_deg(np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]), 0.1) == float("inf")


def _runner(h: float, seed: int = 2) -> JointRunner:
    rng = np.random.default_rng(seed)
    motion = dataclasses.replace(two_segment_motion(rng, kind="ball", n_markers=(4, 3)), template_child=_line(h))
    t = np.arange(2400) / 60.0
    yp, yc = motion.markers_at(t)
    noise = np.random.default_rng(100 + seed)
    frames = np.concatenate([yp, yc], axis=1) + noise.normal(0.0, NOISE_MM, (t.size, 7, 3))
    names = ["P1", "P2", "P3", "P4", "C1", "C2", "C3"]
    cfg = node_config({
        "joints": ["hip"], "marker_names": names, "hip.parent_markers": names[:4], "hip.child_markers": names[4:],
        "hip.attachment": "rigid", "hip.window": 3000,
    })
    runner = JointRunner(cfg.joints[0], cfg)
    router = MessageRouter(cfg, [runner])
    for k in range(t.size):
        router.markers(pose_array_bytes(10**12 + round(t[k] * 1e9), "world", frames[k] / 1000.0))
        if k % 60 == 59:
            runner.estimate(force=True)
    return runner


def test_a_cluster_nearly_on_a_line_warns_and_a_spread_one_does_not() -> None:
    bad = _runner(1.0)  # 21 deg per frame: measured mean e/3 4.5 on this seed
    status = bad.status()
    assert status.level == WARN and "markers lie nearly on a line" in status.message, status.message
    turned = float(status.message.split("+-")[1].split(" deg")[0])
    assert TURN_SD_MAX_DEG < 10.0 < turned < 30.0, turned  # the noise estimate, not the simulated 0.3 mm: ~16-21
    good = _runner(15.0)  # 1.4 deg
    assert good.status().level == OK, good.status().message
