"""One calibration file for a whole node: its segments, each in one frame, and its joints (format version 2).

A per-joint calibration (version 1, :meth:`OnlineJoint.to_dict
<jointfit_core.estimator.OnlineJoint.to_dict>` plus the joint's record:
``joint``, ``parent_markers``, ``child_markers``, ``parent_pose_topic``,
``child_pose_topic``) holds one joint in its own two template frames. A node
calibration (version 2) holds every joint of a node together::

    format: jointfit-node-calibration
    version: 2
    node: /subject_a/jointfit        # who wrote it (informative)
    units: m                         # the length unit of every number in it
    segments:
      RTHI:                          # named as the ~/segments, TF frames and URDF links
        markers: [RTHI1, RTHI2, RTHI3, RTHI4]   # or [] and pose_topic
        pose_topic: ''
        owner: {joint: r_hip, side: child}      # whose template is the segment's one frame
        template: [[x, y, z], ...]              # the owner's template: the markers in that frame
    joints:
      r_knee:
        kind: hinge
        parent: RTHI                 # segment names
        child: RSHK
        in_parent: {point: [...], direction: [...], cov_point: [[...]], cov_direction: [[...]]}
        in_child: {...}              # the same estimate in the child segment's frame
        calibration: {...}           # the joint's version-1 calibration, restored exactly as a file of its own

Everything but ``calibration`` is derived (:func:`node_calibration` computes
it from the joints' calibrations) and read by people and other tools: a
chain's hip centre (``r_hip.in_child``) and knee axis (``r_knee.in_parent``)
are then in the one thigh frame ``RTHI``. The segments and their frames
follow :class:`~jointfit_core.segment_frames.SegmentFrames`: a segment is a
distinct marker list (a pose topic is ``pose:<topic>``, a chained joint's
virtual marker ``chain:<joint>``), its frame the template of its owner (the
first joint with it as the child, else the first joint); another joint's
template of it is aligned to the owner's by Kabsch. The joints with two
marker segments (those of the node's ``~/segments``) are taken first and own
the segments they have, so that these segments' names and frames are those
of ``~/segments`` and TF.

Pure Python and numpy; written atomically with a ``.bak`` by
:func:`save_node_calibration` (:func:`jointfit_core.calibration.save_calibration`).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .calibration import _array, fit_from_dict, load_calibration, save_calibration
from .errors import InputError
from .hinge_from_sums import PoseSumsAxis
from .segment_frames import SegmentFrames, SegmentJoint
from .segments import PoseSumsCentre

__all__ = [
    "NODE_CALIBRATION_FORMAT",
    "NODE_CALIBRATION_VERSION",
    "node_calibration",
    "check_node_calibration",
    "load_node_calibration",
    "save_node_calibration",
    "segment_key",
]

FloatArray = NDArray[np.float64]

#: ``format`` of a node calibration (a per-joint one is ``jointfit-calibration``).
NODE_CALIBRATION_FORMAT = "jointfit-node-calibration"
#: The node calibration's ``version`` (per-joint calibrations are version 1).
NODE_CALIBRATION_VERSION = 2

_SIDES = ("parent", "child")


def segment_key(calibration: Mapping[str, Any], side: str) -> tuple[str, ...]:
    """The marker list that identifies a joint's parent or child segment in a calibration's record.

    Parameters
    ----------
    calibration : mapping
        A per-joint calibration with the joint's record (``<side>_markers``, ``<side>_pose_topic``).
    side : {"parent", "child"}

    Returns
    -------
    tuple of str
        The markers (chained joints as ``chain:<joint>``), or ``("pose:<topic>",)`` for a pose topic.

    Raises
    ------
    InputError
        The record is missing or malformed.
    """
    markers = calibration.get(f"{side}_markers")
    topic = calibration.get(f"{side}_pose_topic") or ""
    if not isinstance(topic, str) or not isinstance(markers, list) or not all(isinstance(m, str) for m in markers):
        raise InputError(
            f"node calibration: joint {calibration.get('joint')!r} has no record of its {side} segment "
            f"({side}_markers: a list of names, {side}_pose_topic: a string)"
        )
    if topic:
        return (f"pose:{topic}",)
    if not markers:
        raise InputError(f"node calibration: joint {calibration.get('joint')!r} has neither {side} markers nor a pose topic")
    return tuple(markers)


def _solution(calibration: Mapping[str, Any]) -> PoseSumsCentre | PoseSumsAxis:
    if calibration.get("kind") == "ball":
        return fit_from_dict(PoseSumsCentre, calibration["estimate"])
    return fit_from_dict(PoseSumsAxis, calibration["estimate"])


def _templates(calibration: Mapping[str, Any]) -> tuple[FloatArray, FloatArray]:
    tp, tc = _array(calibration["template_parent"]), _array(calibration["template_child"])
    if tp.ndim != 2 or tp.shape[1] != 3 or tc.ndim != 2 or tc.shape[1] != 3:
        raise InputError(f"node calibration: joint {calibration.get('joint')!r}: templates are not (P, 3) arrays")
    return tp, tc


def _plain(a: FloatArray | None) -> Any:
    return None if a is None else np.asarray(a, dtype=np.float64).tolist()


def _in_segment(
    sol: PoseSumsCentre | PoseSumsAxis, side: int, A: FloatArray, a: FloatArray
) -> dict[str, Any]:
    """The estimate seen from one side, carried into that side's segment frame (``x_segment = A x_joint + a``)."""
    if isinstance(sol, PoseSumsCentre):
        point, cov = (sol.centre_parent, sol.cov_parent) if side == 0 else (sol.centre_child, sol.cov_child)
        direction = cov_direction = None
    else:
        point, cov = (sol.point_parent, sol.cov_point_parent) if side == 0 else (sol.point_child, sol.cov_point_child)
        direction = sol.direction_parent if side == 0 else sol.direction_child
        cov_direction = sol.cov_direction_parent if side == 0 else sol.cov_direction_child
    return {
        "point": _plain(A @ point + a),
        "direction": None if direction is None else _plain(A @ direction),
        "cov_point": _plain(A @ cov @ A.T),
        "cov_direction": None if cov_direction is None else _plain(A @ cov_direction @ A.T),
    }


