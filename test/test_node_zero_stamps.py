"""A publisher that leaves ``header.stamp`` at 0, through the node in its own process.

Before, the node dropped every frame after the first (``stamp_not_increasing``) and never estimated.
Now it takes the arrival time, publishes the hip with those stamps, and says so in ``jointfit: input``.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")

from test_node import RATE, _Client, _params, _start_node, _stop

from jointfit_ros.conversions import pose_array_bytes
from jointfit_ros.fake_mocap import frame_at, make_rigs

pytestmark = pytest.mark.ros


def test_zero_stamps_are_estimated_on_their_arrival_times(client: _Client, tmp_path: Path) -> None:
    params = _params(tmp_path / "params.yaml", tmp_path / "hip.yaml")
    rigs = make_rigs(3)
    rng = np.random.default_rng(3)
    proc = _start_node(params)
    try:
        assert client.spin_until(lambda: client.pub.get_subscription_count() > 0, 30.0), "node not discovered"
        period = 1.0 / RATE
        begin = time.monotonic()
        wall0 = time.time()
        for k in range(int(8.0 * RATE)):
            client.pub.publish(pose_array_bytes(0, "world", frame_at(rigs, k * period, rng, 0.5, 0.0) / 1e3))
            client.executor.spin_once(timeout_sec=0.0)
            lag = begin + (k + 1) * period - time.monotonic()
            if lag > 0:
                client.spin_until(lambda: False, lag)
            if len(client.hip) > 100:
                break
        assert client.spin_until(lambda: len(client.hip) > 100, 10.0), "no hip output from zero-stamped frames"
        stamps = [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in client.hip]
        assert min(stamps) > wall0 - 60.0, min(stamps)  # the node's clock, not 0
        status = client.status("input")
        assert "header.stamp 0" in status.get("message", ""), status
        assert int(status["messages with header.stamp 0 (arrival time used)"]) > 100
        assert proc.poll() is None, "the node died"
    finally:
        log = _stop(proc)
    assert "Traceback" not in log, log
