"""Raw ROS message bytes <-> numpy, without ROS: parsers, marker ordering, serializers.

Pure numpy/scipy (no rclpy, no message packages), so that the offline tools
(rosbag2 files read with ``rosbags``, the ``jointfit`` CLI) share the node's
exact parsing. :mod:`jointfit_ros.conversions` re-exports everything here and
adds the builders of output message objects.

* **Raw CDR parsers** (:func:`parse_pose_array`, :func:`parse_pointcloud2`,
  :func:`parse_pose_stamped`) read the serialized bytes a subscription created
  with ``raw=True`` (or a rosbag2 file) delivers, with ``numpy.frombuffer`` and
  strided views: no Python message object, no Python loop per point.
* **Message-object versions** (:func:`points_from_pose_array`, ...) for callers
  that already hold a message object (rclpy or rosbags types).
* **Marker ordering** (:func:`frame_from_points`, :func:`label_points`).
* **Serializers** (:func:`pose_array_bytes`, :func:`pointcloud2_bytes`).
* **Rotations** (:func:`rotation_matrix_from_quaternion`, ...).

CDR layout (OMG XCDR version 1, what ``rmw_fastrtps`` and ``rmw_cyclonedds``
send for ROS 2 types): a 4-byte encapsulation header (``00 00`` big-endian
or ``00 01`` little-endian, then two option bytes), then the message, in which
every primitive of size 2, 4 or 8 is aligned to its size, counted from the
first byte *after* the encapsulation header. Strings are a ``uint32`` length
that includes the terminating NUL, then the bytes; sequences are a ``uint32``
count, then the elements. Padding bytes carry no meaning (Fast DDS leaves them
uninitialised). Other encapsulations (parameter lists, XCDR2) are rejected
with :class:`ConversionError`.

Occlusion conventions: a NaN row is a missing marker; an exact ``(0, 0, 0)``
point is also missing when ``zero_is_missing`` is true, since mocap4ros2's
Vicon driver sends occluded markers as zeros.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, DTypeLike, NDArray
from scipy.optimize import linear_sum_assignment

from jointfit_core.checks import as_real_array
from jointfit_core.errors import InputError, JointfitError

__all__ = [
    "ConversionError",
    "RawPoints",
    "RawPose",
    "LabelProblems",
    "parse_pose_array",
    "parse_pointcloud2",
    "parse_pose_stamped",
    "parse_pose_arrays",
    "parse_pointcloud2s",
    "RawPointsGroup",
    "RawPointsBatch",
    "points_from_pose_array",
    "points_from_pointcloud2",
    "pose_from_pose_stamped",
    "frame_from_points",
    "label_problems",
    "label_points",
    "pose_array_bytes",
    "pointcloud2_bytes",
    "ns_from_stamp",
    "rotation_matrix_from_quaternion",
    "quaternion_from_rotation_matrix",
    "quaternion_z_to_direction",
]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
Buffer = bytes | bytearray | memoryview

_NS_PER_S = 1_000_000_000
_CDR_BE = b"\x00\x00"
_CDR_LE = b"\x00\x01"

# sensor_msgs/PointField datatypes -> (name, numpy kind + size)
_POINTFIELD_TYPES: dict[int, tuple[str, str]] = {
    1: ("INT8", "i1"),
    2: ("UINT8", "u1"),
    3: ("INT16", "i2"),
    4: ("UINT16", "u2"),
    5: ("INT32", "i4"),
    6: ("UINT32", "u4"),
    7: ("FLOAT32", "f4"),
    8: ("FLOAT64", "f8"),
}
_FLOAT_TYPES = (7, 8)
_INT_TYPES = (1, 2, 3, 4, 5, 6)
_UINT32_MAX = 2**32 - 1


class ConversionError(JointfitError, ValueError):
    """A message cannot be converted: malformed bytes, wrong fields, wrong shapes.

    The message says what was expected and what came.
    """


@dataclass(frozen=True)
class RawPoints:
    """Points of a marker message (PoseArray or PointCloud2).

    Attributes
    ----------
    stamp_ns : int
        ``header.stamp`` in nanoseconds.
    frame_id : str
        ``header.frame_id``.
    points : ndarray, shape (N, 3), float64
        Positions in the message's units (metres for REP 103 publishers).
        NaN where the message has NaN.
    labels : ndarray, shape (N,), int64, or None
        Per-point integer labels of a labelled point cloud, else None.
    """

    stamp_ns: int
    frame_id: str
    points: FloatArray
    labels: IntArray | None


@dataclass(frozen=True)
class RawPose:
    """A ``geometry_msgs/PoseStamped``.

    Attributes
    ----------
    stamp_ns : int
        ``header.stamp`` in nanoseconds.
    frame_id : str
        ``header.frame_id``.
    position : ndarray, shape (3,), float64
        Position in the message's units.
    quaternion : ndarray, shape (4,), float64
        Orientation as sent, (x, y, z, w); not normalised.
    """

    stamp_ns: int
    frame_id: str
    position: FloatArray
    quaternion: FloatArray


@dataclass(frozen=True)
class LabelProblems:
    """Labels of a cloud that :func:`frame_from_points` could not use.

    Attributes
    ----------
    out_of_range : int
        Points whose label is negative or not below the number of markers.
    duplicated : int
        Markers (rows) that more than one point claimed; the row is set missing.
    """

    out_of_range: int
    duplicated: int


# --------------------------------------------------------------------------- CDR reading


class _Reader:
    """Sequential reader of one CDR (XCDR1) buffer with bounds checks."""

    __slots__ = ("buf", "end", "kind", "pos", "prefix")

    def __init__(self, buf: Buffer, kind: str) -> None:
        self.kind = kind
        self.buf = buf
        self.end = len(buf)
        if self.end < 4:
            raise ConversionError(
                f"{kind}: expected at least the 4-byte CDR encapsulation header, got {self.end} bytes"
            )
        rep = bytes(buf[0:2])
        if rep == _CDR_LE:
            self.prefix = "<"
        elif rep == _CDR_BE:
            self.prefix = ">"
        else:
            raise ConversionError(
                f"{kind}: expected CDR encapsulation 00 00 (big-endian) or 00 01 (little-endian), "
                f"got {rep.hex(' ')} (parameter-list or XCDR2 encodings are not supported)"
            )
        self.pos = 4

    def align(self, n: int) -> None:
        # alignment counts from the byte after the encapsulation header (offset 4)
        self.pos += (-(self.pos - 4)) % n

    def need(self, n: int, what: str) -> None:
        if n < 0 or self.pos + n > self.end:
            raise ConversionError(
                f"{self.kind}: truncated: {what} needs {n} bytes at offset {self.pos}, "
                f"message has {self.end} bytes"
            )

    def u32(self, what: str) -> int:
        self.align(4)
        self.need(4, what)
        (value,) = struct.unpack_from(self.prefix + "I", self.buf, self.pos)
        self.pos += 4
        return int(value)

    def u8(self, what: str) -> int:
        self.need(1, what)
        value = self.buf[self.pos]
        self.pos += 1
        return int(value)

    def stamp_ns(self) -> int:
        self.align(4)
        self.need(8, "header.stamp")
        sec, nanosec = struct.unpack_from(self.prefix + "iI", self.buf, self.pos)
        if nanosec >= _NS_PER_S:
            raise ConversionError(_nanosec_text(int(sec), int(nanosec)))
        self.pos += 8
        return int(sec) * _NS_PER_S + int(nanosec)

    def string(self, what: str) -> str:
        n = self.u32(what + " length")
        self.need(n, what)
        raw = bytes(self.buf[self.pos : self.pos + n])
        self.pos += n
        if raw.endswith(b"\x00"):
            raw = raw[:-1]
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise ConversionError(f"{self.kind}: {what} is not valid UTF-8: {exc}") from None

    def header(self) -> tuple[int, str]:
        stamp = self.stamp_ns()
        return stamp, self.string("header.frame_id")

    def float64s(self, count: int, what: str) -> FloatArray:
        self.align(8)
        self.need(8 * count, what)
        out = np.frombuffer(self.buf, dtype=self.prefix + "f8", count=count, offset=self.pos)
        self.pos += 8 * count
        return out


def parse_pose_array(raw: Buffer) -> RawPoints:
    """Positions of a serialized ``geometry_msgs/PoseArray``.

    Parameters
    ----------
    raw : bytes
        CDR bytes as delivered by a ``raw=True`` subscription (encapsulation
        header included), little- or big-endian.

    Returns
    -------
    RawPoints
        ``points`` shape (N, 3) float64 (the pose positions, NaN kept);
        orientations are ignored; ``labels`` is None.

    Raises
    ------
    ConversionError
        Unknown encapsulation, truncated bytes, invalid UTF-8 frame id.
    """
    r = _Reader(raw, "PoseArray")
    stamp, frame_id = r.header()
    n = r.u32("poses length")
    if n == 0:
        points = np.empty((0, 3))
    else:
        poses = r.float64s(7 * n, f"{n} poses").reshape(n, 7)
        points = np.array(poses[:, :3], dtype=np.float64, order="C")
    return RawPoints(stamp_ns=stamp, frame_id=frame_id, points=points, labels=None)


def parse_pose_stamped(raw: Buffer) -> RawPose:
    """Position and orientation of a serialized ``geometry_msgs/PoseStamped``.

    Parameters
    ----------
    raw : bytes
        CDR bytes (encapsulation header included).

    Returns
    -------
    RawPose
        ``position`` shape (3,), ``quaternion`` shape (4,) as (x, y, z, w).

    Raises
    ------
    ConversionError
        Unknown encapsulation or truncated bytes.
    """
    r = _Reader(raw, "PoseStamped")
    stamp, frame_id = r.header()
    values = np.array(r.float64s(7, "pose"), dtype=np.float64)
    return RawPose(stamp_ns=stamp, frame_id=frame_id, position=values[:3], quaternion=values[3:])


@dataclass(frozen=True)
class _Field:
    name: str
    offset: int
    datatype: int
    count: int


def _field_text(fields: Sequence[_Field]) -> str:
    parts = []
    for f in fields:
        type_name = _POINTFIELD_TYPES.get(f.datatype, (f"datatype {f.datatype}", ""))[0]
        parts.append(f"{f.name}: {type_name} @{f.offset}" + (f" x{f.count}" if f.count > 1 else ""))
    return "[" + ", ".join(parts) + "]"


def _cloud_from_buffer(
    buf: Any,
    data_offset: int,
    data_len: int,
    *,
    fields: Sequence[_Field],
    height: int,
    width: int,
    point_step: int,
    row_step: int,
    big_endian: bool,
    label_field: str | None,
) -> tuple[FloatArray, IntArray | None]:
    """Points (and labels) of a PointCloud2 whose ``data`` is ``buf[data_offset:data_offset + data_len]``."""
    by_name = {f.name: f for f in fields}
    wanted = ["x", "y", "z"] + ([label_field] if label_field is not None else [])
    missing = [name for name in wanted if name not in by_name]
    if missing:
        raise ConversionError(
            "PointCloud2: expected fields x, y, z (FLOAT32 or FLOAT64)"
            + (f" and an integer field {label_field!r}" if label_field is not None else "")
            + f"; missing {missing}, got fields {_field_text(fields)}"
        )
    for name in wanted:
        f = by_name[name]
        allowed = _INT_TYPES if name == label_field else _FLOAT_TYPES
        if f.datatype not in allowed:
            expected = (
                "an integer datatype (INT8..UINT32)" if name == label_field else "FLOAT32 (7) or FLOAT64 (8)"
            )
            raise ConversionError(
                f"PointCloud2: field {name!r}: expected {expected}, got "
                f"{_POINTFIELD_TYPES.get(f.datatype, (str(f.datatype), ''))[0]}; fields {_field_text(fields)}"
            )
        if f.count > 1:
            raise ConversionError(f"PointCloud2: field {name!r}: expected count 1, got {f.count}")
        size = int(_POINTFIELD_TYPES[f.datatype][1][1])
        if f.offset + size > point_step:
            raise ConversionError(
                f"PointCloud2: field {name!r} at offset {f.offset} ({size} bytes) does not fit in point_step {point_step}"
            )
    n = height * width
    if n == 0:
        return np.empty((0, 3)), (np.empty(0, dtype=np.int64) if label_field is not None else None)
    if row_step < width * point_step:
        raise ConversionError(
            f"PointCloud2: row_step {row_step} is smaller than width * point_step = {width} * {point_step}"
        )
    needed = (height - 1) * row_step + width * point_step
    if data_len < needed:
        raise ConversionError(
            f"PointCloud2: data has {data_len} bytes, expected at least {needed} "
            f"(height {height}, width {width}, point_step {point_step}, row_step {row_step})"
        )
    return _cloud_arrays(
        buf,
        data_offset,
        fields=fields,
        height=height,
        width=width,
        point_step=point_step,
        row_step=row_step,
        big_endian=big_endian,
        label_field=label_field,
    )


def _cloud_arrays(
    buf: Any,
    data_offset: int,
    *,
    fields: Sequence[_Field],
    height: int,
    width: int,
    point_step: int,
    row_step: int,
    big_endian: bool,
    label_field: str | None,
    messages: tuple[int, int] | None = None,
) -> tuple[FloatArray, IntArray | None]:
    """Points (and labels) of a checked PointCloud2 layout (:func:`_cloud_from_buffer` checks it).

    ``messages = (G, L)``: ``buf`` holds G messages of this layout, L bytes apart; the arrays then
    have a leading axis of length G. Same views and casts either way.
    """
    by_name = {f.name: f for f in fields}
    n = height * width
    lead: tuple[int, ...] = () if messages is None else (messages[0],)
    lead_strides: tuple[int, ...] = () if messages is None else (messages[1],)
    if n == 0:
        return np.empty((*lead, 0, 3)), (np.empty((*lead, 0), dtype=np.int64) if label_field is not None else None)
    order = ">" if big_endian else "<"

    def column(f: _Field) -> NDArray[Any]:
        view: NDArray[Any] = np.ndarray(
            shape=(*lead, height, width),
            dtype=order + _POINTFIELD_TYPES[f.datatype][1],
            buffer=buf,
            offset=data_offset + f.offset,
            strides=(*lead_strides, row_step, point_step),
        )
        return view.reshape(*lead, n)

    fx, fy, fz = by_name["x"], by_name["y"], by_name["z"]
    step = fy.offset - fx.offset
    if fx.datatype == fy.datatype == fz.datatype and step == fz.offset - fy.offset and step > 0:
        # the usual layout (x, y, z equally spaced, one type): one strided view
        xyz: NDArray[Any] = np.ndarray(
            shape=(*lead, height, width, 3),
            dtype=order + _POINTFIELD_TYPES[fx.datatype][1],
            buffer=buf,
            offset=data_offset + fx.offset,
            strides=(*lead_strides, row_step, point_step, step),
        )
        # A float32 signalling-NaN payload raises numpy's "invalid value" flag in the cast; it is read
        # as a NaN (a missing marker) like any other NaN.
        with np.errstate(invalid="ignore"):
            points = xyz.reshape(*lead, n, 3).astype(np.float64)
    else:
        points = np.empty((*lead, n, 3), dtype=np.float64)
        with np.errstate(invalid="ignore"):
            for k, f in enumerate((fx, fy, fz)):
                points[..., k] = column(f)
    labels = column(by_name[label_field]).astype(np.int64) if label_field is not None else None
    return points, labels


def _read_fields(r: _Reader, n_fields: int) -> list[_Field]:
    """The ``sensor_msgs/PointField`` sequence (inlined reads: this loop dominates the parse time)."""
    buf, end, u32 = r.buf, r.end, struct.Struct(r.prefix + "I").unpack_from
    pos = r.pos
    fields = []
    for _ in range(n_fields):
        pos += (-(pos - 4)) % 4
        if pos + 4 > end:
            break
        (n,) = u32(buf, pos)
        name_end = pos + 4 + n
        pos = name_end + (-(name_end - 4)) % 4  # offset: uint32
        if pos + 9 > end or n > end:
            break
        name = bytes(buf[name_end - n : name_end]).rstrip(b"\x00")
        (offset,) = u32(buf, pos)
        datatype = buf[pos + 4]
        pos += 5
        pos += (-(pos - 4)) % 4
        if pos + 4 > end:
            break
        (count,) = u32(buf, pos)
        pos += 4
        try:
            text = name.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise ConversionError(f"{r.kind}: field name is not valid UTF-8: {exc}") from None
        fields.append(_Field(text, int(offset), int(datatype), int(count)))
    else:
        r.pos = pos
        return fields
    r.pos = pos
    raise ConversionError(
        f"{r.kind}: truncated: field {len(fields)} of {n_fields} ends after the message ({end} bytes)"
    )


def parse_pointcloud2(raw: Buffer, *, label_field: str | None = None) -> RawPoints:
    """Points (and optional integer labels) of a serialized ``sensor_msgs/PointCloud2``.

    Parameters
    ----------
    raw : bytes
        CDR bytes (encapsulation header included).
    label_field : str or None
        Name of an integer field (any of INT8 ... UINT32) holding the marker
        label of each point, or None for an unlabelled cloud.

    Returns
    -------
    RawPoints
        ``points`` shape (height * width, 3) float64 from the fields x, y, z
        (FLOAT32 or FLOAT64, any offsets within ``point_step``, rows
        ``row_step`` apart, byte order from ``is_bigendian``), row-major over
        (height, width); ``labels`` shape (N,) int64 or None.

    Raises
    ------
    ConversionError
        Truncated bytes; x, y, z or the label field missing, of the wrong
        datatype, with count > 1 or not fitting in ``point_step``; ``data``
        shorter than ``height``, ``width``, ``point_step`` and ``row_step`` need.
    """
    lay = _cloud_layout(raw)
    points, labels = _cloud_from_buffer(
        raw,
        lay.data_pos,
        lay.data_len,
        fields=lay.fields,
        height=lay.height,
        width=lay.width,
        point_step=lay.point_step,
        row_step=lay.row_step,
        big_endian=lay.big_endian,
        label_field=label_field,
    )
    return RawPoints(stamp_ns=lay.stamp_ns, frame_id=lay.frame_id, points=points, labels=labels)


@dataclass(frozen=True)
class _CloudLayout:
    """The header of a serialized PointCloud2: everything but the point data."""

    stamp_ns: int
    frame_id: str
    fields: list[_Field]
    height: int
    width: int
    point_step: int
    row_step: int
    big_endian: bool
    data_pos: int
    data_len: int


def _cloud_layout(raw: Buffer) -> _CloudLayout:
    r = _Reader(raw, "PointCloud2")
    stamp, frame_id = r.header()
    height = r.u32("height")
    width = r.u32("width")
    n_fields = r.u32("fields length")
    # each PointField takes at least 13 bytes: a too-large count is garbage, not a long loop
    r.need(13 * n_fields, f"{n_fields} fields")
    fields = _read_fields(r, n_fields)
    big_endian = r.u8("is_bigendian") != 0
    point_step = r.u32("point_step")
    row_step = r.u32("row_step")
    data_len = r.u32("data length")
    r.need(data_len, "data")
    return _CloudLayout(stamp, frame_id, fields, height, width, point_step, row_step, big_endian, r.pos, data_len)


# --------------------------------------------------------------------------- many messages at once


@dataclass(frozen=True)
class RawPointsGroup:
    """Marker messages of one layout, parsed together (see :class:`RawPointsBatch`).

    Attributes
    ----------
    index : ndarray, shape (G,), int64
        Positions of these messages in the parsed sequence, increasing.
    stamps_ns : ndarray, shape (G,), int64
        ``header.stamp`` of each, nanoseconds.
    frame_id : str
        ``header.frame_id`` (the same for the whole group).
    points : ndarray, shape (G, N, 3), float64
        The points of each message, as :func:`parse_pose_array` or
        :func:`parse_pointcloud2` give them.
    labels : ndarray, shape (G, N), int64, or None
        Per-point labels (labelled clouds), else None.
    """

    index: IntArray
    stamps_ns: IntArray
    frame_id: str
    points: FloatArray
    labels: IntArray | None


@dataclass(frozen=True)
class RawPointsBatch:
    """A sequence of marker messages parsed at once.

    Attributes
    ----------
    n_messages : int
        Length of the parsed sequence.
    groups : tuple of RawPointsGroup
        The messages that parsed, by layout (every message in exactly one
        group or in ``errors``).
    errors : dict of int to ConversionError
        The messages that did not parse, by position, with the error the
        per-message parser raises for them.
    """

    n_messages: int
    groups: tuple[RawPointsGroup, ...]
    errors: dict[int, ConversionError]


def _align4(pos: int) -> int:
    return pos + (-(pos - 4)) % 4


def _pose_array_spans(raw: Buffer) -> tuple[list[tuple[int, int]], int, int]:
    """Bytes :func:`parse_pose_array` reads besides the stamp and the poses; the poses' offset and count.

    ``raw`` has parsed: the reads are in bounds.
    """
    u32 = struct.Struct(("<" if bytes(raw[0:2]) == _CDR_LE else ">") + "I").unpack_from
    (n_name,) = u32(raw, 12)
    pos = _align4(16 + n_name)
    (n,) = u32(raw, pos)
    data = pos + 4
    data += (-(data - 4)) % 8
    return [(0, 2), (12, 16 + n_name), (pos, pos + 4)], data, int(n)


def _pointcloud2_spans(raw: Buffer) -> list[tuple[int, int]]:
    """Bytes :func:`parse_pointcloud2` reads besides the stamp and the point data (``raw`` has parsed)."""
    u32 = struct.Struct(("<" if bytes(raw[0:2]) == _CDR_LE else ">") + "I").unpack_from
    (n_name,) = u32(raw, 12)
    spans = [(0, 2), (12, 16 + n_name)]
    pos = _align4(16 + n_name)
    spans.append((pos, pos + 12))  # height, width, fields length
    n_fields = u32(raw, pos + 8)[0]
    pos += 12
    for _ in range(n_fields):
        pos = _align4(pos)
        (n,) = u32(raw, pos)
        spans.append((pos, pos + 4 + n))  # name
        pos = _align4(pos + 4 + n)
        spans.append((pos, pos + 5))  # offset, datatype
        pos = _align4(pos + 5)
        spans.append((pos, pos + 4))  # count
        pos += 4
    spans.append((pos, pos + 1))  # is_bigendian
    pos = _align4(pos + 1)
    spans.append((pos, pos + 12))  # point_step, row_step, data length
    return spans


def _columns(spans: list[tuple[int, int]]) -> NDArray[np.intp]:
    return np.concatenate([np.arange(a, b) for a, b in spans]) if spans else np.zeros(0, np.intp)


def _nanosec_text(sec: int, nanosec: int) -> str:
    return (
        f"header.stamp: nanosec {nanosec} is not below 10^9 (sec {sec}): not a valid time, and no output "
        "header could carry it"
    )


def _bad_nanosec(block: NDArray[np.uint8]) -> IntArray:
    """Rows of ``block`` (G, L >= 12; messages as rows) whose ``header.stamp.nanosec`` is 10^9 or more.

    Only messages with a valid encapsulation (00 00 or 00 01): for the others that is the first error.
    """
    little = block[:, 1] == 1
    valid = (block[:, 0] == 0) & (block[:, 1] <= 1)
    le = block[:, 8:12].copy().view("<u4")[:, 0]
    be = block[:, 8:12].copy().view(">u4")[:, 0]
    nsec = np.where(little, le, be)
    return np.flatnonzero(valid & (nsec >= _NS_PER_S))


def _stamps_ns(block: NDArray[np.uint8], little: bool) -> IntArray:
    """``header.stamp`` of messages stacked as rows of ``block`` (G, L), nanoseconds."""
    order = "<" if little else ">"
    g, length = block.shape
    sec = np.ndarray((g,), dtype=order + "i4", buffer=block, offset=4, strides=(length,)).astype(np.int64)
    nsec = np.ndarray((g,), dtype=order + "u4", buffer=block, offset=8, strides=(length,)).astype(np.int64)
    out: IntArray = sec * _NS_PER_S + nsec
    return out


def _parse_batch(raws: Sequence[Buffer], kind: str, label_field: str | None) -> RawPointsBatch:
    """Group messages by length and layout; parse one message per layout, the rest with strided views."""
    lengths = np.fromiter(map(len, raws), dtype=np.int64, count=len(raws))
    groups: list[RawPointsGroup] = []
    errors: dict[int, ConversionError] = {}
    for length in np.unique(lengths).tolist():
        index = np.flatnonzero(lengths == length)
        joined = b"".join(raws) if index.size == len(raws) else b"".join(raws[i] for i in index.tolist())
        block = np.frombuffer(joined, dtype=np.uint8).reshape(index.size, length)
        not_stamp = np.r_[0:min(4, length), 12:length]
        pending = np.arange(index.size)
        if length >= 12:
            # an invalid stamp is the message's own error: the messages sharing its other bytes are fine
            bad = _bad_nanosec(block)
            for row in bad.tolist():
                sec = int(np.frombuffer(bytes(block[row, 4:8]), dtype="<i4" if block[row, 1] == 1 else ">i4")[0])
                nsec = int(np.frombuffer(bytes(block[row, 8:12]), dtype="<u4" if block[row, 1] == 1 else ">u4")[0])
                errors[int(index[row])] = ConversionError(_nanosec_text(sec, nsec))
            if bad.size:
                pending = np.delete(pending, bad)
        while pending.size:
            ref = raws[int(index[pending[0]])]
            try:
                msg = parse_pose_array(ref) if kind == "PoseArray" else parse_pointcloud2(ref, label_field=label_field)
            except ConversionError as exc:
                # the parse depends on the bytes other than the stamp only: the same error for every copy
                same = (block[np.ix_(pending, not_stamp)] == block[pending[0], not_stamp]).all(axis=1)
                for i in index[pending[same]]:
                    errors[int(i)] = exc
                pending = pending[~same]
                continue
            if kind == "PoseArray":
                spans, data, n = _pose_array_spans(ref)
            else:
                spans = _pointcloud2_spans(ref)
            cols = _columns(spans)
            whole = pending.size == index.size
            same = (block[:, cols] if whole else block[np.ix_(pending, cols)]) == block[pending[0], cols]
            same = same.all(axis=1)
            rows = pending[same]
            pending = pending[~same]
            sub = block if rows.size == index.size else np.ascontiguousarray(block[rows])
            little = bytes(ref[0:2]) == _CDR_LE
            if kind == "PoseArray":
                if n == 0:
                    points = np.empty((rows.size, 0, 3))
                else:
                    poses = np.ndarray(
                        (rows.size, n, 3), dtype=("<" if little else ">") + "f8", buffer=sub, offset=data,
                        strides=(length, 56, 8),
                    )
                    points = np.array(poses, dtype=np.float64, order="C")
                labels = None
            else:
                lay = _cloud_layout(ref)
                points, labels = _cloud_arrays(
                    sub,
                    lay.data_pos,
                    fields=lay.fields,
                    height=lay.height,
                    width=lay.width,
                    point_step=lay.point_step,
                    row_step=lay.row_step,
                    big_endian=lay.big_endian,
                    label_field=label_field,
                    messages=(rows.size, length),
                )
            groups.append(RawPointsGroup(index[rows], _stamps_ns(sub, little), msg.frame_id, points, labels))
    return RawPointsBatch(len(raws), tuple(groups), errors)


def parse_pose_arrays(raws: Sequence[Buffer]) -> RawPointsBatch:
    """Positions of many serialized ``geometry_msgs/PoseArray`` messages at once.

    Parameters
    ----------
    raws : sequence of bytes
        CDR bytes of each message (as :func:`parse_pose_array` takes them).

    Returns
    -------
    RawPointsBatch
        For every message, either its stamp, frame id and points (in a
        group) or the :class:`ConversionError` :func:`parse_pose_array`
        raises for it (in ``errors``); the values are those of
        :func:`parse_pose_array`, bit for bit.

    Notes
    -----
    Messages of the same length whose bytes agree wherever the parser
    reads them, apart from the stamp and the poses (encapsulation, frame
    id, pose count; padding is ignored), share a layout: the first of them
    is parsed with :func:`parse_pose_array` and the others are read through
    one strided view of the stacked bytes. A recording of one publisher is
    typically one group; messages that differ (another frame id, another
    marker count, malformed ones) start groups of their own, so the result
    never depends on how the sequence mixes them.
    """
    return _parse_batch(raws, "PoseArray", None)


def parse_pointcloud2s(raws: Sequence[Buffer], *, label_field: str | None = None) -> RawPointsBatch:
    """Points (and labels) of many serialized ``sensor_msgs/PointCloud2`` messages at once.

    Parameters
    ----------
    raws : sequence of bytes
        CDR bytes of each message (as :func:`parse_pointcloud2` takes them).
    label_field : str or None
        As for :func:`parse_pointcloud2`.

    Returns
    -------
    RawPointsBatch
        For every message, its stamp, frame id, points and labels (in a
        group) or the :class:`ConversionError` :func:`parse_pointcloud2`
        raises for it (in ``errors``); values bit for bit those of
        :func:`parse_pointcloud2`.

    Notes
    -----
    Grouping as :func:`parse_pose_arrays`: messages of the same length
    whose header bytes (frame id, height, width, fields, byte order,
    steps, data length) agree share a layout, parsed once; their points
    are one strided view (float32 or float64 fields, any offsets) of the
    stacked bytes.
    """
    return _parse_batch(raws, "PointCloud2", label_field)


# --------------------------------------------------------------------------- message objects


def ns_from_stamp(stamp: Any) -> int:
    """Nanoseconds of a ``builtin_interfaces/Time`` (``sec * 1e9 + nanosec``, exact integer).

    Raises
    ------
    ConversionError
        ``nanosec`` is 10^9 or more (not a time).
    """
    if int(stamp.nanosec) >= _NS_PER_S:
        raise ConversionError(_nanosec_text(int(stamp.sec), int(stamp.nanosec)))
    return int(stamp.sec) * _NS_PER_S + int(stamp.nanosec)



def points_from_pose_array(msg: Any) -> RawPoints:
    """:class:`RawPoints` of a ``geometry_msgs/PoseArray`` message object (one Python step per pose)."""
    points = np.array(
        [(p.position.x, p.position.y, p.position.z) for p in msg.poses], dtype=np.float64
    ).reshape(-1, 3)
    return RawPoints(ns_from_stamp(msg.header.stamp), str(msg.header.frame_id), points, None)


def points_from_pointcloud2(msg: Any, label_field: str | None = None) -> RawPoints:
    """:class:`RawPoints` of a ``sensor_msgs/PointCloud2`` message object; same rules as :func:`parse_pointcloud2`."""
    fields = [_Field(str(f.name), int(f.offset), int(f.datatype), int(f.count)) for f in msg.fields]
    data = msg.data
    buf = data if isinstance(data, bytes | bytearray) else memoryview(data).cast("B")
    points, labels = _cloud_from_buffer(
        buf,
        0,
        len(buf),
        fields=fields,
        height=int(msg.height),
        width=int(msg.width),
        point_step=int(msg.point_step),
        row_step=int(msg.row_step),
        big_endian=bool(msg.is_bigendian),
        label_field=label_field,
    )
    return RawPoints(ns_from_stamp(msg.header.stamp), str(msg.header.frame_id), points, labels)


def pose_from_pose_stamped(msg: Any) -> RawPose:
    """:class:`RawPose` of a ``geometry_msgs/PoseStamped`` message object."""
    p, q = msg.pose.position, msg.pose.orientation
    return RawPose(
        ns_from_stamp(msg.header.stamp),
        str(msg.header.frame_id),
        np.array([p.x, p.y, p.z], dtype=np.float64),
        np.array([q.x, q.y, q.z, q.w], dtype=np.float64),
    )


# --------------------------------------------------------------------------- marker ordering


def _real_array(value: ArrayLike, name: str, expected: str) -> FloatArray:
    """``value`` as float64; ConversionError if it is not real numbers (complex would lose its imaginary part)."""
    try:
        return as_real_array(value, name=name, expected=expected)
    except InputError as exc:
        raise ConversionError(str(exc)) from None


def _check_points(points: ArrayLike, name: str = "points") -> FloatArray:
    arr = _real_array(points, name, "shape (N, 3)")
    if arr.ndim == 1 and arr.size == 0:
        arr = arr.reshape(0, 3)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ConversionError(f"{name}: expected shape (N, 3), got shape {arr.shape}")
    return arr


def _mark_missing(frame: FloatArray, zero_is_missing: bool) -> FloatArray:
    """Set rows with a non-finite coordinate (and exact zeros if asked) to NaN, in place."""
    bad = ~np.isfinite(frame).all(axis=1)
    if zero_is_missing:
        bad |= (frame == 0.0).all(axis=1)
    frame[bad] = np.nan
    return frame


def _check_labels(labels: ArrayLike, n_points: int) -> IntArray:
    lab = np.asarray(labels)
    if lab.shape != (n_points,) or not (lab.dtype.kind in "iu" or n_points == 0):
        raise ConversionError(
            f"labels: expected an integer array of shape ({n_points},) (one per point), "
            f"got {lab.dtype} shape {lab.shape}"
        )
    return lab.astype(np.int64, copy=False)


def label_problems(labels: ArrayLike, n_markers: int) -> LabelProblems:
    """Count the labels :func:`frame_from_points` ignores.

    Parameters
    ----------
    labels : array_like of int, shape (N,)
    n_markers : int
        Number of configured markers P.

    Returns
    -------
    LabelProblems
        Points with a label outside [0, P) and rows claimed by more than one point.
    """
    lab = np.asarray(labels, dtype=np.int64).reshape(-1)
    valid = (lab >= 0) & (lab < n_markers)
    counts = np.bincount(lab[valid], minlength=n_markers)
    return LabelProblems(
        out_of_range=int(np.count_nonzero(~valid)), duplicated=int(np.count_nonzero(counts > 1))
    )


def frame_from_points(
    points: ArrayLike,
    n_markers: int,
    *,
    labels: ArrayLike | None = None,
    zero_is_missing: bool = True,
) -> FloatArray:
    """Order the points of one message into the frame of the configured markers.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Points of one message (any length unit).
    n_markers : int
        Number of configured markers P.
    labels : array_like of int, shape (N,), optional
        Marker index of each point: label k goes to row k. Labels outside
        [0, P) are ignored; a row that several points claim is set missing
        (the identity is ambiguous). :func:`label_problems` counts both, for
        diagnostics. Without labels, point i is marker i.
    zero_is_missing : bool
        Treat an exact (0, 0, 0) point as missing (mocap4ros2's Vicon driver
        sends occluded markers as zeros). Default True.

    Returns
    -------
    ndarray, shape (P, 3), float64
        A new array; missing markers (no point, NaN or inf in any coordinate,
        zeros if asked) are NaN rows.

    Raises
    ------
    ConversionError
        Bad shapes, or more unlabelled points than markers (the marker order
        cannot be known; configure all published markers, or use labels).
    """
    pts = _check_points(points)
    if n_markers < 0:
        raise ConversionError(f"n_markers: expected a non-negative integer, got {n_markers}")
    out = np.full((n_markers, 3), np.nan)
    if labels is None:
        if pts.shape[0] > n_markers:
            raise ConversionError(
                f"points: expected at most {n_markers} unlabelled points (one per configured marker, in order), "
                f"got {pts.shape[0]}"
            )
        out[: pts.shape[0]] = pts
    else:
        lab = _check_labels(labels, pts.shape[0])
        valid = (lab >= 0) & (lab < n_markers)
        rows = lab[valid]
        out[rows] = pts[valid]
        counts = np.bincount(rows, minlength=n_markers)
        out[counts > 1] = np.nan
    return _mark_missing(out, zero_is_missing)


def label_points(
    points: ArrayLike, predicted: ArrayLike, gate: float, *, zero_is_missing: bool = True
) -> FloatArray:
    """Label an unlabelled cloud by optimal assignment to predicted marker positions.

    For clouds without labels (e.g. IMRCLab ``motion_capture_tracking``
    publishes a PointCloud2 of x, y, z float32 only): each predicted marker
    gets at most one point and each point at most one marker, minimising the
    summed distance (``scipy.optimize.linear_sum_assignment``); a pair farther
    apart than ``gate`` is rejected (the marker is missing). Pairs beyond the
    gate cost more than any set of in-gate pairs, so the assignment first
    maximises the number of in-gate pairs, then minimises their distance.

    Parameters
    ----------
    points : array_like, shape (M, 3)
        The unlabelled points (NaN / inf rows, and exact zeros if
        ``zero_is_missing``, are ignored).
    predicted : array_like, shape (P, 3)
        Where each marker is expected, e.g. the last labelled frame or a
        constant-velocity prediction; NaN rows (no prediction) get NaN.
    gate : float
        Largest accepted distance between a point and its prediction (units
        of the points), > 0.
    zero_is_missing : bool
        Ignore exact (0, 0, 0) points. Default True.

    Returns
    -------
    ndarray, shape (P, 3), float64
        Row k is the point assigned to marker k, NaN when none within the gate.

    Raises
    ------
    ConversionError
        Bad shapes or a non-positive gate.

    Notes
    -----
    Limits: this is nearest-neighbour tracking, not marker identification.
    It needs a prediction (an initial labelled frame or a known pose), and a
    marker that has been missing keeps whatever prediction the caller gives.
    Markers that move more than about half their mutual separation between
    frames (fast motion, low rate, markers closer together than twice the
    frame-to-frame displacement) can be swapped without any sign in the
    distances; a gate of that half separation limits, but does not remove,
    the risk. A ghost point within the gate of an occluded marker is taken
    for it. Cost: O(max(M, P)^3) per frame, fine for tens of markers.
    """
    pts = _check_points(points)
    pred = _check_points(predicted, "predicted")
    gate_arr = _real_array(gate, "gate", "a positive finite distance")
    if gate_arr.shape != () or not (math.isfinite(float(gate_arr)) and float(gate_arr) > 0.0):
        raise ConversionError(f"gate: expected a positive finite distance, got {gate}")
    gate = float(gate_arr)
    out = np.full(pred.shape, np.nan)
    pts_ok = np.isfinite(pts).all(axis=1)
    if zero_is_missing:
        pts_ok &= ~(pts == 0.0).all(axis=1)
    pred_ok = np.isfinite(pred).all(axis=1)
    p_idx = np.flatnonzero(pred_ok)
    q = pts[pts_ok]
    if p_idx.size == 0 or q.shape[0] == 0:
        return out
    dist = np.linalg.norm(pred[p_idx, None, :] - q[None, :, :], axis=2)
    outside = dist > gate
    cost = np.where(outside, gate * (min(dist.shape) + 1.0), dist)
    rows, cols = linear_sum_assignment(cost)
    keep = ~outside[rows, cols]
    out[p_idx[rows[keep]]] = q[cols[keep]]
    return out


# --------------------------------------------------------------------------- serializers


def _cdr_header(stamp_ns: int, frame_id: str, prefix: str) -> bytearray:
    sec, nanosec = divmod(int(stamp_ns), _NS_PER_S)
    if not -(2**31) <= sec < 2**31:
        raise ConversionError(f"stamp_ns: expected seconds within int32, got {stamp_ns} ns")
    name = frame_id.encode("utf-8") + b"\x00"
    out = bytearray(_CDR_BE if prefix == ">" else _CDR_LE)
    out += b"\x00\x00"
    out += struct.pack(prefix + "iII", sec, nanosec, len(name))
    out += name
    return out


def _pad(out: bytearray, n: int) -> None:
    out += b"\x00" * ((-(len(out) - 4)) % n)


def pose_array_bytes(
    stamp_ns: int, frame_id: str, points: ArrayLike, *, orientations: ArrayLike | None = None, big_endian: bool = False
) -> bytes:
    """CDR bytes of a ``geometry_msgs/PoseArray`` whose positions are ``points``.

    Parameters
    ----------
    stamp_ns : int
        ``header.stamp`` in nanoseconds.
    frame_id : str
        ``header.frame_id``.
    points : array_like, shape (N, 3)
        Positions (NaN allowed).
    orientations : array_like, shape (N, 4), optional
        Quaternions (x, y, z, w); default the identity (0, 0, 0, 1).
    big_endian : bool
        Write big-endian CDR (for tests of readers); ROS middlewares on
        little-endian hosts send little-endian. Default False.

    Returns
    -------
    bytes
        Ready for ``Publisher.publish`` (encapsulation header included).
    """
    pts = _check_points(points)
    prefix = ">" if big_endian else "<"
    out = _cdr_header(stamp_ns, frame_id, prefix)
    _pad(out, 4)
    n = pts.shape[0]
    out += struct.pack(prefix + "I", n)
    if n:
        _pad(out, 8)
        poses = np.zeros((n, 7), dtype=prefix + "f8")
        poses[:, :3] = pts
        if orientations is None:
            poses[:, 6] = 1.0
        else:
            q = np.asarray(orientations, dtype=np.float64)
            if q.shape != (n, 4):
                raise ConversionError(f"orientations: expected shape ({n}, 4), got {q.shape}")
            poses[:, 3:] = q
        out += poses.tobytes()
    return bytes(out)


def pointcloud2_bytes(
    stamp_ns: int,
    frame_id: str,
    points: ArrayLike,
    *,
    labels: ArrayLike | None = None,
    dtype: DTypeLike = np.float32,
    big_endian: bool = False,
) -> bytes:
    """CDR bytes of an unorganised ``sensor_msgs/PointCloud2`` (height 1).

    Parameters
    ----------
    stamp_ns : int
        ``header.stamp`` in nanoseconds.
    frame_id : str
        ``header.frame_id``.
    points : array_like, shape (N, 3)
        Positions (NaN allowed; ``is_dense`` is then False).
    labels : array_like of int, shape (N,), optional
        Labels in [0, 2**32 - 1], written as a UINT32 field ``label`` after
        z; anything else (negative, too large, not integers) raises.
    dtype : float32 or float64
        Type of the x, y, z fields. Default float32 (as most mocap drivers).
    big_endian : bool
        Write big-endian CDR and point data (``is_bigendian`` True), for tests.

    Returns
    -------
    bytes
        Ready for ``Publisher.publish``. Fields x, y, z at offsets 0, s, 2s
        (s = 4 or 8), then ``label`` if given; ``point_step`` is the sum of
        their sizes, ``row_step = width * point_step``.

    Raises
    ------
    ConversionError
        Bad shapes, complex or non-numeric points, a finite coordinate
        beyond the float32 range with ``dtype=float32``, bad labels, a
        stamp outside int32 seconds.
    """
    pts = _check_points(points)
    ftype = np.dtype(dtype)
    if ftype not in (np.dtype(np.float32), np.dtype(np.float64)):
        raise ConversionError(f"dtype: expected float32 or float64, got {ftype}")
    if ftype == np.dtype(np.float32):
        finite = pts[np.isfinite(pts)]
        if finite.size and float(np.abs(finite).max()) > float(np.finfo(np.float32).max):
            raise ConversionError(
                f"points: a coordinate ({float(np.abs(finite).max()):.6g} in magnitude) exceeds the float32 "
                "range; write the cloud with dtype=float64"
            )
    prefix = ">" if big_endian else "<"
    size = ftype.itemsize
    n = pts.shape[0]
    names = ["x", "y", "z"]
    formats = [prefix + ftype.str[1:]] * 3
    field_specs = [
        ("x", 0, 7 if size == 4 else 8),
        ("y", size, 7 if size == 4 else 8),
        ("z", 2 * size, 7 if size == 4 else 8),
    ]
    lab = None
    if labels is not None:
        lab = _check_labels(labels, n)
        # range-check the given integers (before any cast: int64 -> uint32, or uint64 -> int64, would wrap)
        given = np.asarray(labels)
        if n and (int(given.min()) < 0 or int(given.max()) > _UINT32_MAX):
            raise ConversionError(
                f"labels: expected integers in [0, {_UINT32_MAX}] for a UINT32 field, got values in "
                f"[{int(given.min())}, {int(given.max())}]"
            )
        names.append("label")
        formats.append(prefix + "u4")
        field_specs.append(("label", 3 * size, 6))
    rec = np.dtype({"names": names, "formats": formats})
    data = np.empty(n, dtype=rec)
    with np.errstate(invalid="ignore"):  # a signalling NaN stays a NaN (missing) in float32, quietly
        data["x"], data["y"], data["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if lab is not None:
        data["label"] = lab
    point_step = rec.itemsize
    out = _cdr_header(stamp_ns, frame_id, prefix)
    _pad(out, 4)
    out += struct.pack(prefix + "III", 1, n, len(field_specs))
    for name, offset, datatype in field_specs:
        _pad(out, 4)
        encoded = name.encode() + b"\x00"
        out += struct.pack(prefix + "I", len(encoded)) + encoded
        _pad(out, 4)
        out += struct.pack(prefix + "I", offset) + bytes([datatype])
        _pad(out, 4)
        out += struct.pack(prefix + "I", 1)
    out += bytes([1 if big_endian else 0])
    _pad(out, 4)
    out += struct.pack(prefix + "III", point_step, n * point_step, n * point_step)
    out += data.tobytes()
    out += bytes([bool(np.isfinite(pts).all())])
    return bytes(out)


# --------------------------------------------------------------------------- rotations


def rotation_matrix_from_quaternion(xyzw: ArrayLike) -> FloatArray:
    """Rotation matrix of a quaternion (x, y, z, w), normalised first.

    Parameters
    ----------
    xyzw : array_like, shape (4,)

    Returns
    -------
    ndarray, shape (3, 3)
        ``R`` such that ``R @ v`` rotates ``v``.

    Raises
    ------
    ConversionError
        Wrong shape, non-finite values, or a (near) zero quaternion.
    """
    x, y, z, w = _unit_quaternion(xyzw).tolist()  # Python floats: the same IEEE operations, ~5x faster
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _unit_quaternion(xyzw: ArrayLike) -> FloatArray:
    """``xyzw`` (4,) divided by its norm; ConversionError for a wrong shape, non-finite or (near) zero one."""
    q = xyzw if isinstance(xyzw, np.ndarray) and xyzw.dtype == np.float64 else _real_array(xyzw, "quaternion", "shape (4,)")
    if q.shape != (4,):
        raise ConversionError(f"quaternion: expected shape (4,) as (x, y, z, w), got shape {q.shape}")
    norm = math.sqrt(q.dot(q))  # = np.linalg.norm(q), without its Python-level overhead
    if not math.isfinite(norm) or norm < 1e-12:
        raise ConversionError(f"quaternion: expected a finite non-zero quaternion, got {q.tolist()}")
    out: FloatArray = q / norm
    return out


def quaternion_from_rotation_matrix(R: ArrayLike) -> FloatArray:
    """Unit quaternion (x, y, z, w), w >= 0, of a proper rotation matrix, shape (3, 3) -> (4,)."""
    mat = _real_array(R, "R", "shape (3, 3)")
    if mat.shape != (3, 3):
        raise ConversionError(f"R: expected shape (3, 3), got shape {mat.shape}")
    if not np.isfinite(mat).all():
        raise ConversionError(f"R: expected finite values, got {mat.tolist()}")
    # Shepperd's method on Python floats (scipy's Rotation costs ~0.1 ms, on the node's executor thread):
    # the largest of 4 w^2, 4 x^2, 4 y^2, 4 z^2 is the pivot, so no division by a small number.
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = mat.tolist()
    trace = m00 + m11 + m22
    if trace >= max(m00, m11, m22):
        s = 2.0 * math.sqrt(max(1.0 + trace, 0.0))
        x, y, z, w = (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s, 0.25 * s
    elif m00 >= m11 and m00 >= m22:
        s = 2.0 * math.sqrt(max(1.0 + m00 - m11 - m22, 0.0))
        x, y, z, w = 0.25 * s, (m01 + m10) / s, (m02 + m20) / s, (m21 - m12) / s
    elif m11 >= m22:
        s = 2.0 * math.sqrt(max(1.0 + m11 - m00 - m22, 0.0))
        x, y, z, w = (m01 + m10) / s, 0.25 * s, (m12 + m21) / s, (m02 - m20) / s
    else:
        s = 2.0 * math.sqrt(max(1.0 + m22 - m00 - m11, 0.0))
        x, y, z, w = (m02 + m20) / s, (m12 + m21) / s, 0.25 * s, (m10 - m01) / s
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if w < 0.0:
        norm = -norm
    return np.array([x / norm, y / norm, z / norm, w / norm])


def _unit(v: ArrayLike, name: str) -> FloatArray:
    arr = v if isinstance(v, np.ndarray) and v.dtype == np.float64 else _real_array(v, name, "shape (3,)")
    if arr.shape != (3,):
        raise ConversionError(f"{name}: expected shape (3,), got shape {arr.shape}")
    norm = math.sqrt(arr.dot(arr))  # = np.linalg.norm(arr)
    if not math.isfinite(norm) or norm < 1e-12:
        raise ConversionError(f"{name}: expected a finite non-zero vector, got {arr.tolist()}")
    out: FloatArray = arr / norm
    return out


def quaternion_z_to_direction(direction: ArrayLike) -> FloatArray:
    """The minimal rotation taking +z to ``direction``, as a quaternion (x, y, z, w).

    Parameters
    ----------
    direction : array_like, shape (3,)
        Non-zero; normalised here.

    Returns
    -------
    ndarray, shape (4,)
        Rotation about ``z x d`` by the angle between z and d. For d = -z,
        where that axis is undefined, the half turn about x, (1, 0, 0, 0).
        Deterministic and continuous except at d = -z.

    Notes
    -----
    ``q ∝ (z × d, 1 + z·d) = (-d_y, d_x, 0, 1 + d_z)``; near d = -z, ``1 + d_z``
    is computed as ``(d_x² + d_y²) / (1 - d_z)`` to avoid cancellation.
    """
    dx, dy, dz = _unit(direction, "direction").tolist()
    w = 1.0 + dz if dz >= 0.0 else (dx * dx + dy * dy) / (1.0 - dz)
    q = np.array([-dy, dx, 0.0, w])
    norm = math.sqrt(q.dot(q))
    if norm < 1e-150:
        return np.array([1.0, 0.0, 0.0, 0.0])
    return q / norm
