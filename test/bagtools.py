"""Test fixtures: rosbag2 bags of marker (and pose) streams written with ``rosbags``' Writer.

The marker messages are serialized with :mod:`jointfit_ros.raw` (the bytes
the node parses); the ``PoseStamped`` messages with the rosbags typestore, an
independent serializer, so a round trip also checks
:func:`jointfit_ros.raw.parse_pose_stamped` against it.

The bags look like ``ros2 bag record`` output: rosbag2 format version 9,
absolute topic names, message definitions and RIHS01 hashes from the Jazzy
typestore, log time = ``header.stamp``.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from jointfit_ros.raw import pointcloud2_bytes, pose_array_bytes, quaternion_from_rotation_matrix

__all__ = ["MSGTYPES", "RawMessage", "write_raw_bag", "pose_stamped_bytes", "write_marker_bag"]

#: ``msgtype`` argument of :func:`write_marker_bag` -> rosbag2 message type.
MSGTYPES = {"pose_array": "geometry_msgs/msg/PoseArray", "pointcloud2": "sensor_msgs/msg/PointCloud2"}
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"

#: (topic, msgtype, log_time_ns, CDR bytes with encapsulation header)
RawMessage = tuple[str, str, int, bytes]


@functools.cache
def _typestore() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def write_raw_bag(
    path: str | os.PathLike[str],
    messages: Iterable[RawMessage],
    *,
    storage: str = "sqlite3",
    compression: str | None = None,
    empty_topics: Mapping[str, str] | None = None,
) -> Path:
    """Write already serialized messages into a new rosbag2 bag directory.

    Parameters
    ----------
    path : str or os.PathLike
        Bag directory to create (must not exist).
    messages : iterable of (topic, msgtype, log_time_ns, raw)
        Written in this order; connections are added at a topic's first message.
    storage : {"sqlite3", "mcap"}
        Storage plugin.
    compression : {None, "storage", "message", "file"}
        zstd compression as ``ros2 bag record`` can write it: ``"storage"`` is
        MCAP chunk compression (the Jazzy recorder's MCAP default), ``"message"``
        and ``"file"`` are ``--compression-mode message|file``.
    empty_topics : mapping of str to str, optional
        Topics (name -> msgtype) registered without any message.

    Returns
    -------
    Path
        The bag directory.
    """
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

    plugins = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}
    modes = {
        None: CompressionMode.NONE,
        "storage": CompressionMode.STORAGE,
        "message": CompressionMode.MESSAGE,
    }
    modes["file"] = CompressionMode.FILE
    if storage not in plugins or compression not in modes:
        raise ValueError(
            f"storage: expected one of {list(plugins)}, got {storage!r}; compression: {compression!r}"
        )
    typestore = _typestore()
    out = Path(path)
    writer = Writer(out, version=9, storage_plugin=plugins[storage])
    writer.set_compression(modes[compression], CompressionFormat.ZSTD)
    with writer:
        conns: dict[str, Any] = {}
        for name, msgtype in (empty_topics or {}).items():
            conns[name] = writer.add_connection(name, msgtype, typestore=typestore)
        for topic, msgtype, log_time_ns, raw in messages:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=typestore)
            writer.write(conns[topic], int(log_time_ns), raw)
    return out


def pose_stamped_bytes(stamp_ns: int, frame_id: str, R: ArrayLike, d: ArrayLike) -> bytes:
    """CDR bytes of a ``geometry_msgs/PoseStamped`` (rosbags serializer, little-endian).

    Parameters
    ----------
    stamp_ns : int
        ``header.stamp`` (ns).
    frame_id : str
        ``header.frame_id``.
    R : array_like, shape (3, 3)
        Orientation; a matrix with NaN gives the quaternion (NaN, NaN, NaN, NaN).
    d : array_like, shape (3,)
        Position (any unit, NaN allowed).
    """
    ts = _typestore()
    Header, Time = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    Pose, Point = ts.types["geometry_msgs/msg/Pose"], ts.types["geometry_msgs/msg/Point"]
    Quaternion, PoseStamped = ts.types["geometry_msgs/msg/Quaternion"], ts.types[POSE_STAMPED]
    rot = np.asarray(R, dtype=np.float64)
    q = quaternion_from_rotation_matrix(rot) if np.isfinite(rot).all() else np.full(4, np.nan)
    x, y, z = (float(v) for v in np.asarray(d, dtype=np.float64))
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    msg = PoseStamped(
        header=Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame_id),
        pose=Pose(
            position=Point(x=x, y=y, z=z),
            orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
        ),
    )
    return bytes(ts.serialize_cdr(msg, POSE_STAMPED, little_endian=True))


def _absolute(topic: str) -> str:
    return topic if topic.startswith("/") else "/" + topic


def write_marker_bag(
    path: str | os.PathLike[str],
    frames: ArrayLike,
    stamps_ns: ArrayLike,
    *,
    storage: str = "sqlite3",
    topic: str = "markers",
    msgtype: str = "pose_array",
    pose_topics: Mapping[str, tuple[ArrayLike, ArrayLike]] | None = None,
    frame_id: str = "world",
    compression: str | None = None,
) -> Path:
    """Write a marker stream (and optional pose streams) as a rosbag2 bag.

    Parameters
    ----------
    path : str or os.PathLike
        Bag directory to create (must not exist).
    frames : array_like, shape (N, P, 3)
        Marker positions (any unit, metres for ROS); NaN = missing, kept as
        NaN in the messages.
    stamps_ns : array_like of int, shape (N,)
        ``header.stamp`` of frame k, and its log time in the bag (ns).
    storage : {"sqlite3", "mcap"}
        Storage plugin.
    topic : str
        Marker topic; stored absolute (``markers`` -> ``/markers``), as the recorder does.
    msgtype : {"pose_array", "pointcloud2"}
        ``PoseArray`` (identity orientations) or a labelled ``PointCloud2``
        (float64 x, y, z, then a UINT32 ``label`` = row index, all P points
        per message), so the positions round-trip exactly.
    pose_topics : mapping of str to (R, d), optional
        ``PoseStamped`` topics: ``R`` shape (N, 3, 3), ``d`` shape (N, 3),
        one message per frame with the frame's stamp, written after its
        marker message.
    frame_id : str
        ``header.frame_id`` of every message.
    compression : {None, "storage", "message", "file"}
        See :func:`write_raw_bag`.

    Returns
    -------
    Path
        The bag directory.
    """
    markers: NDArray[np.float64] = np.asarray(frames, dtype=np.float64)
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    if markers.ndim != 3 or markers.shape[2] != 3 or stamps.shape != (markers.shape[0],):
        raise ValueError(
            f"frames: expected shape (N, P, 3) with stamps_ns (N,), got {markers.shape}, {stamps.shape}"
        )
    if msgtype not in MSGTYPES:
        raise ValueError(f"msgtype: expected one of {list(MSGTYPES)}, got {msgtype!r}")
    poses = {
        _absolute(name): (np.asarray(R, dtype=np.float64), np.asarray(d, dtype=np.float64))
        for name, (R, d) in (pose_topics or {}).items()
    }
    for name, (R, d) in poses.items():
        if R.shape != (len(stamps), 3, 3) or d.shape != (len(stamps), 3):
            raise ValueError(
                f"pose_topics[{name!r}]: expected R (N, 3, 3), d (N, 3), got {R.shape}, {d.shape}"
            )
    labels = np.arange(markers.shape[1])
    marker_topic = _absolute(topic)

    def messages() -> Iterable[RawMessage]:
        for k, stamp in enumerate(stamps.tolist()):
            if msgtype == "pose_array":
                raw = pose_array_bytes(stamp, frame_id, markers[k])
            else:
                raw = pointcloud2_bytes(stamp, frame_id, markers[k], labels=labels, dtype=np.float64)
            yield marker_topic, MSGTYPES[msgtype], stamp, raw
            for name, (R, d) in poses.items():
                yield name, POSE_STAMPED, stamp, pose_stamped_bytes(stamp, frame_id, R[k], d[k])

    return write_raw_bag(path, messages(), storage=storage, compression=compression)
