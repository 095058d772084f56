"""Tests of jointfit_ros.conversions: CDR parsers and serializers against rclpy's, ordering, builders.

Nothing here calls ``rclpy.init()``: ``rclpy.serialization`` and the message
classes work without a context.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np
import pytest
from geometry_msgs.msg import Pose, PoseArray, PoseStamped, PoseWithCovarianceStamped
from numpy.typing import NDArray
from rclpy.serialization import deserialize_message, serialize_message
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import PointCloud2, PointField

from jointfit_ros.conversions import (
    UNKNOWN_ROTATION_VARIANCE,
    ConversionError,
    axis_arrow_marker,
    axis_pose,
    covariance_ellipsoid_marker,
    diagnostic_status,
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
    pose_with_covariance,
    quaternion_from_rotation_matrix,
    quaternion_z_to_direction,
    rotation_matrix_from_quaternion,
    sphere_marker,
    stamp_from_ns,
)
from jointfit_ros.raw import RawPointsBatch, parse_pointcloud2s, parse_pose_arrays

# frame ids of every length modulo 8 (alignment after the string), empty, non-ASCII
FRAME_IDS = [
    "",
    "w",
    "ab",
    "abc",
    "abcd",
    "world",
    "mocap_",
    "wörld",
    "世界",
    "vicon/world/origin_frame_1234",
]
FLOAT_TYPES = {PointField.FLOAT32: "f4", PointField.FLOAT64: "f8"}
INT_TYPES = {
    PointField.INT8: "i1",
    PointField.UINT8: "u1",
    PointField.INT16: "i2",
    PointField.UINT16: "u2",
    PointField.INT32: "i4",
    PointField.UINT32: "u4",
}


def _random_points(rng: np.random.Generator, n: int, nan_fraction: float = 0.2) -> NDArray[np.float64]:
    pts = rng.normal(0.0, 2.0, (n, 3)) + rng.normal(0.0, 1000.0, 3)
    pts[rng.random(n) < nan_fraction] = np.nan
    return pts


def _random_stamp(rng: np.random.Generator) -> int:
    return int(rng.integers(-(2**31), 2**31 - 1)) * 1_000_000_000 + int(rng.integers(0, 1_000_000_000))


def _pose_array_msg(
    stamp_ns: int, frame_id: str, pts: NDArray[np.float64], rng: np.random.Generator
) -> PoseArray:
    msg = PoseArray()
    msg.header.stamp = stamp_from_ns(stamp_ns)
    msg.header.frame_id = frame_id
    poses = []
    for p in pts:
        pose = Pose()
        pose.position.x, pose.position.y, pose.position.z = (float(v) for v in p)
        q = Rotation.random(random_state=rng).as_quat()
        pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = (float(v) for v in q)
        poses.append(pose)
    msg.poses = poses
    return msg


def _cloud_msg(
    rng: np.random.Generator,
    pts: NDArray[np.float64],
    *,
    frame_id: str,
    stamp_ns: int,
    height: int,
    width: int,
    labels: NDArray[np.int64] | None = None,
    label_type: int = PointField.UINT32,
) -> tuple[PointCloud2, NDArray[np.float64]]:
    """A PointCloud2 with shuffled fields, extra fields, padding, row padding and random byte order.

    Returns the message and the points as stored (after rounding to the field types).
    """
    n = pts.shape[0]
    specs: list[tuple[str, int]] = [(name, int(rng.choice(list(FLOAT_TYPES)))) for name in "xyz"]
    specs += [("intensity", PointField.FLOAT32), ("ring", PointField.UINT16), ("rgb", PointField.UINT32)]
    if labels is not None:
        specs.append(("label", label_type))
    order = rng.permutation(len(specs))
    big = bool(rng.integers(2))
    prefix = ">" if big else "<"
    fields, names, formats, offsets = [], [], [], []
    offset = int(rng.integers(0, 5))
    for k in order:
        name, datatype = specs[k]
        code = FLOAT_TYPES.get(datatype) or INT_TYPES[datatype]
        fields.append(PointField(name=name, offset=offset, datatype=datatype, count=1))
        names.append(name)
        formats.append(prefix + code)
        offsets.append(offset)
        offset += int(code[1]) + int(rng.integers(0, 4))  # odd gaps: unaligned fields
    point_step = offset + int(rng.integers(0, 7))
    rec = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})
    data = np.zeros(n, dtype=rec)
    for k, name in enumerate("xyz"):
        data[name] = pts[:, k]
    data["intensity"] = rng.random(n)
    data["ring"] = rng.integers(0, 60000, n)
    data["rgb"] = rng.integers(0, 2**32, n)
    if labels is not None:
        data["label"] = labels
    row_pad = int(rng.integers(0, 9))
    row_step = width * point_step + row_pad
    raw = np.zeros(height * row_step, dtype=np.uint8)
    for row in range(height):
        chunk = data[row * width : (row + 1) * width].tobytes()
        raw[row * row_step : row * row_step + len(chunk)] = np.frombuffer(chunk, dtype=np.uint8)
    msg = PointCloud2()
    msg.header.stamp = stamp_from_ns(stamp_ns)
    msg.header.frame_id = frame_id
    msg.height, msg.width = height, width
    msg.fields = fields
    msg.is_bigendian = big
    msg.point_step, msg.row_step = point_step, row_step
    msg.data = raw.tobytes()
    msg.is_dense = False
    stored = np.stack([data[name].astype(np.float64) for name in "xyz"], axis=1)
    return msg, stored


# --------------------------------------------------------------------------- parsers


def test_parse_pose_array_matches_rclpy_serialization() -> None:
    rng = np.random.default_rng(1)
    for trial in range(60):
        n = int(rng.integers(0, 61))
        pts = _random_points(rng, n)
        stamp = _random_stamp(rng)
        frame_id = FRAME_IDS[trial % len(FRAME_IDS)]
        msg = _pose_array_msg(stamp, frame_id, pts, rng)
        parsed = parse_pose_array(serialize_message(msg))
        assert parsed.stamp_ns == stamp
        assert parsed.frame_id == frame_id
        assert parsed.labels is None
        assert parsed.points.shape == (n, 3) and parsed.points.dtype == np.float64
        np.testing.assert_array_equal(parsed.points, pts)
        from_obj = points_from_pose_array(msg)
        np.testing.assert_array_equal(from_obj.points, pts)
        assert (from_obj.stamp_ns, from_obj.frame_id) == (stamp, frame_id)


def test_parse_pose_stamped_matches_rclpy_serialization() -> None:
    rng = np.random.default_rng(2)
    for frame_id in FRAME_IDS:
        msg = PoseStamped()
        stamp = _random_stamp(rng)
        msg.header.stamp = stamp_from_ns(stamp)
        msg.header.frame_id = frame_id
        pos, quat = rng.normal(size=3), rng.normal(size=4)
        msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (float(v) for v in pos)
        o = msg.pose.orientation
        o.x, o.y, o.z, o.w = (float(v) for v in quat)
        for parsed in (parse_pose_stamped(serialize_message(msg)), pose_from_pose_stamped(msg)):
            assert (parsed.stamp_ns, parsed.frame_id) == (stamp, frame_id)
            np.testing.assert_array_equal(parsed.position, pos)
            np.testing.assert_array_equal(parsed.quaternion, quat)


@pytest.mark.parametrize("label_type", [None, *INT_TYPES])
def test_parse_pointcloud2_matches_rclpy_serialization(label_type: int | None) -> None:
    rng = np.random.default_rng(3 + (label_type or 0))
    for trial in range(25):
        height = int(rng.choice([0, 1, 1, 2, 3]))
        width = int(rng.integers(0, 21))
        n = height * width
        pts = _random_points(rng, n)
        labels = None
        if label_type is not None:
            lo = -100 if INT_TYPES[label_type][0] == "i" else 0
            labels = rng.integers(lo, 100, n)
        stamp = _random_stamp(rng)
        frame_id = FRAME_IDS[trial % len(FRAME_IDS)]
        msg, stored = _cloud_msg(
            rng,
            pts,
            frame_id=frame_id,
            stamp_ns=stamp,
            height=height,
            width=width,
            labels=labels,
            label_type=label_type or PointField.UINT32,
        )
        label_field = "label" if label_type is not None else None
        for parsed in (
            parse_pointcloud2(serialize_message(msg), label_field=label_field),
            points_from_pointcloud2(msg, label_field=label_field),
        ):
            assert (parsed.stamp_ns, parsed.frame_id) == (stamp, frame_id)
            assert parsed.points.shape == (n, 3) and parsed.points.dtype == np.float64
            np.testing.assert_array_equal(parsed.points, stored)
            np.testing.assert_allclose(parsed.points, pts, rtol=1e-6)
            if labels is None:
                assert parsed.labels is None
            else:
                assert parsed.labels is not None and parsed.labels.dtype == np.int64
                np.testing.assert_array_equal(parsed.labels, labels)


# --------------------------------------------------------------------------- many messages at once


def _same_as_one_by_one(
    raws: list[bytes], batch: RawPointsBatch, parse: Callable[[bytes], object], *, groups_at_most: int
) -> None:
    """Every message is in exactly one group or in ``errors``, with the values or error of ``parse``."""
    assert batch.n_messages == len(raws)
    seen: list[int] = []
    for g in batch.groups:
        assert g.points.dtype == np.float64 and g.stamps_ns.dtype == np.int64
        assert np.all(np.diff(g.index) > 0)
        for j, i in enumerate(g.index.tolist()):
            one = parse(raws[i])
            assert (one.stamp_ns, one.frame_id) == (int(g.stamps_ns[j]), g.frame_id)  # type: ignore[attr-defined]
            np.testing.assert_array_equal(g.points[j], one.points)  # type: ignore[attr-defined]
            if one.labels is None:  # type: ignore[attr-defined]
                assert g.labels is None
            else:
                assert g.labels is not None and g.labels.dtype == np.int64
                np.testing.assert_array_equal(g.labels[j], one.labels)  # type: ignore[attr-defined]
            seen.append(i)
    for i, exc in batch.errors.items():
        with pytest.raises(ConversionError) as info:
            parse(raws[i])
        assert str(info.value) == str(exc)
        seen.append(i)
    assert sorted(seen) == list(range(len(raws)))
    assert len(batch.groups) <= groups_at_most


def test_parse_pose_arrays_equals_one_by_one() -> None:
    """Groups by layout (frame id, count, byte order); ignores padding bytes; malformed ones as the parser says."""
    rng = np.random.default_rng(21)
    raws: list[bytes] = []
    for k in range(400):
        n = 5 if rng.random() < 0.8 else int(rng.integers(0, 8))
        frame_id = FRAME_IDS[int(rng.integers(0, 3))]
        raw = pose_array_bytes(_random_stamp(rng), frame_id, _random_points(rng, n), big_endian=bool(k % 9 == 0))
        if k % 5 == 1:  # rclpy's serializer (random orientations)
            raw = serialize_message(_pose_array_msg(_random_stamp(rng), frame_id, _random_points(rng, n), rng))
        if k % 7 == 3 and len(frame_id) % 4 != 3:  # padding bytes after the frame id: meaningless
            pad = 16 + len(frame_id) + 1
            raw = raw[:pad] + bytes(rng.integers(0, 256, (-(pad - 4)) % 4, dtype=np.uint8)) + raw[pad + (-(pad - 4)) % 4 :]
        if k % 23 == 5:
            raw = raw[: int(rng.integers(0, len(raw)))]  # truncated
        if k % 31 == 7:
            raw = b"\x00\x07" + raw[2:]  # unknown encapsulation
        raws.append(raw)
    raws += [raws[-1][:30]] * 3 + [b"", b"\x00\x01\x00\x00"]
    batch = parse_pose_arrays(raws)
    assert batch.errors and max(len(g.index) for g in batch.groups) > 100
    _same_as_one_by_one(raws, batch, parse_pose_array, groups_at_most=60)
    empty = parse_pose_arrays([])
    assert (empty.n_messages, empty.groups, empty.errors) == (0, (), {})


@pytest.mark.parametrize("label_field", [None, "label"])
def test_parse_pointcloud2s_equals_one_by_one(label_field: str | None) -> None:
    """Labelled and unlabelled, float32 and float64, any field layout, organised clouds, malformed ones."""
    rng = np.random.default_rng(22)
    raws: list[bytes] = []
    for k in range(300):
        n = 6 if rng.random() < 0.8 else int(rng.integers(0, 9))
        labels = rng.permutation(n) if k % 3 else None
        dtype = np.float32 if k % 4 else np.float64
        raws.append(
            pointcloud2_bytes(
                _random_stamp(rng), "world", _random_points(rng, n), labels=labels, dtype=dtype, big_endian=k % 11 == 0
            )
        )
    for k in range(4):  # shuffled and padded fields, organised: one layout each, many messages of it
        height, width = (2, 4) if k % 2 else (1, 7)
        msg, _ = _cloud_msg(
            rng, _random_points(rng, height * width), frame_id="mocap", stamp_ns=0, height=height, width=width,
            labels=rng.integers(-3, 9, height * width), label_type=PointField.INT16,
        )
        for _ in range(40):
            msg.header.stamp = stamp_from_ns(_random_stamp(rng))
            msg.data = rng.integers(0, 256, len(msg.data), dtype=np.uint8).tobytes()  # any bits: NaN, inf, sNaN
            raws.append(serialize_message(msg))
    good = pointcloud2_bytes(5, "world", rng.normal(size=(4, 3)), labels=np.arange(4))
    raws += [good[:cut] for cut in range(0, len(good) - 1, 7)]  # truncated
    raws += [_cloud_with_fields([_f("x", 0), _f("y", 4)], 12)] * 2  # no z
    raws += [_cloud_with_fields([_f("x", 0), _f("y", 4), _f("z", 8)], 12, data_len=35)]
    order = rng.permutation(len(raws))
    raws = [raws[i] for i in order]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        batch = parse_pointcloud2s(raws, label_field=label_field)
    assert batch.errors and max(len(g.index) for g in batch.groups) > 50
    _same_as_one_by_one(
        raws, batch, lambda raw: parse_pointcloud2(raw, label_field=label_field), groups_at_most=len(raws) // 4
    )


# --------------------------------------------------------------------------- serializers


@pytest.mark.parametrize("big_endian", [False, True])
def test_pose_array_bytes_round_trip(big_endian: bool) -> None:
    rng = np.random.default_rng(4)
    for trial in range(40):
        n = int(rng.integers(0, 61))
        pts = _random_points(rng, n)
        stamp = _random_stamp(rng)
        frame_id = FRAME_IDS[trial % len(FRAME_IDS)]
        raw = pose_array_bytes(stamp, frame_id, pts, big_endian=big_endian)
        parsed = parse_pose_array(raw)
        assert (parsed.stamp_ns, parsed.frame_id) == (stamp, frame_id)
        np.testing.assert_array_equal(parsed.points, pts)
        if big_endian:
            continue  # rclpy reads little-endian only on this host
        msg = deserialize_message(raw, PoseArray)
        assert ns_from_stamp(msg.header.stamp) == stamp and msg.header.frame_id == frame_id
        np.testing.assert_array_equal(points_from_pose_array(msg).points, pts)
        assert all(p.orientation.w == 1.0 for p in msg.poses)


@pytest.mark.parametrize("big_endian", [False, True])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("with_labels", [False, True])
def test_pointcloud2_bytes_round_trip(big_endian: bool, dtype: type, with_labels: bool) -> None:
    rng = np.random.default_rng(5)
    for trial in range(15):
        n = int(rng.integers(0, 61))
        pts = _random_points(rng, n)
        labels = rng.integers(0, 2**32, n) if with_labels else None
        stamp = _random_stamp(rng)
        frame_id = FRAME_IDS[trial % len(FRAME_IDS)]
        raw = pointcloud2_bytes(stamp, frame_id, pts, labels=labels, dtype=dtype, big_endian=big_endian)
        expected = pts.astype(dtype).astype(np.float64)
        parsed = parse_pointcloud2(raw, label_field="label" if with_labels else None)
        assert (parsed.stamp_ns, parsed.frame_id) == (stamp, frame_id)
        np.testing.assert_array_equal(parsed.points, expected)
        if with_labels:
            assert parsed.labels is not None
            np.testing.assert_array_equal(parsed.labels, labels)
        if big_endian:
            continue
        msg = deserialize_message(raw, PointCloud2)
        assert ns_from_stamp(msg.header.stamp) == stamp and msg.header.frame_id == frame_id
        assert (msg.height, msg.width) == (1, n)
        assert msg.row_step == n * msg.point_step and len(msg.data) == msg.row_step
        assert msg.is_dense == bool(np.isfinite(pts).all())
        assert [f.name for f in msg.fields] == ["x", "y", "z"] + (["label"] if with_labels else [])
        again = points_from_pointcloud2(msg, label_field="label" if with_labels else None)
        np.testing.assert_array_equal(again.points, expected)


@pytest.mark.parametrize(
    "labels",
    [
        np.array([2**32 + 5, 1]),
        np.array([2**32, 0], dtype=np.uint64),
        np.array([2**63 + 1, 0], dtype=np.uint64),
        np.array([-1, 0]),
        np.array([0.0, 1.0]),
        np.array([True, False]),
        np.array([1 + 0j, 0j]),
        [0, 1, 2],
    ],
)
def test_pointcloud2_bytes_rejects_labels_outside_uint32(labels: object) -> None:
    """Regression: labels were cast to UINT32 unchecked, so 2**32 + 5 was written (and read back) as 5."""
    with pytest.raises(ConversionError, match="labels"):
        pointcloud2_bytes(0, "world", np.ones((2, 3)), labels=labels)  # type: ignore[arg-type]
    top = np.array([2**32 - 1, 0], dtype=np.uint64)
    parsed = parse_pointcloud2(pointcloud2_bytes(0, "world", np.ones((2, 3)), labels=top), label_field="label")
    assert parsed.labels is not None and parsed.labels.tolist() == [2**32 - 1, 0]


def test_float32_signalling_nan_reads_as_nan_without_warning() -> None:
    """Regression: the FLOAT32 -> float64 cast of a signalling-NaN payload raised numpy's RuntimeWarning."""
    snan32 = np.array([0x7FA00000], dtype=np.uint32).view(np.float32)[0]
    snan64 = np.array([0x7FF4000000000000], dtype=np.uint64).view(np.float64)[0]
    for big_endian in (False, True):
        raw = pointcloud2_bytes(0, "world", np.zeros((2, 3)), big_endian=big_endian)
        data_end = len(raw) - 1  # the is_dense byte follows the data
        patched = bytearray(raw)
        patched[data_end - 12 : data_end - 8] = np.array([0x7FA00000], dtype=">u4" if big_endian else "<u4").tobytes()
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            parsed = parse_pointcloud2(bytes(patched))
            msg = None if big_endian else deserialize_message(bytes(patched), PointCloud2)
            msg_points = None if msg is None else points_from_pointcloud2(msg).points
            written = parse_pointcloud2(
                pointcloud2_bytes(0, "w", np.array([[snan64, 1.0, 2.0]]), big_endian=big_endian)
            )
            from_f32 = pointcloud2_bytes(0, "w", np.array([[snan32, 1.0, 2.0]], dtype=np.float32))
        assert np.isnan(parsed.points[1, 0]) and np.count_nonzero(np.isnan(parsed.points)) == 1
        if msg_points is not None:
            assert np.isnan(msg_points[1, 0]) and np.count_nonzero(np.isnan(msg_points)) == 1
        assert np.isnan(written.points[0, 0]) and written.points[0, 1:].tolist() == [1.0, 2.0]
        assert np.isnan(parse_pointcloud2(from_f32).points[0, 0])


