"""A URDF of calibrated joints: segments as links at their templates, hinges and ball joints as revolute joints.

Input: saved calibrations (:meth:`OnlineJoint.to_dict
<jointfit_core.estimator.OnlineJoint.to_dict>` plus the node's record of the
joint: ``joint``, ``parent_markers``, ``child_markers``). Layout:

* **Links = segments.** A segment is its marker list: two joints whose
  child and parent marker lists are equal share the link. Its frame is its
  template frame (origin at the marker centroid) of the joint that has it as
  the child (the root: of the first joint that has it as the parent); another
  joint's template of the same markers is aligned to it (Kabsch). A link is
  named by its markers' common prefix without trailing digits and ``_``
  (``RTHI1..4`` -> ``RTHI``; ``segment_<k>`` when there is none or it is
  taken) and carries small spheres at its template markers as visuals.
* **Hinge** ``<j>``: a ``continuous`` joint ``<j>`` from the parent link,
  origin at the fitted axis point in the parent's template frame (axes of
  that frame), ``axis`` the fitted direction, to a massless link
  ``<j>_axis``; then a ``fixed`` joint ``<j>_to_child`` to the child link at
  minus the same axis point in the child frame (the calibration's
  ``point_child_matched``; a calibration saved before it existed gives the
  child's own nearest axis point, which may lie elsewhere on the axis: the
  child then sits shifted along it).
* **Ball** ``<j>``: ``continuous`` joints ``<j>_x``, ``<j>_y``, ``<j>_z``
  about x, y, z through the fitted centre (origin as for the hinge), with
  massless links ``<j>_link_x``, ``<j>_link_y``, ``<j>_link_z``; then a fixed
  joint ``<j>_to_child`` at minus the child-frame centre. The chain is
  ``Rx(alpha) Ry(beta) Rz(gamma)``, the intrinsic X-Y-Z Cardan angles of
  :func:`~jointfit_core.joint_angles.cardan_xyz`.

With the joint angles of :mod:`jointfit_core.joint_angles` (the node's
``~/joint_states``), forward kinematics give each child template frame in its
parent's: zero angles are the reference pose (both template frames aligned,
the joint point shared). Lengths are in the calibration's units (metres
for ROS, REP 103).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any
from xml.sax.saxutils import quoteattr

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from .errors import InputError
from .pose import kabsch

__all__ = [
    "UrdfJoint", "urdf_joint_from_calibration", "urdf_from_calibrations", "joint_state_names", "link_names",
    "segment_names", "kabsch",
]

FloatArray = NDArray[np.float64]

#: Visual sphere radius at each template marker, as a fraction of the template's rms radius.
MARKER_SPHERE_FRACTION = 0.08
#: Two templates of the same markers must agree (after Kabsch) to this fraction of their rms radius.
TEMPLATE_MATCH_RTOL = 0.1


def joint_state_names(name: str, kind: str) -> list[str]:
    """The ``~/joint_states`` (and URDF revolute joint) names of a joint: ``[name]`` or ``name_x, _y, _z``."""
    return [name] if kind == "hinge" else [f"{name}_{a}" for a in "xyz"]


@dataclass(frozen=True)
class UrdfJoint:
    """What the URDF needs of one calibrated joint (lengths in the calibration's units).

    Attributes
    ----------
    name, kind : str
    parent_markers, child_markers : tuple of str
    template_parent, template_child : ndarray, shape (P, 3)
    point_parent, point_child : ndarray, shape (3,)
        Ball: the centre; hinge: the axis point (each in its template frame).
    direction_parent : ndarray, shape (3,) or None
        Hinge: the unit axis in the parent template frame.
    """

    name: str
    kind: str
    parent_markers: tuple[str, ...]
    child_markers: tuple[str, ...]
    template_parent: FloatArray
    template_child: FloatArray
    point_parent: FloatArray
    point_child: FloatArray
    direction_parent: FloatArray | None


def _floats(value: Any) -> FloatArray:
    """``value`` as a float64 array (a string or a mapping in it raises ValueError / TypeError)."""
    return np.array(value, dtype=np.float64)


def urdf_joint_from_calibration(data: Mapping[str, Any], source: str = "calibration") -> UrdfJoint:
    """A :class:`UrdfJoint` from a saved calibration dict.

    Raises
    ------
    InputError
        A field is missing or malformed (e.g. a calibration saved without the node's
        ``joint`` / ``parent_markers`` / ``child_markers`` record).
    """
    try:
        name = str(data["joint"])
        kind = str(data["kind"])
        pm = tuple(str(m) for m in data["parent_markers"])
        cm = tuple(str(m) for m in data["child_markers"])
        tp = np.array(data["template_parent"], dtype=np.float64)
        tc = np.array(data["template_child"], dtype=np.float64)
        est = data["estimate"]
        if kind == "ball":
            pp, pc, direction = _floats(est["centre_parent"]), _floats(est["centre_child"]), None
        elif kind == "hinge":
            pp, pc = _floats(est["point_parent"]), _floats(est["point_child"])
            direction = _floats(est["direction_parent"])
            if data.get("point_child_matched") is not None:  # the child-frame twin of point_parent
                pc = _floats(data["point_child_matched"])
        else:
            raise InputError(f"{source}: kind {kind!r} is neither ball nor hinge")
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(
            f"{source}: not a calibration with the joint's record (joint, kind, parent_markers, child_markers, "
            f"templates, estimate): missing or malformed {exc}"
        ) from None
    arrays = [tp, tc, pp, pc] + ([] if direction is None else [direction])
    if tp.shape != (len(pm), 3) or tc.shape != (len(cm), 3) or not all(np.isfinite(a).all() for a in arrays):
        raise InputError(f"{source}: templates of shapes {tp.shape}, {tc.shape} do not match the marker lists or are not finite")
    if pp.shape != (3,) or pc.shape != (3,) or (direction is not None and direction.shape != (3,)):
        raise InputError(f"{source}: the estimate's points and direction must have 3 coordinates")
    if direction is not None:
        norm = float(np.linalg.norm(direction))
        if not (math.isfinite(norm) and norm > 0.0):
            raise InputError(f"{source}: the hinge direction {direction.tolist()} has no direction (length {norm:g})")
        direction = direction / norm
    return UrdfJoint(name, kind, pm, cm, tp, tc, pp.astype(np.float64), pc.astype(np.float64), direction)


def _prefix(markers: tuple[str, ...]) -> str:
    first, last = min(markers), max(markers)
    k = 0
    while k < min(len(first), len(last)) and first[k] == last[k]:
        k += 1
    return re.sub(r"[\d_\-.:]+$", "", first[:k])


def segment_names(
    marker_lists: Sequence[tuple[str, ...]], given: Mapping[tuple[str, ...], str] | None = None
) -> dict[tuple[str, ...], str]:
    """Marker list -> segment name, in order of first appearance.

    The name ``given`` for the list (the node's configured ``segments``), else the markers'
    common prefix without trailing digits and ``_`` (``RTHI1..4`` -> ``RTHI``), else
    ``segment_<k>`` when there is none or it is taken.
    """
    given = given or {}
    out: dict[tuple[str, ...], str] = {}
    taken = set(given.values())
    for markers in marker_lists:
        if markers in out:
            continue
        if markers in given:
            out[markers] = given[markers]
            continue
        name = _prefix(markers)
        if not re.fullmatch(r"[A-Za-z_][\w]*", name) or name in out.values() or name in taken:
            name = f"segment_{len(out)}"
        out[markers] = name
    return out


def link_names(
    joints: Sequence[UrdfJoint], given: Mapping[tuple[str, ...], str] | None = None
) -> dict[tuple[str, ...], str]:
    """Marker list -> link name (see the module docstring, :func:`segment_names`), in order of first appearance."""
    return segment_names([m for j in joints for m in (j.parent_markers, j.child_markers)], given)


def _origin(R: FloatArray, xyz: FloatArray) -> str:
    rpy = Rotation.from_matrix(R).as_euler("xyz")  # URDF rpy: fixed-axis roll, pitch, yaw (R = Rz Ry Rx)
    return f'<origin xyz="{" ".join(f"{v:.12g}" for v in xyz)}" rpy="{" ".join(f"{v:.12g}" for v in rpy)}"/>'


def _joint_xml(name: str, kind: str, parent: str, child: str, origin: str, axis: FloatArray | None = None) -> str:
    axis_xml = "" if axis is None else f'<axis xyz="{" ".join(f"{v:.12g}" for v in axis)}"/>'
    return (
        f"  <joint name={quoteattr(name)} type={quoteattr(kind)}><parent link={quoteattr(parent)}/>"
        f"<child link={quoteattr(child)}/>{origin}{axis_xml}</joint>"
    )


def _link_xml(name: str, template: FloatArray | None = None) -> str:
    if template is None:
        return f"  <link name={quoteattr(name)}/>"
    r = MARKER_SPHERE_FRACTION * float(np.sqrt(((template - template.mean(axis=0)) ** 2).sum(axis=1).mean()))
    visuals = "".join(
        f'<visual>{_origin(np.eye(3), p)}<geometry><sphere radius="{r:.6g}"/></geometry></visual>' for p in template
    )
    return f"  <link name={quoteattr(name)}>{visuals}</link>"


def _tree(joints: Sequence[UrdfJoint], links: Mapping[tuple[str, ...], str]) -> None:
    """Raise unless the joints form one tree of segments."""
    children: dict[tuple[str, ...], str] = {}
    for j in joints:
        if j.child_markers in children:
            raise InputError(
                f"segment {links[j.child_markers]} is the child of both {children[j.child_markers]} and {j.name}: "
                "a URDF is a tree (each segment has one parent joint)"
            )
        if j.parent_markers == j.child_markers:
            raise InputError(f"{j.name}: the parent and the child are the same markers")
        children[j.child_markers] = j.name
    roots = {j.parent_markers for j in joints if j.parent_markers not in children}
    if len(roots) != 1:
        raise InputError(
            f"the joints form {len(roots)} separate trees (roots {sorted(links[r] for r in roots)}) "
            "or a loop: a URDF has one root; give calibrations that connect the segments"
        )


def urdf_from_calibrations(
    calibrations: Sequence[Mapping[str, Any]],
    robot_name: str = "subject",
    metres_per_unit: float = 1.0,
    segment_labels: Mapping[tuple[str, ...], str] | None = None,
) -> str:
    """The URDF text of the calibrated joints (see the module docstring).

    Parameters
    ----------
    calibrations : sequence of dict
        Saved calibrations (the node's ``~/save`` or ``jointfit fit``'s), one per joint.
    robot_name : str
        ``<robot name>``.
    metres_per_unit : float
        The calibrations' length unit in metres (URDF lengths are metres): 1 for the node's
        (metres by REP 103), 0.001 for a fit of a C3D/TRC in mm.
    segment_labels : mapping, optional
        Link names by marker list (the node's ``segments``); others are named by
        :func:`segment_names`.

    Raises
    ------
    InputError
        A malformed calibration, two joints of one name, segments that do not form one
        tree, or two templates of the same markers that do not match.
    """
    joints = [urdf_joint_from_calibration(c, f"calibration {k + 1}") for k, c in enumerate(calibrations)]
    if not (math.isfinite(metres_per_unit) and metres_per_unit > 0.0):
        raise InputError(f"metres_per_unit: expected a number > 0, got {metres_per_unit!r}")
    if metres_per_unit != 1.0:
        m = metres_per_unit
        joints = [
            replace(j, template_parent=j.template_parent * m, template_child=j.template_child * m,
                    point_parent=j.point_parent * m, point_child=j.point_child * m)
            for j in joints
        ]  # fmt: skip
    if not joints:
        raise InputError("no calibrations given")
    names = [j.name for j in joints]
    if len(set(names)) != len(names):
        raise InputError(f"joint names repeat: {names}")
    links = link_names(joints, segment_labels)
    _tree(joints, links)
    # Each segment's link frame: the template of the joint that has it as the child (the root: as the parent).
    frame: dict[tuple[str, ...], FloatArray] = {j.child_markers: j.template_child for j in joints}
    for j in joints:
        frame.setdefault(j.parent_markers, j.template_parent)
    body = [_link_xml(links[m], frame[m]) for m in links]
    for j in joints:
        # the joint's parent template frame in the parent link frame: x_link = R x_tpl + d
        R, d = kabsch(frame[j.parent_markers], j.template_parent)
        misfit = np.sqrt(((j.template_parent @ R.T + d - frame[j.parent_markers]) ** 2).sum(axis=1).mean())
        radius = np.sqrt((j.template_parent**2).sum(axis=1).mean())
        if misfit > TEMPLATE_MATCH_RTOL * radius:
            raise InputError(
                f"{j.name}: its template of {links[j.parent_markers]} differs from the link's by {misfit:.3g} rms "
                "(the same markers moved between the calibrations?)"
            )
        origin = _origin(R, R @ j.point_parent + d)
        parent = links[j.parent_markers]
        if j.kind == "hinge":
            assert j.direction_parent is not None
            body += [_link_xml(f"{j.name}_axis"), _joint_xml(j.name, "continuous", parent, f"{j.name}_axis", origin, j.direction_parent)]
            last = f"{j.name}_axis"
        else:
            prev = parent
            for k, a in enumerate("xyz"):
                body.append(_link_xml(f"{j.name}_link_{a}"))
                o = origin if k == 0 else _origin(np.eye(3), np.zeros(3))
                body.append(_joint_xml(f"{j.name}_{a}", "continuous", prev, f"{j.name}_link_{a}", o, np.eye(3)[k]))
                prev = f"{j.name}_link_{a}"
            last = prev
        body.append(_joint_xml(f"{j.name}_to_child", "fixed", last, links[j.child_markers], _origin(np.eye(3), -j.point_child)))
    return (
        '<?xml version="1.0"?>\n'
        f"<!-- jointfit: calibrated joints {', '.join(names)}; see jointfit_core.urdf -->\n"
        f"<robot name={quoteattr(robot_name)}>\n" + "\n".join(body) + "\n</robot>\n"
    )
