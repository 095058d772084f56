"""Never a confident wrong answer, through the node in its own process (real publishers and services).

A still stance, a joint that the motion cannot identify, absurd marker values,
freeze and save: what a controller reading only the topics gets.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("rclpy")


from geometry_msgs.msg import PoseWithCovarianceStamped
from std_srvs.srv import SetBool, Trigger
from test_node import RATE, _Client, _start_node, _stop

from jointfit_ros.conversions import pose_array_bytes
from jointfit_ros.fake_mocap import frame_at, make_rigs, marker_names, truth_at

pytestmark = pytest.mark.ros


def _params(path: Path, tmp: Path) -> Path:
    names = marker_names(0)
    path.write_text(f"""jointfit:
  ros__parameters:
    joints: [hip, knee]
    marker_names: [{", ".join(names)}]
    estimate_period: 0.05
    diagnostics_period: 0.25
    hip:
      type: ball
      parent_markers: [PELV1, PELV2, PELV3, PELV4]
      child_markers: [THIGH1, THIGH2, THIGH3, THIGH4]
      template_frames: 30
      calibration_file: "{tmp / "hip.yaml"}"
    knee:
      type: ball                    # the knee rig is a hinge: as a ball joint it is never identifiable
      parent_markers: [FEMUR1, FEMUR2, FEMUR3, FEMUR4]
      child_markers: [SHANK1, SHANK2, SHANK3, SHANK4]
      template_frames: 30
      calibration_file: "{tmp / "knee.yaml"}"
""")
    return path


def _publish(cl: _Client, rigs: Any, rng: np.random.Generator, stamps: np.ndarray, motion_t: np.ndarray,
             bad: dict[int, tuple[int, float]] | None = None) -> None:
    """Frames at ``motion_t`` stamped ``stamps`` (s), paced at RATE; ``bad``: frame -> (marker, value of x)."""
    start = time.monotonic()
    for k, (st, t) in enumerate(zip(stamps, motion_t, strict=True)):
        frame = frame_at(rigs, float(t), rng, 0.5, 0.0) / 1000.0
        if bad and k in bad:
            frame[bad[k][0], 0] = bad[k][1]
        cl.pub.publish(pose_array_bytes(int(st * 1e9), "world", frame))
        cl.executor.spin_once(timeout_sec=0.0)
        lag = start + (k + 1) / RATE - time.monotonic()
        if lag > 0:
            cl.spin_until(lambda: False, lag)


def test_stance_unidentified_joint_and_absurd_values(client: _Client, tmp_path: Path) -> None:
    params = _params(tmp_path / "params.yaml", tmp_path)
    knee_out: list[PoseWithCovarianceStamped] = []
    client.node.create_subscription(PoseWithCovarianceStamped, "knee/centre", knee_out.append, 1000)
    rigs = make_rigs(7)
    rng = np.random.default_rng(7)
    t0 = 1000.0
    proc = _start_node(params)
    try:
        assert client.spin_until(lambda: client.pub.get_subscription_count() > 0, 30.0), "node not discovered"
        # A still stance of 2 s: nothing is identifiable, nothing is published.
        n = int(2 * RATE)
        _publish(client, rigs, rng, t0 + np.arange(n) / RATE, np.zeros(n))
        assert client.spin_until(lambda: "not identifiable" in client.status("hip").get("message", ""), 5.0)
        assert client.hip == [] and knee_out == []
        refused = client.call("freeze", SetBool.Request(data=True))
        assert not refused.success and "not identifiable" in refused.message, refused.message

        # Movement: the hip becomes identifiable and is published; the knee (a hinge fitted as a ball) never.
        n = int(5 * RATE)
        bad = {int(4 * RATE): (2, 2.5e299)}  # one finite absurd pelvis marker once the hip is estimated
        _publish(client, rigs, rng, t0 + 2.0 + np.arange(n) / RATE, np.arange(n) / RATE, bad)
        assert client.spin_until(lambda: len(client.hip) > 200, 10.0)
        assert knee_out == []
        client.spin_until(lambda: False, 0.6)
        knee = client.status("knee")
        assert "no per-frame output" in knee["message"] and int(knee["outputs withheld (not identifiable)"]) > 100

        frozen = client.call("freeze", SetBool.Request(data=True))
        assert not frozen.success and "knee: cannot freeze" in frozen.message and "hip: frozen" in frozen.message
        saved = client.call("save", Trigger.Request())
        assert not saved.success and "knee: not saved" in saved.message, saved.message
        assert (tmp_path / "hip.yaml").exists() and not (tmp_path / "knee.yaml").exists()

        # The frozen hip meets another absurd value.
        n = int(1 * RATE)
        _publish(client, rigs, rng, t0 + 7.0 + np.arange(n) / RATE, 5.0 + np.arange(n) / RATE, {50: (1, 2.5e299)})
        client.spin_until(lambda: False, 0.6)
        hip = client.status("hip")
        assert int(hip["absurd markers (treated as missing)"]) >= 2, hip
        assert knee_out == []
        for msg in client.hip:
            p = msg.pose.pose.position
            stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9 - t0
            truth = truth_at(rigs, max(stamp - 2.0, 0.0)).centres["hip"] / 1000.0
            cov = np.array(msg.pose.covariance).reshape(6, 6)[:3, :3]
            assert np.isfinite(cov).all() and np.sqrt(np.diag(cov)).max() < 0.05
            assert np.linalg.norm(np.array([p.x, p.y, p.z]) - truth) < 0.05
        assert proc.poll() is None, "the node died"
    finally:
        log = _stop(proc)
    assert "Traceback" not in log, log
