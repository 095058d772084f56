"""The node's parameters: declarations, defaults, descriptions and validation.

Pure Python (no rclpy): :data:`NODE_PARAMS` and :data:`JOINT_PARAMS` list every
parameter once with its type, default, unit and meaning; :func:`node_config`
turns a flat ``{name: value}`` mapping (as read from the ROS parameter server
or a YAML file) into a checked :class:`NodeConfig`, raising
:class:`ConfigError` with a message that names the parameter, what was
expected and what came. The node declares exactly these parameters and runs
the same checks on run-time changes.

Joint parameters live under the joint's name: ``hip.type``, ``hip.parent_markers``, ...
"""

from __future__ import annotations

import difflib
import math
import os
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from jointfit_core.errors import JointfitError
from jointfit_core.window_entries import WINDOW_MAX_FRAMES

from .naming import DEFAULT_NODE, entry_matches, is_wildcard, node_path

__all__ = [
    "ConfigError",
    "ParamSpec",
    "NODE_PARAMS",
    "JOINT_PARAMS",
    "JointConfig",
    "NodeConfig",
    "node_config",
    "check_value",
    "joint_param_names",
    "RUNTIME_PARAMS",
    "parameters_markdown",
    "params_from_file",
    "check_known",
    "calibration_path",
    "ANATOMICAL_GROUPS",
    "SEGMENT_PARAMS",
    "SegmentConfig",
]


class ConfigError(JointfitError, ValueError):
    """A parameter is missing, of the wrong type or out of range."""


@dataclass(frozen=True)
class ParamSpec:
    """One parameter: name, type, default, description and limits.

    Attributes
    ----------
    name : str
        Parameter name (joint parameters: the part after ``<joint>.``).
    kind : str
        ``"string"``, ``"int"``, ``"double"``, ``"bool"`` or ``"string_array"``.
    default : object
        Default value (``[]`` for string arrays).
    description : str
        Meaning and unit, shown by ``ros2 param describe`` and in the README.
    choices : tuple of str, optional
        Allowed values of a string parameter.
    minimum : float, optional
        Smallest allowed number.
    runtime : bool
        Whether it may be changed while the node runs (the others are read-only).
    maximum : float, optional
        Largest allowed number (what timers, integer nanoseconds and memory can honour).
    nonzero_minimum : float, optional
        Smallest allowed number other than 0 (for rates where 0 means off).
    """

    name: str
    kind: str
    default: Any
    description: str
    choices: tuple[str, ...] | None = None
    minimum: float | None = None
    runtime: bool = False
    maximum: float | None = None
    nonzero_minimum: float | None = None


