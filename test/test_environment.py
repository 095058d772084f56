"""Checks of the environment itself: the core stays free of ROS, the ROS wheels import."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]

# Third-party packages jointfit_core may use only optionally; a submodule that
# needs one of them is allowed to fail to import when it is not installed.
OPTIONAL_DEPS = {"ezc3d", "rosbags", "matplotlib"}

_PROBE = textwrap.dedent(
    """
    import importlib, json, pkgutil, sys

    optional = set(json.loads(sys.argv[1]))
    import jointfit_core

    skipped = []
    for info in pkgutil.walk_packages(jointfit_core.__path__, "jointfit_core."):
        if info.name.rsplit(".", 1)[-1] == "__main__":
            continue  # importing it would run the program
        try:
            importlib.import_module(info.name)
        except ModuleNotFoundError as exc:
            if (exc.name or "").split(".")[0] not in optional:
                raise
            skipped.append(info.name)
    print(json.dumps({"modules": sorted(sys.modules), "skipped": skipped}))
    """
)


def _is_ros_module(name: str) -> bool:
    top = name.split(".")[0]
    return top.startswith(("rclpy", "rosidl", "rmw")) or top.endswith("_msgs") or top == "std_srvs"


def test_core_never_imports_ros() -> None:
    """Importing jointfit_core and every submodule pulls in no rclpy or message package."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO_ROOT), env.get("PYTHONPATH")]))
    proc = subprocess.run(
        [sys.executable, "-c", _PROBE, json.dumps(sorted(OPTIONAL_DEPS))],
        cwd=REPO_ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 0, f"importing jointfit_core failed:\n{proc.stderr}"
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    ros_modules = [name for name in result["modules"] if _is_ros_module(name)]
    assert ros_modules == [], f"jointfit_core imported ROS modules: {ros_modules}"


@pytest.mark.ros
def test_ros_wheels_import() -> None:
    """The pinned ROS 2 Jazzy wheels provide rclpy and every message type the node uses."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseArray
    from sensor_msgs.msg import PointCloud2
    from std_srvs.srv import Trigger
    from visualization_msgs.msg import MarkerArray

    assert callable(rclpy.init)
    for msg_type in (PoseArray, PointCloud2, DiagnosticArray, MarkerArray):
        assert msg_type().__class__ is msg_type
    assert Trigger.Request is not None and Trigger.Response is not None


#: jointfit_ros modules the offline tools use: they must work without ROS too.
ROS_FREE = [
    "jointfit_ros.raw",
    "jointfit_ros.params",
    "jointfit_ros.sync",
    "jointfit_ros.runner",
    "jointfit_ros.inputs",
    "jointfit_ros.bag",
    "jointfit_ros.replay",
    "jointfit_ros.offline",
    "jointfit_ros.report",
    "jointfit_ros.cli",
]


def test_offline_parts_of_jointfit_ros_never_import_ros() -> None:
    """Parsers, parameters, pairing and the runner are pure Python/numpy (the offline CLI needs them)."""
    code = "import importlib, json, sys\n" + "".join(f"importlib.import_module({m!r})\n" for m in ROS_FREE)
    code += "print(json.dumps(sorted(sys.modules)))"
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO_ROOT), env.get("PYTHONPATH")]))
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=120, check=False
    )
    assert proc.returncode == 0, proc.stderr
    ros_modules = [name for name in json.loads(proc.stdout.strip().splitlines()[-1]) if _is_ros_module(name)]
    assert ros_modules == [], f"{ROS_FREE} imported ROS modules: {ros_modules}"
