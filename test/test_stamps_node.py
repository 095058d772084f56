"""Bad stamps, looped replays and silence, through the node in its own process (issue 15, items 5 and 6).

The hip starts frozen from a calibration file (made here without ROS), the
knee estimates with a 2 s stamp-time window. A user meets: one message
stamped 2^31-1 s, or with nanosec 0xFFFFFFFF, or both, in a good stream; a
replay that jumps back to its start; a stream that stops; a stream whose
frames are all dropped. The node must go on publishing, count what it
dropped, and say in /diagnostics what is going on.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("rclpy")

from geometry_msgs.msg import PoseArray
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from test_node import RATE, _Client, _start_node, _stop

from jointfit_ros.conversions import pose_array_bytes
from jointfit_ros.fake_mocap import frame_at, make_rigs, marker_names
from jointfit_ros.inputs import MessageRouter
from jointfit_ros.params import node_config, params_from_file
from jointfit_ros.runner import OK, STALE, WARN, JointRunner
from jointfit_ros.timeline import RESTART_FRAMES

pytestmark = pytest.mark.ros

S = 1_000_000_000
T0 = 1000.0  # stamp (s) of the stream's time 0
PERIOD = 1.0 / RATE


def _params(tmp_path: Path) -> Path:
    path = tmp_path / "params.yaml"
    path.write_text(f"""jointfit:
  ros__parameters:
    joints: [hip, knee]
    marker_names: [{", ".join(marker_names(0))}]
    estimate_period: 0.05
    diagnostics_period: 0.2
    stale_after: 1.0
    qos_reliability: reliable  # the single bad messages must arrive to be counted (best effort may drop them)
    hip:
      type: ball
      parent_markers: [PELV1, PELV2, PELV3, PELV4]
      child_markers: [THIGH1, THIGH2, THIGH3, THIGH4]
      template_frames: 30
      calibration_file: "{tmp_path / "hip.yaml"}"
    knee:
      type: hinge
      parent_markers: [FEMUR1, FEMUR2, FEMUR3, FEMUR4]
      child_markers: [SHANK1, SHANK2, SHANK3, SHANK4]
      template_frames: 30
      window_s: 2.0
""")
    return path


def _frame(rigs: Any, rng: np.random.Generator, t: float) -> np.ndarray:
    return frame_at(rigs, t, rng, 0.5, 0.0) / 1000.0


def _hip_calibration(params: Path, rigs: Any) -> None:
    """The hip's calibration file, from 8 s of the stream fitted without ROS: the node starts with it frozen."""
    cfg = node_config(params_from_file(params))
    hip = JointRunner(cfg.joints[0], cfg)
    router = MessageRouter(cfg, [hip])
    rng = np.random.default_rng(1)
    router.markers_many([pose_array_bytes(int(k * PERIOD * S), "world", _frame(rigs, rng, k * PERIOD)) for k in range(2000)])
    assert hip.estimate(force=True)
    hip.freeze(True)
    hip.save()


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[tuple[_Client, Any, Any]]:
    """The client, the rigs and the running node (hip frozen from its calibration, knee estimating)."""
    params = _params(tmp_path)
    rigs = make_rigs(11)
    _hip_calibration(params, rigs)
    client = _Client()
    # reliable, as the node's subscription here: each bad message is sent once and must be counted (in place of
    # the client's best-effort publisher: two publishers of the marker topic are a WARN of their own)
    client.node.destroy_publisher(client.pub)
    client.pub = client.node.create_publisher(
        PoseArray, "markers", QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    )
    proc = _start_node(params)
    try:
        assert client.spin_until(lambda: client.pub.get_subscription_count() > 0, 30.0), "node not discovered"
        yield client, rigs, proc
    finally:
        log = _stop(proc)
        client.close()
    assert "Traceback" not in log, log


def _publish(client: _Client, stamp_ns: int, frame: np.ndarray) -> None:
    client.pub.publish(pose_array_bytes(stamp_ns, "world", frame))


def _stream(client: _Client, rigs: Any, t_start: float, seconds: float, stamp: Any = None) -> None:
    """Publish frames at RATE paced by the wall clock, stamped T0 + t (or ``stamp(t)`` ns)."""
    rng = np.random.default_rng(int(t_start * 1000))
    start = time.monotonic()
    for k in range(int(seconds * RATE)):
        t = t_start + k * PERIOD
        _publish(client, int((T0 + t) * S) if stamp is None else stamp(t), _frame(rigs, rng, t))
        client.executor.spin_once(timeout_sec=0.0)
        lag = start + (k + 1) * PERIOD - time.monotonic()
        if lag > 0:
            client.spin_until(lambda: False, lag)


