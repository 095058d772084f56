"""Message <-> numpy conversions for the jointfit ROS 2 adapter.

Pure functions, usable without ``rclpy.init()``. The parsers, marker ordering,
serializers and rotation helpers live in :mod:`jointfit_ros.raw` (no ROS
imports, shared with the offline tools) and are re-exported here; this module
adds the **output builders** that return message objects: poses with
covariance, visualisation markers, diagnostics and stamps.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping, Sequence

import numpy as np
from builtin_interfaces.msg import Duration, Time
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, PoseWithCovarianceStamped
from numpy.typing import ArrayLike, NDArray
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker

from jointfit_core.checks import small_all_finite

from .raw import (
    _NS_PER_S,
    Buffer,
    ConversionError,
    LabelProblems,
    RawPoints,
    RawPose,
    _cdr_header,
    _unit,
    _unit_quaternion,
    frame_from_points,
    label_points,
    label_problems,
    ns_from_stamp,
    parse_pointcloud2,
    parse_pose_array,
    parse_pose_stamped,
    pointcloud2_bytes,
    points_from_pointcloud2,
    points_from_pose_array,
    pose_array_bytes,
    pose_from_pose_stamped,
    quaternion_from_rotation_matrix,
    quaternion_z_to_direction,
    rotation_matrix_from_quaternion,
)

__all__ = [
    "ConversionError",
    "RawPoints",
    "RawPose",
    "LabelProblems",
    "Buffer",
    "UNKNOWN_ROTATION_VARIANCE",
    "parse_pose_array",
    "parse_pointcloud2",
    "parse_pose_stamped",
    "points_from_pose_array",
    "points_from_pointcloud2",
    "pose_from_pose_stamped",
    "frame_from_points",
    "label_problems",
    "label_points",
    "pose_array_bytes",
    "pointcloud2_bytes",
    "pose_with_covariance",
    "pose_with_covariance_bytes",
    "axis_pose",
    "axis_pose_bytes",
    "covariance_ellipsoid_marker",
    "axis_arrow_marker",
    "sphere_marker",
    "diagnostic_status",
    "stamp_from_ns",
    "ns_from_stamp",
    "rotation_matrix_from_quaternion",
    "quaternion_from_rotation_matrix",
    "quaternion_z_to_direction",
]

FloatArray = NDArray[np.float64]

#: Variance (rad^2) written for a rotation that is not estimated (the orientation
#: of a point, the rotation of an axis pose about its own axis). ROS has no
#: "unknown" flag for ``PoseWithCovariance`` (the ``-1`` of ``sensor_msgs/Imu``
#: is specific to that message); the convention of robot_localization and the
#: GPS/odometry drivers is a very large variance. 1e6 rad^2 is far above the
#: variance of an angle spread uniformly over the circle (pi^2/3 = 3.3 rad^2)
#: yet keeps the 6x6 matrix invertible in double precision next to
#: sub-millimetre position variances (1e-8 m^2), which 1e9 or more would not.
UNKNOWN_ROTATION_VARIANCE = 1.0e6
_UNKNOWN_ROTATION_COV = UNKNOWN_ROTATION_VARIANCE * np.eye(3)
_IDENTITY_XYZW = np.array([0.0, 0.0, 0.0, 1.0])
#: position (3), orientation (4), covariance (36): the float64s of a PoseWithCovariance, little-endian.
_POSE_COV_LE = struct.Struct("<43d")


def stamp_from_ns(ns: int) -> Time:
    """A ``builtin_interfaces/Time`` from integer nanoseconds (floor division, so ``nanosec`` is in [0, 1e9)).

    Raises
    ------
    ConversionError
        The seconds do not fit the message's int32.
    """
    sec, nanosec = divmod(int(ns), _NS_PER_S)
    if not -(2**31) <= sec < 2**31:
        raise ConversionError(f"stamp: expected seconds within int32, got {ns} ns")
    return Time(sec=sec, nanosec=nanosec)


# --------------------------------------------------------------------------- output builders


def _check_cov(cov: ArrayLike, name: str, n: int = 3) -> FloatArray:
    arr = cov if isinstance(cov, np.ndarray) and cov.dtype == np.float64 else np.asarray(cov, dtype=np.float64)
    if arr.shape != (n, n):
        raise ConversionError(f"{name}: expected shape ({n}, {n}), got shape {arr.shape}")
    if not small_all_finite(arr):
        raise ConversionError(f"{name}: expected finite values, got {arr.tolist()}")
    return arr


def _vector3(v: ArrayLike, name: str) -> FloatArray:
    arr = v if isinstance(v, np.ndarray) and v.dtype == np.float64 else np.asarray(v, dtype=np.float64)
    if arr.shape != (3,):
        raise ConversionError(f"{name}: expected shape (3,), got shape {arr.shape}")
    return arr


def _pose_parts(
    position: ArrayLike, cov: ArrayLike, orientation_xyzw: ArrayLike | None, orientation_cov: ArrayLike | None
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Checked position (3,), unit quaternion (4,) and 6x6 covariance of a pose with covariance."""
    pos = _vector3(position, "position")
    c6 = np.zeros((6, 6))
    c6[:3, :3] = _check_cov(cov, "cov")
    if orientation_xyzw is None:
        quat = _IDENTITY_XYZW
    else:
        quat = _unit_quaternion(orientation_xyzw)  # validates (as rotation_matrix_from_quaternion) and normalises
    if orientation_cov is None:
        c6[3:, 3:] = _UNKNOWN_ROTATION_COV
    else:
        c6[3:, 3:] = _check_cov(orientation_cov, "orientation_cov")
    return pos, quat, c6


