"""A publisher whose QoS the node cannot take, through the node in its own process: the input status says so.

A best-effort publisher into ``qos_reliability: reliable`` delivers nothing. Before, the node only said
"waiting for markers" (rclpy's default warning went to the console); now ``jointfit: input`` is WARN
and names the topic and the policy. (Another message type on the topic was already named, from the
graph: ``jointfit_ros.graph``.)
"""

from __future__ import annotations

from pathlib import Path

import pytest

pytest.importorskip("rclpy")

from test_node import _Client, _params, _start_node, _stop

pytestmark = pytest.mark.ros


def _input_status_says(client: _Client, words: str, timeout: float = 15.0) -> dict[str, str]:
    client.spin_until(lambda: words in client.status("input").get("message", ""), timeout)
    return client.status("input")


def test_a_best_effort_publisher_into_a_reliable_subscription_is_named(client: _Client, tmp_path: Path) -> None:
    params = _params(tmp_path / "params.yaml", tmp_path / "hip.yaml")
    params.write_text(params.read_text().replace("    estimate_period: 0.05\n", "    estimate_period: 0.05\n    qos_reliability: reliable\n"))
    proc = _start_node(params)  # the client's publisher is best effort (sensor data)
    try:
        status = _input_status_says(client, "offers a QoS")
        assert "RELIABILITY" in status.get("message", ""), status
        assert int(status["publishers not matched: incompatible QoS"]) >= 1, status
        assert proc.poll() is None
    finally:
        log = _stop(proc)
    assert "Traceback" not in log, log
