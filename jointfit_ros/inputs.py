"""From message bytes to what the joint runners take: shared by the node and the offline tools.

ROS-free: :class:`MessageRouter` parses marker messages (PoseArray or
PointCloud2, labelled, ordered or unlabelled) into ``(P, 3)`` frames in
``marker_names`` order and pose messages into rotations and translations,
hands them to the :class:`~jointfit_ros.runner.JointRunner` of each joint,
and counts what it drops. The node calls it from its subscription callbacks;
``jointfit fit`` calls it for every message of a recording, so that both
compute exactly the same thing.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from jointfit_core.estimator import JointOutput

from .params import NodeConfig
from .raw import (
    ConversionError,
    frame_from_points,
    label_points,
    label_problems,
    parse_pointcloud2,
    parse_pose_array,
    parse_pose_stamped,
    rotation_matrix_from_quaternion,
)
from .runner import JointRunner

__all__ = ["MessageRouter", "Routed"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Routed:
    """One joint's output for one message: the runner, the stamp, the frame id and the output."""

    runner: JointRunner
    stamp_ns: int
    frame_id: str
    output: JointOutput


class MessageRouter:
    """Parse messages and route them to the joints that use them.

    Parameters
    ----------
    cfg : NodeConfig
    runners : iterable of JointRunner

    Attributes
    ----------
    counters : dict of str to int
        ``messages``, ``malformed`` (unparsable or inconsistent messages),
        ``wrong_frame_id`` (messages whose ``header.frame_id`` is not
        ``input_frame_id``, when that is set),
        ``label_problems`` (labelled clouds with out-of-range or duplicated
        labels), ``unassigned`` (markers of unlabelled clouds left without a
        point).
    last_problem : tuple of (str, str) or None
        ``(key, text)`` of the latest dropped message, for a one-time log line.
    frame_id : str
        frame_id of the latest message.
    recorded : list of (int, ndarray) or None
        When set to a list (the offline fit does, for its report), every
        parsed marker frame is appended as ``(stamp_ns, frame (P, 3))``.
    """

    def __init__(self, cfg: NodeConfig, runners: Iterable[JointRunner]) -> None:
        self.cfg = cfg
        self.runners = list(runners)
        self.marker_runners = [r for r in self.runners if r.uses_marker_topic]
        self.pose_topics: dict[str, list[tuple[JointRunner, int]]] = {}
        for r in self.runners:
            for source, topic in ((0, r.cfg.parent_pose_topic), (1, r.cfg.child_pose_topic)):
                if topic:
                    self.pose_topics.setdefault(topic, []).append((r, source))
        self.counters = {"messages": 0, "malformed": 0, "wrong_frame_id": 0, "label_problems": 0, "unassigned": 0}
        self.last_problem: tuple[str, str] | None = None
        self.frame_id = ""
        self._last_frame: FloatArray | None = None
        self.recorded: list[tuple[int, FloatArray]] | None = None

    def reset(self) -> None:
        """Forget the unlabelled-cloud prediction (after a reset of the joints)."""
        self._last_frame = None

    def _problem(self, key: str, text: str, counter: str = "malformed") -> None:
        self.counters[counter] += 1
        self.last_problem = (key, text)

    def _frame_id_ok(self, frame_id: str, topic: str) -> bool:
        wanted = self.cfg.input_frame_id
        if not wanted or frame_id == wanted:
            return True
        self._problem(
            f"frame_id:{topic}",
            f"dropped a message on {topic} in frame {frame_id!r}; input_frame_id is {wanted!r}",
            "wrong_frame_id",
        )
        return False

    def frame(self, raw: bytes) -> tuple[int, str, FloatArray] | None:
        """Parse a marker message into ``(stamp_ns, frame_id, frame (P, 3))``; None when dropped."""
        cfg = self.cfg
        n = len(cfg.marker_names)
        try:
            if cfg.marker_type == "pose_array":
                msg = parse_pose_array(raw)
            else:
                msg = parse_pointcloud2(raw, label_field=cfg.label_field or None)
            if np.isinf(msg.points).any():
                raise ConversionError("infinite coordinates (NaN marks an occluded marker; inf is corrupt data)")
            if msg.labels is None and not cfg.unlabelled and msg.points.shape[0] != n:
                raise ConversionError(
                    f"{msg.points.shape[0]} points without labels, expected {n} (one per name in marker_names, "
                    "in order; an occluded marker must be sent as NaN or zeros, not left out)"
                )
            if msg.labels is not None:
                problems = label_problems(msg.labels, n)
                if problems.out_of_range or problems.duplicated:
                    self.counters["label_problems"] += 1
                frame = frame_from_points(msg.points, n, labels=msg.labels, zero_is_missing=cfg.zero_is_missing)
            elif cfg.unlabelled and self._last_frame is not None:
                frame = label_points(msg.points, self._last_frame, cfg.assignment_gate, zero_is_missing=cfg.zero_is_missing)
                missing = np.isnan(frame[:, 0])
                if missing.any():
                    self.counters["unassigned"] += int(missing.sum())
            else:
                frame = frame_from_points(msg.points, n, zero_is_missing=cfg.zero_is_missing)
        except ConversionError as exc:
            self._problem("malformed", f"dropped a malformed message on {cfg.marker_topic}: {exc}")
            return None
        if not self._frame_id_ok(msg.frame_id, cfg.marker_topic):
            return None
        if cfg.unlabelled:
            # The prediction for the next cloud: the latest position of every marker seen.
            if self._last_frame is None:
                if not np.isnan(frame).any():
                    self._last_frame = frame.copy()
            else:
                seen = ~np.isnan(frame[:, 0])
                self._last_frame[seen] = frame[seen]
        return msg.stamp_ns, msg.frame_id, frame

    def markers(self, raw: bytes) -> list[Routed]:
        """A message of ``marker_topic``: the outputs of the joints it produced one for."""
        self.counters["messages"] += 1
        got = self.frame(raw)
        if got is None:
            return []
        stamp_ns, frame_id, frame = got
        self.frame_id = frame_id
        if self.recorded is not None:
            self.recorded.append((stamp_ns, frame))
        out = []
        for runner in self.marker_runners:
            result = runner.markers_frame(stamp_ns, frame)
            if result is not None:
                out.append(Routed(runner, stamp_ns, frame_id, result))
        return out

    def pose(self, topic: str, raw: bytes) -> list[Routed]:
        """A message of a pose topic: the outputs of the joints it produced one for."""
        self.counters["messages"] += 1
        try:
            msg = parse_pose_stamped(raw)
            R = rotation_matrix_from_quaternion(msg.quaternion)
        except ConversionError as exc:
            self._problem(f"malformed:{topic}", f"dropped a malformed message on {topic}: {exc}")
            return []
        if not np.isfinite(msg.position).all():
            self._problem(f"nan:{topic}", f"dropped a pose with a non-finite position on {topic}")
            return []
        if not self._frame_id_ok(msg.frame_id, topic):
            return []
        self.frame_id = self.frame_id or msg.frame_id
        out = []
        for runner, source in self.pose_topics.get(topic, []):
            result = runner.pose(source, msg.stamp_ns, R, msg.position)
            if result is not None:
                out.append(Routed(runner, msg.stamp_ns, msg.frame_id, result))
        return out