def node_calibration(
    calibrations: Sequence[Mapping[str, Any]],
    *,
    node: str = "",
    units: str = "",
    segment_labels: Mapping[tuple[str, ...], str] | None = None,
) -> dict[str, Any]:
    """A node calibration (version 2) from its joints' per-joint calibrations.

    Parameters
    ----------
    calibrations : sequence of mapping
        Per joint, in the node's order, its calibration as a per-joint file
        holds it (:meth:`OnlineJoint.to_dict <jointfit_core.estimator.OnlineJoint.to_dict>`
        with the joint's record: ``joint``, ``parent_markers``,
        ``child_markers``, ``parent_pose_topic``, ``child_pose_topic``).
    node : str
        The node's name (recorded, not checked on load).
    units : str
        The length unit of the markers (``m``, ``cm``, ``mm``; checked on load).
    segment_labels : mapping, optional
        Segment names by marker list (the node's configured ``segments``), as in
        ``~/segments``; the others are named by :func:`~jointfit_core.urdf.segment_names`.

    Returns
    -------
    dict
        Plain types (see the module docstring); ``calibration`` of each joint is its input, unchanged.

    Raises
    ------
    InputError
        A calibration without its joint's record or estimate, two with the same joint name.

    Notes
    -----
    Joint ``i``'s point ``p`` and direction ``d`` in its side's template frame
    become ``A p + a`` and ``A d`` in the segment frame, its covariances
    ``A C A^T``, with ``(A, a)`` the Kabsch alignment of the segment owner's
    template onto the joint's (:meth:`SegmentFrames.alignment
    <jointfit_core.segment_frames.SegmentFrames.alignment>`: identity for the
    owner). The parent side is :meth:`SegmentFrames.joint_frames
    <jointfit_core.segment_frames.SegmentFrames.joint_frames>`' point and
    direction (what TF publishes); a hinge's point on the child side is its
    own axis point nearest the child template's origin, another point of the same axis.
    """
    names = [str(c.get("joint", "")) for c in calibrations]
    if len(set(names)) != len(names) or not all(names):
        raise InputError(f"node calibration: every joint needs its own non-empty name, got {names}")
    keys = [(segment_key(c, "parent"), segment_key(c, "child")) for c in calibrations]
    try:
        sols = [_solution(c) for c in calibrations]
        templates = [_templates(c) for c in calibrations]
    except (KeyError, TypeError) as exc:
        raise InputError(f"node calibration: a joint's calibration has no estimate or templates ({exc!r})") from None

    def plain_markers(k: int) -> bool:  # the joints of ~/segments: two marker segments, no chain, no pose topic
        return all(not m.startswith(("chain:", "pose:")) for key in keys[k] for m in key)

    plain = [k for k in range(len(names)) if plain_markers(k)]
    order = plain + [k for k in range(len(names)) if not plain_markers(k)]
    frames = SegmentFrames(
        [SegmentJoint(names[k], keys[k][0], keys[k][1]) for k in order], segment_labels, primary=len(plain)
    )
    ordered_templates = [templates[k] for k in order]
    joint_frames = {
        jf.name: jf
        for jf in frames.joint_frames([sols[k] for k in order], ordered_templates, [False] * len(order))
    }
    segments: dict[str, Any] = {}
    for s, name in enumerate(frames.names):
        i, side = frames.owner[s]
        key = keys[order[i]][side]
        topic = key[0][len("pose:"):] if key[0].startswith("pose:") else ""
        segments[name] = {
            "markers": [] if topic else list(key),
            "pose_topic": topic,
            "owner": {"joint": names[order[i]], "side": _SIDES[side]},
            "template": _plain(ordered_templates[i][side]),
        }
    joints: dict[str, Any] = {}
    position = {k: i for i, k in enumerate(order)}
    for k, name in enumerate(names):
        i = position[k]
        entry: dict[str, Any] = {
            "kind": calibrations[k].get("kind"),
            "parent": frames.names[frames.segment_of(i, 0)],
            "child": frames.names[frames.segment_of(i, 1)],
        }
        for side in (0, 1):
            al = frames.alignment(i, side, ordered_templates)
            assert al is not None  # every template is given
            entry[f"in_{_SIDES[side]}"] = _in_segment(sols[k], side, *al)
        jf = joint_frames[name]  # the parent side as TF has it (the same numbers)
        entry["in_parent"]["point"] = _plain(np.asarray(jf.point, dtype=np.float64))
        if jf.direction is not None:
            entry["in_parent"]["direction"] = _plain(np.asarray(jf.direction, dtype=np.float64))
        entry["calibration"] = dict(calibrations[k])
        joints[name] = entry
    return {
        "format": NODE_CALIBRATION_FORMAT,
        "version": NODE_CALIBRATION_VERSION,
        "node": node,
        "units": units,
        "segments": segments,
        "joints": joints,
    }


