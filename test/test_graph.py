"""Same-name nodes and wrong-type publishers are found on the graph and said in /diagnostics."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from jointfit_ros.graph import graph_problems


def test_graph_problems_name_twins_and_wrong_types() -> None:
    me = ("jointfit", "/")
    assert graph_problems([me, ("other", "/")], me, {"/markers": ["geometry_msgs/msg/PoseArray"]},
                          {"/markers": "geometry_msgs/msg/PoseArray"}) == []
    twins = graph_problems([me, me, ("jointfit", "/lab2")], me, {}, {})
    assert len(twins) == 1 and twins[0].startswith("2 nodes named /jointfit")
    lab = graph_problems([("jointfit", "/lab1")] * 3, ("jointfit", "/lab1"), {}, {})
    assert lab[0].startswith("3 nodes named /lab1/jointfit")
    wrong = graph_problems([me], me, {"/markers": ["sensor_msgs/msg/PointCloud2", "geometry_msgs/msg/PoseArray"]},
                           {"/markers": "geometry_msgs/msg/PoseArray"})
    assert len(wrong) == 1 and "publishers of sensor_msgs/msg/PointCloud2" in wrong[0]


def test_graph_problems_name_two_publishers_of_an_input() -> None:
    """Two drivers on /markers interleave two streams into one: said, not only seen as missed frames and rejections."""
    me = ("jointfit", "/")
    pose_array = "geometry_msgs/msg/PoseArray"
    two = graph_problems([me], me, {"/markers": [pose_array, pose_array], "/pelvis": ["geometry_msgs/msg/PoseStamped"]},
                         {"/markers": pose_array, "/pelvis": "geometry_msgs/msg/PoseStamped"})
    assert len(two) == 1 and two[0].startswith("/markers has 2 publishers of geometry_msgs/msg/PoseArray"), two
    poses = graph_problems([me], me, {"/pelvis": ["geometry_msgs/msg/PoseStamped"] * 3},
                           {"/pelvis": "geometry_msgs/msg/PoseStamped"})
    assert len(poses) == 1 and "/pelvis has 3 publishers" in poses[0], poses


@pytest.mark.ros
def test_node_reports_a_twin_and_a_wrong_type_publisher(tmp_path: Path) -> None:
    rclpy = pytest.importorskip("rclpy")
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.node import Node
    from sensor_msgs.msg import PointCloud2

    from jointfit_ros.fake_mocap import marker_names

    domain = str(90 + os.getpid() % 30)
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": domain}
    params = tmp_path / "p.yaml"
    params.write_text(f"""jointfit:
  ros__parameters:
    joints: [hip]
    marker_names: [{", ".join(marker_names(0))}]
    diagnostics_period: 0.25
    hip: {{type: ball, parent_markers: [PELV1, PELV2, PELV3, PELV4], child_markers: [THIGH1, THIGH2, THIGH3, THIGH4]}}
""")
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=int(domain))
    node = Node("graph_test", context=context)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)
    node.create_publisher(PointCloud2, "markers", 10)  # the node expects PoseArray there
    messages: list[str] = []

    def on_diag(msg: DiagnosticArray) -> None:
        messages.extend(s.message for s in msg.status if s.name == "jointfit: input")

    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 100)
    cmd = [sys.executable, "-m", "jointfit_ros.node", "--ros-args", "--params-file", str(params)]
    procs = [subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for _ in range(2)]
    try:
        end = time.monotonic() + 40.0
        while time.monotonic() < end and not any("2 nodes named /jointfit" in m and "PointCloud2" in m
                                                 for m in messages):
            executor.spin_once(timeout_sec=0.1)
        assert any("2 nodes named /jointfit" in m for m in messages), messages[-3:]
        assert any("has publishers of sensor_msgs/msg/PointCloud2" in m for m in messages), messages[-3:]
    finally:
        for p in procs:
            p.terminate()
        logs = [p.communicate(timeout=20)[0] for p in procs]
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    assert all("Traceback" not in log for log in logs), logs
    assert any("2 nodes named /jointfit" in log for log in logs)  # also said in the console, once
