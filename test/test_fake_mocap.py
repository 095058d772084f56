"""Tests of jointfit_ros.fake_mocap: the pure frame generator and one run of the publishing node."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from jointfit_ros.conversions import RawPoints, parse_pose_array
from jointfit_ros.fake_mocap import (
    RIG_OFFSETS_MM,
    extra_marker_positions,
    frame_at,
    make_rigs,
    marker_names,
    parse_args,
    truth_at,
)

pytestmark = pytest.mark.ros

REPO_ROOT = Path(__file__).resolve().parents[1]


def test_marker_names_order() -> None:
    names = marker_names()
    assert names[:4] == ["PELV1", "PELV2", "PELV3", "PELV4"]
    assert names[4:8] == ["THIGH1", "THIGH2", "THIGH3", "THIGH4"]
    assert names[8:16] == [f"FEMUR{i}" for i in range(1, 5)] + [f"SHANK{i}" for i in range(1, 5)]
    with_extra = marker_names(24)
    assert len(with_extra) == 40 and with_extra[16] == "EXTRA1" and with_extra[-1] == "EXTRA24"
    with pytest.raises(ValueError, match="non-negative"):
        marker_names(-1)


def test_make_rigs_is_reproducible_and_placed_in_the_lab() -> None:
    a, b, c = make_rigs(3), make_rigs(3), make_rigs(4)
    assert list(a) == ["hip", "knee"] and a["hip"].kind == "ball" and a["knee"].kind == "hinge"
    np.testing.assert_array_equal(a["hip"].template_child, b["hip"].template_child)
    assert not np.array_equal(a["hip"].template_child, c["hip"].template_child)
    np.testing.assert_allclose(np.subtract(RIG_OFFSETS_MM["knee"], RIG_OFFSETS_MM["hip"]), [1500.0, 0.0, 0.0])
    frame = frame_at(a, 1.0, np.random.default_rng(0), 0.0, 0.0)
    assert np.linalg.norm(frame, axis=1).min() > 1000.0  # mm: far from the origin


def test_frame_at_shapes_noise_and_occlusion_rate() -> None:
    rigs = make_rigs(0)
    extra = extra_marker_positions(24, 0)
    rng = np.random.default_rng(1)
    clean = frame_at(rigs, 2.5, rng, 0.0, 0.0, extra=extra)
    assert clean.shape == (40, 3)
    parent, child = rigs["knee"].markers_at(2.5)
    np.testing.assert_array_equal(clean[8:12], parent[0])
    np.testing.assert_array_equal(clean[12:16], child[0])
    np.testing.assert_array_equal(clean[16:], extra)
    frames = np.stack([frame_at(rigs, 2.5, rng, 0.5, 0.1, extra=extra) for _ in range(1000)])
    missing = np.isnan(frames).any(axis=2)
    assert (np.isnan(frames).all(axis=2) == missing).all()  # whole rows
    n, p = missing.size, 0.1
    assert abs(missing.mean() - p) < 5.0 * np.sqrt(p * (1 - p) / n)
    errors = (frames - clean)[~missing]
    assert abs(errors.std() - 0.5) < 0.01 and abs(errors.mean()) < 0.01
    assert frame_at(rigs, 0.0, rng, 0.5, 0.0).shape == (16, 3)
    with pytest.raises(ValueError, match="occlusion"):
        frame_at(rigs, 0.0, rng, 0.5, 1.5)


def test_truth_is_consistent_with_the_markers() -> None:
    rigs = make_rigs(5, cycle_s=10.0)
    times = np.linspace(0.0, 20.0, 200)
    rng = np.random.default_rng(0)
    frames = np.stack([frame_at(rigs, t, rng, 0.0, 0.0) for t in times])
    truths = [truth_at(rigs, t) for t in times]
    # ball joint: every hip marker (parent and child) keeps its distance to the centre
    centre = np.stack([tr.centres["hip"] for tr in truths])
    dist = np.linalg.norm(frames[:, 0:8] - centre[:, None], axis=2)
    assert np.ptp(dist, axis=0).max() < 1e-9
    np.testing.assert_allclose(centre, rigs["hip"].centre_world_at(times), atol=1e-9)
    # hinge: shank markers keep their distance to the axis line and their position along it
    point = np.stack([tr.centres["knee"] for tr in truths])
    axis = np.stack([tr.axes["knee"] for tr in truths])
    np.testing.assert_allclose(np.linalg.norm(axis, axis=1), 1.0)
    rel = frames[:, 12:16] - point[:, None]
    along = np.einsum("npi,ni->np", rel, axis)
    radial = np.linalg.norm(rel - along[..., None] * axis[:, None], axis=2)
    assert np.ptp(along, axis=0).max() < 1e-9 and np.ptp(radial, axis=0).max() < 1e-9
    assert np.ptp(radial, axis=0).max() < 1e-9
    assert np.ptp(np.degrees(np.arccos(np.clip(axis @ axis[0], -1, 1)))) > 5.0  # the knee moves


def test_parse_args_validation() -> None:
    opts = parse_args([])
    assert (opts.rate, opts.duration, opts.noise, opts.occlusion) == (100.0, 0.0, 0.5, 0.02)
    assert (opts.format, opts.units, opts.topic, opts.frame_id, opts.cycle) == (
        "pose_array",
        "m",
        "markers",
        "world",
        20.0,
    )
    assert parse_args(["--extra-markers", "24", "--zeros"]).extra_markers == 24
    for bad in (["--rate", "0"], ["--occlusion", "2"], ["--format", "csv"], ["--extra-markers", "-1"]):
        with pytest.raises(SystemExit):
            parse_args(bad)


def _ros_env() -> tuple[int, dict[str, str]]:
    """A domain id of this test run and the environment of a child process on it (localhost only)."""
    domain_id = 60 + os.getpid() % 30
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(domain_id))
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO_ROOT), env.get("PYTHONPATH")]))
    return domain_id, env


def test_fake_mocap_stops_after_duration() -> None:
    _, env = _ros_env()
    cmd = [sys.executable, "-m", "jointfit_ros.fake_mocap", "--rate", "100", "--duration", "0.5"]
    proc = subprocess.run(
        cmd, env=env, cwd=REPO_ROOT, capture_output=True, text=True, timeout=15, check=False
    )
    assert proc.returncode == 0, proc.stderr
    log = proc.stdout + proc.stderr
    assert "marker order (row / label k): 0:PELV1, 1:PELV2" in log
    frames = int(log.split("published ")[-1].split(" frames")[0])
    assert 30 <= frames <= 60


def test_fake_mocap_publishes_parsable_frames() -> None:
    """Receive the raw frames of the console script in this process, then stop it with SIGINT.

    Fast DDS discovery with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST sometimes
    waits for the second participant announcement (~3.5 s here), so the
    script runs until enough frames arrived rather than for a fixed time.
    """
    import rclpy
    from geometry_msgs.msg import PointStamped, PoseArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import qos_profile_sensor_data

    domain_id, env = _ros_env()
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain_id)
    frames: list[RawPoints] = []
    truth_stamps: list[int] = []

    def on_markers(raw: bytes) -> None:
        frames.append(parse_pose_array(raw))

    def on_truth(msg: PointStamped) -> None:
        truth_stamps.append(msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec)

    node = None
    proc = None
    try:
        node = Node("test_fake_mocap_listener", context=context)
        node.create_subscription(PoseArray, "fake/markers", on_markers, qos_profile_sensor_data, raw=True)
        node.create_subscription(PointStamped, "truth/hip/centre", on_truth, 10)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        cmd = [sys.executable, "-m", "jointfit_ros.fake_mocap", "--rate", "200", "--duration", "8",
               "--extra-markers", "4", "--zeros", "--ros-args", "-r", "markers:=fake/markers", "--log-level", "warn"]  # fmt: skip
        proc = subprocess.Popen(cmd, env=env, cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 9.0
        while proc.poll() is None and len(frames) < 150 and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        proc.send_signal(signal.SIGINT)
        output = proc.communicate(timeout=5)[0].decode(errors="replace")
        assert proc.returncode == 0, f"fake mocap exited with {proc.returncode}:\n{output}"
        executor.spin_once(timeout_sec=0.05)
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown(context=context)
    assert len(frames) >= 150, f"received {len(frames)} frames"
    assert all(f.points.shape == (20, 3) and f.frame_id == "world" for f in frames)
    points = np.concatenate([f.points for f in frames])
    zeros = (points == 0.0).all(axis=1)
    assert 0 < zeros.sum() < 0.1 * len(points)  # --zeros: occluded markers are (0, 0, 0)
    norms = np.linalg.norm(points[~zeros], axis=1)
    assert 1.0 < norms.min() and norms.max() < 10.0  # metres
    stamps = [f.stamp_ns for f in frames]
    assert stamps == sorted(stamps)
    assert set(truth_stamps) & set(stamps)  # truth and markers share stamps