def check_node_calibration(data: Any, source: str = "node calibration") -> dict[str, Any]:
    """Check a node calibration's header and shape; return it.

    Only what concerns the whole file is checked here: the format, the
    version, ``joints`` a mapping of joint name to a mapping with a
    ``calibration`` mapping. Each joint's calibration is validated by
    whoever restores it (as a per-joint file is), so that one bad joint does
    not refuse the others.

    Raises
    ------
    InputError
        Not a node calibration (a per-joint one is named as such), a newer version, no ``joints`` mapping.
    """
    if not isinstance(data, dict):
        raise InputError(f"{source}: expected a mapping, got {type(data).__name__}")
    fmt = data.get("format")
    if fmt == "jointfit-calibration":
        raise InputError(
            f"{source}: this is one joint's calibration (version {data.get('version')!r}, joint "
            f"{data.get('joint')!r}), not a node calibration: give it as <joint>.calibration_file"
        )
    if fmt != NODE_CALIBRATION_FORMAT:
        raise InputError(f"{source}: expected format {NODE_CALIBRATION_FORMAT!r}, got {fmt!r}")
    version = data.get("version")
    if not isinstance(version, int) or isinstance(version, bool) or version != NODE_CALIBRATION_VERSION:
        raise InputError(
            f"{source}: version {version!r} is not supported (this jointfit reads node calibrations of version "
            f"{NODE_CALIBRATION_VERSION})"
        )
    joints = data.get("joints")
    if not isinstance(joints, dict):
        raise InputError(f"{source}: expected 'joints', a mapping of joint name to its entry")
    for name, entry in joints.items():
        if not isinstance(entry, dict) or not isinstance(entry.get("calibration"), dict):
            raise InputError(f"{source}: joint {name!r} has no 'calibration' mapping")
    units = data.get("units")
    if not isinstance(units, str):
        raise InputError(f"{source}: expected 'units', a string, got {units!r}")
    return data


def load_node_calibration(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read and check a node calibration written by :func:`save_node_calibration`.

    Raises
    ------
    FileNotFoundError
        No such file.
    InputError
        Not YAML, or not a node calibration this jointfit reads (:func:`check_node_calibration`).
    UnicodeDecodeError
        Not UTF-8.
    """
    return check_node_calibration(load_calibration(path), f"node calibration {path}")


def save_node_calibration(path: str | os.PathLike[str], data: Mapping[str, Any]) -> Path:
    """Write a node calibration atomically, the previous file kept as ``<path>.bak``.

    See :func:`jointfit_core.calibration.save_calibration` (temporary file,
    fsync, rename: a reader or a crash sees the old or the new file, never a part).

    Raises
    ------
    InputError
        ``data`` is not a node calibration (:func:`check_node_calibration`); nothing is written.
    OSError
        The file cannot be written (the previous one is kept).
    """
    return save_calibration(path, check_node_calibration(dict(data), "node calibration"))
