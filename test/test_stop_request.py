"""SIGINT / SIGTERM stop the node between callbacks, never inside one (:mod:`jointfit_ros.stop_request`).

Unit: the handler sets a flag, a second signal raises ``KeyboardInterrupt``, the previous handlers come
back. Live (ROS): ``jointfit_node`` busy with the full-body stream at 100 Hz, stopped with SIGINT three
times: no traceback and no FATAL. Before, rclpy's handler raised ``KeyboardInterrupt`` inside the marker
callback and the ``EventsExecutor`` logged it as FATAL with a traceback in 4 of 5 stops.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from jointfit_ros.stop_request import StopRequest

ROOT = Path(__file__).resolve().parents[1]


def test_a_signal_is_a_request_and_a_second_one_interrupts() -> None:
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    with StopRequest() as stop:
        assert not stop.requested
        signal.raise_signal(signal.SIGTERM)
        assert stop.requested and stop.signal_name == "SIGTERM"
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGINT)
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before


@pytest.mark.ros
def test_ctrl_c_on_a_busy_node_stops_it_without_a_traceback() -> None:
    pytest.importorskip("rclpy")
    env = {
        **os.environ,
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "ROS_DOMAIN_ID": str(30 + os.getpid() % 10),
        "PYTHONPATH": str(ROOT),
    }
    pub = subprocess.Popen(
        [sys.executable, "-m", "jointfit_ros.fake_mocap", "--skeleton", "full", "--rate", "100"],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        for k in range(3):
            node = subprocess.Popen(
                [sys.executable, "-m", "jointfit_ros.node", "--ros-args", "--params-file",
                 str(ROOT / "config" / "full_body.yaml")],
                env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            )  # fmt: skip
            time.sleep(7.0 + 0.37 * k)  # busy with the 12 joints (templates built, estimating)
            assert node.poll() is None, node.communicate()[0][-3000:]
            t0 = time.monotonic()
            node.send_signal(signal.SIGINT)
            try:
                out = node.communicate(timeout=20)[0]
            except subprocess.TimeoutExpired:
                node.kill()
                pytest.fail("the node did not stop within 20 s of SIGINT")
            assert node.returncode == 0, out[-3000:]
            assert time.monotonic() - t0 < 5.0
            assert "estimating" in out  # it was running, not still starting
            for word in ("Traceback", "FATAL", "Exception in"):
                assert word not in out, out[-3000:]
    finally:
        pub.send_signal(signal.SIGINT)
        try:
            pub.wait(timeout=10)
        except subprocess.TimeoutExpired:
            pub.kill()