NODE_PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("joints", "string_array", [], "Names of the joints to estimate; each has `<name>.*` parameters."),
    ParamSpec("marker_topic", "string", "markers", "Topic with the labelled (or unlabelled) markers of all segments."),
    ParamSpec(
        "marker_type",
        "string",
        "pose_array",
        "Message type of marker_topic: pose_array (geometry_msgs/PoseArray, positions used) or pointcloud2 "
        "(sensor_msgs/PointCloud2 with x, y, z float32 or float64).",
        choices=("pose_array", "pointcloud2"),
    ),
    ParamSpec(
        "marker_names",
        "string_array",
        [],
        "Names of the markers in the order of the points in marker_topic (or of the label values).",
    ),
    ParamSpec(
        "label_field",
        "string",
        "",
        "PointCloud2 integer field holding each point's index into marker_names; empty: points are in "
        "marker_names order (or unlabelled).",
    ),
    ParamSpec(
        "unlabelled",
        "bool",
        False,
        "PointCloud2 without labels in a varying order: label each cloud by optimal assignment to the markers' "
        "last positions (needs a first cloud in marker_names order with every marker visible).",
    ),
    ParamSpec(
        "assignment_gate",
        "double",
        0.03,
        "Unlabelled clouds: largest distance between a point and a marker's last position to accept the "
        "assignment (input units, m for ROS).",
        minimum=0.0,
        runtime=True,
        maximum=1e6,
    ),
    ParamSpec(
        "zero_is_missing",
        "bool",
        True,
        "Treat a point at exactly (0, 0, 0) as an occluded marker (mocap4ros2 Vicon convention). With `false`, "
        "such points are taken as positions, counted and named in the input status (WARN).",
        runtime=True,
    ),
    ParamSpec(
        "qos_reliability",
        "string",
        "best_effort",
        "Reliability of the input subscriptions: best_effort (sensor data) or reliable.",
        choices=("best_effort", "reliable"),
    ),
    ParamSpec("qos_depth", "int", 10, "Queue depth of the input subscriptions (messages).", minimum=1, maximum=10000),
    ParamSpec(
        "world_frame",
        "string",
        "",
        "frame_id of the world outputs; empty: the frame_id of the input messages.",
    ),
    ParamSpec(
        "input_frame_id",
        "string",
        "",
        "Accept only input messages with this header.frame_id (others are dropped and counted); "
        "empty: any frame_id.",
        runtime=True,
    ),
    ParamSpec(
        "units",
        "string",
        "m",
        "Length unit of the inputs (m by REP 103). Only checked: a diagnostic warns when the marker clusters' "
        "size is implausible for it (e.g. millimetres sent to a node configured for metres).",
        choices=("m", "cm", "mm"),
        runtime=True,
    ),
    ParamSpec(
        "estimate_period",
        "double",
        0.1,
        "Seconds between re-solving each joint's estimate from its window (the per-frame outputs use the latest); "
        "with solver_process all joints are solved in one request per period, else they take turns within it.",
        minimum=0.001,
        runtime=True,
        maximum=3600.0,
    ),
    ParamSpec(
        "solver_process",
        "bool",
        True,
        "Solve the estimates in a worker process, so that a solve (0.3-0.4 ms per joint, 0.7-1.8 ms with attachment "
        "skin) does not delay the frames arriving meanwhile; every joint's due window goes to it in one request. "
        "False: on the executor thread, one joint per estimate tick (one process). Set at start.",
    ),
    ParamSpec(
        "local_rate",
        "double",
        10.0,
        "Rate (Hz) of `<joint>/centre_local` and `<joint>/axis_local`; 0 disables them.",
        minimum=0.0,
        runtime=True,
        maximum=1000.0, nonzero_minimum=1e-3,
    ),
    ParamSpec(
        "rviz_rate",
        "double",
        5.0,
        "Rate (Hz) of each joint's `~/markers` (RViz MarkerArray, one joint per message in turn); 0 disables them.",
        minimum=0.0,
        runtime=True,
        maximum=100.0, nonzero_minimum=1e-3,
    ),
    ParamSpec(
        "diagnostics_period",
        "double",
        1.0,
        "Seconds between /diagnostics messages.",
        minimum=0.01,
        runtime=True,
        maximum=3600.0,
    ),
    ParamSpec(
        "sync_tolerance",
        "double",
        0.002,
        "Largest stamp difference (s) to pair parent and child data from different topics.",
        minimum=0.0,
        runtime=True,
        maximum=10.0,
    ),
    ParamSpec(
        "ellipsoid_sigma",
        "double",
        2.0,
        "Size of the RViz covariance ellipsoids in standard deviations.",
        minimum=0.0,
        runtime=True,
        maximum=100.0,
    ),
    ParamSpec(
        "max_cloud_points",
        "int",
        2000,
        "Unlabelled PointCloud2: a cloud with more points than this is dropped and counted (labelling costs grow "
        "with the points, and a flood of ghosts would corrupt the tracking); the tracking goes on from the "
        "clouds before it.",
        minimum=1,
        maximum=10_000_000,
        runtime=True,
    ),
    ParamSpec(
        "workspace",
        "double",
        0.0,
        "Half-width of the capture volume in metres (converted by units): a marker with a coordinate beyond it "
        "is treated as missing and counted, and no output beyond it is published; 0 (default): no limit (markers "
        "far outside their segment are still treated as missing).",
        minimum=0.0,
        runtime=True,
        maximum=1e6,
    ),
    ParamSpec(
        "max_stamp_jump",
        "double",
        1.0,
        "Largest step (s) of header.stamp ahead of a topic's latest stamp (beyond the time since it arrived) "
        "taken as the stream going on; a single message further ahead is dropped and counted, a steady run of "
        "them is adopted.",
        minimum=0.001,
        runtime=True,
        maximum=3600.0,
    ),
    ParamSpec(
        "calibration_file",
        "string",
        "",
        "One YAML file for the whole node (version 2: its segments, each in one frame, and every joint's "
        "calibration; `~` and environment variables are expanded): `~/save` and auto_freeze write it, and it is "
        "loaded at start when it exists (the joints found in it start frozen). Not together with "
        "`<joint>.calibration_file` (the per-joint files, version 1). Empty: none.",
    ),
    ParamSpec(
        "stale_after",
        "double",
        3.0,
        "Seconds without input after which a status is STALE; also the wall-clock span the input rates are "
        "measured over.",
        minimum=0.1,
        runtime=True,
        maximum=86400.0,
    ),
    ParamSpec(
        "segments",
        "string_array",
        [],
        "Names of the body segments (optional; e.g. [PELV, RTHI, RSHK]): each has `<segment>.markers` or "
        "`<segment>.pose_topic`, and joints name theirs with `<joint>.parent` / `<joint>.child` instead of listing "
        "markers. A segment shared by two joints (the thigh: the hip's child and the knee's parent) is one "
        "segment, named so in `~/segments`, the TF tree and the URDF.",
    ),
)

#: Parameters of one segment of ``segments``, under its name (``RTHI.markers``).
SEGMENT_PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("markers", "string_array", [], "Names (from marker_names) of the segment's markers (>= 3 to be posed)."),
    ParamSpec(
        "pose_topic",
        "string",
        "",
        "Instead of markers: a geometry_msgs/PoseStamped topic with the segment's rigid-body pose.",
    ),
)

_PELVIS_USE = (
    "Ball joints with all four iliac spines: the centre in the ISB pelvis frame (Wu et al. 2002; origin mid-ASIS, "
    "x anterior, y superior, z right), as % of the inter-ASIS width, beside the Bell et al. (1990) and "
    "Harrington et al. (2007) regressions."
)
_EPICONDYLE_USE = (
    "Hinges with both epicondyles: the axis's angle to the epicondyle line and its distance from their midpoint."
)

_ANATOMICAL_PARAMS: tuple[ParamSpec, ...] = tuple(
    ParamSpec(
        f"anatomical.{role}",
        "string",
        "",
        f"Anatomical landmark ({what}): a name from marker_names, moving with the parent segment. {use} "
        "Used by `jointfit fit` (summary, report) and in the node's /diagnostics; empty: none.",
    )
    for role, what, use in (
        ("rasis", "right anterior superior iliac spine", _PELVIS_USE),
        ("lasis", "left anterior superior iliac spine", "With the other three spines, see anatomical.rasis."),
        ("rpsis", "right posterior superior iliac spine", "With the other three spines, see anatomical.rasis."),
        ("lpsis", "left posterior superior iliac spine", "With the other three spines, see anatomical.rasis."),
        ("lateral_epicondyle", "lateral femoral epicondyle", _EPICONDYLE_USE),
        ("medial_epicondyle", "medial femoral epicondyle", "With the lateral one, see anatomical.lateral_epicondyle."),
    )
)

