"""``python -m jointfit_ros.replay`` in its own process, received by a raw subscriber in the test process.

A synthetic recording (jointfit_ros.fake_mocap, 600 frames at 200 Hz, metres,
with occlusions) is written as a rosbag2 bag; the replay must deliver every
message in order, byte for byte, with the recorded header stamps, at the
recorded timing divided by ``--rate``.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("rosbags.rosbag2")

import rclpy
from bagtools import write_marker_bag, write_raw_bag
from geometry_msgs.msg import PoseArray, PoseStamped
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import PointCloud2

from jointfit_ros.bag import iter_bag_messages
from jointfit_ros.fake_mocap import frame_at, make_rigs
from jointfit_ros.raw import parse_pointcloud2, parse_pose_array, parse_pose_stamped
from jointfit_ros.replay import replay_main

pytestmark = pytest.mark.ros

DOMAIN = 150 + os.getpid() % 50
ENV = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": str(DOMAIN)}
RATE_HZ = 200.0
N = 600
T0_NS = 1_700_000_000_000_000_000


def _recording(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(N, 16, 3) marker frames in metres (NaN = occluded) and their stamps (ns), 200 Hz."""
    rigs = make_rigs(seed)
    rng = np.random.default_rng(seed + 1)
    frames = np.stack([frame_at(rigs, k / RATE_HZ, rng, 0.5, 0.05) for k in range(N)]) / 1000.0
    stamps = T0_NS + np.round(np.arange(N) * 1e9 / RATE_HZ).astype(np.int64)
    return frames, stamps


