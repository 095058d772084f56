"""The node's input status and its freeze / save services, without ROS (:mod:`jointfit_ros.input_status`,
:mod:`jointfit_ros.node_services`).

Fed through the message router as the node feeds it: malformed messages and frames that never
arrive make the input WARN and say why, silence makes it STALE, and the services name every joint
(one that cannot freeze, one without a calibration file) instead of failing as a whole.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers import fake_rig_values

from jointfit_ros.fake_mocap import frame_at, make_rigs
from jointfit_ros.frame_load import FrameLoad
from jointfit_ros.input_status import InputStatus
from jointfit_ros.inputs import MessageRouter
from jointfit_ros.joint_diagnostics import OK, STALE, WARN
from jointfit_ros.node_services import freeze_joints, save_joints
from jointfit_ros.params import node_config
from jointfit_ros.raw import pose_array_bytes
from jointfit_ros.runner import JointRunner

T0 = 1_000_000_000_000
RATE = 100.0


def _router(**extra: object) -> tuple[MessageRouter, list[JointRunner]]:
    cfg = node_config(fake_rig_values(**extra))
    runners = [JointRunner(j, cfg) for j in cfg.joints]
    return MessageRouter(cfg, runners), runners


def _raw(rigs: object, k: int) -> bytes:
    rng = np.random.default_rng(k)
    return pose_array_bytes(T0 + round(k / RATE * 1e9), "world", frame_at(rigs, k / RATE, rng, 0.0005, 0.0))  # type: ignore[arg-type]


def test_the_input_status_says_waiting_receiving_missed_and_stale() -> None:
    router, _ = _router(stale_after=2.0)
    status = InputStatus()
    values: dict[str, object] = {}
    level, message = status.status(0.0, router.counters, router.gaps, router.cfg, values)
    assert level == OK and message == "waiting for markers" and values["messages"] == 0
    rigs = make_rigs(0)
    for k in range(330):
        if not 230 <= k < 260:  # 30 frames (0.3 s, shorter than a pause; after the period is known) never arrive
            router.markers(_raw(rigs, k))
    router.markers(b"\x00\x01garbage")
    values = {}
    level, message = status.status(1.0, router.counters, router.gaps, router.cfg, values)
    assert level == WARN
    assert message.startswith("receiving; 1 malformed messages dropped")
    assert "30 of the last 330 frames never arrived" in message, message
    assert values["malformed messages"] == 1 and values["frames missed (gaps in the stamps)"] == 30
    level, message = status.status(4.0, router.counters, router.gaps, router.cfg, {})  # silent for 3 s > stale_after
    assert level == STALE and message.startswith("no messages for 3.0 s")


def _missing_frames(load: FrameLoad | None, per_message: float = 0.0) -> tuple[int, str, dict[str, object]]:
    """The input status after 300 frames of the fake rigs at 100 Hz, every 4th of the last 100 lost.

    Each message received is timed at ``per_message`` seconds (with a load); ticks at 0 s and 3 s.
    """
    router, _ = _router()
    status = InputStatus()
    status.status(0.0, router.counters, router.gaps, router.cfg, {}, load=load)
    rigs = make_rigs(0)
    for k in range(300):
        if k < 200 or k % 4 != 3:
            router.markers(_raw(rigs, k))
            if load is not None:
                load.add(per_message)
    values: dict[str, object] = {}
    level, message = status.status(3.0, router.counters, router.gaps, router.cfg, values, load=load)
    return level, message, values


def test_frames_that_never_arrived_are_blamed_on_the_node_only_when_it_was_busy() -> None:
    """9.5 ms per 10 ms frame: the node's; 0.2 ms: the network's or the driver's; not timed: either."""
    level, message, values = _missing_frames(FrameLoad(), 0.0095)
    assert level == WARN and "the node is not keeping up: a message takes it 9.50 ms (2 joints)" in message, message
    assert "the stream sends one every 10.00 ms" in message and "give part of the joints to a second node" in message
    assert values["time per input message in the node (ms)"] == 9.5
    assert values["node busy with input messages (%)"] == pytest.approx(100.0 * 275 * 0.0095 / 3.0, abs=0.05)
    level, message, values = _missing_frames(FrameLoad(), 0.0002)
    assert level == WARN and "the node had time for them (busy with messages 2 % of the time, 0.20 ms each)" in message
    assert message.endswith("the network or the driver drops them"), message
    level, message, values = _missing_frames(None)
    assert level == WARN and message.endswith("the node is not keeping up, or the network or the driver drops them")
    assert "node busy with input messages (%)" not in values


