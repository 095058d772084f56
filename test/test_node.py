"""The node in its own process, driven through real rclpy publishers, subscribers and services.

A synthetic stream with known joints (jointfit_ros.fake_mocap.frame_at) is
published from the test process; the node's outputs are compared with the
truth; malformed messages must show up in /diagnostics, not crash the node;
a saved calibration must be loaded (frozen) after a restart.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("rclpy")

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from scipy.spatial.transform import Rotation
from std_srvs.srv import SetBool, Trigger

from jointfit_core.calibration_fit import JOINT_MISFIT_FRAMES
from jointfit_ros.conversions import pose_array_bytes
from jointfit_ros.fake_mocap import frame_at, make_rigs, marker_names, truth_at

pytestmark = pytest.mark.ros

DOMAIN = str(60 + os.getpid() % 30)
ENV = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": DOMAIN}
RATE = 250.0


def _params(path: Path, calibration: Path) -> Path:
    names = marker_names(0)
    text = f"""jointfit:
  ros__parameters:
    joints: [hip, knee]
    marker_names: [{", ".join(names)}]
    estimate_period: 0.05
    diagnostics_period: 0.25
    hip:
      type: ball
      parent_markers: [PELV1, PELV2, PELV3, PELV4]
      child_markers: [THIGH1, THIGH2, THIGH3, THIGH4]
      window: 2000
      template_frames: 30
      calibration_file: "{calibration}"
    knee:
      type: hinge
      parent_markers: [FEMUR1, FEMUR2, FEMUR3, FEMUR4]
      child_markers: [SHANK1, SHANK2, SHANK3, SHANK4]
      template_frames: 30
      axis_toward_marker: FEMUR1
      axis_from_marker: FEMUR4
"""
    path.write_text(text)
    return path


class _Client:
    """The test's side: a publisher of markers, subscribers of the outputs and service clients."""

    def __init__(self, domain: str = DOMAIN) -> None:
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=int(domain))
        self.node = Node("jointfit_test_client", context=self.context)
        self.executor = rclpy.executors.SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.pub = self.node.create_publisher(PoseArray, "markers", qos_profile_sensor_data)
        self.hip: list[PoseWithCovarianceStamped] = []
        self.knee: list[PoseWithCovarianceStamped] = []
        self.diag: list[DiagnosticArray] = []
        self.node.create_subscription(PoseWithCovarianceStamped, "hip/centre", self.hip.append, 1000)
        self.node.create_subscription(PoseWithCovarianceStamped, "knee/axis", self.knee.append, 1000)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self.diag.append, 100)
        self.segments: list[PoseArray] = []
        self.node.create_subscription(PoseArray, "/jointfit/segments", self.segments.append, 1000)
        self.clients = {
            "freeze": self.node.create_client(SetBool, "/jointfit/freeze"),
            "save": self.node.create_client(Trigger, "/jointfit/save"),
            "reset": self.node.create_client(Trigger, "/jointfit/reset"),
        }

    def spin_until(self, done: Callable[[], bool], timeout: float) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.02)
            if done():
                return True
        return False

    def call(self, name: str, request: Any) -> Any:
        client = self.clients[name]
        assert client.wait_for_service(timeout_sec=15.0), f"service {name} not available"
        future = client.call_async(request)
        assert self.spin_until(future.done, 15.0), f"service {name} did not answer"
        return future.result()

    def status(self, name: str) -> dict[str, str]:
        for arr in reversed(self.diag):
            for st in arr.status:
                if st.name == f"jointfit: {name}":
                    return {"message": st.message, **{kv.key: kv.value for kv in st.values}}
        return {}

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def _start_node(params: Path, env: dict[str, str] | None = None) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "jointfit_ros.node", "--ros-args", "--params-file", str(params)],
        env=ENV if env is None else env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )


def _stop(proc: subprocess.Popen[bytes]) -> str:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    out = proc.stdout.read().decode(errors="replace") if proc.stdout else ""
    return out


