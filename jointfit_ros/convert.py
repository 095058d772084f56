"""``jointfit convert FILE --to BAG``: a C3D or TRC recording as a rosbag2 bag for the node, replay and fit.

Usage::

    jointfit convert FILE --to BAG [--type {posearray,pointcloud2}] [--topic /markers]
                     [--frame-id world] [--storage {mcap,sqlite3}] [--start S] [--units {m,cm,mm}]
                     [--force]

ROS-free (the bag is written with ``rosbags``, the messages serialized by
:mod:`jointfit_ros.raw`, the bytes the node parses). What the bag holds:

* one message per frame of the file on ``--topic`` (default ``/markers``),
  ``header.frame_id`` ``--frame-id`` (default ``world``), positions in metres
  (converted from the file's units, REP 103);
* ``--type posearray`` (default): a ``geometry_msgs/PoseArray`` of every
  marker in file order (identity orientations), a missing marker as NaN
  (the node's convention for an occluded marker in a PoseArray);
  ``pointcloud2``: a labelled ``sensor_msgs/PointCloud2`` (float64 x, y, z and
  a uint32 ``label`` = the marker's index in ``marker_names``), missing
  markers left out, as the node's ``label_field: label`` reads it;
* ``header.stamp`` (and the bag's log time) of frame k:
  ``(first_frame + k) / rate`` s, the time line ``jointfit fit`` gives the
  file (0 for a file starting at its frame 1), or ``--start + k / rate``;
* ``BAG/jointfit_markers.yaml``: the node's marker parameters for the bag
  (``marker_topic``, ``marker_type``, ``marker_names``, ``label_field``,
  ``units``), also printed; add the joints to it.

Markers whose label is empty or repeated in the file cannot be named in
``marker_names`` and are left out (said on stderr). The bag is written into a
hidden temporary directory beside ``BAG`` and renamed into place when
complete; an existing ``BAG`` is refused unless ``--force`` (then replaced,
only once the new bag is complete).

Exit status: 0 written; 1 bad input (a missing or unreadable file, units that
cannot be converted, an existing output without ``--force``; one line on
stderr, nothing written); 2 bad arguments; 130 interrupted.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
import tempfile
from collections import Counter
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
from numpy.typing import NDArray

from jointfit_core.errors import InputError, JointfitError, MissingDependencyError
from jointfit_core.io import MarkerData

from .markers_cli import marker_names_line
from .offline import checked_frame_stamps, read_marker_file
from .raw import pointcloud2_bytes, pose_array_bytes

__all__ = ["convert_main", "frame_stamps_ns", "marker_messages", "params_snippet", "PARAMS_FILE"]

PROG = "jointfit convert"
#: The node's marker parameters for the bag, written into the bag directory.
PARAMS_FILE = "jointfit_markers.yaml"
#: ``--type`` -> (the node's marker_type, the rosbag2 message type).
TYPES = {
    "posearray": ("pose_array", "geometry_msgs/msg/PoseArray"),
    "pointcloud2": ("pointcloud2", "sensor_msgs/msg/PointCloud2"),
}
LABEL_FIELD = "label"
#: Largest stamp a header can carry (int32 seconds), ns.
_MAX_STAMP_NS = (2**31 - 1) * 1_000_000_000


class _UsageError(Exception):
    """Bad command-line arguments (one line)."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        raise _UsageError(message)


def _parser() -> argparse.ArgumentParser:
    p = _Parser(prog=PROG, description="Write a C3D or TRC recording as a rosbag2 bag of marker messages (metres).")
    p.add_argument("input", help="a .c3d or .trc file")
    p.add_argument("--to", required=True, metavar="BAG", help="the bag directory to create")
    p.add_argument("--type", choices=tuple(TYPES), default="posearray",
                   help="posearray (default; every marker in order, missing as NaN) or pointcloud2 "
                   "(labelled, missing markers left out)")
    p.add_argument("--topic", default="/markers", help="marker topic (default /markers)")
    p.add_argument("--frame-id", default="world", help="header.frame_id (default world)")
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap", help="rosbag2 storage (default mcap)")
    p.add_argument("--start", type=float, metavar="S",
                   help="stamp of the first frame, s (default: (first frame - 1) / rate, the file's own time line)")
    p.add_argument("--units", choices=("m", "cm", "mm"),
                   help="the file's length unit, when it declares none (or a wrong one)")
    p.add_argument("--force", action="store_true", help="replace an existing BAG")
    return p


