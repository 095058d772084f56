"""The jointfit ROS 2 node: marker (or pose) topics in, joint estimates with covariance out.

Console script ``jointfit_node``::

    jointfit_node --ros-args --params-file config/hip_knee.yaml

The node stays thin: ``__init__`` declares the parameters
(:mod:`jointfit_ros.node_parameters`, from the specs of :mod:`jointfit_ros.params`),
creates one :class:`~jointfit_ros.runner.JointRunner` per joint, the subscriptions
(``raw=True``: messages are parsed from their bytes with numpy,
:mod:`jointfit_ros.conversions`), publishers, timers and services; the callbacks
convert and hand over to the runners. What it publishes besides the joints' outputs
is made elsewhere: the input's diagnostics status (:mod:`jointfit_ros.input_status`),
the joints' (:mod:`jointfit_ros.joint_diagnostics`), the RViz markers
(:mod:`jointfit_ros.rviz_output`), ``~/segments`` and TF; the freeze and save
services' work is :mod:`jointfit_ros.node_services`'s. SIGINT and SIGTERM stop
it between callbacks (:mod:`jointfit_ros.stop_request`). Topics, parameters and
services are listed in the README.
"""

from __future__ import annotations

import dataclasses
import re
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseStamped, PoseWithCovarianceStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSPolicyKind, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import JointState, PointCloud2
from std_msgs.msg import String
from std_srvs.srv import SetBool, Trigger
from visualization_msgs.msg import MarkerArray

from jointfit_core.estimator import JointOutput, SolveRequest
from jointfit_core.hinge_from_sums import PoseSumsAxis

from .calibration_store import NodeCalibrationFile
from .conversions import (
    axis_pose_bytes,
    diagnostic_status,
    pose_with_covariance_bytes,
    stamp_from_ns,
)
from .description import RobotDescription
from .frame_load import FrameLoad
from .graph import graph_problems
from .guard import CallbackGuard
from .input_status import InputStatus
from .inputs import MessageRouter, Routed
from .joint_states import JointStates, joint_state_bytes
from .naming import entry_hint, params_files, status_prefix
from .node_parameters import declare_parameters, runtime_changes
from .node_services import freeze_joints, save_joints
from .params import (
    ConfigError,
    NodeConfig,
    node_config,
)
from .runner import ERROR, WARN, JointRunner
from .rviz_output import joint_markers
from .segment_output import SegmentOutput
from .solver_process import SolverProcess
from .status_log import StatusLog
from .stop_request import StopRequest
from .tf_output import TfOutput

__all__ = ["JointfitNode", "main"]

RCLError = _rclpy.RCLError