def test_pointcloud2_bytes_rejects_values_beyond_float32() -> None:
    """A finite coordinate float32 cannot hold is an error, not an inf (and not a RuntimeWarning)."""
    with pytest.raises(ConversionError, match="float32"):
        pointcloud2_bytes(0, "world", np.array([[0.0, -1e39, 0.0]]))
    raw = pointcloud2_bytes(0, "world", np.array([[0.0, -1e39, np.inf]]), dtype=np.float64)
    assert parse_pointcloud2(raw).points.tolist() == [[0.0, -1e39, np.inf]]


@pytest.mark.parametrize(
    "call",
    [
        lambda z: frame_from_points(z, 4),
        lambda z: frame_from_points([[1 + 0j, 2, 3]], 4),
        lambda z: label_points(z, z.real, 1.0),
        lambda z: label_points(z.real, z.real, 1.0 + 0j),  # type: ignore[arg-type]
        lambda z: pose_array_bytes(0, "world", z),
        lambda z: pointcloud2_bytes(0, "world", z),
        lambda z: rotation_matrix_from_quaternion(np.array([0, 0, 0, 1 + 0j])),
        lambda z: quaternion_z_to_direction(z[0]),
    ],
)
def test_complex_input_raises_conversion_error(call: Callable[[np.ndarray], object]) -> None:
    """Regression: complex points were cast with numpy's ComplexWarning, dropping the imaginary part."""
    points = np.arange(12.0).reshape(4, 3) + 0j
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ConversionError, match=r"complex|real"):
            call(points)