def frame_stamps_ns(data: MarkerData, start: float | None = None) -> NDArray[np.int64]:
    """``header.stamp`` of every frame, ns, shape (N,).

    Parameters
    ----------
    data : MarkerData
    start : float, optional
        Stamp of the first frame, s (>= 0). Default: the file's time line,
        ``(first_frame + k) / rate`` (as ``jointfit fit`` stamps the file's frames).

    Raises
    ------
    InputError
        A stamp beyond what a header carries (int32 seconds), or frames on one nanosecond
        (:func:`~jointfit_ros.offline.checked_frame_stamps`).
    """
    k = np.arange(data.n_frames, dtype=np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        if start is None:
            stamps = np.rint((data.first_frame + k) / data.rate * 1e9)
        else:
            stamps = round(start * 1e9) + np.rint(k / data.rate * 1e9)
    if stamps.size and not stamps[-1] < _MAX_STAMP_NS:
        raise InputError(f"the last frame's stamp ({stamps[-1] * 1e-9:.6g} s) exceeds what a header carries (2^31 s)")
    return checked_frame_stamps(stamps, data.rate, "the recording")


def marker_messages(
    markers_m: NDArray[np.float64], stamps_ns: NDArray[np.int64], frame_id: str, kind: str
) -> Iterator[bytes]:
    """CDR bytes of one marker message per frame.

    Parameters
    ----------
    markers_m : ndarray, shape (N, P, 3)
        Marker positions, metres, NaN = missing.
    stamps_ns : ndarray of int, shape (N,)
        ``header.stamp`` of each frame, ns.
    frame_id : str
    kind : {"posearray", "pointcloud2"}
        See the module docstring.
    """
    labels = np.arange(markers_m.shape[1], dtype=np.int64)
    for frame, stamp in zip(markers_m, stamps_ns.tolist(), strict=True):
        if kind == "posearray":
            yield pose_array_bytes(stamp, frame_id, frame)
        else:
            seen = ~np.isnan(frame).any(axis=1)
            yield pointcloud2_bytes(stamp, frame_id, frame[seen], labels=labels[seen], dtype=np.float64)


def params_snippet(names: Sequence[str], topic: str, kind: str, source: str) -> str:
    """The node's marker parameters for a converted bag (a ROS 2 parameter file without joints)."""
    import yaml

    params: dict[str, Any] = {"marker_topic": topic, "marker_type": TYPES[kind][0], "marker_names": list(names)}
    if kind == "pointcloud2":
        params["label_field"] = LABEL_FIELD
    params["units"] = "m"
    body = yaml.safe_dump({"jointfit": {"ros__parameters": params}}, default_flow_style=None, sort_keys=False,
                          width=1 << 20, allow_unicode=True)
    return (f"# jointfit convert {source}: the marker parameters of this bag, for the node and jointfit fit.\n"
            "# Add the joints (joints: [...], <joint>: {type, parent_markers, child_markers}) under ros__parameters.\n"
            + body)


def _named(data: MarkerData) -> tuple[MarkerData, list[str]]:
    """The markers whose labels can be named (non-empty, once in the file), and the labels left out."""
    counts = Counter(data.labels)
    keep = [k for k, label in enumerate(data.labels) if label and counts[label] == 1]
    dropped = [label for label in data.labels if not (label and counts[label] == 1)]
    if len(keep) == len(data.labels):
        return data, []
    return MarkerData(data.markers[:, keep], tuple(data.labels[k] for k in keep), data.rate, data.units,
                      data.first_frame), dropped


def _in_metres(data: MarkerData, units: str | None, source: str) -> MarkerData:
    if units is not None:
        data = MarkerData(data.markers, data.labels, data.rate, units, data.first_frame)
    if data.units not in ("m", "cm", "mm"):
        raise InputError(f"{source}: its length unit {data.units!r} is none of m, cm, mm; give it with --units")
    return data.to_units("m")


def _write_bag(tmp: Path, data_m: MarkerData, stamps_ns: NDArray[np.int64], opts: argparse.Namespace) -> None:
    try:
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise MissingDependencyError("writing rosbag2 files needs rosbags: pip install 'jointfit[bag]'") from None
    plugin = StoragePlugin.MCAP if opts.storage == "mcap" else StoragePlugin.SQLITE3
    msgtype = TYPES[opts.type][1]
    topic = opts.topic if opts.topic.startswith("/") else "/" + opts.topic
    with Writer(tmp, version=9, storage_plugin=plugin) as writer:
        conn = writer.add_connection(topic, msgtype, typestore=get_typestore(Stores.ROS2_JAZZY))
        for stamp, raw in zip(stamps_ns.tolist(), marker_messages(data_m.markers, stamps_ns, opts.frame_id,
                                                                   opts.type), strict=True):
            writer.write(conn, stamp, raw)


def _install(tmp_root: Path, built: Path, target: Path) -> None:
    """Rename the complete bag into place; an existing target (``--force``) goes only once it is."""
    old = tmp_root / "previous"
    replaced = target.exists() or target.is_symlink()
    if replaced:
        os.rename(target, old)
    try:
        os.rename(built, target)
    except BaseException:
        if replaced:
            os.rename(old, target)
        raise


def _check_args(opts: argparse.Namespace) -> None:
    if opts.start is not None and not (math.isfinite(opts.start) and opts.start >= 0.0):
        raise _UsageError(f"--start: expected a stamp >= 0 s, got {opts.start!r}")
    if Path(opts.to).suffix.lower() in (".db3", ".mcap", ".c3d", ".trc", ".yaml"):
        raise _UsageError(f"--to: expected the name of a bag directory to create, got {opts.to!r}")
    name = opts.topic.lstrip("/")
    if not name or any(not (c.isalnum() or c in "_/~") for c in name) or "//" in name:
        raise _UsageError(f"--topic: expected a ROS topic name such as /markers, got {opts.topic!r}")


def convert_main(argv: Sequence[str]) -> int:
    """Run ``jointfit convert`` (see the module docstring); returns the exit status."""
    try:
        opts = _parser().parse_args(list(argv))
        _check_args(opts)
    except _UsageError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    except SystemExit as exc:  # --help
        return exc.code if isinstance(exc.code, int) else 0
    target = Path(opts.to)
    source = Path(opts.input)
    tmp_root: Path | None = None
    try:
        if source.suffix.lower() not in (".c3d", ".trc"):
            raise InputError(f"{source}: expected a .c3d or .trc file")
        data = read_marker_file(source)
        assert data is not None
        data, dropped = _named(data)
        data_m = _in_metres(data, opts.units, str(source))
        stamps = frame_stamps_ns(data_m, opts.start)
        if (target.exists() or target.is_symlink()) and not opts.force:
            raise InputError(f"{target}: exists; give --force to replace it")
        if not data_m.labels:
            raise InputError(f"{source}: no marker with a label of its own")
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp_root = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent))
        built = tmp_root / target.name
        _write_bag(built, data_m, stamps, opts)
        snippet = params_snippet(data_m.labels, opts.topic, opts.type, source.name)
        (built / PARAMS_FILE).write_text(snippet, encoding="utf-8")
        _install(tmp_root, built, target)
    except (JointfitError, OSError, ValueError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    finally:
        if tmp_root is not None:
            shutil.rmtree(tmp_root, ignore_errors=True)
    if dropped:
        print(f"{PROG}: left out {len(dropped)} marker(s) with an empty or repeated label: {dropped}", file=sys.stderr)
    span = (stamps[-1] - stamps[0]) * 1e-9 if stamps.size else 0.0
    print(f"wrote {target} ({opts.storage}): {data_m.n_frames} {TYPES[opts.type][1]} messages on {opts.topic}, "
          f"{len(data_m.labels)} markers in m (from {data.units if opts.units is None else opts.units}), "
          f"{data_m.rate:g} Hz, stamps {stamps[0] * 1e-9 if stamps.size else 0.0:.6g} s + {span:.6g} s")
    print(f"node parameters: {target / PARAMS_FILE}")
    print(marker_names_line(data_m.labels))
    return 0