def _warm_up(client: _Client, rigs: Any) -> float:
    """Stream until both joints publish (the knee once solved: the worker process may take a while to start); the time reached."""
    t = 0.0
    while t < 15.0 and not (client.knee and client.hip):
        _stream(client, rigs, t, 0.5)
        t += 0.5
    assert client.knee and client.hip, "no outputs"
    return t


def _second_pass(msgs: list[Any]) -> list[Any]:
    """The outputs from the first whose stamp goes back on (the replay's second pass)."""
    stamps = np.array([_stamp_s(m) for m in msgs])
    back = np.flatnonzero(np.diff(stamps) < 0)
    assert back.size == 1, stamps[back]
    return msgs[int(back[0]) + 1 :]


def _stamp_s(msg: Any) -> float:
    return float(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)


def _level(client: _Client, name: str) -> int | None:
    for arr in reversed(client.diag):
        for st in arr.status:
            if st.name == f"jointfit: {name}":
                return st.level if isinstance(st.level, int) else ord(st.level)
    return None


def _count(client: _Client, name: str, key: str) -> int:
    return int(client.status(name).get(key, "0"))


def _node_counts(client: _Client, name: str) -> tuple[int, int]:
    """(frames received, outputs published) of a joint, or (messages, 0) of the input, from its last status."""
    if name == "input":
        return _count(client, name, "messages"), 0
    return _count(client, name, "frames received"), _count(client, name, "outputs")


def _with_nanosec(raw: bytes, nanosec: int) -> bytes:
    """A message with its header.stamp.nanosec replaced (bytes 8-12: after the encapsulation and sec)."""
    return raw[:8] + nanosec.to_bytes(4, "little") + raw[12:]


def test_bad_stamps_do_not_stop_the_stream_nor_the_node(rig: tuple[_Client, Any, Any]) -> None:
    client, rigs, proc = rig
    t = _warm_up(client, rigs)
    frame = _frame(rigs, np.random.default_rng(0), t)
    _publish(client, (2**31 - 1) * S, frame)  # far ahead: dropped, not adopted
    client.pub.publish(_with_nanosec(pose_array_bytes(int((T0 + t) * S), "world", frame), 0xFFFFFFFF))
    client.pub.publish(_with_nanosec(pose_array_bytes((2**31 - 1) * S, "world", frame), 0xFFFFFFFF))
    _stream(client, rigs, t + PERIOD, 1.0)
    after = T0 + t

    def published_after(msgs: list[Any]) -> int:
        return sum(1 for m in msgs if _stamp_s(m) > after)

    # the frozen hip and the estimating knee publish the good frames after the bad ones (the failure this
    # guards against published 1 frame in 20 s; best-effort frames seen here can be lost on a loaded machine)
    assert client.spin_until(lambda: published_after(client.hip) > 0.5 * RATE, 5.0), published_after(client.hip)
    assert client.spin_until(lambda: published_after(client.knee) > 0.5 * RATE, 5.0), published_after(client.knee)
    assert all(_stamp_s(m) < 2**31 - 1 for m in client.hip + client.knee)  # no output carries the bad stamp
    assert client.spin_until(
        lambda: _count(client, "input", "malformed messages") == 2
        and _count(client, "input", "messages stamped too far ahead (max_stamp_jump)") == 1,
        5.0,
    ), client.status("input")
    assert "bad stamps dropped" in client.status("input")["message"]
    assert client.status("hip")["frozen"] == "True"
    assert _count(client, "knee", "dropped: stamp_not_increasing") == 0
    assert proc.poll() is None, "the node died"


def _input_ok_but_for_lost_frames(client: _Client) -> bool:
    """The input status is OK, or WARN only because best-effort frames were lost on the way.

    On a loaded machine DDS drops some of this test's own best-effort frames before the node sees
    them, and the node then rightly warns "N of the last M frames never arrived" (that warning has
    its own tests: ``test/test_stamp_gaps.py`` and the withheld-frames test below). Any other
    warning (a stamp problem, dropped messages) still fails.
    """
    st = client.status("input")
    if _level(client, "input") == OK:
        return True
    message = st.get("message", "")
    others = ("bad stamps dropped", "were dropped", "no messages")
    return _level(client, "input") == WARN and "never arrived" in message and not any(o in message for o in others)