# --------------------------------------------------------------------------- malformed input


def _valid_cloud_bytes() -> bytes:
    rng = np.random.default_rng(6)
    return pointcloud2_bytes(7, "world", rng.normal(size=(5, 3)), labels=np.arange(5))


def test_truncated_messages_raise_conversion_error() -> None:
    rng = np.random.default_rng(7)
    pose_array = pose_array_bytes(1, "world", rng.normal(size=(4, 3)))
    for cut in range(len(pose_array)):
        with pytest.raises(ConversionError):
            parse_pose_array(pose_array[:cut])
    cloud = _valid_cloud_bytes()
    # the final byte (is_dense) is not needed; everything before it is
    for cut in range(len(cloud) - 1):
        with pytest.raises(ConversionError):
            parse_pointcloud2(cloud[:cut], label_field="label")
    msg = PoseStamped()
    stamped = serialize_message(msg)
    for cut in range(len(stamped)):
        with pytest.raises(ConversionError):
            parse_pose_stamped(stamped[:cut])


def test_bad_encapsulation_and_counts() -> None:
    raw = bytearray(pose_array_bytes(1, "world", np.zeros((2, 3))))
    for rep in (b"\x00\x02", b"\x00\x03", b"\x00\x07", b"\x01\x00"):
        with pytest.raises(ConversionError, match="encapsulation"):
            parse_pose_array(bytes(rep) + bytes(raw[2:]))
    with pytest.raises(ConversionError, match="CDR encapsulation header"):
        parse_pose_array(b"")
    huge = bytearray(raw)
    huge[24:28] = (2**32 - 1).to_bytes(4, "little")  # poses length, after "world\0" + 2 pad bytes
    with pytest.raises(ConversionError, match="truncated"):
        parse_pose_array(bytes(huge))
    bad_utf8 = bytearray(raw)
    bad_utf8[16] = 0xFF  # first byte of "world"
    with pytest.raises(ConversionError, match="UTF-8"):
        parse_pose_array(bytes(bad_utf8))