class _Receiver:
    """Raw, reliable keep-all subscriptions in the test process (own context)."""

    def __init__(self, topics: dict[str, Any]) -> None:
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=DOMAIN)
        self.node = Node("replay_test_receiver", context=self.context)
        self.executor = rclpy.executors.SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
        self.got: list[tuple[str, float, bytes]] = []
        for topic, msg_type in topics.items():
            self.node.create_subscription(msg_type, topic, self._callback(topic), qos, raw=True)

    def _callback(self, topic: str) -> Any:
        def callback(raw: bytes) -> None:
            self.got.append((topic, time.monotonic(), raw))

        return callback

    def spin_while(self, proc: subprocess.Popen[str], expected: int, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        after_exit: float | None = None
        while time.monotonic() < deadline and len(self.got) < expected:
            self.executor.spin_once(timeout_sec=0.01)
            if proc.poll() is not None:
                after_exit = after_exit or time.monotonic()
                if time.monotonic() - after_exit > 2.0:
                    break

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


@pytest.fixture
def receiver_factory(monkeypatch: pytest.MonkeyPatch) -> Iterator[Any]:
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    made: list[_Receiver] = []

    def make(topics: dict[str, Any]) -> _Receiver:
        made.append(_Receiver(topics))
        return made[-1]

    yield make
    for r in made:
        r.close()


def _replay(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "jointfit_ros.replay", *args],
        env=ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _finish(proc: subprocess.Popen[str]) -> tuple[int, str, str]:
    """(exit status, our stdout lines, stderr); Fast DDS may log its own lines on stdout, dropped here."""
    try:
        out, err = proc.communicate(timeout=10.0)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
    ours = "".join(line for line in out.splitlines(keepends=True) if line.startswith("jointfit replay"))
    return proc.returncode, ours, err


def test_replay_round_trip_timed(tmp_path: Path, receiver_factory: Any) -> None:
    """Every message, in order, same bytes and stamps; timing = recording / rate."""
    frames, stamps = _recording()
    bag = write_marker_bag(tmp_path / "bag", frames, stamps, storage="mcap")
    expected = [m.raw for m in iter_bag_messages(bag, ["markers"])]
    rx = receiver_factory({"/markers": PoseArray})
    proc = _replay(str(bag), "--rate", "2", "--reliable", "--wait-subscribers", "1")
    rx.spin_while(proc, N, timeout_s=15.0)
    code, out, err = _finish(proc)
    assert code == 0, err
    assert out.startswith("jointfit replay: published 600 messages on 1 topic in "), out
    assert len(out.strip().splitlines()) == 1
    raws = [raw for _, _, raw in rx.got]
    assert len(raws) == N
    assert raws == expected  # same order, same bytes
    for k, raw in enumerate(raws[:: N // 20]):
        msg = parse_pose_array(raw)
        assert msg.stamp_ns == stamps[k * (N // 20)]
        assert np.array_equal(msg.points, frames[k * (N // 20)], equal_nan=True)
    assert [parse_pose_array(raw).stamp_ns for raw in raws] == stamps.tolist()
    # timing: the recording lasts (N - 1) / 200 s; at rate 2 half of it (loose: scheduler and executor jitter)
    t = np.array([t for _, t, _ in rx.got])
    span = t[-1] - t[0]
    nominal = (N - 1) / RATE_HZ / 2.0
    assert 0.9 * nominal < span < 1.25 * nominal, (span, nominal)
    half = N // 2  # uniform pacing, not a burst: the middle message arrives about mid-way
    assert abs((t[half] - t[0]) - nominal * half / (N - 1)) < 0.15 * nominal


def test_replay_every_topic(tmp_path: Path, receiver_factory: Any) -> None:
    """sqlite3, labelled PointCloud2 + PoseStamped on two topics, --rate 4: reliable loses nothing."""
    frames, stamps = _recording(3)
    rng = np.random.default_rng(7)
    R, d = Rotation.random(N, random_state=rng).as_matrix(), rng.normal(0.0, 1.0, (N, 3))
    bag = write_marker_bag(
        tmp_path / "bag",
        frames,
        stamps,
        storage="sqlite3",
        msgtype="pointcloud2",
        pose_topics={"tracker/pose": (R, d)},
    )
    rx = receiver_factory({"/markers": PointCloud2, "/tracker/pose": PoseStamped})
    proc = _replay(str(bag), "--rate", "4", "--reliable", "--wait-subscribers", "1")
    rx.spin_while(proc, 2 * N, timeout_s=15.0)
    code, out, err = _finish(proc)
    assert code == 0, err
    assert "published 1200 messages on 2 topics" in out and "rate 4" in out
    clouds = [raw for topic, _, raw in rx.got if topic == "/markers"]
    poses = [raw for topic, _, raw in rx.got if topic == "/tracker/pose"]
    assert len(clouds) == N and len(poses) == N
    assert [parse_pointcloud2(raw).stamp_ns for raw in clouds] == stamps.tolist()
    assert [parse_pose_stamped(raw).stamp_ns for raw in poses] == stamps.tolist()
    assert all(
        np.array_equal(parse_pointcloud2(raw, label_field="label").points, frames[k], equal_nan=True)
        for k, raw in enumerate(clouds)
    )
    assert all(np.array_equal(parse_pose_stamped(raw).position, d[k]) for k, raw in enumerate(poses))


def test_replay_loop_stops_cleanly_on_sigint(tmp_path: Path) -> None:
    frames, stamps = _recording()
    bag = write_marker_bag(tmp_path / "bag", frames[:100], stamps[:100])
    proc = _replay(str(bag), "--loop", "--rate", "1")
    time.sleep(5.0)  # rclpy start-up (2-4 s on a loaded machine), then a few passes of 0.5 s
    proc.send_signal(signal.SIGINT)
    code, out, err = _finish(proc)
    assert code == 130, err
    assert out.startswith("jointfit replay: published ") and out.rstrip().endswith("passes, interrupted)"), (
        out
    )
    assert "Traceback" not in err


def test_replay_missing_bag_subprocess(tmp_path: Path) -> None:
    proc = _replay(str(tmp_path / "no_such_bag"), "--reliable")
    code, out, err = _finish(proc)
    assert code == 1 and out == ""
    assert err == f"jointfit replay: no such bag: {tmp_path / 'no_such_bag'}\n"


@pytest.mark.parametrize(
    ("args", "code", "start"),
    [
        (
            ["{tmp}/bag", "--topics", "nothing"],
            1,
            "jointfit replay: {tmp}/bag: topics not in the bag: nothing; ",
        ),
        (
            ["{tmp}/bag/metadata.yaml", "--topics", "/markers", "chatter"],
            1,
            "jointfit replay: {tmp}/bag/metadata.yaml: topics not in",
        ),
        (
            ["{tmp}/bag", "--rate", "-2"],
            2,
            "jointfit replay: error: argument --rate: expected a number >= 0 or 'max'",
        ),
        (
            ["{tmp}/bag", "--rate", "fast"],
            2,
            "jointfit replay: error: argument --rate: expected a number >= 0 or 'max'",
        ),
        (
            ["{tmp}/bag", "--wait-subscribers", "-1"],
            2,
            "jointfit replay: error: argument --wait-subscribers: ",
        ),
        (
            ["{tmp}/bag", "--start-delay", "nan"],
            2,
            "jointfit replay: error: argument --start-delay: expected",
        ),
        (["{tmp}/bag", "--bogus"], 2, "jointfit replay: error: unrecognized arguments: --bogus"),
        ([], 2, "jointfit replay: error: the following arguments are required: bag"),
        (
            ["{tmp}/empty"],
            1,
            "jointfit replay: not a rosbag2 bag: directory {tmp}/empty has no metadata.yaml",
        ),
    ],
)
def test_replay_bad_input(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], code: int, start: str
) -> None:
    """Errors found before ROS starts: exit status, one line on stderr, nothing on stdout."""
    frames, stamps = _recording()
    write_marker_bag(tmp_path / "bag", frames[:5], stamps[:5])
    (tmp_path / "empty").mkdir()
    assert replay_main([a.format(tmp=tmp_path) for a in args]) == code
    out, err = capsys.readouterr()
    assert out == ""
    assert len(err.splitlines()) == 1, err
    assert err.startswith(start.format(tmp=tmp_path)), err


def test_replay_bag_without_supported_topics(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_raw_bag(tmp_path / "bag", [], empty_topics={"/markers": "geometry_msgs/msg/PoseArray"})
    assert replay_main([str(tmp_path / "bag")]) == 1
    assert capsys.readouterr().err == (
        f"jointfit replay: {tmp_path / 'bag'}: no messages of a supported type (geometry_msgs/msg/PoseArray, "
        "sensor_msgs/msg/PointCloud2, geometry_msgs/msg/PoseStamped); "
        "the bag has /markers (geometry_msgs/msg/PoseArray, 0 messages)\n"
    )


def test_replay_help(capsys: pytest.CaptureFixture[str]) -> None:
    assert replay_main(["--help"]) == 0
    assert "--wait-subscribers N" in capsys.readouterr().out


def test_replay_wait_subscribers_times_out(tmp_path: Path) -> None:
    frames, stamps = _recording()
    bag = write_marker_bag(tmp_path / "bag", frames[:5], stamps[:5])
    proc = _replay(str(bag), "--wait-subscribers", "1", "--wait-timeout", "0.5")
    code, out, err = _finish(proc)
    assert code == 1 and out == ""
    assert err.strip().splitlines()[-1] == (
        "jointfit replay: timed out after 0.5 s waiting for 1 subscriber(s) per topic (have /markers: 0)"
    )
