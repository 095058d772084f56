"""Input mistakes the node names: an unlabelled stream must start ordered (the fake mocap does), a scrambled start
is named in the joints' statuses, and zeros taken as positions are named in the input status.

Before, ``jointfit_fake_mocap --format pointcloud2_unlabelled`` shuffled every cloud, the first too, so it
could never drive a node (every identity scrambled), and the joints said only "no relative rotation
beyond the pose noise ... move the joint" (the hunt of 2026-12-03, D4).
"""

from __future__ import annotations

import numpy as np
from helpers import fake_rig_values

from jointfit_ros.fake_mocap import ORDERED_START_S, frame_at, make_rigs, marker_message, truth_at
from jointfit_ros.inputs import MessageRouter
from jointfit_ros.params import node_config
from jointfit_ros.raw import parse_pointcloud2
from jointfit_ros.runner import JointRunner

RATE = 100.0


def _run(skip: int, ordered_start: bool) -> tuple[MessageRouter, list[float]]:
    """The fake mocap's unlabelled stream (2 % occlusion past its ordered start) into a router, the first
    ``skip`` clouds lost; the hip's per-frame sqrt(e' C^-1 e) against the truth."""
    cfg = node_config(fake_rig_values(marker_type="pointcloud2", unlabelled=True, assignment_gate=0.05))
    router = MessageRouter(cfg, [JointRunner(j, cfg) for j in cfg.joints])
    rigs = make_rigs(4)
    rng = np.random.default_rng(4)
    z = []
    for k in range(1500):
        t = k / RATE
        ordered = ordered_start and t < ORDERED_START_S
        frame = frame_at(rigs, t, rng, 0.5, 0.0 if ordered else 0.02) / 1000.0
        raw = marker_message("pointcloud2_unlabelled", False, 10**18 + k * 10**7, "world", frame, rng, ordered)
        if k < skip:
            continue
        for routed in router.markers(raw):
            if routed.runner.cfg.name == "hip":
                e = routed.output.position - truth_at(rigs, t).centres["hip"] / 1000.0
                z.append(float(np.sqrt(e @ np.linalg.solve(routed.output.cov, e))))
        if k % 50 == 49:
            for r in router.runners:
                r.estimate(force=True)
    return router, z


def test_the_fake_mocaps_unlabelled_start_is_complete_and_ordered() -> None:
    frame = frame_at(make_rigs(0), 0.0, np.random.default_rng(0), 0.5, 0.0)
    rng = np.random.default_rng(1)
    ordered = parse_pointcloud2(marker_message("pointcloud2_unlabelled", False, 1, "world", frame.copy(), rng, True))
    np.testing.assert_allclose(ordered.points, frame, rtol=0, atol=1e-3)  # float32 on the wire
    shuffled = parse_pointcloud2(marker_message("pointcloud2_unlabelled", False, 1, "world", frame.copy(), rng, False))
    assert not np.allclose(shuffled.points, frame, atol=1e-3)


def test_an_unlabelled_stream_that_starts_ordered_drives_the_joints_even_with_its_first_clouds_lost() -> None:
    _, z = _run(skip=20, ordered_start=True)
    assert len(z) > 1000
    assert np.mean(np.asarray(z) > 5.0) < 0.01


def test_a_scrambled_first_cloud_is_named_in_the_joints_statuses() -> None:
    router, z = _run(skip=0, ordered_start=False)
    assert z == []  # nothing published: no segment is rigid
    for r in router.runners:
        message = r.status().message
        assert "learnt from the first complete cloud" in message and "~/reset" in message, message


def test_markers_at_the_origin_with_zero_is_missing_false_are_named_in_the_input_status() -> None:
    """A driver that sends occluded markers as (0, 0, 0) into ``zero_is_missing: false`` (hunt D5): before, the
    joints blamed swapped labels, ghosts or jumps, and nothing said that markers sat at the origin."""
    from jointfit_ros.input_status import InputStatus
    from jointfit_ros.joint_diagnostics import WARN
    from jointfit_ros.raw import pose_array_bytes

    statuses = []
    for zero_is_missing in (True, False):
        cfg = node_config(fake_rig_values(zero_is_missing=zero_is_missing))
        router = MessageRouter(cfg, [JointRunner(j, cfg) for j in cfg.joints])
        rigs = make_rigs(4)
        rng = np.random.default_rng(4)
        for k in range(300):
            frame = frame_at(rigs, k / RATE, rng, 0.5, 0.1) / 1000.0
            frame[np.isnan(frame[:, 0])] = 0.0
            router.markers(pose_array_bytes(10**18 + k * 10**7, "world", frame))
        values: dict[str, object] = {}
        statuses.append((InputStatus().status(0.0, router.counters, router.gaps, router.cfg, values), values))
    (level, message), values = statuses[0]
    assert "(0, 0, 0)" not in message and values["markers at exactly (0, 0, 0) (zero_is_missing false)"] == 0
    (level, message), values = statuses[1]
    assert level == WARN and "taken as positions (zero_is_missing is false)" in message, message
    assert 300 <= int(values["markers at exactly (0, 0, 0) (zero_is_missing false)"]) <= 700  # 10 % of 16 x 300


def test_a_chained_joint_whose_chain_has_no_output_says_so() -> None:
    """Before: "building templates from fully visible frames: parent 0/20" and nothing about the chain (hunt)."""
    cfg = node_config(fake_rig_values(**{"knee.parent_chain": ["hip"]}))
    runners = [JointRunner(j, cfg) for j in cfg.joints]
    router = MessageRouter(cfg, runners)
    rigs = make_rigs(4)
    rng = np.random.default_rng(4)
    for k in range(300):  # a still recording: the hip is never identifiable, so it has no output
        frame = frame_at(rigs, 0.0, rng, 0.5, 0.0) / 1000.0
        router.markers(pose_array_bytes_for(k, frame))
        if k % 50 == 49:
            for r in runners:
                r.estimate(force=True)
    hip, knee = runners
    assert hip.estimator.solution is None or not hip.estimator.solution.identifiable
    waiting = knee.waiting()
    assert waiting.startswith("building templates") and "outputs of hip as markers" in waiting, waiting
    assert "outputs of hip as markers" in knee.live_status(0.0).message
    assert hip.waiting() == hip.estimator.status()  # not chained: the estimator's own words


def pose_array_bytes_for(k: int, frame: np.ndarray) -> bytes:
    from jointfit_ros.raw import pose_array_bytes

    return pose_array_bytes(10**18 + k * 10**7, "world", frame)