def _cloud_with_fields(fields: list[PointField], point_step: int, n: int = 3, **kwargs: int) -> bytes:
    msg = PointCloud2()
    msg.height, msg.width = 1, n
    msg.fields = fields
    msg.point_step = point_step
    msg.row_step = kwargs.get("row_step", n * point_step)
    msg.data = bytes(kwargs.get("data_len", n * point_step))
    return serialize_message(msg)


def _f(name: str, offset: int, datatype: int = PointField.FLOAT32, count: int = 1) -> PointField:
    return PointField(name=name, offset=offset, datatype=datatype, count=count)


@pytest.mark.parametrize(
    ("fields", "point_step", "kwargs", "label_field", "match"),
    [
        ([_f("x", 0), _f("y", 4)], 12, {}, None, r"missing \['z'\]"),
        ([_f("x", 0), _f("y", 4), _f("Z", 8)], 12, {}, None, r"missing \['z'\].*Z: FLOAT32"),
        ([_f("x", 0, PointField.UINT8), _f("y", 4), _f("z", 8)], 12, {}, None, "'x': expected FLOAT32"),
        ([_f("x", 0), _f("y", 4), _f("z", 8, 9)], 12, {}, None, "'z': expected FLOAT32.*got 9"),
        ([_f("x", 0), _f("y", 4), _f("z", 8)], 12, {}, "label", r"missing \['label'\]"),
        (
            [_f("x", 0), _f("y", 4), _f("z", 8), _f("label", 12)],
            16,
            {},
            "label",
            "'label': expected an integer",
        ),
        ([_f("x", 0), _f("y", 4), _f("z", 8, count=3)], 20, {}, None, "count 1"),
        ([_f("x", 0), _f("y", 4), _f("z", 10)], 12, {}, None, "does not fit in point_step"),
        ([_f("x", 0), _f("y", 4), _f("z", 8)], 12, {"data_len": 35}, None, "data has 35 bytes"),
        ([_f("x", 0), _f("y", 4), _f("z", 8)], 12, {"row_step": 24}, None, "row_step 24 is smaller"),
    ],
)
def test_wrong_cloud_fields_raise_clear_errors(
    fields: list[PointField], point_step: int, kwargs: dict[str, int], label_field: str | None, match: str
) -> None:
    raw = _cloud_with_fields(fields, point_step, **kwargs)
    with pytest.raises(ConversionError, match=match):
        parse_pointcloud2(raw, label_field=label_field)