def test_a_replay_looping_to_its_start_is_followed(rig: tuple[_Client, Any, Any]) -> None:
    client, rigs, proc = rig
    t = _warm_up(client, rigs)
    _stream(client, rigs, t, max(0.0, 2.5 - t))
    assert client.spin_until(lambda: client.status("knee").get("message", "").startswith("estimating"), 10.0), (
        client.status("knee")
    )
    client.spin_until(lambda: False, 0.5)  # a status from after the first pass
    before = {name: _node_counts(client, name) for name in ("hip", "knee", "input")}
    _stream(client, rigs, 0.0, 1.5)  # the bag again from its start: the same stamps
    assert client.spin_until(lambda: _count(client, "input", "timeline restarts") == 1, 5.0), client.status("input")
    assert _level(client, "hip") == OK and _level(client, "knee") == OK, (client.status("hip"), client.status("knee"))
    assert _input_ok_but_for_lost_frames(client), client.status("input")
    client.spin_until(lambda: False, 0.5)  # the last outputs in, and a status from after the replay
    replay_hip, replay_knee = _second_pass(client.hip), _second_pass(client.knee)
    # recognised within a few frames: the frozen hip publishes from then on, with the replay's own stamps
    assert replay_hip and _stamp_s(replay_hip[0]) <= T0 + (RESTART_FRAMES + 2) * PERIOD, _stamp_s(replay_hip[0])
    # In the node: an output for every replayed frame it received, but the few before the restart was recognised.
    # The frames and outputs lost on the way (keep-last queues on a loaded machine) are counted apart, each < 10 %.
    sent = int(1.5 * RATE)
    received = _node_counts(client, "input")[0] - before["input"][0]
    assert sent - received <= 0.1 * sent, (sent, received)  # (a machine that loses more is too loaded for this test)
    for name, outputs in (("hip", replay_hip), ("knee", replay_knee)):
        frames, published = (now - was for now, was in zip(_node_counts(client, name), before[name], strict=True))
        assert frames == received, (name, frames, received)
        assert published >= frames - RESTART_FRAMES - 1, (name, published, frames)
        assert published >= len(outputs) >= 0.9 * published, (name, len(outputs), published)
    # the knee goes on estimating: its 2 s window slid on over the loop (it holds frames of both passes)
    client.spin_until(lambda: False, 0.3)  # a status from after the stream
    knee = client.status("knee")
    assert "estimating" in knee["message"], knee
    assert 1.8 * RATE <= int(knee["frames in window"]) <= 2.0 * RATE + 1, knee
    assert int(knee.get("dropped: stamp_not_increasing", "0")) <= RESTART_FRAMES - 1, knee
    assert proc.poll() is None


def test_silence_is_stale_and_all_dropped_is_not_ok(rig: tuple[_Client, Any, Any]) -> None:
    client, rigs, proc = rig
    t = _warm_up(client, rigs)
    _stream(client, rigs, t, 0.5)
    assert client.spin_until(lambda: _level(client, "hip") == OK and float(client.status("hip")["input rate (Hz)"]) > 100, 5.0)
    # every frame dropped: the same stamp over and over
    _stream(client, rigs, t + 0.5, 1.0, stamp=lambda _: int((T0 + t) * S))
    assert client.spin_until(lambda: _level(client, "hip") == WARN, 3.0), client.status("hip")
    assert "stamp_not_increasing" in client.status("hip")["message"]
    # then nothing: STALE after stale_after (1 s), the rates fall to 0
    client.diag.clear()
    assert client.spin_until(lambda: _level(client, "hip") == STALE and _level(client, "knee") == STALE, 4.0)
    assert client.spin_until(lambda: _level(client, "input") == STALE, 2.0), client.status("input")
    assert client.status("hip")["message"].startswith("no input for")
    assert client.spin_until(lambda: float(client.status("hip")["input rate (Hz)"]) == 0.0, 3.0)
    assert float(client.status("input")["input rate (Hz)"]) == 0.0
    assert proc.poll() is None