def pose_with_covariance_bytes(
    stamp_ns: int,
    frame_id: str,
    position: ArrayLike,
    cov: ArrayLike,
    orientation_xyzw: ArrayLike | None = None,
    orientation_cov: ArrayLike | None = None,
) -> bytes:
    """The CDR bytes (little-endian) of :func:`pose_with_covariance`'s message, for ``publish(bytes)``.

    Building a message object costs ~20-50 us in Python; the node publishes
    its per-frame outputs with these bytes instead (same content, checked
    against rclpy's serializer in the tests).
    """
    pos = _vector3(position, "position")
    c = _check_cov(cov, "cov").tolist()
    quat = _IDENTITY_XYZW if orientation_xyzw is None else _unit_quaternion(orientation_xyzw)
    r = _UNKNOWN_ROTATION_COV_ROWS if orientation_cov is None else _check_cov(orientation_cov, "orientation_cov").tolist()
    z = _ZERO3
    # the 6 x 6 covariance of _pose_parts, row by row, as Python floats (the same numbers, fewer numpy calls)
    c6 = [*c[0], *z, *c[1], *z, *c[2], *z, *z, *r[0], *z, *r[1], *z, *r[2]]
    out = _cdr_header(stamp_ns, frame_id, "<")
    out += bytes((-(len(out) - 4)) % 8)  # float64s align to 8 after the encapsulation header
    out += _POSE_COV_LE.pack(*pos.tolist(), *quat.tolist(), *c6)
    return bytes(out)


_ZERO3 = [0.0, 0.0, 0.0]
_UNKNOWN_ROTATION_COV_ROWS = _UNKNOWN_ROTATION_COV.tolist()


def axis_pose_bytes(
    stamp_ns: int,
    frame_id: str,
    point: ArrayLike,
    direction: ArrayLike,
    cov_point: ArrayLike,
    cov_direction: ArrayLike,
    *,
    rotation_frame: str = "local",
) -> bytes:
    """The CDR bytes of :func:`axis_pose`'s message (see :func:`pose_with_covariance_bytes`)."""
    quat, rot = _axis_parts(direction, cov_direction, rotation_frame)
    return pose_with_covariance_bytes(stamp_ns, frame_id, point, cov_point, quat, rot)