JOINT_PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("type", "string", "ball", "ball (centre of rotation) or hinge (axis).", choices=("ball", "hinge")),
    ParamSpec(
        "parent",
        "string",
        "",
        "The parent segment, a name from `segments` (instead of parent_markers / parent_pose_topic).",
    ),
    ParamSpec(
        "child",
        "string",
        "",
        "The child segment, a name from `segments` (instead of child_markers / child_pose_topic).",
    ),
    ParamSpec("parent_markers", "string_array", [], "Names (from marker_names) of the parent segment's markers, >= 3."),
    ParamSpec("child_markers", "string_array", [], "Names (from marker_names) of the child segment's markers, >= 3."),
    ParamSpec(
        "parent_chain",
        "string_array",
        [],
        "Skeleton chain (Pham et al. V-B): earlier joints (from `joints`) whose per-frame world centre (ball) or "
        "axis point (hinge) is added to the parent segment's markers as a virtual marker.",
    ),
    ParamSpec(
        "child_chain",
        "string_array",
        [],
        "As parent_chain, for the child segment (e.g. the hip centre as a marker of the thigh).",
    ),
    ParamSpec(
        "parent_pose_topic",
        "string",
        "",
        "Instead of markers: a geometry_msgs/PoseStamped topic with the parent segment's rigid-body pose.",
    ),
    ParamSpec(
        "child_pose_topic",
        "string",
        "",
        "Instead of markers: a geometry_msgs/PoseStamped topic with the child segment's rigid-body pose.",
    ),
    ParamSpec(
        "pose_translation_sd",
        "double",
        0.0005,
        "Pose inputs: standard deviation of the pose position per axis (input units, m for ROS).",
        minimum=0.0,
        maximum=1e6,
    ),
    ParamSpec(
        "pose_rotation_sd_deg",
        "double",
        0.2,
        "Pose inputs: standard deviation of the pose orientation per axis (degrees).",
        minimum=0.0,
        maximum=180.0,
    ),
    ParamSpec(
        "window",
        "int",
        3000,
        "Sliding window length in frames (used when window_s and half_life_s are 0): 30 s at 100 Hz, but 6 s at "
        "500 Hz; a joint that is not identifiable with a full window of under 20 s says so in its status. It keeps "
        "every frame (5-8.6 KB each): at high rates prefer window_s, which window_max_frames bounds.",
        minimum=3,
        maximum=1_000_000,
    ),
    ParamSpec(
        "window_s",
        "double",
        0.0,
        "Sliding window length in seconds of stamp time; 0: use window.",
        minimum=0.0,
        maximum=3600.0,
    ),
    ParamSpec(
        "window_max_frames",
        "int",
        WINDOW_MAX_FRAMES,
        "Most frames a window_s window holds (5-8.6 KB of memory each): fed faster than window_max_frames / "
        "window_s per second, at most one frame per window_s / window_max_frames seconds enters the window; every "
        "frame still gets its output. 0: every frame enters (30 s at 1 kHz: 258 MB per skin hinge).",
        minimum=0,
        maximum=1_000_000,
    ),
    ParamSpec(
        "half_life_s",
        "double",
        0.0,
        "Exponential forgetting instead of a window: a frame's weight halves every half_life_s seconds; 0: off.",
        minimum=0.0,
        maximum=86400.0,
    ),
    ParamSpec(
        "template_frames",
        "int",
        50,
        "Fully visible frames averaged into each segment's template.",
        minimum=1,
        maximum=10_000,
    ),
    ParamSpec(
        "outlier_gate",
        "double",
        5.0,
        "Outlier gate: a segment whose markers jump by more than this many times their normal frame-to-frame "
        "change (or fail the residual test, this many times the noise, while moving more than usual) has swapped "
        "labels put right, else loses its worst marker (down to 3) or is not posed in that frame (ghosts, jumps; "
        "smooth skin motion passes); 0: off.",
        minimum=0.0,
        maximum=1e3,
    ),
    ParamSpec(
        "attachment",
        "string",
        "auto",
        "How both segments' markers are attached: skin (markers or clusters on the skin: the covariance adds a "
        "soft-tissue-artefact part that does not shrink with the window) or rigid (markers on rigid bodies, "
        "robots, bone pins, rigid-body pose inputs, the fake mocap); auto: rigid when both segments are pose "
        "topics (rigid-body inputs), else skin. A rigid body tracked on a skin-mounted plate or strap is skin: "
        "set it.",
        choices=("auto", "skin", "rigid"),
    ),
    ParamSpec(
        "calibration_file",
        "string",
        "",
        "YAML file for `~/save` (`~` is expanded); loaded at start when it exists (the joint then starts frozen). "
        "Not together with the node's calibration_file. Empty: none.",
    ),
    ParamSpec(
        "axis_toward_marker",
        "string",
        "",
        "Hinge sign: the axis direction points toward this marker (any name from marker_names): from "
        "axis_from_marker when that is set, else from the clusters' centre (only when the marker lies beyond "
        "both clusters along the axis; otherwise the diagnostics say it is ambiguous). Chosen once, from the "
        "first identifiable estimate with a direction sd below 5 deg; empty: the parent-frame axis with the "
        "largest component is positive at the first identifiable estimate, and later estimates keep that sign.",
    ),
    ParamSpec(
        "axis_from_marker",
        "string",
        "",
        "Hinge sign with axis_toward_marker: the axis points from this marker toward that one (e.g. from the "
        "medial to the lateral epicondyle), whatever the clusters' positions; empty: the one-marker form.",
    ),
    ParamSpec(
        "publish_unidentified",
        "bool",
        False,
        "Publish the per-frame outputs while the joint is not identifiable, with their covariance widened along "
        "what the motion leaves undetermined; false (default): no per-frame output until it is identifiable.",
    ),
    ParamSpec(
        "freeze_unidentified",
        "bool",
        False,
        "Let `~/freeze` and `~/save` accept an estimate that is not identifiable (and load such a calibration); "
        "false (default): they refuse it, with the reason.",
    ),
    ParamSpec(
        "local_frame_id",
        "string",
        "",
        "frame_id of `<joint>/centre_local` (the parent template frame); empty: `<joint>_parent`.",
    ),
    *_ANATOMICAL_PARAMS,
    ParamSpec(
        "target_sd",
        "double",
        0.0,
        "Done signal: /diagnostics says `done` once the joint is identifiable, its status has no warning and "
        "its sd is at most this (ball: the centre's largest sd, input units, m for ROS; hinge: the direction's "
        "largest sd, degrees); 0 (default): no done signal.",
        minimum=0.0,
        maximum=1e6,
    ),
    ParamSpec(
        "auto_freeze",
        "bool",
        False,
        "Once done (needs target_sd > 0): freeze the joint and save its calibration_file (or its entry of the "
        "node's calibration_file; when set) by itself, once (logged; after `~/freeze` false it waits for "
        "`~/reset`); false (default): you call `~/freeze` and `~/save`.",
    ),
)