def test_frames_that_never_arrive_are_counted_and_warned(rig: tuple[_Client, Any, Any]) -> None:
    client, rigs, proc = rig
    t = _warm_up(client, rigs)
    _stream(client, rigs, t, 2.0)  # the period is known after 200 frames
    assert client.spin_until(lambda: "frames missed (gaps in the stamps)" in client.status("input"), 3.0)
    client.spin_until(lambda: False, 0.5)  # a status after the last frame (stamps go on where they stopped)
    missed_before = _count(client, "input", "frames missed (gaps in the stamps)")
    assert "messages" in client.status("input")
    received_before = _count(client, "input", "messages")
    # every 4th frame lost on the way (as when the node or the network cannot keep up)
    t += 2.0
    rng = np.random.default_rng(4)
    start = time.monotonic()
    for k in range(int(2.0 * RATE)):
        tk = t + k * PERIOD
        if k % 4 != 3:
            _publish(client, int((T0 + tk) * S), _frame(rigs, rng, tk))
        client.executor.spin_once(timeout_sec=0.0)
        lag = start + (k + 1) * PERIOD - time.monotonic()
        if lag > 0:
            client.spin_until(lambda: False, lag)
    assert client.spin_until(lambda: "never arrived" in client.status("input").get("message", ""), 3.0), (
        client.status("input")
    )
    assert _level(client, "input") == WARN
    # the node had time for every frame: it blames the way there, not itself (its input callbacks are timed)
    status = client.status("input")
    assert "the node had time for them" in status["message"] and "the network or the driver drops them" in status["message"]
    assert float(status["node busy with input messages (%)"]) < 50.0 and float(status["time per input message in the node (ms)"]) > 0.0
    client.spin_until(lambda: False, 0.5)  # a status after the last frame
    missed = _count(client, "input", "frames missed (gaps in the stamps)") - missed_before
    # frames a loaded machine loses on its own (best effort) are missed too: the count must cover exactly those
    lost = int(2.0 * RATE) - int(2.0 * RATE) // 4 - (_count(client, "input", "messages") - received_before)
    assert 0 <= lost <= 0.1 * RATE * 2.0, lost  # (a machine that loses more is too loaded for this test)
    assert 0.8 * RATE * 2.0 / 4 <= missed <= RATE * 2.0 / 4 + lost + 5, (missed, lost)
    assert proc.poll() is None


def test_joint_states_carry_the_frozen_and_the_estimating_joint(rig: tuple[_Client, Any, Any]) -> None:
    """~/joint_states from the node's own process: hip_x/_y/_z (frozen ball) and knee (estimating hinge), stamped."""
    client, rigs, _ = rig
    states: list[JointState] = []
    client.node.create_subscription(JointState, "/jointfit/joint_states", states.append, 1000)
    t = _warm_up(client, rigs)
    _stream(client, rigs, t + PERIOD, 2.0)
    assert client.spin_until(lambda: sum("knee" in m.name for m in states) > 20, 5.0), len(states)
    assert {"hip_x", "hip_y", "hip_z", "knee"} <= {n for m in states for n in m.name}
    knee = np.array([m.position[list(m.name).index("knee")] for m in states if "knee" in m.name])
    assert np.isfinite(knee).all() and np.ptp(knee) > 0.1  # rad: the fake knee flexes over 2 s
    assert all(_stamp_s(m) >= T0 for m in states)  # the input stamps


def test_robot_description_of_the_frozen_joint_is_latched(rig: tuple[_Client, Any, Any], tmp_path: Path) -> None:
    """~/robot_description (transient local): the hip, frozen from its file at start, as a URDF a late subscriber gets."""
    client, rigs, _ = rig
    _warm_up(client, rigs)
    texts: list[String] = []
    latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
    client.node.create_subscription(String, "/jointfit/robot_description", texts.append, latched)
    assert client.spin_until(lambda: bool(texts), 10.0), client.status("input")
    yourdfpy = pytest.importorskip("yourdfpy")
    (tmp_path / "subject.urdf").write_text(texts[-1].data)
    robot = yourdfpy.URDF.load(str(tmp_path / "subject.urdf"))
    assert {"hip_x", "hip_y", "hip_z"} <= set(robot.joint_map) and "knee" not in robot.joint_map  # knee: estimating
    assert client.status("input")["robot description"] == "published (1 frozen joints)"
