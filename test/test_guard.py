"""No traceback for any value: the callback guard, bounded parameters, timers re-armed, not re-created."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from jointfit_ros.guard import CallbackGuard
from jointfit_ros.params import JOINT_PARAMS, NODE_PARAMS, ConfigError, check_value


def test_guard_counts_logs_once_and_survives() -> None:
    logged: list[str] = []
    guard = CallbackGuard(logged.append)

    def broken(x: int) -> int:
        return 1 // x

    f = guard.wrap("markers", broken)
    assert f(1) == 1
    assert f(0) is None and f(0) is None
    assert guard.count == 2 and guard.recent
    assert len(logged) == 1 and "markers: ZeroDivisionError" in logged[0] and "test_guard.py" in logged[0]
    assert "ZeroDivisionError" in guard.last

    class Response:
        success = True
        message = ""

    def service(request: Any, response: Any) -> Any:
        raise RuntimeError("disk on fire")

    answer = guard.wrap_service("~/save", service)(None, Response())
    assert answer.success is False and "disk on fire" in answer.message
    assert guard.count == 3 and len(logged) == 2


def test_guard_lets_interrupts_through() -> None:
    guard = CallbackGuard(lambda text: None)

    def stop() -> None:
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        guard.wrap("timer", stop)()


@pytest.mark.parametrize("spec", [s for s in NODE_PARAMS + JOINT_PARAMS if s.kind in ("int", "double")],
                         ids=lambda s: s.name)
def test_every_numeric_parameter_is_bounded(spec: Any) -> None:
    assert spec.maximum is not None, f"{spec.name} has no maximum"
    for bad in (spec.maximum * 10 + 1, -1e300, math.nan, math.inf, "1", True):
        if spec.minimum is not None and isinstance(bad, float) and bad < 0 and spec.minimum < 0:
            continue
        with pytest.raises(ConfigError, match=spec.name):
            check_value(spec, bad)
    if spec.kind == "double":
        assert check_value(spec, int(spec.maximum)) == float(int(spec.maximum))  # an integer for a double
    if spec.nonzero_minimum is not None:
        assert check_value(spec, 0.0) == 0.0
        with pytest.raises(ConfigError, match="0 \\(off\\)"):
            check_value(spec, spec.nonzero_minimum / 1e9)


def test_unknown_keys_are_refused_with_a_suggestion() -> None:
    values = {"joints": ["hip"], "marker_names": list("ABCDEF"), "hip.parent_markers": list("ABC"),
              "hip.child_markers": list("DEF")}
    from jointfit_ros.params import node_config

    node_config(values)
    with pytest.raises(ConfigError, match=r"hip\.outlier_gat: unknown parameter; did you mean 'hip\.outlier_gate'"):
        node_config({**values, "hip.outlier_gat": 0.0})
    with pytest.raises(ConfigError, match=r"knee\.type: unknown parameter; 'knee' is not in joints \['hip'\]"):
        node_config({**values, "knee.type": "hinge"})
    node_config({**values, "use_sim_time": False})


# --------------------------------------------------------------------------- the node


rclpy = pytest.importorskip("rclpy")
DOMAIN = str(210 + os.getpid() % 20)  # 210-229: no other test file uses these
ENV = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": DOMAIN}


def _params(path: Path, extra: str = "") -> Path:
    from jointfit_ros.fake_mocap import marker_names

    path.write_text(
        f"""jointfit:
  ros__parameters:
    joints: [hip]
    marker_names: [{", ".join(marker_names(0))}]
    solver_process: false
{extra}    hip: {{type: ball, parent_markers: [PELV1, PELV2, PELV3, PELV4], child_markers: [THIGH1, THIGH2, THIGH3, THIGH4]}}
""",
        encoding="utf-8",
    )
    return path


@pytest.fixture
def node(tmp_path: Path) -> Iterator[Any]:
    from jointfit_ros.node import JointfitNode

    context = rclpy.Context()
    rclpy.init(args=["--ros-args", "--params-file", str(_params(tmp_path / "p.yaml"))], context=context,
               domain_id=int(DOMAIN))
    n = JointfitNode(context=context)
    yield n
    n.destroy_node()
    rclpy.shutdown(context=context)


@pytest.mark.ros
def test_an_exception_in_a_callback_is_counted_and_survived(node: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    from jointfit_ros.conversions import pose_array_bytes

    def broken(raw: bytes) -> list[Any]:
        raise ValueError("a bug")

    monkeypatch.setattr(node.router, "markers", broken)
    callback = node.guard.wrap("markers", node._on_markers)
    callback(pose_array_bytes(10**18, "world", [[0.0, 0.0, 0.0]] * 16))
    published: list[Any] = []
    monkeypatch.setattr(node._diag_pub, "publish", published.append)
    node._on_diagnostics_timer()
    status = {s.name: s for s in published[-1].status}["jointfit: input"]
    assert status.level == b"\x02" and "a bug" in status.message  # ERROR
    assert {kv.key: kv.value for kv in status.values}["unexpected errors (callbacks)"] == "1"


@pytest.mark.ros
def test_parameter_changes_rearm_timers_and_refuse_bad_values(node: Any) -> None:
    from rclpy.parameter import Parameter

    timers = dict(node._jf_timers)
    for k in range(200):
        result = node.set_parameters([Parameter("local_rate", value=5.0 + k % 7)])[0]
        assert result.successful
    assert len(list(node.timers)) == len(timers) and all(node._jf_timers[n] is t for n, t in timers.items())
    assert node._jf_timers["local"].timer_period_ns == round(1e9 / (5.0 + 199 % 7))
    for name, value in (("local_rate", 1e-12), ("diagnostics_period", 1e12), ("estimate_period", 1e300),
                        ("rviz_rate", 1e6), ("local_rate", 1e9), ("diagnostics_period", math.nan)):
        result = node.set_parameters([Parameter(name, value=value)])[0]
        assert not result.successful and name in result.reason, (name, value)
    assert node.set_parameters([Parameter("local_rate", value=0.0)])[0].successful
    assert "local" not in node._jf_timers
    assert node.set_parameters([Parameter("local_rate", value=2)])[0].successful  # an integer for a double
    assert node._jf_timers["local"].timer_period_ns == 500_000_000


@pytest.mark.ros
@pytest.mark.parametrize(
    ("extra", "name"),
    [
        ("    local_rate: 1.0e-12\n", "local_rate"),
        ("    diagnostics_period: 1.0e12\n", "diagnostics_period"),
        ("    estimate_period: 1.0e300\n", "estimate_period"),
        ("    qos_depth: 'ten'\n", "qos_depth"),
        ("    estimate_period: 'fast'\n", "estimate_period"),
        ("    marker_names: PELV1\n", "marker_names"),
        ("    marker_topik: mocap\n", "did you mean 'marker_topic'"),
    ],
)
def test_bad_values_at_start_give_one_line_and_exit_2(tmp_path: Path, extra: str, name: str) -> None:
    params = _params(tmp_path / "p.yaml", extra)
    proc = subprocess.run(
        [sys.executable, "-m", "jointfit_ros.node", "--ros-args", "--params-file", str(params)],
        env=ENV, capture_output=True, text=True, timeout=60,
    )
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr + proc.stdout and name in proc.stderr


@pytest.mark.ros
def test_an_integer_for_a_double_starts_the_node(tmp_path: Path) -> None:
    params = _params(tmp_path / "p.yaml", "    estimate_period: 1\n    local_rate: 0\n")
    proc = subprocess.Popen(
        [sys.executable, "-m", "jointfit_ros.node", "--ros-args", "--params-file", str(params)],
        env=ENV, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    try:
        time.sleep(3.0)
        alive = proc.poll() is None
    finally:
        proc.terminate()
        out = proc.communicate(timeout=20)[0]
    assert alive, out
    assert "Traceback" not in out, out


@pytest.mark.ros
@pytest.mark.attack
def test_any_value_for_any_parameter_at_run_time_never_kills_the_node(tmp_path: Path) -> None:
    """Hypothesis over every declared parameter and hostile values, sent to a node in its own process."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st
    from rcl_interfaces.msg import Parameter as ParameterMsg
    from rcl_interfaces.srv import SetParameters
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    names = [s.name for s in NODE_PARAMS] + [f"hip.{s.name}" for s in JOINT_PARAMS]
    values = st.one_of(
        st.sampled_from([0, -1, 1, 0.0, -0.0, 1e-300, 5e-324, 1e300, -1e300, math.nan, math.inf, -math.inf,
                         2**63 - 1, -(2**63), "", "x" * 1000, "fast", True, False, ["a"], [], [1.5]]),
        st.floats(allow_nan=True, allow_infinity=True),
        st.integers(min_value=-(2**63), max_value=2**63 - 1),
        st.text(max_size=20),
    )
    proc = subprocess.Popen(
        [sys.executable, "-m", "jointfit_ros.node", "--ros-args", "--params-file", str(_params(tmp_path / "p.yaml"))],
        env=ENV, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=int(DOMAIN))
    client_node = Node("param_fuzz", context=context)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(client_node)
    client = client_node.create_client(SetParameters, "/jointfit/set_parameters")
    answers = {"refused": 0, "accepted": 0}
    try:
        assert client.wait_for_service(timeout_sec=30.0)

        @settings(max_examples=150, deadline=None, suppress_health_check=list(HealthCheck), database=None)
        @given(st.sampled_from(names), values)
        def send(name: str, value: object) -> None:
            try:
                msg: ParameterMsg = Parameter(name, value=value).to_parameter_msg()
            except (TypeError, ValueError, OverflowError):
                return  # not representable as a ROS parameter at all
            future = client.call_async(SetParameters.Request(parameters=[msg]))
            executor.spin_until_future_complete(future, timeout_sec=30.0)
            assert future.done(), f"no answer to {name} = {value!r}: the node is stuck or dead"
            result = future.result().results[0]
            answers["accepted" if result.successful else "refused"] += 1
            assert proc.poll() is None, f"the node died on {name} = {value!r}"

        send()
        # still alive and answering; diagnostics, timers and estimates went on meanwhile
        assert proc.poll() is None
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            out = proc.communicate(timeout=20)[0]
        except subprocess.TimeoutExpired:
            proc.kill()
            out = proc.communicate()[0]
        executor.shutdown()
        client_node.destroy_node()
        rclpy.try_shutdown(context=context)
    assert "Traceback" not in out, out[-3000:]
    assert answers["refused"] > 50 and answers["accepted"] > 0, answers


def test_node_help_prints_the_usage() -> None:
    proc = subprocess.run([sys.executable, "-m", "jointfit_ros.node", "--help"], capture_output=True, text=True,
                          timeout=60, env=ENV)
    assert proc.returncode == 0 and proc.stdout.startswith("usage: jointfit_node --ros-args --params-file")
    assert "README" in proc.stdout