def pose_with_covariance(
    stamp_ns: int,
    frame_id: str,
    position: ArrayLike,
    cov: ArrayLike,
    orientation_xyzw: ArrayLike | None = None,
    orientation_cov: ArrayLike | None = None,
) -> PoseWithCovarianceStamped:
    """A ``geometry_msgs/PoseWithCovarianceStamped`` for a point (and optionally an orientation).

    Parameters
    ----------
    stamp_ns : int
        Stamp in nanoseconds.
    frame_id : str
        Frame of ``position``.
    position : array_like, shape (3,)
        Position (message units, metres by REP 103).
    cov : array_like, shape (3, 3)
        Covariance of ``position`` (units squared).
    orientation_xyzw : array_like, shape (4,), optional
        Orientation quaternion (normalised here). None: a point without
        orientation; the identity is written and the rotation is unknown.
    orientation_cov : array_like, shape (3, 3), optional
        Covariance of the rotation (rad^2), in whatever axes the caller
        documents (the message says fixed axes). None: every rotation
        variance is :data:`UNKNOWN_ROTATION_VARIANCE`.

    Returns
    -------
    geometry_msgs.msg.PoseWithCovarianceStamped
        ``pose.covariance`` is the 6x6 row-major matrix over (x, y, z, rot x,
        rot y, rot z); the position block is ``cov``, the rotation block
        ``orientation_cov`` (or ``UNKNOWN_ROTATION_VARIANCE * I``), cross
        terms zero.

    Notes
    -----
    ROS has no "unknown" marker for this message (``-1`` is a
    ``sensor_msgs/Imu`` convention and would break consumers that invert the
    matrix, like robot_localization); a large variance is the convention.
    """
    pos, quat, c6 = _pose_parts(position, cov, orientation_xyzw, orientation_cov)
    msg = PoseWithCovarianceStamped()
    msg.header.stamp = stamp_from_ns(stamp_ns)
    msg.header.frame_id = frame_id
    p = msg.pose.pose
    p.position.x, p.position.y, p.position.z = (float(v) for v in pos)
    p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = (float(v) for v in quat)
    msg.pose.covariance = c6.reshape(36).tolist()
    return msg


def axis_pose(
    stamp_ns: int,
    frame_id: str,
    point: ArrayLike,
    direction: ArrayLike,
    cov_point: ArrayLike,
    cov_direction: ArrayLike,
    *,
    rotation_frame: str = "local",
) -> PoseWithCovarianceStamped:
    """A hinge axis as a ``PoseWithCovarianceStamped``: position the point, local z the direction.

    Parameters
    ----------
    stamp_ns : int
        Stamp in nanoseconds.
    frame_id : str
        Frame of ``point`` and ``direction``.
    point : array_like, shape (3,)
        A point of the axis (message units).
    direction : array_like, shape (3,)
        Axis direction (normalised here).
    cov_point : array_like, shape (3, 3)
        Covariance of ``point`` (units squared).
    cov_direction : array_like, shape (3, 3)
        Covariance of the unit direction (rad^2 for small angles), rank 2
        (nothing along the direction), in ``frame_id`` axes.
    rotation_frame : {"local", "fixed"}
        Axes of the rotation covariance. "local" (default): about the pose's
        own x, y, z axes; the x and y variances come from ``cov_direction``
        and z (the spin about the axis, which a hinge axis does not define)
        is :data:`UNKNOWN_ROTATION_VARIANCE`. "fixed": the same covariance
        rotated to the axes of ``frame_id`` (what the message's comment
        says), in which the unknown spin spreads into every component.

    Returns
    -------
    geometry_msgs.msg.PoseWithCovarianceStamped
        Orientation: the minimal rotation taking z to the direction
        (:func:`quaternion_z_to_direction`; a half turn about x for -z).

    Notes
    -----
    A small rotation ``δθ`` about the local axes moves the direction by
    ``δd = R (δθ × e_z) = δθ_y e_x' - δθ_x e_y'`` (``e_x' = R e_x``,
    ``e_y' = R e_y``), so ``(δθ_x, δθ_y) = J^T δd`` with ``J = [-e_y', e_x']``
    and their covariance is ``J^T cov_direction J``. rviz shows it with the
    covariance display's orientation frame set to "Local".
    """
    quat, rot = _axis_parts(direction, cov_direction, rotation_frame)
    return pose_with_covariance(stamp_ns, frame_id, _vector3(point, "point"), cov_point, quat, rot)