def _stream(client: _Client, rigs: Any, rng: np.random.Generator, t0: float, n: int, t_start: float) -> None:
    """Publish n frames at RATE (metres), stamped t0 + frame time, paced by the wall clock."""
    period = 1.0 / RATE
    start = time.monotonic()
    for k in range(n):
        t = t_start + k * period
        frame = frame_at(rigs, t, rng, 0.5, 0.02) / 1000.0
        client.pub.publish(pose_array_bytes(int((t0 + t) * 1e9), "world", frame))
        client.executor.spin_once(timeout_sec=0.0)
        lag = start + (k + 1) * period - time.monotonic()
        if lag > 0:
            client.spin_until(lambda: False, lag)


def _hip_errors(client: _Client, rigs: Any, t0: float, last: int = 200) -> tuple[float, float, float]:
    """Median error (mm), mean e/3 and median sqrt(tr cov) (mm) of the last hip outputs."""
    err, e3, sd = [], [], []
    for msg in client.hip[-last:]:
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        truth = truth_at(rigs, stamp - t0).centres["hip"] / 1000.0
        p = msg.pose.pose.position
        e = np.array([p.x, p.y, p.z]) - truth
        cov = np.array(msg.pose.covariance).reshape(6, 6)[:3, :3]
        assert np.all(np.linalg.eigvalsh(cov) > 0.0)
        err.append(np.linalg.norm(e) * 1000.0)
        e3.append(float(e @ np.linalg.solve(cov, e)) / 3.0)
        sd.append(np.sqrt(np.trace(cov)) * 1000.0)
    return float(np.median(err)), float(np.mean(e3)), float(np.median(sd))