def test_random_corruption_never_raises_other_errors() -> None:
    rng = np.random.default_rng(8)
    sources = [
        (pose_array_bytes(3, "world", rng.normal(size=(6, 3))), parse_pose_array),
        (_valid_cloud_bytes(), lambda raw: parse_pointcloud2(raw, label_field="label")),
        (serialize_message(PoseStamped()), parse_pose_stamped),
    ]
    for raw, parse in sources:
        for _ in range(300):
            corrupt = bytearray(raw)
            for pos in rng.integers(0, len(raw), int(rng.integers(1, 4))):
                corrupt[pos] = int(rng.integers(0, 256))
            try:
                parse(bytes(corrupt))
            except ConversionError:
                pass


# --------------------------------------------------------------------------- ordering


def test_frame_from_points_labels() -> None:
    rng = np.random.default_rng(9)
    truth = rng.normal(size=(6, 3))
    perm = rng.permutation(6)
    frame = frame_from_points(truth[perm], 6, labels=perm)
    np.testing.assert_array_equal(frame, truth)
    # out-of-range labels ignored, a duplicated label makes its row missing, missing label -> NaN row
    pts = np.vstack([truth[[0, 1, 2, 3]], [[9.0, 9.0, 9.0]], [[7.0, 7.0, 7.0]], [[8.0, 8.0, 8.0]]])
    labels = np.array([0, 1, 2, 2, 6, -1, 4])
    frame = frame_from_points(pts, 6, labels=labels)
    np.testing.assert_array_equal(frame[[0, 1, 4]], np.vstack([truth[[0, 1]], [[8.0, 8.0, 8.0]]]))
    assert np.isnan(frame[[2, 3, 5]]).all()
    assert label_problems(labels, 6).out_of_range == 2
    assert label_problems(labels, 6).duplicated == 1
    with pytest.raises(ConversionError, match=r"shape \(7,\)"):
        frame_from_points(pts, 6, labels=labels[:3])


