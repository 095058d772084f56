"""A frozen chained joint whose chain joint has no output says it waits for that joint.

A knee whose parent segment is two thigh markers and the hip centre (``knee.parent_chain: [hip]``)
cannot be posed while the hip publishes nothing, e.g. the hip's calibration was withheld because the
pelvis cluster was put back elsewhere. Before, the knee's status stayed OK "frozen" for the whole
session while every frame was dropped as ``parent_not_posed`` (the hunt of 2026-12-06, hunt-calib2).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from jointfit_core.synthetic import TwoSegmentMotion, two_segment_motion
from jointfit_ros.inputs import MessageRouter
from jointfit_ros.joint_diagnostics import WARN
from jointfit_ros.params import node_config
from jointfit_ros.raw import pose_array_bytes
from jointfit_ros.runner import JointRunner

NAMES = ["P1", "P2", "P3", "T1", "T2", "T3", "S1", "S2", "S3"]
RATE = 100.0
AXIS = np.array([1.0, 0.2, 0.0]) / np.linalg.norm([1.0, 0.2, 0.0])


def _leg(hip: TwoSegmentMotion, t: np.ndarray, seed: int) -> np.ndarray:
    """Pelvis, thigh (the hip's rig) and a shank hinged 420 mm below the hip centre (mm), 0.5 mm noise."""
    rng = np.random.default_rng(seed)
    _, _, R_th, d_th = hip.poses_at(t)
    pelvis, thigh = hip.markers_at(t)
    knee = hip.centre_child + np.array([0.0, 0.0, -420.0])
    shank_local = knee + np.array([[40.0, 60.0, -150.0], [-50.0, 40.0, -250.0], [30.0, -60.0, -320.0]])
    angle = 0.9 * np.sin(2 * np.pi * 0.4 * t + 0.3) - 0.4
    R_knee = Rotation.from_rotvec(angle[:, None] * AXIS).as_matrix()
    local = np.einsum("nij,pj->npi", R_knee, shank_local - knee) + knee
    shank = np.einsum("nij,npj->npi", R_th, local) + d_th[:, None, :]
    return np.concatenate([pelvis, thigh, shank], axis=1) + rng.normal(0.0, 0.5, (t.size, 9, 3))


def _feed(router: MessageRouter, runners: list[JointRunner], frames: np.ndarray, t: np.ndarray, solve: bool) -> None:
    for k, frame in enumerate(frames):
        router.markers(pose_array_bytes(int(1e9 + round(t[k] * 1e9)), "world", frame))
        if solve and k % 10 == 9:
            for r in runners:
                r.estimate()


def test_a_frozen_chain_knee_whose_hip_is_withheld_says_it_waits_for_the_hip(tmp_path: Path) -> None:
    cfg = node_config({
        "joints": ["hip", "knee"], "marker_names": NAMES, "units": "mm",
        "hip.type": "ball", "hip.parent_markers": ["P1", "P2", "P3"], "hip.child_markers": ["T1", "T2", "T3"],
        "hip.template_frames": 20, "hip.attachment": "rigid", "hip.calibration_file": str(tmp_path / "hip.yaml"),
        "knee.type": "hinge", "knee.parent_markers": ["T1", "T2"], "knee.parent_chain": ["hip"],
        "knee.child_markers": ["S1", "S2", "S3"], "knee.template_frames": 20, "knee.attachment": "rigid",
        "knee.calibration_file": str(tmp_path / "knee.yaml"),
    })
    hip = two_segment_motion(np.random.default_rng(2), kind="ball", n_markers=(3, 3))
    t = np.arange(3000) / RATE
    runners = [JointRunner(j, cfg) for j in cfg.joints]
    router = MessageRouter(cfg, runners)
    _feed(router, runners, _leg(hip, t, 2), t, solve=True)
    for r in runners:
        assert r.estimate(force=True) and r.freeze(True) and r.save()
    # a later session: the pelvis cluster put back 20 mm away; the calibrations loaded from their files
    moved = dataclasses.replace(hip, template_parent=hip.template_parent + np.array([20.0, 0.0, 0.0]))
    t2 = 300.0 + np.arange(600) / RATE
    runners = [JointRunner(j, cfg) for j in cfg.joints]
    router = MessageRouter(cfg, runners)
    _feed(router, runners, _leg(moved, t2, 7), t2, solve=False)
    hip_runner, knee_runner = runners
    assert "no longer fits the joint" in hip_runner.status().message
    knee = knee_runner.status()
    assert knee_runner.counters["outputs"] == 0
    assert knee.level == WARN and "per-frame output of hip as a marker, and hip has none" in knee.message, knee
