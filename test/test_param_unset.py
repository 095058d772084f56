"""A run-time parameter cannot be unset (``ros2 param delete``): refused, it stays declared and settable.

The node declares its parameters with dynamic typing, so rclpy lets a value of type NOT_SET
through to the node's check and then undeclares the parameter. ``check_value`` reads ``None``
as "the default": before the fix the node accepted the request, went back to the default
silently (an ``input_frame_id`` filter or a ``workspace`` limit switched off), and every
later change of that parameter was refused as undeclared.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

rclpy = pytest.importorskip("rclpy")

DOMAIN = 95  # 93-99: this file's own domain

pytestmark = pytest.mark.ros


def _params(path: Path) -> Path:
    from jointfit_ros.fake_mocap import marker_names

    path.write_text(
        f"""jointfit:
  ros__parameters:
    joints: [hip]
    marker_names: [{", ".join(marker_names(0))}]
    solver_process: false
    input_frame_id: world
    estimate_period: 0.2
    hip: {{type: ball, parent_markers: [PELV1, PELV2, PELV3, PELV4], child_markers: [THIGH1, THIGH2, THIGH3, THIGH4]}}
""",
        encoding="utf-8",
    )
    return path


@pytest.fixture
def node(tmp_path: Path) -> Iterator[Any]:
    from jointfit_ros.node import JointfitNode

    context = rclpy.Context()
    rclpy.init(args=["--ros-args", "--params-file", str(_params(tmp_path / "p.yaml"))], context=context,
               domain_id=DOMAIN)
    n = JointfitNode(context=context)
    yield n
    n.destroy_node()
    rclpy.shutdown(context=context)


@pytest.mark.parametrize(("name", "kept"), [("estimate_period", 0.2), ("input_frame_id", "world")])
def test_unsetting_a_runtime_parameter_is_refused_and_it_stays_settable(node: Any, name: str, kept: Any) -> None:
    from rclpy.parameter import Parameter

    result = node.set_parameters([Parameter(name, Parameter.Type.NOT_SET)])[0]
    assert not result.successful and name in result.reason and "unset" in result.reason, result.reason
    assert getattr(node.cfg, name) == kept  # not silently back to the default
    assert node.has_parameter(name) and node.get_parameter(name).value == kept
    new = 0.3 if name == "estimate_period" else "mocap"
    assert node.set_parameters([Parameter(name, value=new)])[0].successful
    assert getattr(node.cfg, name) == new and node.get_parameter(name).value == new