def test_frame_from_points_unlabelled_and_occlusion_conventions() -> None:
    pts = np.array([[1.0, 2.0, 3.0], [0.0, 0.0, 0.0], [np.nan, 1.0, 1.0], [0.0, 0.0, 1.0], [np.inf, 0, 0]])
    frame = frame_from_points(pts, 7)
    assert frame.shape == (7, 3)
    np.testing.assert_array_equal(frame[[0, 3]], pts[[0, 3]])
    assert np.isnan(frame[[1, 2, 4, 5, 6]]).all()
    kept = frame_from_points(pts, 5, zero_is_missing=False)
    np.testing.assert_array_equal(kept[1], [0.0, 0.0, 0.0])
    assert np.isnan(kept[2]).all()  # a partly NaN row is wholly missing
    with pytest.raises(ConversionError, match="at most 4 unlabelled points"):
        frame_from_points(pts, 4)
    assert frame_from_points(np.empty((0, 3)), 3).shape == (3, 3)


def test_label_points_recovers_permutation_and_gates() -> None:
    rng = np.random.default_rng(10)
    for _ in range(30):
        p = int(rng.integers(1, 41))
        truth = rng.uniform(-1.0, 1.0, (p, 3))  # markers ~10 cm or more apart on average
        predicted = truth + rng.normal(0.0, 0.002, (p, 3))
        measured = truth + rng.normal(0.0, 0.0005, (p, 3))
        perm = rng.permutation(p)
        labelled = label_points(measured[perm], predicted, gate=0.02)
        close = np.linalg.norm(truth[:, None] - truth[None], axis=2) + np.eye(p) < 0.03
        ok = ~close.any(axis=1)  # markers with no neighbour within 3 cm are unambiguous
        np.testing.assert_array_equal(labelled[ok], measured[ok])
    truth = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]) + 5.0
    predicted = truth.copy()
    predicted[2] = np.nan  # no prediction -> NaN
    points = np.vstack([truth[[3, 0]] + 0.01, truth[[1]] + 0.5, [[50.0, 50.0, 50.0]], truth[[2]]])
    labelled = label_points(points, predicted, gate=0.1)
    np.testing.assert_array_equal(labelled[[0, 3]], truth[[0, 3]] + 0.01)
    assert np.isnan(labelled[[1, 2]]).all()  # marker 1 beyond the gate, marker 2 unpredicted
    # fewer points than markers, NaN and zero points ignored
    labelled = label_points(np.array([[np.nan] * 3, [0.0, 0.0, 0.0], truth[1]]), truth, gate=0.1)
    np.testing.assert_array_equal(labelled[1], truth[1])
    assert np.isnan(labelled[[0, 2, 3]]).all()
    assert np.isnan(label_points(np.empty((0, 3)), truth, gate=0.1)).all()
    with pytest.raises(ConversionError, match="gate"):
        label_points(truth, truth, gate=0.0)


def test_label_points_prefers_more_matches_over_shorter_distances() -> None:
    predicted = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]) + 3.0
    # point A is right on marker 0's prediction but also within marker 1's gate;
    # point B is within the gate of marker 0 only: the best in-gate assignment is B->0, A->1
    points = np.array([[0.55, 0.0, 0.0], [-0.3, 0.0, 0.0]]) + 3.0
    labelled = label_points(points, predicted, gate=0.5)
    np.testing.assert_array_equal(labelled, points[[1, 0]])


