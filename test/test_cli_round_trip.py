"""Round trip: a bag replayed into the running node gives the calibration ``jointfit fit`` computes from it.

The synthetic recording (fake mocap hip ball joint + knee hinge, 2 %
occlusions) is written as rosbag2 in both storages. The node runs in its own
process with reliable inputs, a history deeper than the recording and windows
covering it; ``jointfit replay`` (in another process, reliable, waiting for the
node) plays the bag; the node's ``~/save`` then writes calibrations that must
equal ``jointfit fit``'s on the same bag to near machine precision.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("rosbags")

import rclpy
from bagtools import write_marker_bag
from rclpy.node import Node
from std_srvs.srv import Trigger

from jointfit_core.calibration import load_calibration
from jointfit_ros.cli import fit_main
from jointfit_ros.fake_mocap import frame_at, make_rigs, marker_names

pytestmark = pytest.mark.ros

DOMAIN = str(120 + os.getpid() % 30)
ENV = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": DOMAIN}
N = 1200
RATE = 100.0


def _params(path: Path, calibration_dir: Path) -> Path:
    path.write_text(
        f"""jointfit:
  ros__parameters:
    joints: [hip, knee]
    marker_names: [{", ".join(marker_names(0))}]
    qos_reliability: reliable
    qos_depth: {2 * N}
    estimate_period: 0.05
    hip:
      type: ball
      parent_markers: [PELV1, PELV2, PELV3, PELV4]
      child_markers: [THIGH1, THIGH2, THIGH3, THIGH4]
      window: {2 * N}
      template_frames: 30
      calibration_file: "{calibration_dir / "hip.yaml"}"
    knee:
      type: hinge
      parent_markers: [FEMUR1, FEMUR2, FEMUR3, FEMUR4]
      child_markers: [SHANK1, SHANK2, SHANK3, SHANK4]
      window: {2 * N}
      template_frames: 30
      calibration_file: "{calibration_dir / "knee.yaml"}"
"""
    )
    return path


def _save_until_complete(node: Node, executor: Any, calibration_dir: Path, n_frames: dict[str, int], timeout: float) -> dict[str, dict]:
    """Call ~/save until both saved estimates hold every frame (the node may still be taking messages)."""
    client = node.create_client(Trigger, "/jointfit/save")
    assert client.wait_for_service(timeout_sec=20.0), "node's ~/save not available"
    end = time.monotonic() + timeout
    saved: dict[str, dict] = {}
    while time.monotonic() < end:
        future = client.call_async(Trigger.Request())
        executor.spin_until_future_complete(future, timeout_sec=10.0)
        result = future.result()
        if result is not None and result.success:
            saved = {name: load_calibration(calibration_dir / f"{name}.yaml") for name in n_frames}
            if all(saved[name]["estimate"]["n_frames"] == n for name, n in n_frames.items()):
                return saved
        time.sleep(0.2)
    raise AssertionError(f"node's saved estimates never reached {n_frames}: {({k: v['estimate']['n_frames'] for k, v in saved.items()})}")


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_replayed_bag_in_node_equals_fit(tmp_path: Path, storage: str, capsys: pytest.CaptureFixture[str]) -> None:
    rigs = make_rigs(11)
    rng = np.random.default_rng(11)
    t = np.arange(N) / RATE
    frames = np.stack([frame_at(rigs, float(tk), rng, 0.5, 0.02) for tk in t]) / 1000.0  # metres, as ROS
    stamps = (1_700_000_000_000_000_000 + np.rint(t * 1e9)).astype(np.int64)
    bag = write_marker_bag(tmp_path / "rec", frames, stamps, storage=storage, topic="/markers")

    calibration_dir = tmp_path / "node"
    params = _params(tmp_path / "params.yaml", calibration_dir)
    assert fit_main([str(bag), "--config", str(params), "--out", str(tmp_path / "fit"), "--no-report", "--quiet"]) == 0
    fitted = {name: load_calibration(tmp_path / "fit" / f"{name}.calibration.yaml") for name in ("hip", "knee")}

    node_proc = subprocess.Popen(
        [sys.executable, "-m", "jointfit_ros.node", "--ros-args", "--params-file", str(params)],
        env=ENV, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
    )
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=int(DOMAIN))
    client_node = Node("round_trip_client", context=context)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(client_node)
    try:
        replay = subprocess.run(
            [sys.executable, "-m", "jointfit_ros.cli", "replay", str(bag), "--rate", "4", "--reliable",
             "--wait-subscribers", "1", "--wait-timeout", "30"],
            env=ENV, capture_output=True, text=True, timeout=120,
        )
        assert replay.returncode == 0, replay.stderr
        assert f"{N} messages" in replay.stdout or str(N) in replay.stdout, replay.stdout
        want = {name: fitted[name]["estimate"]["n_frames"] for name in fitted}
        saved = _save_until_complete(client_node, executor, calibration_dir, want, timeout=30.0)
    finally:
        executor.shutdown()
        client_node.destroy_node()
        rclpy.try_shutdown(context=context)
        node_proc.terminate()
        try:
            node_proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            node_proc.kill()
            node_proc.wait()
    for name in ("hip", "knee"):
        a, b = saved[name], fitted[name]
        np.testing.assert_allclose(a["template_parent"], b["template_parent"], rtol=0, atol=1e-15)
        for key, value in b["estimate"].items():
            if isinstance(value, list):
                np.testing.assert_allclose(np.array(a["estimate"][key], dtype=float), np.array(value, dtype=float),
                                           rtol=1e-9, atol=1e-15, err_msg=f"{name}.{key}")
            elif isinstance(value, float):
                # near machine precision: the node's frame window and the fit's no-forgetting sums add
                # the same frames in a different order
                assert a["estimate"][key] == pytest.approx(value, rel=1e-9), f"{name}.{key}"
            else:
                assert a["estimate"][key] == value, f"{name}.{key}"