def _axis_parts(direction: ArrayLike, cov_direction: ArrayLike, rotation_frame: str) -> tuple[FloatArray, FloatArray]:
    """Quaternion taking z to the direction, and the rotation covariance of an axis pose."""
    cd = _check_cov(cov_direction, "cov_direction")
    quat = quaternion_z_to_direction(direction)
    R = rotation_matrix_from_quaternion(quat)
    J = np.empty((3, 2))
    J[:, 0] = -R[:, 1]
    J[:, 1] = R[:, 0]
    rot = np.zeros((3, 3))
    rot[:2, :2] = J.T @ cd @ J
    rot[2, 2] = UNKNOWN_ROTATION_VARIANCE
    if rotation_frame == "fixed":
        rot = R @ rot @ R.T
    elif rotation_frame != "local":
        raise ConversionError(f"rotation_frame: expected 'local' or 'fixed', got {rotation_frame!r}")
    return quat, 0.5 * (rot + rot.T)


def _marker(
    stamp_ns: int,
    frame_id: str,
    marker_type: int,
    *,
    ns: str,
    marker_id: int,
    rgba: Sequence[float],
    lifetime_ns: int,
) -> Marker:
    if len(rgba) != 4:
        raise ConversionError(f"rgba: expected 4 values (red, green, blue, alpha in [0, 1]), got {len(rgba)}")
    m = Marker()
    m.header.stamp = stamp_from_ns(stamp_ns)
    m.header.frame_id = frame_id
    m.ns = ns
    m.id = int(marker_id)
    m.type = marker_type
    m.action = Marker.ADD
    m.color = ColorRGBA(r=float(rgba[0]), g=float(rgba[1]), b=float(rgba[2]), a=float(rgba[3]))
    sec, nanosec = divmod(int(lifetime_ns), _NS_PER_S)
    m.lifetime = Duration(sec=sec, nanosec=nanosec)
    m.pose.orientation.w = 1.0
    return m


def covariance_ellipsoid_marker(
    stamp_ns: int,
    frame_id: str,
    centre: ArrayLike,
    cov: ArrayLike,
    *,
    k_sigma: float = 2.0,
    min_diameter: float = 0.0,
    ns: str = "covariance",
    marker_id: int = 0,
    rgba: Sequence[float] = (1.0, 0.5, 0.0, 0.4),
    lifetime_ns: int = 0,
) -> Marker:
    """A ``visualization_msgs/Marker`` SPHERE scaled into the k-sigma ellipsoid of a 3x3 covariance.

    Parameters
    ----------
    stamp_ns : int
        Stamp in nanoseconds.
    frame_id : str
        Frame of ``centre`` and ``cov``.
    centre : array_like, shape (3,)
        Ellipsoid centre (message units).
    cov : array_like, shape (3, 3)
        Covariance (units squared); symmetrised, negative eigenvalues clipped to 0.
    k_sigma : float
        Mahalanobis radius. In 3-D, 1, 2 and 3 sigma enclose 20 %, 74 % and
        97 % of a Gaussian. Default 2.
    min_diameter : float
        Smallest diameter written (units), so that a degenerate covariance
        stays visible (rviz warns on a zero scale). Default 0.
    ns, marker_id : str, int
        Marker namespace and id.
    rgba : sequence of 4 floats
        Colour and alpha in [0, 1].
    lifetime_ns : int
        Marker lifetime; 0 keeps it until replaced.

    Returns
    -------
    visualization_msgs.msg.Marker
        ``scale = 2 k sqrt(eigvals)`` along the eigenvectors, the
        orientation their matrix made proper (det +1), so that
        ``R diag(scale / 2)^2 R^T = k^2 cov``.
    """
    c = _vector3(centre, "centre")
    C = _check_cov(cov, "cov")
    eigvals, eigvecs = np.linalg.eigh(0.5 * (C + C.T))
    if np.linalg.det(eigvecs) < 0.0:
        eigvecs[:, 2] = -eigvecs[:, 2]
    scale = np.maximum(2.0 * k_sigma * np.sqrt(np.clip(eigvals, 0.0, None)), min_diameter)
    quat = quaternion_from_rotation_matrix(eigvecs)
    m = _marker(
        stamp_ns, frame_id, Marker.SPHERE, ns=ns, marker_id=marker_id, rgba=rgba, lifetime_ns=lifetime_ns
    )
    m.pose.position.x, m.pose.position.y, m.pose.position.z = (float(v) for v in c)
    o = m.pose.orientation
    o.x, o.y, o.z, o.w = (float(v) for v in quat)
    m.scale.x, m.scale.y, m.scale.z = (float(v) for v in scale)
    return m