# --------------------------------------------------------------------------- builders


def _rot_block(msg: PoseWithCovarianceStamped) -> NDArray[np.float64]:
    return np.asarray(msg.pose.covariance).reshape(6, 6)


def test_stamp_round_trip() -> None:
    for ns in (0, 1, 999_999_999, 1_000_000_000, 1_700_000_000_123_456_789, -1, -1_500_000_000):
        stamp = stamp_from_ns(ns)
        assert 0 <= stamp.nanosec < 1_000_000_000
        assert ns_from_stamp(stamp) == ns
    with pytest.raises(ConversionError):
        stamp_from_ns(2**31 * 1_000_000_000)


def test_rotation_matrix_from_quaternion() -> None:
    rng = np.random.default_rng(11)
    for _ in range(20):
        q = rng.normal(size=4)
        np.testing.assert_allclose(
            rotation_matrix_from_quaternion(q), Rotation.from_quat(q).as_matrix(), atol=1e-12
        )
    for bad in ([0, 0, 0, 0], [np.nan, 0, 0, 1]):
        with pytest.raises(ConversionError, match="non-zero"):
            rotation_matrix_from_quaternion(bad)
    with pytest.raises(ConversionError, match=r"shape \(4,\)"):
        rotation_matrix_from_quaternion([0, 0, 1])



def test_quaternion_from_rotation_matrix_matches_scipy() -> None:
    # random rotations, and every branch of Shepperd's pivot: identity and the three half turns
    mats = list(Rotation.random(2000, random_state=3).as_matrix())
    mats += [np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]
    mats += list(Rotation.from_rotvec(np.pi * (1 - 1e-9) * np.eye(3)).as_matrix())  # near half turns
    for R in mats:
        q = quaternion_from_rotation_matrix(R)
        ref = Rotation.from_matrix(R).as_quat()
        ref = -ref if ref[3] < 0 else ref
        assert q[3] >= 0.0 and abs(np.linalg.norm(q) - 1.0) < 1e-15
        if q[3] > 1e-12:  # else q and -q are the same rotation, both with w = 0
            np.testing.assert_allclose(q, ref, atol=1e-12)
        np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), R, atol=1e-12)
    with pytest.raises(ConversionError, match="finite"):
        quaternion_from_rotation_matrix(np.full((3, 3), np.nan))
    with pytest.raises(ConversionError, match=r"shape \(3, 3\)"):
        quaternion_from_rotation_matrix(np.eye(2))

def test_pose_with_covariance_layout() -> None:
    cov = np.array([[1.0, 0.1, 0.2], [0.1, 2.0, 0.3], [0.2, 0.3, 3.0]])
    msg = pose_with_covariance(5_000_000_001, "world", [1.0, 2.0, 3.0], cov)
    c6 = _rot_block(msg)
    np.testing.assert_array_equal(c6[:3, :3], cov)
    np.testing.assert_array_equal(c6[3:, 3:], UNKNOWN_ROTATION_VARIANCE * np.eye(3))
    np.testing.assert_array_equal(c6[:3, 3:], 0.0)
    o = msg.pose.pose.orientation
    assert (o.x, o.y, o.z, o.w) == (0.0, 0.0, 0.0, 1.0)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (5, 1, "world")
    msg = pose_with_covariance(
        0, "w", np.zeros(3), cov, orientation_xyzw=[0, 0, 2, 0], orientation_cov=2 * cov
    )
    o = msg.pose.pose.orientation
    assert (o.x, o.y, o.z, o.w) == (0.0, 0.0, 1.0, 0.0)
    np.testing.assert_array_equal(_rot_block(msg)[3:, 3:], 2 * cov)
    with pytest.raises(ConversionError, match=r"cov: expected shape \(3, 3\)"):
        pose_with_covariance(0, "w", np.zeros(3), np.eye(2))


def test_axis_pose_z_axis_is_direction_and_covariance() -> None:
    rng = np.random.default_rng(12)
    directions = [np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0]), np.array([1e-9, 0.0, -1.0])]
    directions += [rng.normal(size=3) for _ in range(20)]
    for d in directions:
        d = d / np.linalg.norm(d)
        var_x, var_y = rng.uniform(1e-6, 1e-3, 2)
        R_ref = rotation_matrix_from_quaternion(quaternion_z_to_direction(d))
        # rotating by θx about local x moves d along -e_y', by θy about local y along +e_x'
        cov_d = var_x * np.outer(R_ref[:, 1], R_ref[:, 1]) + var_y * np.outer(R_ref[:, 0], R_ref[:, 0])
        cov_p = np.diag(rng.uniform(0.1, 1.0, 3))
        point = rng.normal(size=3)
        msg = axis_pose(1, "world", point, 3.0 * d, cov_p, cov_d)
        o = msg.pose.pose.orientation
        R = rotation_matrix_from_quaternion([o.x, o.y, o.z, o.w])
        np.testing.assert_allclose(R[:, 2], d, atol=1e-12)
        assert np.isclose(np.linalg.det(R), 1.0)
        # minimal rotation: its angle is the angle between z and d
        np.testing.assert_allclose(
            2.0 * np.arccos(np.clip(o.w, -1, 1)), np.arccos(np.clip(d[2], -1, 1)), atol=1e-7
        )
        c6 = _rot_block(msg)
        np.testing.assert_allclose(c6[3:, 3:], np.diag([var_x, var_y, UNKNOWN_ROTATION_VARIANCE]), atol=1e-15)
        np.testing.assert_array_equal(c6[:3, :3], cov_p)
        p = msg.pose.pose.position
        np.testing.assert_array_equal([p.x, p.y, p.z], point)
        fixed = _rot_block(axis_pose(1, "world", point, d, cov_p, cov_d, rotation_frame="fixed"))[3:, 3:]
        np.testing.assert_allclose(fixed, R @ c6[3:, 3:] @ R.T, rtol=1e-12, atol=1e-9)
    q = quaternion_z_to_direction([0.0, 0.0, -1.0])
    np.testing.assert_array_equal(q, [1.0, 0.0, 0.0, 0.0])
    with pytest.raises(ConversionError, match="non-zero"):
        axis_pose(0, "w", np.zeros(3), np.zeros(3), np.eye(3), np.eye(3))


