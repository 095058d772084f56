"""Unlabelled clouds are bounded: a flood of points is dropped and counted, and the tracking goes on."""

from __future__ import annotations

import numpy as np
from helpers import fake_rig_values

from jointfit_ros.fake_mocap import frame_at, make_rigs
from jointfit_ros.inputs import MessageRouter
from jointfit_ros.params import node_config
from jointfit_ros.raw import pointcloud2_bytes
from jointfit_ros.runner import JointRunner


def test_a_flood_of_points_is_dropped_and_tracking_recovers() -> None:
    cfg = node_config(fake_rig_values(marker_type="pointcloud2", unlabelled=True, assignment_gate=0.05,
                                      max_cloud_points=500))
    router = MessageRouter(cfg, [JointRunner(j, cfg) for j in cfg.joints])
    rigs = make_rigs(2)
    rng = np.random.default_rng(2)
    truth = []
    for k in range(1200):
        frame = frame_at(rigs, k / 100.0, rng, 0.5, 0.0) / 1000.0
        truth.append(frame)
        points = frame if k == 0 else frame[rng.permutation(frame.shape[0])]
        if k == 600:
            flood = rng.uniform(-5.0, 5.0, (100_000, 3))
            router.markers(pointcloud2_bytes(10**18 + k * 10**7 - 5 * 10**6, "world", flood))
        router.markers(pointcloud2_bytes(10**18 + k * 10**7, "world", points))
        if k % 50 == 49:
            for r in router.runners:
                r.estimate(force=True)
    assert router.counters["oversized_clouds"] == 1 and router.counters["malformed"] == 0
    assert router.last_problem is not None and "100000 points" in router.last_problem[1]
    # the prediction was not touched by the flood: the last cloud is labelled exactly
    assert router.parser.last_frame is not None
    assert np.abs(router.parser.last_frame - truth[-1]).max() < 1e-5
    hip = router.runners[0]
    assert hip.counters["outputs"] > 900