def axis_arrow_marker(
    stamp_ns: int,
    frame_id: str,
    point: ArrayLike,
    direction: ArrayLike,
    *,
    length: float,
    shaft_diameter: float,
    head_diameter: float | None = None,
    head_length: float = 0.0,
    ns: str = "axis",
    marker_id: int = 0,
    rgba: Sequence[float] = (0.0, 0.6, 1.0, 0.9),
    lifetime_ns: int = 0,
) -> Marker:
    """An ARROW marker along an axis, centred on ``point`` and pointing along ``direction``.

    Parameters
    ----------
    stamp_ns : int
        Stamp in nanoseconds.
    frame_id : str
        Frame of ``point`` and ``direction``.
    point : array_like, shape (3,)
        Middle of the arrow (message units).
    direction : array_like, shape (3,)
        Arrow direction (normalised here).
    length : float
        Arrow length (units), from ``point - length/2 d`` to ``point + length/2 d``.
    shaft_diameter : float
        ``scale.x``.
    head_diameter : float, optional
        ``scale.y``; default twice the shaft diameter.
    head_length : float
        ``scale.z``; 0 lets rviz choose.
    ns, marker_id, rgba, lifetime_ns
        As :func:`covariance_ellipsoid_marker`.

    Returns
    -------
    visualization_msgs.msg.Marker
        Type ARROW given by its two ``points``.
    """
    p = _vector3(point, "point")
    d = _unit(direction, "direction")
    m = _marker(
        stamp_ns, frame_id, Marker.ARROW, ns=ns, marker_id=marker_id, rgba=rgba, lifetime_ns=lifetime_ns
    )
    start = p - 0.5 * length * d
    end = p + 0.5 * length * d
    m.points = [Point(x=float(v[0]), y=float(v[1]), z=float(v[2])) for v in (start, end)]
    m.scale.x = float(shaft_diameter)
    m.scale.y = float(2.0 * shaft_diameter if head_diameter is None else head_diameter)
    m.scale.z = float(head_length)
    return m


def sphere_marker(
    stamp_ns: int,
    frame_id: str,
    centre: ArrayLike,
    diameter: float,
    *,
    ns: str = "centre",
    marker_id: int = 0,
    rgba: Sequence[float] = (1.0, 0.0, 0.0, 0.9),
    lifetime_ns: int = 0,
) -> Marker:
    """A SPHERE marker of the given diameter (units) at ``centre``, shape (3,)."""
    c = _vector3(centre, "centre")
    m = _marker(
        stamp_ns, frame_id, Marker.SPHERE, ns=ns, marker_id=marker_id, rgba=rgba, lifetime_ns=lifetime_ns
    )
    m.pose.position.x, m.pose.position.y, m.pose.position.z = (float(v) for v in c)
    m.scale.x = m.scale.y = m.scale.z = float(diameter)
    return m


def _value_text(value: object) -> str:
    if isinstance(value, float | np.floating):
        return f"{float(value):.6g}"
    return str(value)


def diagnostic_status(
    name: str, level: int | bytes, message: str, values: Mapping[str, object], *, hardware_id: str = ""
) -> DiagnosticStatus:
    """A ``diagnostic_msgs/DiagnosticStatus``.

    Parameters
    ----------
    name : str
        Status name, e.g. ``"jointfit: hip"``.
    level : int
        0 OK, 1 WARN, 2 ERROR, 3 STALE (``DiagnosticStatus.OK`` ... as bytes is accepted too).
    message : str
        Short human-readable summary.
    values : mapping of str to object
        Key/value pairs; floats are written with 6 significant digits, other
        values with ``str``.
    hardware_id : str
        Optional hardware id.

    Returns
    -------
    diagnostic_msgs.msg.DiagnosticStatus
    """
    lev = level[0] if isinstance(level, bytes) and len(level) == 1 else level
    if not isinstance(lev, int) or lev not in (0, 1, 2, 3):
        raise ConversionError(f"level: expected 0 (OK), 1 (WARN), 2 (ERROR) or 3 (STALE), got {level!r}")
    status = DiagnosticStatus()
    status.level = bytes([lev])
    status.name = name
    status.message = message
    status.hardware_id = hardware_id
    status.values = [KeyValue(key=str(k), value=_value_text(v)) for k, v in values.items()]
    return status