def test_covariance_ellipsoid_marker_reproduces_covariance() -> None:
    rng = np.random.default_rng(13)
    for k_sigma in (1.0, 2.0, 3.0):
        for rank in (3, 3, 2):
            A = rng.normal(size=(3, rank))
            cov = A @ A.T
            m = covariance_ellipsoid_marker(1, "world", [1.0, 2.0, 3.0], cov, k_sigma=k_sigma)
            o = m.pose.orientation
            R = rotation_matrix_from_quaternion([o.x, o.y, o.z, o.w])
            half = np.array([m.scale.x, m.scale.y, m.scale.z]) / 2.0
            np.testing.assert_allclose(R @ np.diag(half**2) @ R.T, k_sigma**2 * cov, atol=1e-12)
            assert (m.pose.position.x, m.pose.position.y, m.pose.position.z) == (1.0, 2.0, 3.0)
            assert m.type == m.SPHERE
    m = covariance_ellipsoid_marker(1, "w", np.zeros(3), np.zeros((3, 3)), min_diameter=0.01)
    assert (m.scale.x, m.scale.y, m.scale.z) == (0.01, 0.01, 0.01)


def test_arrow_sphere_and_diagnostics() -> None:
    arrow = axis_arrow_marker(
        1, "w", [1.0, 0.0, 0.0], [0.0, 0.0, 2.0], length=0.4, shaft_diameter=0.01, marker_id=3
    )
    assert arrow.type == arrow.ARROW and arrow.id == 3
    assert [(p.x, p.y, p.z) for p in arrow.points] == [(1.0, 0.0, -0.2), (1.0, 0.0, 0.2)]
    assert (arrow.scale.x, arrow.scale.y) == (0.01, 0.02)
    sphere = sphere_marker(1, "w", [0.0, 1.0, 2.0], 0.05, rgba=(0.0, 1.0, 0.0, 1.0))
    assert sphere.scale.x == sphere.scale.y == sphere.scale.z == 0.05 and sphere.color.g == 1.0
    status = diagnostic_status(
        "jointfit: hip", 1, "few frames", {"frames": 12, "rms": np.float64(0.00123456789)}
    )
    assert status.level == b"\x01" and status.name == "jointfit: hip" and status.message == "few frames"
    assert [(kv.key, kv.value) for kv in status.values] == [("frames", "12"), ("rms", "0.00123457")]
    assert diagnostic_status("x", b"\x02", "", {}).level == b"\x02"
    with pytest.raises(ConversionError, match="level"):
        diagnostic_status("x", 4, "", {})


def test_output_bytes_match_rclpy_serialization_of_the_message_objects() -> None:
    """The node publishes its per-frame outputs as bytes: they must equal the message objects' content."""
    from rclpy.serialization import deserialize_message

    from jointfit_ros.conversions import (
        axis_pose,
        axis_pose_bytes,
        pose_with_covariance,
        pose_with_covariance_bytes,
    )

    rng = np.random.default_rng(3)
    for frame_id in ("", "w", "world", "mocap_origin", "wörld"):
        a = rng.normal(size=(3, 3))
        cov = a @ a.T
        stamp = int(rng.integers(-(10**12), 10**18))
        pos = rng.normal(size=3)
        direction = rng.normal(size=3)
        pairs = [
            (pose_with_covariance(stamp, frame_id, pos, cov), pose_with_covariance_bytes(stamp, frame_id, pos, cov)),
            (
                axis_pose(stamp, frame_id, pos, direction, cov, cov * 1e-3),
                axis_pose_bytes(stamp, frame_id, pos, direction, cov, cov * 1e-3),
            ),
        ]
        for msg, raw in pairs:
            back = deserialize_message(raw, PoseWithCovarianceStamped)
            assert back.header.frame_id == msg.header.frame_id
            assert (back.header.stamp.sec, back.header.stamp.nanosec) == (msg.header.stamp.sec, msg.header.stamp.nanosec)
            assert back.pose.pose == msg.pose.pose
            np.testing.assert_array_equal(np.array(back.pose.covariance), np.array(msg.pose.covariance))
