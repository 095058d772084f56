"""Two publishers on ``/markers``, through the node in its own process: no output from their mixed frames.

A second driver of another subject starts beside the first one for 3 s and is then stopped. Before,
every hip output of the mixed stream was published 30+ sd off (the hunt of 2026-12-03, D3); now the
node holds those frames back, says why in ``jointfit: input``, and publishes again, honestly, once the
second publisher is gone.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")

from geometry_msgs.msg import PoseArray
from rclpy.qos import qos_profile_sensor_data
from test_node import RATE, _Client, _params, _start_node, _stop

from jointfit_ros.conversions import pose_array_bytes
from jointfit_ros.fake_mocap import frame_at, make_rigs, truth_at

pytestmark = pytest.mark.ros


def _z(client: _Client, rigs: object, t0: float, since: float) -> list[float]:
    """sqrt(e' C^-1 e) of every hip output stamped from ``since`` (s of motion time) on."""
    z = []
    for msg in client.hip:
        t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9 - t0
        if t < since:
            continue
        p = msg.pose.pose.position
        e = np.array([p.x, p.y, p.z]) - truth_at(rigs, t).centres["hip"] / 1000.0  # type: ignore[arg-type]
        cov = np.array(msg.pose.covariance).reshape(6, 6)[:3, :3]
        z.append(float(np.sqrt(e @ np.linalg.solve(cov, e))))
    return z


def test_a_second_publisher_of_another_subject_is_held_back(client: _Client, tmp_path: Path) -> None:
    params = _params(tmp_path / "params.yaml", tmp_path / "hip.yaml")
    rigs, other = make_rigs(3), make_rigs(11)
    rng = np.random.default_rng(3)
    t0 = 500.0
    proc = _start_node(params)
    second = None
    try:
        assert client.spin_until(lambda: client.pub.get_subscription_count() > 0, 30.0), "node not discovered"

        def stream(seconds: float, start: float, both: bool) -> None:
            period = 1.0 / RATE
            begin = time.monotonic()
            for k in range(int(seconds * RATE)):
                t = start + k * period
                client.pub.publish(pose_array_bytes(int((t0 + t) * 1e9), "world", frame_at(rigs, t, rng, 0.5, 0.0) / 1e3))
                if both:
                    assert second is not None  # the other driver stamps its own frames, half a period later
                    b = frame_at(other, t, rng, 0.5, 0.0) / 1e3
                    second.publish(pose_array_bytes(int((t0 + t + period / 2) * 1e9), "world", b))
                client.executor.spin_once(timeout_sec=0.0)
                lag = begin + (k + 1) * period - time.monotonic()
                if lag > 0:
                    client.spin_until(lambda: False, lag)

        stream(3.0, 0.0, both=False)
        assert client.spin_until(lambda: len(client.hip) > 100, 10.0), "no hip output from one publisher"
        second = client.node.create_publisher(PoseArray, "markers", qos_profile_sensor_data)
        client.spin_until(lambda: False, 1.0)  # discovery (the node sees the match before any frame of it)
        n_before = len(client.hip)
        stream(3.0, 3.0, both=True)
        client.spin_until(lambda: False, 0.6)
        mixed = len(client.hip) - n_before
        assert mixed == 0, mixed
        status = client.status("input")
        assert "held back while a second publisher" in status.get("message", ""), status
        assert int(status["frames held back: a second publisher"]) >= 2 * 3 * RATE * 0.9

        client.node.destroy_publisher(second)
        second = None
        client.spin_until(lambda: False, 1.0)
        n_before = len(client.hip)
        stream(2.0, 7.0, both=False)
        assert client.spin_until(lambda: len(client.hip) - n_before > 300, 10.0), "no output once it was gone"
        z = np.asarray(_z(client, rigs, t0, 0.0))
        assert z.size > 500 and np.mean(z > 5.0) < 0.01 and z.max() < 8.0, (z.size, np.mean(z > 5.0), z.max())
        assert proc.poll() is None, "the node died"
    finally:
        log = _stop(proc)
    assert "Traceback" not in log, log