def test_the_frame_load_is_the_recent_share_of_time_in_the_callbacks() -> None:
    load = FrameLoad()
    assert load.sample(0.0, 5.0) == (None, None)  # the first tick: nothing to compare with
    for _ in range(100):
        load.add(0.002)
    per_frame, busy = load.sample(1.0, 5.0)
    assert per_frame == pytest.approx(0.002) and busy == pytest.approx(0.2)
    # no frame in the second second: the share over both (the ticks of the last 5 s)
    assert load.sample(2.0, 5.0) == (pytest.approx(0.002), pytest.approx(0.1))
    load.sample(3.0, 5.0)
    for _ in range(10):
        load.add(0.05)
    per_frame, busy = load.sample(9.0, 5.0)  # ticks 0-2 left the last 5 s: from the tick at 3 s
    assert per_frame == pytest.approx(0.05) and busy == pytest.approx(0.5 / 6.0)


def test_freeze_and_save_name_every_joint(tmp_path: Path) -> None:
    router, runners = _router(**{"hip.calibration_file": str(tmp_path / "hip.yaml")})
    ok, message = freeze_joints(runners, True)  # nothing estimated yet: neither joint can freeze
    assert not ok and "hip: cannot freeze" in message and "knee: cannot freeze" in message
    ok, message = save_joints(runners, None)
    assert not ok and "knee: no calibration_file configured" in message and "hip: not saved" in message
    rigs = make_rigs(0)
    for k in range(600):
        router.markers(_raw(rigs, k))
    for r in runners:
        assert r.estimate(force=True), r.last_error
    ok, message = save_joints(runners, None)
    assert ok and f"hip: saved {tmp_path / 'hip.yaml'}" in message and (tmp_path / "hip.yaml").exists()
    ok, message = freeze_joints(runners, True)
    assert ok and all(r.estimator.frozen for r in runners), message


def test_rviz_markers_are_an_ellipsoid_and_for_a_hinge_an_arrow() -> None:
    import dataclasses

    from jointfit_core.joint_world import JointOutput
    from jointfit_ros.rviz_output import joint_markers

    cov = np.diag([4e-6, 1e-6, 9e-6])
    ball = JointOutput("ball", np.array([1.0, 2.0, 0.5]), cov, None, None, float("nan"))
    hinge = dataclasses.replace(ball, kind="hinge", direction=np.array([0.0, 0.0, 1.0]), cov_direction=np.eye(3) * 1e-4)
    (ellipsoid,) = joint_markers("hip", 3, T0, "world", ball, 2.0, 5.0, 0.3)
    assert ellipsoid.ns == "hip/covariance" and ellipsoid.id == 3 and ellipsoid.header.frame_id == "world"
    np.testing.assert_allclose([ellipsoid.pose.position.x, ellipsoid.pose.position.y], [1.0, 2.0])
    # 2 sd of sd (2, 1, 3) mm: diameters 8, 4, 12 mm in some order
    np.testing.assert_allclose(sorted([ellipsoid.scale.x, ellipsoid.scale.y, ellipsoid.scale.z]), [0.004, 0.008, 0.012])
    assert ellipsoid.lifetime.sec * 10**9 + ellipsoid.lifetime.nanosec == 400_000_000  # two periods at 5 Hz
    markers = joint_markers("knee", 4, T0, "world", hinge, 2.0, 5.0, 0.3)
    assert [m.ns for m in markers] == ["knee/covariance", "knee/axis"]