#: Landmark roles of ``<joint>.anatomical.*`` by group: all of a group or none.
ANATOMICAL_GROUPS: dict[str, tuple[str, ...]] = {
    "pelvis": ("rasis", "lasis", "rpsis", "lpsis"),
    "epicondyles": ("lateral_epicondyle", "medial_epicondyle"),
}

#: Parameters that may change while the node runs.
RUNTIME_PARAMS = frozenset(p.name for p in NODE_PARAMS if p.runtime)

_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
#: The node parameters' names: a joint or a segment may not take one (their keys would clash in a parameter file).
_NODE_NAMES = frozenset(p.name for p in NODE_PARAMS)


@dataclass(frozen=True)
class JointConfig:
    """Checked parameters of one joint (see :data:`JOINT_PARAMS`)."""

    name: str
    type: str
    parent_markers: tuple[str, ...]
    child_markers: tuple[str, ...]
    parent_chain: tuple[str, ...]
    child_chain: tuple[str, ...]
    parent_pose_topic: str
    child_pose_topic: str
    pose_translation_sd: float
    pose_rotation_sd_deg: float
    window: int
    window_s: float
    half_life_s: float
    template_frames: int
    outlier_gate: float
    calibration_file: str
    axis_toward_marker: str
    local_frame_id: str
    axis_from_marker: str = ""
    publish_unidentified: bool = False
    freeze_unidentified: bool = False
    anatomical: tuple[tuple[str, str], ...] = ()
    target_sd: float = 0.0
    auto_freeze: bool = False
    attachment: str = "skin"
    parent_segment: str = ""
    child_segment: str = ""
    window_max_frames: int = WINDOW_MAX_FRAMES

    def landmarks(self, group: str) -> dict[str, str] | None:
        """The markers of a landmark group of :data:`ANATOMICAL_GROUPS` by role, or None when not configured."""
        given = dict(self.anatomical)
        roles = ANATOMICAL_GROUPS[group]
        return {r: given[r] for r in roles} if all(r in given for r in roles) else None

    def segment_names(self) -> tuple[str, str]:
        """The parent and the child by role and segment name or markers (or pose topic).

        E.g. ``parent RTHI`` with ``segments``, else ``parent (RTHI1, RTHI2, RTHI3)``.
        """
        return (
            f"parent {self.parent_segment}" if self.parent_segment
            else f"parent ({', '.join(self.parent_markers) or self.parent_pose_topic})",
            f"child {self.child_segment}" if self.child_segment
            else f"child ({', '.join(self.child_markers) or self.child_pose_topic})",
        )

    def window_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of :class:`jointfit_core.estimator.OnlineJoint` for the window."""
        if self.window_s > 0.0:
            return {"window_s": self.window_s}
        if self.half_life_s > 0.0:
            return {"half_life_s": self.half_life_s}
        return {"window": self.window}


@dataclass(frozen=True)
class SegmentConfig:
    """Checked parameters of one segment of ``segments`` (see :data:`SEGMENT_PARAMS`)."""

    name: str
    markers: tuple[str, ...]
    pose_topic: str


@dataclass(frozen=True)
class NodeConfig:
    """Checked node parameters (see :data:`NODE_PARAMS`)."""

    marker_topic: str
    marker_type: str
    marker_names: tuple[str, ...]
    label_field: str
    unlabelled: bool
    assignment_gate: float
    zero_is_missing: bool
    qos_reliability: str
    qos_depth: int
    world_frame: str
    input_frame_id: str
    units: str
    estimate_period: float
    solver_process: bool
    local_rate: float
    rviz_rate: float
    diagnostics_period: float
    sync_tolerance: float
    ellipsoid_sigma: float
    joints: tuple[JointConfig, ...]
    workspace: float = 0.0
    max_cloud_points: int = 2000
    max_stamp_jump: float = 1.0
    stale_after: float = 3.0
    segments: tuple[SegmentConfig, ...] = ()
    calibration_file: str = ""

    def segment_labels(self) -> dict[tuple[str, ...], str]:
        """The configured segments' names by marker list (empty without ``segments``)."""
        return {s.markers: s.name for s in self.segments if s.markers}

    def marker_index(self, name: str) -> int:
        """Row of a marker in the marker frame."""
        return self.marker_names.index(name)


def joint_param_names(joint: str) -> list[str]:
    """Full names of a joint's parameters (``<joint>.<name>``)."""
    return [f"{joint}.{p.name}" for p in JOINT_PARAMS]


def check_value(spec: ParamSpec, value: Any, full_name: str | None = None) -> Any:
    """Check one value against its spec and return it in its Python type.

    ``None`` (a parameter declared by type but never set) gives the default.

    Raises
    ------
    ConfigError
    """
    name = full_name or spec.name
    if value is None:
        return list(spec.default) if spec.kind == "string_array" else spec.default
    if spec.kind == "string":
        if not isinstance(value, str):
            raise ConfigError(f"{name}: expected a string, got {value!r}")
        if spec.choices is not None and value not in spec.choices:
            raise ConfigError(f"{name}: expected one of {list(spec.choices)}, got {value!r}")
        return value
    if spec.kind == "bool":
        if not isinstance(value, bool):
            raise ConfigError(f"{name}: expected true or false, got {value!r}")
        return value
    if spec.kind == "string_array":
        if isinstance(value, str) or not isinstance(value, Sequence) or not all(isinstance(v, str) for v in value):
            raise ConfigError(f"{name}: expected a list of strings, got {value!r}")
        return list(value)
    if spec.kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{name}: expected an integer, got {value!r}")
    elif spec.kind == "double":
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)):
            raise ConfigError(f"{name}: expected a finite number, got {value!r}")
        value = float(value)
    if spec.minimum is not None and value < spec.minimum:
        raise ConfigError(f"{name}: expected a value >= {spec.minimum:g}, got {value!r}")
    if spec.maximum is not None and value > spec.maximum:
        raise ConfigError(f"{name}: expected a value <= {spec.maximum:g}, got {value!r}")
    if spec.nonzero_minimum is not None and value != 0 and value < spec.nonzero_minimum:
        raise ConfigError(f"{name}: expected 0 (off) or a value >= {spec.nonzero_minimum:g}, got {value!r}")
    return value