def _ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def test_node_end_to_end(client: _Client, tmp_path: Path) -> None:
    calibration = tmp_path / "hip.yaml"
    params = _params(tmp_path / "params.yaml", calibration)
    rigs = make_rigs(7)
    rng = np.random.default_rng(7)
    t0 = 1000.0
    proc = _start_node(params)
    try:
        assert client.spin_until(lambda: client.pub.get_subscription_count() > 0, 30.0), "node not discovered"
        # 8 s: no output until a joint is identifiable (~3.5 s of this motion)
        _stream(client, rigs, rng, t0, int(8 * RATE), 0.0)
        assert client.spin_until(lambda: len(client.hip) > 500 and len(client.knee) > 500, 10.0)
        err, e3, sd = _hip_errors(client, rigs, t0)
        assert err < 10.0 and sd < 10.0, (err, sd)
        assert 0.2 < e3 < 3.0, e3  # per-frame outputs carry a covariance consistent with the error
        knee = client.knee[-1]
        cov = np.array(knee.pose.covariance).reshape(6, 6)
        assert np.all(np.linalg.eigvalsh(cov[:3, :3]) > 0.0) and cov[3, 3] > 0.0

        # Malformed input: garbage bytes, too many points, all-NaN, a stamp going backwards.
        n_outputs = len(client.hip)
        client.pub.publish(b"\x00\x01\x00\x00garbage")
        client.pub.publish(pose_array_bytes(int((t0 + 8.5) * 1e9), "world", np.zeros((40, 3))))
        client.pub.publish(pose_array_bytes(int((t0 + 8.6) * 1e9), "world", np.full((16, 3), np.nan)))
        client.pub.publish(pose_array_bytes(int((t0 + 1.0) * 1e9), "world", frame_at(rigs, 1.0, rng, 0.5, 0.0) / 1e3))
        _stream(client, rigs, rng, t0, int(RATE), 9.0)
        assert client.spin_until(lambda: len(client.hip) > n_outputs + 100, 10.0), "no outputs after bad input"
        assert client.spin_until(lambda: int(client.status("input").get("malformed messages", "0")) >= 2, 5.0)
        assert client.spin_until(lambda: "dropped: stamp_not_increasing" in client.status("hip"), 5.0)
        assert proc.poll() is None, "the node died"

        # Services: freeze, save; a restarted node loads the calibration and starts frozen.
        assert client.call("freeze", SetBool.Request(data=True)).success
        saved = client.call("save", Trigger.Request())
        assert saved.success and calibration.exists(), saved.message

        # ~/segments: every segment's pose per frame; the frozen hip centre carried by the pelvis pose is the
        # published centre of the same frame.
        _stream(client, rigs, rng, t0, int(RATE), 10.0)
        assert client.spin_until(lambda: len(client.hip) > n_outputs + 250, 10.0)
        inp = client.status("input")
        assert inp["segments (~/segments order)"] == "PELV, THIGH, FEMUR, SHANK", inp
        assert inp["TF"].startswith("tf2_ros is not installed") or inp["TF"].startswith("broadcast"), inp
        centre = np.array(json.loads(client.status("hip")["centre_parent (m)"]))
        by_stamp = {_ns(m.header.stamp): m for m in client.segments}
        matched = 0
        for out in client.hip[-80:]:
            seg = by_stamp.get(_ns(out.header.stamp))
            if seg is None:
                continue
            assert len(seg.poses) == 4 and seg.header.frame_id == "world"
            pelvis = seg.poses[0]
            q = [pelvis.orientation.x, pelvis.orientation.y, pelvis.orientation.z, pelvis.orientation.w]
            t = np.array([pelvis.position.x, pelvis.position.y, pelvis.position.z])
            carried = Rotation.from_quat(q).as_matrix() @ centre + t
            p = out.pose.pose.position
            np.testing.assert_allclose(carried, [p.x, p.y, p.z], atol=2e-6)  # the diagnostics round to 1e-6 m
            matched += 1
        assert matched > 40, matched
        client.spin_until(lambda: False, 1.0)  # the last outputs in, before the restart below counts its own
    finally:
        log = _stop(proc)
    assert "Traceback" not in log, log

    client.hip.clear()
    client.diag.clear()
    proc = _start_node(params)
    try:
        assert client.spin_until(lambda: client.pub.get_subscription_count() > 0, 30.0)
        _stream(client, rigs, rng, t0, int(2 * RATE), 20.0)
        # Outputs once the loaded calibration is judged against these markers (its first JOINT_MISFIT_FRAMES
        # frames, held): no template phase, no estimate to wait for. The node's own counters say so (every
        # other frame it received with a posed pelvis gave an output); the count seen here may be lower,
        # since best-effort frames sent while discovery completes are lost.
        assert client.spin_until(lambda: len(client.hip) > 0.5 * RATE, 10.0), len(client.hip)
        assert client.spin_until(lambda: "calibration loaded from" in client.status("hip"), 5.0)
        client.spin_until(lambda: False, 1.0)  # the stream has ended: let the last outputs and diagnostics in
        hip = client.status("hip")
        not_posed = int(hip.get("dropped: parent_not_posed", "0"))  # occluded pelvis: no centre to give
        checked = int(hip.get("dropped: calibration_being_checked", "0"))
        # the frames before the 100th with both segments posed (the last of them is judged and published), and
        # the few with the thigh occluded among them; frames without a pelvis count as not posed
        assert JOINT_MISFIT_FRAMES - 1 <= checked <= JOINT_MISFIT_FRAMES + 10, hip
        assert int(hip["outputs"]) == int(hip["frames received"]) - not_posed - checked >= len(client.hip), hip
        assert client.status("hip")["frozen"] == "True"
        err, e3, _ = _hip_errors(client, rigs, t0, last=100)
        assert err < 10.0, err
        assert client.call("reset", Trigger.Request()).success
        assert client.spin_until(lambda: client.status("hip").get("frozen") == "False", 5.0)
    finally:
        log = _stop(proc)
    assert "Traceback" not in log, log
