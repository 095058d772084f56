"""jointfit_fake_mocap --skeleton: the skeleton source (no ROS) and one short publishing run in its own process."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers import diagnostics_status, stop_processes

from jointfit_core.skeleton_truth import make_skeleton
from jointfit_ros.conversions import RawPoints, parse_pose_array
from jointfit_ros.fake_mocap import parse_args
from jointfit_ros.fake_skeleton import SkeletonSource

pytestmark = pytest.mark.ros

REPO_ROOT = Path(__file__).resolve().parents[1]


def test_parse_args_skeleton() -> None:
    opts = parse_args(["--skeleton", "full"])
    assert (opts.skeleton, opts.cycle) == ("full", 10.0)
    assert parse_args([]).skeleton is None and parse_args([]).cycle == 20.0
    assert parse_args(["--skeleton", "lower", "--cycle", "5"]).cycle == 5.0
    with pytest.raises(SystemExit):
        parse_args(["--skeleton", "upper"])


def test_skeleton_source_frames_and_truth_in_mm() -> None:
    extra = np.array([[1000.0, 2000.0, 500.0]])
    src = SkeletonSource("lower", 0, 10.0, extra)
    sk = make_skeleton("lower", cycle_s=10.0, seed=0)
    names = src.marker_names()
    assert names[:-1] == sk.marker_names() and names[-1] == "EXTRA1"
    assert src.kinds == {"r_hip": "ball", "r_knee": "hinge", "r_ankle": "hinge",
                         "l_hip": "ball", "l_knee": "hinge", "l_ankle": "hinge"}  # fmt: skip
    clean = src.frame(3.0, np.random.default_rng(0), 0.0, 0.0)
    np.testing.assert_allclose(clean[:-1], sk.markers_at([3.0])[0] * 1000.0)
    np.testing.assert_array_equal(clean[-1], extra[0])
    noisy = src.frame(3.0, np.random.default_rng(0), 0.5, 0.0)
    assert 0.2 < np.std(noisy - clean) < 0.8
    centres, axes = src.truth(3.0)
    world = sk.joints_world_at([3.0])
    for j, (point, direction) in world.items():
        np.testing.assert_allclose(centres[j], point[0] * 1000.0)
        if direction is not None:
            np.testing.assert_allclose(axes[j], direction[0])
    assert set(axes) == {"r_knee", "r_ankle", "l_knee", "l_ankle"}
    lines = src.truth_lines(1e-3, "m")
    assert len(lines) == 6 and lines[1].startswith("truth r_knee (hinge, r_thigh -> r_shank)")
    with pytest.raises(ValueError, match="occlusion"):
        src.frame(0.0, np.random.default_rng(0), 0.5, 2.0)


def _ros(domain_id: int) -> tuple[dict[str, str], Any]:
    """The child processes' environment (this host only, the domain, this checkout first) and an initialised
    rclpy context on the same domain."""
    import rclpy

    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(domain_id))
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO_ROOT), env.get("PYTHONPATH")]))
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain_id)
    return env, context


def test_fake_mocap_skeleton_publishes() -> None:
    """Receive the full skeleton's frames and one truth topic from the console script, then SIGINT it."""
    import rclpy
    from geometry_msgs.msg import PointStamped, PoseArray, Vector3Stamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import qos_profile_sensor_data

    env, context = _ros(230 + os.getpid() % 3)
    frames: list[RawPoints] = []
    wrist: list[PointStamped] = []
    elbow_axis: list[Vector3Stamped] = []
    node = proc = None
    try:
        node = Node("test_fake_skeleton_listener", context=context)
        node.create_subscription(
            PoseArray, "markers", lambda raw: frames.append(parse_pose_array(raw)), qos_profile_sensor_data, raw=True
        )
        node.create_subscription(PointStamped, "truth/l_wrist/centre", wrist.append, 10)
        node.create_subscription(Vector3Stamped, "truth/r_elbow/axis", elbow_axis.append, 10)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        cmd = [sys.executable, "-m", "jointfit_ros.fake_mocap", "--skeleton", "full", "--rate", "100",
               "--duration", "20", "--occlusion", "0"]  # fmt: skip
        proc = subprocess.Popen(cmd, env=env, cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 20.0  # discovery on a loaded machine can take seconds
        while proc.poll() is None and (len(frames) < 100 or not wrist or not elbow_axis):
            executor.spin_once(timeout_sec=0.05)
            if time.monotonic() > deadline:
                break
        proc.send_signal(signal.SIGINT)
        output = proc.communicate(timeout=10)[0].decode(errors="replace")
        assert proc.returncode == 0, f"fake mocap exited with {proc.returncode}:\n{output}"
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown(context=context)
    assert "truth r_elbow (hinge, r_upper_arm -> r_forearm)" in output
    assert len(frames) >= 100 and wrist and elbow_axis, (len(frames), len(wrist), len(elbow_axis))
    assert all(f.points.shape == (56, 3) and np.isfinite(f.points).all() for f in frames)
    points = np.concatenate([f.points for f in frames])
    assert 1.0 < np.linalg.norm(points, axis=1).min() and points[:, 2].max() < 2.0  # metres, in the lab
    a = elbow_axis[-1].vector
    assert abs(np.linalg.norm([a.x, a.y, a.z]) - 1.0) < 1e-9


def test_node_runs_the_lower_body_config_with_its_segments_named() -> None:
    """config/lower_body.yaml (segments, joints naming their parent and child) in the node's own process.

    The node declares the segments' parameters from the file, reports ~/segments in the configured
    names and estimates the stream's joints (the fake skeleton in its own process).
    """
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    env, context = _ros(90 + os.getpid() % 3)  # (FastDDS takes domain ids up to 232)
    diag: list[DiagnosticArray] = []
    hips: list[PoseWithCovarianceStamped] = []
    segments: list[PoseArray] = []
    node = mocap = jf = None

    def status(name: str) -> dict[str, str]:
        return diagnostics_status(diag, name)

    try:
        node = Node("test_lower_body_listener", context=context)
        node.create_subscription(DiagnosticArray, "/diagnostics", diag.append, 100)
        node.create_subscription(PoseWithCovarianceStamped, "/r_hip/centre", hips.append, 100)
        node.create_subscription(PoseArray, "/jointfit/segments", segments.append, 100)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        jf = subprocess.Popen(
            [sys.executable, "-m", "jointfit_ros.node", "--ros-args", "--params-file",
             str(REPO_ROOT / "config" / "lower_body.yaml")],
            env=env, cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
        )  # fmt: skip
        mocap = subprocess.Popen(
            [sys.executable, "-m", "jointfit_ros.fake_mocap", "--skeleton", "lower", "--rate", "100",
             "--duration", "60"],
            env=env, cwd=REPO_ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        deadline = time.monotonic() + 45.0
        while time.monotonic() < deadline and jf.poll() is None:
            executor.spin_once(timeout_sec=0.05)
            if status("input").get("segments (~/segments order)") and len(hips) >= 20 and len(segments) >= 20:
                break
    finally:
        output = stop_processes([mocap, jf], jf)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown(context=context)
    names = "pelvis, r_thigh, r_shank, r_foot, l_thigh, l_shank, l_foot"
    assert status("input").get("segments (~/segments order)") == names, (status("input"), output[-2000:])
    assert len(segments) >= 20 and all(len(m.poses) == 7 for m in segments), len(segments)
    assert len(hips) >= 20, (len(hips), status("r_hip"), output[-2000:])
    assert "Traceback" not in output, output[-2000:]