def _values(specs: Sequence[ParamSpec], values: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    return {s.name: check_value(s, values.get(prefix + s.name), prefix + s.name) for s in specs}


def _minimal_hint(v: Mapping[str, Any], name: str) -> str:
    """What Pham et al.'s marker-count rules say about a joint with fewer than 3 markers on a side."""
    from jointfit_core.identifiability import marker_count_identifiability

    n_p = 4 if v["parent_pose_topic"] else len(v["parent_markers"]) + len(v["parent_chain"])
    n_c = 4 if v["child_pose_topic"] else len(v["child_markers"]) + len(v["child_chain"])
    if min(n_p, n_c) < 1:
        return ""
    verdict = marker_count_identifiability(v["type"], n_p, n_c)
    if not verdict.identifiable:
        return f"; {verdict.reason}"
    return (
        f"; ({n_p}, {n_c}) markers identify a {v['type']} joint only with the batch minimal-marker method "
        f"jointfit_core.{verdict.function} (the online estimator poses each segment from >= 3 markers)"
    )


def _joint_config(
    name: str, values: Mapping[str, Any], marker_names: Sequence[str], earlier: Mapping[str, JointConfig]
) -> JointConfig:
    v = _values(JOINT_PARAMS, values, name + ".")
    known = set(marker_names)
    for side in ("parent", "child"):
        markers = v[f"{side}_markers"]
        topic = v[f"{side}_pose_topic"]
        chain = v[f"{side}_chain"]
        for source in chain:
            if source not in earlier:
                raise ConfigError(
                    f"{name}.{side}_chain: {source!r} is not a joint listed before {name!r} in joints "
                    f"(earlier joints: {list(earlier)})"
                )
            if not (earlier[source].parent_markers or earlier[source].child_markers):
                raise ConfigError(f"{name}.{side}_chain: {source!r} reads only pose topics; chain joints read markers")
        if len(set(chain)) != len(chain):
            raise ConfigError(f"{name}.{side}_chain: a joint is listed twice: {chain!r}")
        if topic:
            if markers or chain:
                raise ConfigError(
                    f"{name}.{side}_markers/{side}_chain: give markers (and chain joints) or "
                    f"{name}.{side}_pose_topic, not both"
                )
            continue
        if chain and not markers:
            raise ConfigError(f"{name}.{side}_chain: needs at least one real marker in {name}.{side}_markers too")
        if len(markers) + len(chain) < 3:
            raise ConfigError(
                f"{name}.{side}_markers: expected at least 3 marker names (with {name}.{side}_chain joints; or "
                f"{name}.{side}_pose_topic), got {markers!r}" + _minimal_hint(v, name)
            )
        _check_marker_list(f"{name}.{side}_markers", markers, marker_names)
    shared = set(v["parent_markers"]) & set(v["child_markers"])
    if shared:
        raise ConfigError(f"{name}: markers {sorted(shared)} are on both the parent and the child")
    if v["window_s"] > 0.0 and v["half_life_s"] > 0.0:
        raise ConfigError(f"{name}: give window_s or half_life_s (or neither, for window), not both")
    for side in ("parent", "child"):
        if v[f"{side}_pose_topic"] and (v["pose_translation_sd"] <= 0.0 or v["pose_rotation_sd_deg"] <= 0.0):
            raise ConfigError(f"{name}: pose inputs need pose_translation_sd > 0 and pose_rotation_sd_deg > 0")
    marker = v["axis_toward_marker"]
    from_marker = v["axis_from_marker"]
    if from_marker:
        if not marker:
            raise ConfigError(f"{name}.axis_from_marker: needs axis_toward_marker too")
        if from_marker not in known:
            raise ConfigError(f"{name}.axis_from_marker: expected a name from marker_names, got {from_marker!r}")
        if from_marker == marker:
            raise ConfigError(f"{name}.axis_from_marker: must differ from axis_toward_marker ({marker!r})")
    if marker:
        if v["type"] != "hinge":
            raise ConfigError(f"{name}.axis_toward_marker: only for hinges (type is {v['type']!r})")
        if marker not in known:
            raise ConfigError(f"{name}.axis_toward_marker: expected a name from marker_names, got {marker!r}")
        if not (v["parent_markers"] or v["child_markers"]):
            raise ConfigError(
                f"{name}.axis_toward_marker: needs marker inputs (this joint reads only pose topics); "
                "leave it empty"
            )
    anatomical = _anatomical(name, v, known)
    if v["auto_freeze"] and not v["target_sd"] > 0.0:
        raise ConfigError(f"{name}.auto_freeze: needs {name}.target_sd > 0 (the done signal it waits for)")
    return JointConfig(
        name=name,
        type=v["type"],
        parent_markers=tuple(v["parent_markers"]),
        child_markers=tuple(v["child_markers"]),
        parent_chain=tuple(v["parent_chain"]),
        child_chain=tuple(v["child_chain"]),
        parent_pose_topic=v["parent_pose_topic"],
        child_pose_topic=v["child_pose_topic"],
        pose_translation_sd=v["pose_translation_sd"],
        pose_rotation_sd_deg=v["pose_rotation_sd_deg"],
        window=v["window"],
        window_s=v["window_s"],
        half_life_s=v["half_life_s"],
        window_max_frames=v["window_max_frames"],
        template_frames=v["template_frames"],
        outlier_gate=v["outlier_gate"],
        calibration_file=v["calibration_file"],
        axis_toward_marker=marker,
        local_frame_id=v["local_frame_id"] or f"{name}_parent",
        axis_from_marker=from_marker,
        publish_unidentified=v["publish_unidentified"],
        freeze_unidentified=v["freeze_unidentified"],
        anatomical=anatomical,
        target_sd=v["target_sd"],
        auto_freeze=v["auto_freeze"],
        attachment=_attachment(v),
    )


def _attachment(v: Mapping[str, Any]) -> str:
    """``<joint>.attachment`` resolved: ``auto`` is rigid for two pose topics (rigid-body inputs), else skin."""
    value = str(v["attachment"])
    if value != "auto":
        return value
    return "rigid" if v["parent_pose_topic"] and v["child_pose_topic"] else "skin"


def _anatomical(name: str, v: Mapping[str, Any], known: set[str]) -> tuple[tuple[str, str], ...]:
    """The ``anatomical.*`` landmarks, checked: names from marker_names, whole groups, the right joint type."""
    given = {role: v[f"anatomical.{role}"] for roles in ANATOMICAL_GROUPS.values() for role in roles}
    for role, marker in given.items():
        if marker and marker not in known:
            raise ConfigError(f"{name}.anatomical.{role}: expected a name from marker_names, got {marker!r}")
    for group, roles in ANATOMICAL_GROUPS.items():
        named = [r for r in roles if given[r]]
        if named and len(named) < len(roles):
            missing = [f"{name}.anatomical.{r}" for r in roles if not given[r]]
            raise ConfigError(f"{name}.anatomical: the {group} landmarks go together; missing {', '.join(missing)}")
        markers = [given[r] for r in named]
        if len(set(markers)) != len(markers):
            raise ConfigError(f"{name}.anatomical: a marker is named for two {group} landmarks: {markers!r}")
    kind = {"pelvis": "ball", "epicondyles": "hinge"}
    for group, roles in ANATOMICAL_GROUPS.items():
        if given[roles[0]] and v["type"] != kind[group]:
            raise ConfigError(f"{name}.anatomical.{roles[0]}: the {group} landmarks are for {kind[group]} joints "
                              f"(type is {v['type']!r})")
        if given[roles[0]] and not (v["parent_markers"] or v["child_markers"]):
            raise ConfigError(f"{name}.anatomical.{roles[0]}: needs marker inputs (this joint reads only pose topics)")
    return tuple((r, m) for r, m in given.items() if m)


def calibration_path(text: str) -> Path:
    """A ``calibration_file`` value as a path: ``~`` and environment variables (``$HOME/...``) expanded.

    Raises
    ------
    ConfigError
        A variable that is not set (the path would be taken literally, relative to the working directory).
    """
    expanded = os.path.expanduser(os.path.expandvars(text))
    if "$" in expanded:
        raise ConfigError(f"calibration_file: {text!r} names an environment variable that is not set")
    return Path(expanded)


def _check_marker_list(key: str, markers: Sequence[str], marker_names: Sequence[str]) -> None:
    """A joint side's or a segment's markers (parameter ``key``): names from marker_names, each once."""
    unknown = [m for m in markers if m not in marker_names]
    if unknown:
        raise ConfigError(f"{key}: {unknown} are not in marker_names {list(marker_names)}")
    if len(set(markers)) != len(markers):
        raise ConfigError(f"{key}: a marker is listed twice: {list(markers)!r}")


def _segment_configs(
    values: Mapping[str, Any], segments: Sequence[str], marker_names: Sequence[str]
) -> dict[str, SegmentConfig]:
    """The ``segments`` and their ``<segment>.*`` parameters, checked (names, markers, one input each)."""
    out: dict[str, SegmentConfig] = {}
    owner: dict[str, str] = {}
    for name in segments:
        v = _values(SEGMENT_PARAMS, values, name + ".")
        markers, topic = v["markers"], v["pose_topic"]
        if bool(markers) == bool(topic):
            raise ConfigError(
                f"{name}: give {name}.markers (names from marker_names) or {name}.pose_topic, "
                + ("not both" if markers else "got neither")
            )
        _check_marker_list(f"{name}.markers", markers, marker_names)
        for m in markers:
            if m in owner:
                raise ConfigError(f"{name}.markers: {m!r} is also on segment {owner[m]!r}; a marker is on one segment")
            owner[m] = name
        out[name] = SegmentConfig(name=name, markers=tuple(markers), pose_topic=topic)
    return out


def _check_segment_names(segments: Sequence[str], joints: Sequence[str]) -> None:
    """Segment names: valid, each once, none a joint's or a node parameter's (their keys would share a prefix)."""
    for name in segments:
        if not _NAME.match(name):
            raise ConfigError(f"segments: {name!r} is not a valid name (letters, digits and _; starting with a letter)")
        if name in joints:
            raise ConfigError(f"segments: {name!r} is also a joint's name; a segment needs a name of its own")
        if name in _NODE_NAMES:
            raise ConfigError(f"segments: {name!r} is the name of a node parameter; give the segment another name")
    if len(set(segments)) != len(segments):
        raise ConfigError(f"segments: a name is listed twice: {list(segments)!r}")


def _with_segments(
    values: Mapping[str, Any], joints: Sequence[str], segments: Mapping[str, SegmentConfig]
) -> tuple[dict[str, Any], dict[str, tuple[str, str]]]:
    """The joints' ``parent`` / ``child`` segments written out as their markers or pose topics.

    Returns the values with ``<joint>.<side>_markers`` (or ``_pose_topic``) filled in
    and, per joint, its (parent, child) segment names ("" where not given).
    """
    specs = {s.name: s for s in JOINT_PARAMS}
    out = dict(values)
    named: dict[str, tuple[str, str]] = {}
    for j in joints:
        sides = []
        for side in ("parent", "child"):
            seg = check_value(specs[side], values.get(f"{j}.{side}"), f"{j}.{side}")
            sides.append(seg)
            if not seg:
                continue
            if seg not in segments:
                raise ConfigError(f"{j}.{side}: {seg!r} is not in segments {list(segments)}")
            if values.get(f"{j}.{side}_markers") or values.get(f"{j}.{side}_pose_topic"):
                raise ConfigError(
                    f"{j}.{side}: give the segment ({j}.{side}) or {j}.{side}_markers / {j}.{side}_pose_topic, "
                    "not both"
                )
            cfg = segments[seg]
            chain = check_value(specs[f"{side}_chain"], values.get(f"{j}.{side}_chain"), f"{j}.{side}_chain")
            if cfg.markers and len(cfg.markers) + len(chain) < 3:
                raise ConfigError(
                    f"{j}.{side}: segment {seg!r} has {len(cfg.markers)} marker(s) {list(cfg.markers)}; a joint's "
                    f"segment needs at least 3 to be posed (with {j}.{side}_chain joints)"
                )
            if cfg.markers:
                out[f"{j}.{side}_markers"] = list(cfg.markers)
            else:
                out[f"{j}.{side}_pose_topic"] = cfg.pose_topic
        if sides[0] and sides[0] == sides[1]:
            raise ConfigError(f"{j}: parent and child are the same segment {sides[0]!r}")
        named[j] = (sides[0], sides[1])
    return out, named


def check_known(names: Iterable[str], joints: Sequence[str], segments: Sequence[str] = ()) -> None:
    """Refuse parameter names that no declaration knows (a misspelt key would be ignored in silence).

    Parameters
    ----------
    names : iterable of str
        Full names as given (``marker_topic``, ``hip.outlier_gate``, ...);
        ``use_sim_time`` and ``qos_overrides.*`` (rclpy's own) are allowed.
    joints : sequence of str
        The configured joints.
    segments : sequence of str
        The configured segments (``segments``).

    Raises
    ------
    ConfigError
        Naming the first unknown key and the closest known one.
    """
    known = {s.name for s in NODE_PARAMS} | {f"{j}.{s.name}" for j in joints for s in JOINT_PARAMS}
    known |= {f"{g}.{s.name}" for g in segments for s in SEGMENT_PARAMS}
    for name in names:
        if name in known or name == "use_sim_time" or name.startswith("qos_overrides."):
            continue
        head = name.split(".")[0]
        if "." in name and head not in joints and head not in segments:
            hint = f"; {head!r} is not in joints {list(joints)}" + (
                f" nor in segments {list(segments)}" if segments else ""
            )
        else:
            close = difflib.get_close_matches(name, sorted(known), n=1, cutoff=0.6)
            hint = f"; did you mean {close[0]!r}?" if close else ""
        raise ConfigError(f"{name}: unknown parameter{hint}")


def node_config(values: Mapping[str, Any]) -> NodeConfig:
    """Check every parameter and build the node's configuration.

    Parameters
    ----------
    values : mapping
        Full parameter names (``marker_topic``, ``hip.type``, ...) to values;
        missing names take their defaults.

    Raises
    ------
    ConfigError
        The first problem found, naming the parameter.
    """
    v = _values(NODE_PARAMS, values)
    joints = v["joints"]
    if not joints:
        raise ConfigError("joints: expected at least one joint name, got none")
    for j in joints:
        if not _NAME.match(j):
            raise ConfigError(f"joints: {j!r} is not a valid name (letters, digits and _; starting with a letter)")
        if j in _NODE_NAMES:  # `units: m` and `units: {type: ball}` cannot both be in a parameter file
            raise ConfigError(f"joints: {j!r} is the name of a node parameter; give the joint another name")
    if len(set(joints)) != len(joints):
        raise ConfigError(f"joints: a name is listed twice: {joints!r}")
    _check_segment_names(v["segments"], joints)
    check_known(values, joints, v["segments"])
    names = v["marker_names"]
    if len(set(names)) != len(names):
        raise ConfigError(f"marker_names: a name is listed twice: {names!r}")
    if v["unlabelled"] and (v["marker_type"] != "pointcloud2" or v["label_field"]):
        raise ConfigError("unlabelled: only for marker_type pointcloud2 without a label_field")
    segments = _segment_configs(values, v["segments"], names)
    resolved, named = _with_segments(values, joints, segments)
    done: dict[str, JointConfig] = {}
    for j in joints:
        parent, child = named[j]
        done[j] = replace(_joint_config(j, resolved, names, done), parent_segment=parent, child_segment=child)
    configs = tuple(done.values())
    files: dict[str, str] = {}
    for c in configs:
        if c.calibration_file:
            key = os.path.normpath(calibration_path(c.calibration_file))
            if key in files:
                raise ConfigError(
                    f"{c.name}.calibration_file: {c.calibration_file!r} is also {files[key]}'s; each joint needs a "
                    "file of its own (saves would overwrite each other)"
                )
            files[key] = c.name
    if v["calibration_file"]:
        calibration_path(v["calibration_file"])  # an unset environment variable: an error at start
        if files:
            raise ConfigError(
                f"calibration_file: the node's calibration file and "
                f"{', '.join(f'{n}.calibration_file' for n in files.values())} are set; give the node's file "
                "(all joints, version 2) or per-joint files (version 1), not both"
            )
    if not names and any(c.parent_markers or c.child_markers for c in configs):
        raise ConfigError("marker_names: expected the names of the points of marker_topic, got none")
    return NodeConfig(
        marker_topic=v["marker_topic"],
        marker_type=v["marker_type"],
        marker_names=tuple(names),
        label_field=v["label_field"],
        unlabelled=v["unlabelled"],
        assignment_gate=v["assignment_gate"],
        zero_is_missing=v["zero_is_missing"],
        qos_reliability=v["qos_reliability"],
        qos_depth=v["qos_depth"],
        world_frame=v["world_frame"],
        input_frame_id=v["input_frame_id"],
        units=v["units"],
        estimate_period=v["estimate_period"],
        solver_process=v["solver_process"],
        local_rate=v["local_rate"],
        rviz_rate=v["rviz_rate"],
        diagnostics_period=v["diagnostics_period"],
        sync_tolerance=v["sync_tolerance"],
        ellipsoid_sigma=v["ellipsoid_sigma"],
        joints=configs,
        workspace=v["workspace"],
        max_cloud_points=v["max_cloud_points"],
        max_stamp_jump=v["max_stamp_jump"],
        stale_after=v["stale_after"],
        segments=tuple(segments.values()),
        calibration_file=v["calibration_file"],
    )


def _default_text(spec: ParamSpec) -> str:
    if spec.kind == "string_array":
        return "(required)" if spec.name in ("joints",) else "`[]`"
    if spec.kind == "string":
        return f'`"{spec.default}"`'
    if spec.kind == "bool":
        return "`true`" if spec.default else "`false`"
    return f"`{spec.default}`"


def range_text(spec: ParamSpec) -> str:
    """The allowed range of a numeric parameter in words (empty for others), e.g. `` Range: 0 or 0.001-1000.``."""
    if spec.minimum is None and spec.maximum is None:
        return ""
    low = "" if spec.minimum is None else f"{spec.minimum:g}"
    if spec.nonzero_minimum is not None:
        low = f"0 or {spec.nonzero_minimum:g}"
    high = "" if spec.maximum is None else f"{spec.maximum:g}"
    if low and high:
        return f" Range: {low} to {high}."
    return f" Range: >= {low}." if low else f" Range: <= {high}."


def parameters_markdown() -> str:
    """The parameter tables of the README (generated from the specs, so that they stay true)."""
    lines = ["| parameter | type | default | run-time | meaning |", "|---|---|---|---|---|"]
    for spec in NODE_PARAMS:
        choices = f" One of: {', '.join(spec.choices)}." if spec.choices else ""
        lines.append(
            f"| `{spec.name}` | {spec.kind} | {_default_text(spec)} | {'yes' if spec.runtime else 'no'} | "
            f"{spec.description}{choices}{range_text(spec)} |"
        )
    lines += ["", "Per joint, under its name (`hip.type`, ...):", ""]
    lines += ["| parameter | type | default | meaning |", "|---|---|---|---|"]
    for spec in JOINT_PARAMS:
        choices = f" One of: {', '.join(spec.choices)}." if spec.choices else ""
        lines.append(
            f"| `<joint>.{spec.name}` | {spec.kind} | {_default_text(spec)} | {spec.description}{choices}"
            f"{range_text(spec)} |"
        )
    lines += ["", "Per segment of `segments`, under its name (`RTHI.markers`, ...):", ""]
    lines += ["| parameter | type | default | meaning |", "|---|---|---|---|"]
    for spec in SEGMENT_PARAMS:
        lines.append(f"| `<segment>.{spec.name}` | {spec.kind} | {_default_text(spec)} | {spec.description} |")
    return "\n".join(lines) + "\n"


def _flatten(values: Mapping[str, Any], prefix: str, out: dict[str, Any]) -> None:
    for key, value in values.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            _flatten(value, name + ".", out)
        else:
            out[name] = value


def params_from_file(path: str | os.PathLike[str], node_name: str | None = None) -> dict[str, Any]:
    """Read a ROS 2 parameter file (``--params-file``) into flat ``{name: value}`` for :func:`node_config`.

    Parameters
    ----------
    path : str or os.PathLike
        YAML file of the form ``<node>: {ros__parameters: {...}}``; nested
        mappings become dotted names (``hip: {type: ball}`` is ``hip.type``).
    node_name : str, optional
        The node the entries are read for, with its namespace
        (``/subject_a/jointfit``; ``jointfit`` is ``/jointfit``). Its entries
        are those the node would get from ``--params-file``
        (:func:`~jointfit_ros.naming.entry_matches`: its full name, ``/**``,
        ``/*/jointfit`` ...), in the file's order, wildcard entries before the
        node's own so that it overrides them. None (default): the file's only
        entry without a wildcard (with the wildcard entries), whatever its
        name (``/subject_a/jointfit``), else ``/jointfit``.

    Returns
    -------
    dict of str to object

    Raises
    ------
    ConfigError
        The file is missing or unreadable, is not YAML, or holds no
        ``ros__parameters`` for the node (the message lists the entries found).
    """
    import yaml  # a runtime dependency (PyYAML), imported late like the other readers

    file = Path(path)
    try:
        doc = yaml.safe_load(file.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{file}: no such parameter file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{file}: cannot read the parameter file ({exc})") from None
    except yaml.YAMLError as exc:
        where = getattr(exc, "problem_mark", None)
        line = f" at line {where.line + 1}" if where is not None else ""
        raise ConfigError(f"{file}: not valid YAML{line}") from None
    if not isinstance(doc, Mapping):
        raise ConfigError(f"{file}: expected a mapping '<node name>: {{ros__parameters: ...}}', got {type(doc).__name__}")
    entries = {str(k): v for k, v in doc.items()}
    named = [k for k in entries if not is_wildcard(k)]
    if node_name is None:
        node_name = named[0] if len(named) == 1 else DEFAULT_NODE
    full = node_path(node_name)
    chosen = [k for k in entries if is_wildcard(k) and entry_matches(k, full)]
    chosen += [k for k in named if entry_matches(k, full)]
    if not chosen:
        raise ConfigError(
            f"{file}: no entry for node {full} (its full name, '/**' or another wildcard); entries: {sorted(entries)}"
        )
    out: dict[str, Any] = {}
    for key in chosen:
        entry = entries[key]
        params = entry.get("ros__parameters") if isinstance(entry, Mapping) else None
        if not isinstance(params, Mapping):
            raise ConfigError(f"{file}: entry {key!r} has no 'ros__parameters' mapping")
        _flatten(params, "", out)
    return out