class JointfitNode(Node):
    """Online joint centres and axes from motion-capture markers (see the module docstring).

    Raises
    ------
    ConfigError
        When the parameters are invalid (the message names the parameter).
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("jointfit", **kwargs)
        self.guard = CallbackGuard(self.get_logger().error)
        self.cfg: NodeConfig = node_config(declare_parameters(self))
        reliability = (
            ReliabilityPolicy.RELIABLE if self.cfg.qos_reliability == "reliable" else ReliabilityPolicy.BEST_EFFORT
        )
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=self.cfg.qos_depth, reliability=reliability)

        self.runners = {j.name: JointRunner(j, self.cfg) for j in self.cfg.joints}
        self.calibration_file: NodeCalibrationFile | None = None
        if self.cfg.calibration_file:
            self.calibration_file = NodeCalibrationFile(
                self.cfg.calibration_file, list(self.runners.values()), self.get_fully_qualified_name(), self.cfg.units
            )
            self.calibration_file.load()
            for note in self.calibration_file.notes:
                self.get_logger().info(note)
        for name, runner in self.runners.items():
            for note in runner.load_notes:
                self.get_logger().info(f"{name}: {note}")
            if runner.loaded_from:
                self.get_logger().info(f"{name}: calibration loaded from {runner.loaded_from}; starting frozen")
            elif runner.last_error:
                self.get_logger().warning(f"{name}: {runner.last_error}")

        # Outputs.
        self._world_pubs: dict[str, Any] = {}
        self._local_pubs: dict[str, Any] = {}
        for j in self.cfg.joints:
            suffix = "centre" if j.type == "ball" else "axis"
            self._world_pubs[j.name] = self.create_publisher(PoseWithCovarianceStamped, f"{j.name}/{suffix}", 10)
            self._local_pubs[j.name] = self.create_publisher(
                PoseWithCovarianceStamped, f"{j.name}/{suffix}_local", 10
            )
        self._joint_states = JointStates([(j.name, j.type) for j in self.cfg.joints])
        self._joint_state_pub = self.create_publisher(JointState, "~/joint_states", 10)
        self._rviz_pub = self.create_publisher(MarkerArray, "~/markers", 10)
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._description = RobotDescription(self.cfg.units, self.cfg.segment_labels())
        ns = self.get_namespace().strip("/")
        self._segments = SegmentOutput(list(self.runners.values()), f"{ns}/" if ns else "")
        self._segments_pub = self.create_publisher(PoseArray, "~/segments", 10) if self._segments.names else None
        self._tf = TfOutput(self) if self._segments.names else None
        self._subscribers_due = 0.0
        self._input_status = InputStatus()  # the input status's samples between diagnostics ticks
        self._frame_load = FrameLoad()  # the input callbacks' times: whose frames went missing
        self._wants = (False, False)
        if self._tf is not None and self._tf.problem:
            self.get_logger().info(self._tf.problem)
        self._description_pub = self.create_publisher(
            String, "~/robot_description", QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        )

        # Inputs.
        self.router = MessageRouter(
            self.cfg, self.runners.values(), clock=time.monotonic_ns, stamp_clock=self._now_ns
        )
        # one joint's exception on a frame: logged and counted by the guard, the other joints still get the frame
        self.router.on_joint_error = lambda runner, exc: self.guard.caught(f"markers (joint {runner.cfg.name})", exc)
        self.router.defer_bookkeeping = True  # _on_markers publishes a frame's outputs before its bookkeeping
        self.counters = self.router.counters
        self._warned: set[str] = set()
        self._status_log = StatusLog()  # WARN/ERROR statuses on the console, once per change
        self._last_outputs: dict[str, tuple[int, str, JointOutput]] = {}
        if self.router.marker_runners:
            msg_type = PoseArray if self.cfg.marker_type == "pose_array" else PointCloud2
            self.create_subscription(
                msg_type, self.cfg.marker_topic, self.guard.wrap("markers", self._on_markers), qos, raw=True,
                event_callbacks=self._publisher_count(self.cfg.marker_topic),
            )
        for topic in self.router.pose_topics:
            self.create_subscription(
                PoseStamped, topic, self.guard.wrap(f"pose {topic}", self._pose_callback(topic)), qos, raw=True,
                event_callbacks=self._publisher_count(topic),
            )

        # Timers and services.
        self._solver = SolverProcess() if self.cfg.solver_process else None
        self._requests: dict[str, SolveRequest] = {}  # the requests the worker is answering, by joint
        self._jf_timers: dict[str, Any] = {}
        self._estimate_turn = -1  # the joint the estimate timer solved last
        self._rviz_turn = -1  # the joint whose RViz markers were published last
        self._make_timers()
        self.create_service(Trigger, "~/reset", self.guard.wrap_service("~/reset", self._on_reset))
        self.create_service(SetBool, "~/freeze", self.guard.wrap_service("~/freeze", self._on_freeze))
        self.create_service(Trigger, "~/save", self.guard.wrap_service("~/save", self._on_save))
        self.add_on_set_parameters_callback(self._on_set_parameters_guarded)
        self.get_logger().info(
            f"estimating {', '.join(f'{j.name} ({j.type})' for j in self.cfg.joints)} from "
            f"{self.cfg.marker_topic if self.router.marker_runners else 'pose topics'}"
        )

    # ------------------------------------------------------------------ parameters

    def _on_set_parameters_guarded(self, params: list[Parameter]) -> SetParametersResult:
        try:
            return self._on_set_parameters(params)
        except Exception as exc:  # refuse the change rather than end the node
            self.guard.caught("parameters", exc)
            return SetParametersResult(successful=False, reason=f"internal error: {type(exc).__name__}: {exc}")

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        """Validate run-time changes with the same checks as at start; apply them when all pass."""
        changes = runtime_changes(params)
        if isinstance(changes, str):
            return SetParametersResult(successful=False, reason=changes)
        if changes:
            self.cfg = dataclasses.replace(self.cfg, **changes)
            self.router.cfg = self.cfg
            self.router.timeline.max_jump_ns = round(self.cfg.max_stamp_jump * 1e9)
            if self.calibration_file is not None:
                self.calibration_file.units = self.cfg.units  # the unit the next save records
            for runner in self.runners.values():
                runner.node = self.cfg
                if runner.matcher is not None:
                    runner.matcher.tolerance_ns = round(self.cfg.sync_tolerance * 1e9)
            self._make_timers()
        return SetParametersResult(successful=True)

    def _timer_periods(self) -> dict[str, tuple[float, Callable[[], None]]]:
        """Each timer's period (s; 0: off) and callback, from the current parameters."""
        n = max(1, len(self.runners))
        return {
            # on the executor thread, one joint per tick, in turn: each joint is re-solved every
            # estimate_period, and no tick blocks the frame callbacks for more than one joint's solve;
            # with the solver process, every joint's due window goes in one request and the answers
            # are installed at the next tick: a tick each, so each joint is re-solved every estimate_period
            "estimate": (self.cfg.estimate_period / (n if self._solver is None else 2), self._on_estimate_timer),
            "diagnostics": (self.cfg.diagnostics_period, self._on_diagnostics_timer),
            "local": (1.0 / self.cfg.local_rate if self.cfg.local_rate > 0 else 0.0, self._on_local_timer),
            # one joint's markers per tick, in turn (each joint at rviz_rate): shorter ticks on the frames' thread
            "rviz": (1.0 / self.cfg.rviz_rate / n if self.cfg.rviz_rate > 0 else 0.0, self._on_rviz_timer),
        }

    def _make_timers(self) -> None:
        """Create, re-arm (a changed period) or destroy (0: off) the timers; an unchanged one is left alone.

        Re-arming instead of re-creating: a burst of parameter changes must not
        pile up timers on the clock (rclpy warns for each beyond a few hundred).
        """
        for name, (period, callback) in self._timer_periods().items():
            timer = self._jf_timers.get(name)
            period_ns = round(period * 1e9)
            if period_ns <= 0:
                if timer is not None:
                    self.destroy_timer(self._jf_timers.pop(name))
            elif timer is None:
                self._jf_timers[name] = self.create_timer(period, self.guard.wrap(f"{name} timer", callback))
            elif timer.timer_period_ns != period_ns:
                timer.timer_period_ns = period_ns

    # ------------------------------------------------------------------ inputs

    def _warn_once(self, key: str, text: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            self.get_logger().warning(text + " (reported once; counted in /diagnostics)")

    def _report_problem(self) -> None:
        problem = self.router.last_problem
        if problem is not None:
            self._warn_once(*problem)
            self.router.last_problem = None

    def _on_markers(self, raw: bytes) -> None:
        start = time.perf_counter()
        routed = self.router.markers(raw)  # (defer_bookkeeping: the outputs first, then after_outputs)
        try:
            for r in routed:
                self._publish_world(r)
            segments, joint_states = self._subscribed()
            if joint_states:
                self._publish_joint_states(routed)
            if segments and self.router.routed_stamp_ns is not None:
                self._publish_segments(self.router.routed_stamp_ns)
        finally:
            self.router.after_outputs()  # stamp gaps, live-geometry samples: after the frame's outputs are out
            self._frame_load.add(time.perf_counter() - start)
        self._report_problem()

    def _publish_segments(self, stamp_ns: int) -> None:
        """``~/segments`` of the frame just routed and, when tf2_ros imports, its TF tree."""
        assert self._segments_pub is not None
        R, t = self._segments.poses()
        frame = self.cfg.world_frame or self.router.frame_id
        self._segments_pub.publish(self._segments.pose_array(stamp_ns, frame, R, t))
        if self._tf is not None and self._tf.available:
            self._tf.send(self._segments.tree(R, t, frame), stamp_ns)

    def _publisher_count(self, topic: str) -> SubscriptionEventCallbacks:
        """The input's events: matched (the router holds frames back while two publishers' frames interleave),
        and publishers whose QoS cannot be matched (said in ``jointfit: input``; another message type on the
        topic is found in the graph, :mod:`jointfit_ros.graph`)."""

        def qos(event: Any) -> None:
            try:
                policy = QoSPolicyKind(int(event.last_policy_kind)).name
            except ValueError:
                policy = str(event.last_policy_kind)
            self.router.set_incompatible(topic, int(event.total_count), policy)
            self._report_problem()

        return SubscriptionEventCallbacks(
            matched=self.guard.wrap(
                f"publishers {topic}", lambda event: self.router.set_publishers(topic, int(event.current_count))
            ),
            incompatible_qos=self.guard.wrap(f"incompatible QoS {topic}", qos),
        )

    def _pose_callback(self, topic: str) -> Callable[[bytes], None]:
        def callback(raw: bytes) -> None:
            start = time.perf_counter()
            routed = self.router.pose(topic, raw)
            for r in routed:
                self._publish_world(r)
            if self._subscribed()[1]:
                self._publish_joint_states(routed)
            self._frame_load.add(time.perf_counter() - start)
            self._report_problem()

        return callback

    #: Seconds between looks at who subscribes to ``~/segments`` and ``~/joint_states``.
    SUBSCRIBERS_PERIOD = 0.25

    def _subscribed(self) -> tuple[bool, bool]:
        """Whether to make ``~/segments`` (or the TF tree) and ``~/joint_states`` for this frame.

        Each costs ~0.1-0.2 ms per frame, so it is made only while someone subscribes
        (looked at every :attr:`SUBSCRIBERS_PERIOD` s: a new subscriber is served from at
        most that much later). A skipped stretch leaves the next angle without a velocity
        (it is longer than the velocity's largest gap).
        """
        now = time.monotonic()
        if now >= self._subscribers_due:
            self._subscribers_due = now + self.SUBSCRIBERS_PERIOD
            pub = self._segments_pub
            tf = self._tf is not None and self._tf.available
            self._wants = (
                pub is not None and (tf or pub.get_subscription_count() > 0),
                self._joint_state_pub.get_subscription_count() > 0,
            )
        return self._wants

    # ------------------------------------------------------------------ outputs

    def _publish_world(self, routed: Routed) -> None:
        runner, stamp_ns, out = routed.runner, routed.stamp_ns, routed.output
        frame = self.cfg.world_frame or routed.frame_id
        # CDR bytes, not message objects: building those costs more than the estimator (bench/node_latency.py).
        if out.direction is None:
            raw = pose_with_covariance_bytes(stamp_ns, frame, out.position, out.cov)
        else:
            assert out.cov_direction is not None
            raw = axis_pose_bytes(stamp_ns, frame, out.position, out.direction, out.cov, out.cov_direction)
        self._world_pubs[runner.cfg.name].publish(raw)
        self._last_outputs[runner.cfg.name] = (stamp_ns, frame, out)

    def _publish_joint_states(self, routed: list[Routed]) -> None:
        """One ``~/joint_states`` per input stamp among ``routed`` (a message's outputs), with the joints that have angles."""
        stamps = sorted({r.stamp_ns for r in routed})
        for stamp in stamps:
            group = routed if len(stamps) == 1 else [r for r in routed if r.stamp_ns == stamp]
            angles = self._joint_states.frame(stamp, group)
            if angles is not None:
                frame = self.cfg.world_frame or group[0].frame_id
                self._joint_state_pub.publish(joint_state_bytes(stamp, frame, angles))

    def _now_ns(self) -> int:
        return int(self.get_clock().now().nanoseconds)

    def _on_estimate_timer(self) -> None:
        runners = list(self.runners.values())
        if not runners:
            return
        solver = self._solver
        if solver is not None:
            answers = solver.collect()
            for name, result in answers:  # each joint's answer on its own: a stale one is dropped there
                self.runners[name].install(result, self._requests.pop(name, None))
            if solver.alive:
                if not answers and solver.idle:
                    self._submit_due(solver)
                return  # a tick installs the answers (or waits for them) or sends, never both
            self.get_logger().warning(f"{solver.problem}: solving on the executor thread from now on")
            self._solver = None
            self._requests.clear()
            self._make_timers()  # one joint per tick from now on
        self._estimate_turn = (self._estimate_turn + 1) % len(runners)
        runners[self._estimate_turn].estimate(time.monotonic(), force=True)

    def _submit_due(self, solver: SolverProcess) -> None:
        """Send every joint's due window to the worker in one request (a joint with nothing new has none)."""
        now = time.monotonic()
        batch: list[tuple[str, SolveRequest]] = []
        for name, runner in self.runners.items():  # (per tick, not per frame)
            request = runner.solve_request(now, force=True)
            if request is not None:
                batch.append((name, request))
        if batch and solver.submit(batch):
            self._requests = dict(batch)  # an error answer is dropped if its window is gone by then

    def _on_local_timer(self) -> None:
        stamp = self._now_ns()
        for name, runner in self.runners.items():
            sol = runner.estimator.solution
            if sol is None or not sol.identifiable or runner.sign_pending:
                continue  # not identifiable (no widening here) or a sign convention not honoured yet: would mislead
            frame = runner.cfg.local_frame_id
            # CDR bytes, as the per-frame outputs: a message object costs ~0.1 ms more, on the frames' thread
            if isinstance(sol, PoseSumsAxis):
                raw = axis_pose_bytes(
                    stamp, frame, sol.point_parent, sol.direction_parent, sol.cov_point_parent, sol.cov_direction_parent
                )
            else:
                raw = pose_with_covariance_bytes(stamp, frame, sol.centre_parent, sol.cov_parent)
            self._local_pubs[name].publish(raw)

    def _on_rviz_timer(self) -> None:
        names = list(self.runners)
        if not names:
            return
        self._rviz_turn = (self._rviz_turn + 1) % len(names)
        k = self._rviz_turn
        name = names[k]
        markers = MarkerArray()
        if name in self._last_outputs:
            stamp, frame, out = self._last_outputs[name]
            length = 2.0 * self.runners[name].estimator.length_scale  # the segments' size
            markers.markers = joint_markers(name, k, stamp, frame, out, self.cfg.ellipsoid_sigma, self.cfg.rviz_rate, length)
        if markers.markers:
            self._rviz_pub.publish(markers)

    def _publish_description(self) -> None:
        """``~/robot_description`` when the frozen joints changed (:mod:`jointfit_ros.description`)."""
        text = self._description.update(self.runners.values())
        if text is not None:
            self._description_pub.publish(String(data=text))
            self.get_logger().info(f"robot description published ({self._description.joints} frozen joints)")

    def _on_diagnostics_timer(self) -> None:
        self._publish_description()
        arr = DiagnosticArray()
        arr.header.stamp = stamp_from_ns(self._now_ns())
        node_values: dict[str, object] = {}
        now = time.monotonic()
        level, message = self._input_status.status(
            now, self.counters, self.router.gaps, self.cfg, node_values, self.router.incompatible, self._frame_load
        )
        node_values.update({
            "robot description": self._description.problem or f"published ({self._description.joints} frozen joints)",
            "input frame_id": self.router.frame_id,
            "segments (~/segments order)": ", ".join(self._segments.names) or "none (no marker joints)",
            "TF": "no marker joints" if self._tf is None else self._tf.problem or "broadcast (/tf, /tf_static)",
            "estimates solved in": "a worker process" if self._solver is not None else "the executor thread",
            "unexpected errors (callbacks)": self.guard.count,
        })
        if self.guard.count:
            node_values["last unexpected error"] = self.guard.last
            level = ERROR if self.guard.recent else max(level, WARN)
            message += f"; {self.guard.count} unexpected error(s), last: {self.guard.last}"
        graph = self._graph_problems()
        if graph:
            level = max(level, WARN)
            message += "; " + "; ".join(graph)
            node_values["graph problems"] = " | ".join(graph)
        node_id = self.get_fully_qualified_name()  # which node a status is from (`jointfit status --node`)
        prefix = status_prefix(node_id)  # "jointfit", or "subject_a/jointfit" in a namespace
        arr.status.append(diagnostic_status(f"{prefix}: input", level, message, node_values, hardware_id=node_id))
        for name, runner in self.runners.items():
            st = runner.live_status(now)
            arr.status.append(
                diagnostic_status(f"{prefix}: {name}", st.level, st.message, st.values, hardware_id=node_id)
            )
            note = runner.auto_freeze()  # once done: freeze and save (the next status says frozen)
            if note:
                self.get_logger().info(f"{name}: {note}")
        self._diag_pub.publish(arr)
        self._status_log.log(((st.name, st.level[0], st.message) for st in arr.status), self.get_logger())

    def _graph_problems(self) -> list[str]:
        """Same-name nodes and wrong-type publishers on the inputs (:func:`~jointfit_ros.graph.graph_problems`); logged once each."""
        marker_type = "geometry_msgs/msg/PoseArray" if self.cfg.marker_type == "pose_array" else "sensor_msgs/msg/PointCloud2"
        expected = {self.resolve_topic_name(t): "geometry_msgs/msg/PoseStamped" for t in self.router.pose_topics}
        if self.router.marker_runners:
            expected[self.resolve_topic_name(self.cfg.marker_topic)] = marker_type
        publishers = {t: [i.topic_type for i in self.get_publishers_info_by_topic(t)] for t in expected}
        problems = graph_problems(
            self.get_node_names_and_namespaces(), (self.get_name(), self.get_namespace()), publishers, expected
        )
        for text in problems:
            self._warn_once(f"graph:{text}", text)
        return problems

    def destroy_node(self) -> None:
        if self._solver is not None:
            self._solver.close()
            self._solver = None
        super().destroy_node()

    # ------------------------------------------------------------------ services

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        for runner in self.runners.values():
            runner.reset()
        self._last_outputs.clear()
        self._joint_states.reset()
        self.router.reset()
        response.success = True
        response.message = f"reset {', '.join(self.runners)}"
        self.get_logger().info(response.message)
        return response

    def _on_freeze(self, request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        response.success, response.message = freeze_joints(self.runners.values(), bool(request.data))
        self.get_logger().info(response.message)
        return response

    def _on_save(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success, response.message = save_joints(self.runners.values(), self.calibration_file)
        self.get_logger().info(response.message)
        return response


def _executor() -> Any:
    """The events executor (handles 1 kHz inputs here without drops), else the single-threaded one."""
    try:
        from rclpy.experimental import EventsExecutor

        return EventsExecutor()
    except (ImportError, AttributeError, RuntimeError):  # pragma: no cover - other rclpy versions
        return rclpy.executors.SingleThreadedExecutor()


USAGE = """usage: jointfit_node --ros-args --params-file PARAMS.yaml [-r __ns:=/NAMESPACE] [-p NAME:=VALUE ...]

Online joint centres (ball joints) and axes (hinges) from motion-capture markers.
The parameters (joints, marker_names, <joint>.parent_markers, ...) are listed with their
meaning, unit, default and range in the README ("Parameters") and, for a running node, by
`ros2 param describe`; commented examples are in config/*.yaml (config/fake_mocap.yaml
runs against `python -m jointfit_ros.fake_mocap`).
"""


def _rcl_message(exc: Exception) -> str:
    """rcl's error text without the ``, at /project/src/...`` source locations."""
    return re.sub(r",? at /\S+:\d+", "", str(exc)).replace("failed to initialize rcl: ", "").strip().rstrip(",")


def _params_entry_hint(argv: list[str]) -> str:
    """Why the parameters may be missing: no entry of the ``--params-file`` files is for this node's full name."""
    files = []
    for path in params_files(argv):
        try:
            doc = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, yaml.YAMLError):
            continue  # rcl has read it already; nothing to add
        files.append((path, [str(k) for k in doc] if isinstance(doc, dict) else []))
    probe = Node("jointfit", enable_rosout=False)  # the name and namespace after the remaps (-r __ns:=..., -r __node:=...)
    try:
        return entry_hint(files, probe.get_fully_qualified_name())
    finally:
        probe.destroy_node()


def main(args: list[str] | None = None) -> None:
    """Console script ``jointfit_node``."""
    argv = list(sys.argv[1:] if args is None else args)
    ros_at = argv.index("--ros-args") if "--ros-args" in argv else len(argv)
    if {"-h", "--help"} & set(argv[:ros_at]):
        print(USAGE, end="")
        raise SystemExit(0)
    with StopRequest() as stop:
        _run(args, argv, stop)


def _run(args: list[str] | None, argv: list[str], stop: StopRequest) -> None:
    """Start rclpy and the node, spin until ``stop`` is requested (SIGINT, SIGTERM) or rclpy shuts down."""
    try:
        # rclpy's own handlers would raise KeyboardInterrupt inside whatever callback runs (a FATAL and a
        # traceback from the executor): SIGINT and SIGTERM are StopRequest's, read between callbacks
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except RCLError as exc:  # an unreadable --params-file, a bad remap: rcl's message without its source lines
        print(f"jointfit_node: cannot start: {_rcl_message(exc)}", file=sys.stderr)
        raise SystemExit(2) from None
    node: JointfitNode | None = None
    try:
        try:
            node = JointfitNode()
        except (ConfigError, ParameterException) as exc:
            hint = _params_entry_hint(argv)
            print(
                f"jointfit_node: invalid parameters: {exc}{'; ' + hint if hint else ''} "
                "(jointfit_node --help: where they are described)",
                file=sys.stderr,
            )
            raise SystemExit(2) from None
        executor = _executor()
        executor.add_node(node)
        # spin_once in a loop: with this rclpy, EventsExecutor.spin() stops firing timers.
        while rclpy.ok() and not stop.requested:
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        if rclpy.ok():
            raise
        # the context shut down while the node was starting (another owner of the context, or rclpy's
        # handlers where StopRequest could not install its own), and whatever rcl call came next failed
        # (e.g. "error creating node: the given context is not valid"): a stop, not an error
        print("jointfit_node: stopped while starting", file=sys.stderr)
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
