"""Marker messages (PoseArray or PointCloud2; labelled, ordered or unlabelled) into frames in ``marker_names`` order.

ROS-free. :func:`parse_markers` parses a block of labelled or ordered
messages with array operations (a function of the bytes and the
configuration); :class:`MarkerParser` parses one message at a time, keeps
the unlabelled clouds' prediction (:attr:`MarkerParser.last_frame`) and
counts what it drops in the :class:`~jointfit_ros.inputs.MessageRouter`'s
counters. Both give the same frames and drops for the same messages.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .params import NodeConfig
from .raw import (
    ConversionError,
    frame_from_points,
    label_points,
    label_problems,
    parse_pointcloud2,
    parse_pointcloud2s,
    parse_pose_array,
    parse_pose_arrays,
)

__all__ = ["MarkerParser", "ParsedMarkers", "parse_markers"]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Why :meth:`MarkerParser.frame` drops a message with infinite coordinates.
_INF_TEXT = "infinite coordinates (NaN marks an occluded marker; inf is corrupt data)"


@dataclass(frozen=True)
class ParsedMarkers:
    """A block of ``marker_topic`` messages parsed: what :meth:`MessageRouter.route_parsed` takes.

    Attributes
    ----------
    n : int
        Marker messages in the block (kept or not).
    index : ndarray, shape (K,), int64
        Positions, among the block's marker messages, of those kept, increasing.
    stamps_ns : ndarray, shape (K,), int64
    frame_ids : list of str, length K
    frames : ndarray, shape (K, P, 3)
        In ``marker_names`` order, NaN where missing.
    problems : list of (int, str, str, str)
        ``(position, key, text, counter)`` of each message dropped, in position order.
    label_problems : int
        Kept labelled clouds with out-of-range or duplicated labels.
    zero_markers : int
        Markers at exactly (0, 0, 0) in the kept frames taken as positions (``zero_is_missing`` false).
    """

    n: int
    index: IntArray
    stamps_ns: IntArray
    frame_ids: list[str]
    frames: FloatArray
    problems: list[tuple[int, str, str, str]]
    label_problems: int = 0
    zero_markers: int = 0


def parse_markers(cfg: NodeConfig, raws: Sequence[bytes]) -> ParsedMarkers:
    """Parse a block of labelled or ordered marker messages (a function of the bytes and ``cfg`` only).

    Parameters
    ----------
    cfg : NodeConfig
        ``marker_type``, ``marker_names``, ``label_field``, ``zero_is_missing``,
        ``input_frame_id`` and ``marker_topic`` (for the texts) are used.
    raws : sequence of bytes
        Messages of ``marker_topic``, oldest first.

    Returns
    -------
    ParsedMarkers

    Raises
    ------
    ValueError
        ``cfg.unlabelled``: unlabelled clouds are labelled against the previous
        frame, so they are parsed by :meth:`MarkerParser.frame`, in order.

    Notes
    -----
    Messages are parsed in groups of one layout
    (:func:`~jointfit_ros.raw.parse_pose_arrays`,
    :func:`~jointfit_ros.raw.parse_pointcloud2s`), ordered by labels or by
    position with array operations, and checked (infinite coordinates, point
    count, labels, frame id) per message: the same frames and drops as
    :meth:`MarkerParser.frame` of each message.
    """
    if cfg.unlabelled:
        raise ValueError("unlabelled clouds are parsed one by one (MarkerParser.frame)")
    n = len(cfg.marker_names)
    problems: list[tuple[int, str, str, str]] = []
    flagged_total = 0
    topic = cfg.marker_topic
    if cfg.marker_type == "pose_array":
        batch = parse_pose_arrays(raws)
    else:
        batch = parse_pointcloud2s(raws, label_field=cfg.label_field or None)
    malformed = f"dropped a malformed message on {topic}: "
    for i, exc in batch.errors.items():
        problems.append((i, "malformed", malformed + str(exc), "malformed"))
    parts: list[tuple[IntArray, IntArray, str, FloatArray]] = []
    for g in batch.groups:
        inf = np.isinf(g.points.reshape(g.points.shape[0], -1)).any(axis=1)
        problems.extend((int(i), "malformed", malformed + _INF_TEXT, "malformed") for i in g.index[inf])
        ok = ~inf
        index, points = g.index[ok], g.points[ok]
        if g.labels is None and points.shape[1] != n:
            text = malformed + _count_text(points.shape[1], n)
            problems.extend((int(i), "malformed", text, "malformed") for i in index)
            continue
        if g.labels is not None:
            frames, flagged = _frames_from_labels(points, g.labels[ok], n)
            flagged_total += int(np.count_nonzero(flagged))
        else:
            frames = points.copy()
        frames = _mark_missing_many(frames, cfg.zero_is_missing)
        wanted = cfg.input_frame_id
        if wanted and g.frame_id != wanted:
            text = f"dropped a message on {topic} in frame {g.frame_id!r}; input_frame_id is {wanted!r}"
            problems.extend((int(i), f"frame_id:{topic}", text, "wrong_frame_id") for i in index)
            continue
        parts.append((index, g.stamps_ns[ok], g.frame_id, frames))
    problems.sort(key=lambda p: p[0])
    zeros = 0 if cfg.zero_is_missing else sum(int(np.count_nonzero((p[3] == 0.0).all(axis=2))) for p in parts)
    if not parts:
        empty = np.zeros(0, dtype=np.int64)
        return ParsedMarkers(len(raws), empty, empty.copy(), [], np.zeros((0, n, 3)), problems, flagged_total)
    if len(parts) == 1:
        index, stamps, frame_id, frames = parts[0]
        return ParsedMarkers(len(raws), index, stamps, [frame_id] * index.size, frames, problems, flagged_total, zeros)
    index = np.concatenate([p[0] for p in parts])
    order = np.argsort(index, kind="stable")
    ids = [p[2] for p in parts for _ in range(p[0].size)]
    return ParsedMarkers(
        len(raws),
        index[order],
        np.concatenate([p[1] for p in parts])[order],
        [ids[k] for k in order],
        np.concatenate([p[3] for p in parts])[order],
        problems,
        flagged_total,
        zeros,
    )


def _count_text(got: int, n: int) -> str:
    return (
        f"{got} points without labels, expected {n} (one per name in marker_names, "
        "in order; an occluded marker must be sent as NaN or zeros, not left out)"
    )


def _frames_from_labels(points: FloatArray, labels: IntArray, n: int) -> tuple[FloatArray, NDArray[np.bool_]]:
    """:func:`~jointfit_ros.raw.frame_from_points` with labels for G messages (before marking missing rows).

    Returns the frames (G, n, 3) and which messages :func:`~jointfit_ros.raw.label_problems` flags.
    """
    g = points.shape[0]
    out = np.full((g, n, 3), np.nan)
    valid = (labels >= 0) & (labels < n)
    flat = (np.arange(g)[:, None] * n + np.where(valid, labels, 0))[valid]
    out.reshape(g * n, 3)[flat] = points[valid]
    claimed = np.bincount(flat, minlength=g * n).reshape(g, n)
    out[claimed > 1] = np.nan
    flagged = np.asarray((~valid).any(axis=1) | (claimed > 1).any(axis=1), dtype=bool)
    return out, flagged


def _mark_missing_many(frames: FloatArray, zero_is_missing: bool) -> FloatArray:
    """Rows with a non-finite coordinate (and exact zeros if asked) set to NaN, in place, (G, n, 3)."""
    x, y, z = frames[..., 0], frames[..., 1], frames[..., 2]
    bad = ~(np.isfinite(x) & np.isfinite(y) & np.isfinite(z))
    if zero_is_missing:
        bad |= (x == 0.0) & (y == 0.0) & (z == 0.0)
    frames[bad] = np.nan
    return frames

class MarkerParser:
    """One marker message at a time into a frame (P, 3); the unlabelled clouds' prediction.

    Parameters
    ----------
    cfg : NodeConfig
    counters : dict of str to int
        The router's counters (``label_problems``, ``unassigned``, ``zero_markers``, and those
        ``report`` counts).
    report : callable (key, text, counter)
        A dropped message: its counter is counted there and its text kept
        (:meth:`MessageRouter._problem <jointfit_ros.inputs.MessageRouter>`).

    Attributes
    ----------
    last_frame : ndarray, shape (P, 3) or None
        Unlabelled clouds: the latest position of every marker seen, against which the next
        cloud is labelled (None until a complete cloud arrived, and after :meth:`reset`).
    """

    def __init__(self, cfg: NodeConfig, counters: dict[str, int], report: Callable[[str, str, str], None]) -> None:
        self.cfg = cfg
        self.counters = counters
        self._report = report
        self.last_frame: FloatArray | None = None

    def reset(self) -> None:
        """Forget the unlabelled clouds' prediction (the identities are learnt again from the next complete cloud)."""
        self.last_frame = None

    def frame_id_ok(self, frame_id: str, topic: str) -> bool:
        """Whether a message's frame id is ``input_frame_id`` (or none is set); else counted and reported."""
        wanted = self.cfg.input_frame_id
        if not wanted or frame_id == wanted:
            return True
        self._report(
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
            finite = np.isfinite(msg.points)
            all_finite = bool(finite.all())
            if not all_finite and np.isinf(msg.points).any():
                raise ConversionError(_INF_TEXT)
            if msg.labels is None and not cfg.unlabelled and msg.points.shape[0] != n:
                raise ConversionError(_count_text(msg.points.shape[0], n))
            if msg.labels is None and not cfg.unlabelled and cfg.marker_type == "pose_array":
                # Steady-state fast path: one point per marker, in order, in a new array of
                # parse_pose_array's own: frame_from_points' result without its copy and checks.
                frame = msg.points
                bad = ~finite.all(axis=1) if not all_finite else None
                if cfg.zero_is_missing:
                    zero = (frame == 0.0).all(axis=1)
                    bad = zero if bad is None else bad | zero
                if bad is not None and bad.any():
                    frame[bad] = np.nan
            elif msg.labels is not None:
                problems = label_problems(msg.labels, n)
                if problems.out_of_range or problems.duplicated:
                    self.counters["label_problems"] += 1
                frame = frame_from_points(msg.points, n, labels=msg.labels, zero_is_missing=cfg.zero_is_missing)
            elif cfg.unlabelled and msg.points.shape[0] > cfg.max_cloud_points:
                self._report(
                    "oversized",
                    f"dropped an unlabelled cloud of {msg.points.shape[0]} points on {cfg.marker_topic} "
                    f"(max_cloud_points {cfg.max_cloud_points})",
                    "oversized_clouds",
                )
                return None
            elif cfg.unlabelled and self.last_frame is not None:
                frame = label_points(msg.points, self.last_frame, cfg.assignment_gate, zero_is_missing=cfg.zero_is_missing)
                missing = np.isnan(frame[:, 0])
                if missing.any():
                    self.counters["unassigned"] += int(missing.sum())
            else:
                frame = frame_from_points(msg.points, n, zero_is_missing=cfg.zero_is_missing)
        except ConversionError as exc:
            self._report("malformed", f"dropped a malformed message on {cfg.marker_topic}: {exc}", "malformed")
            return None
        if not self.frame_id_ok(msg.frame_id, cfg.marker_topic):
            return None
        if not cfg.zero_is_missing:
            zeros = int(np.count_nonzero((frame == 0.0).all(axis=1)))
            if zeros:  # taken as positions: a driver's occluded markers would be read as markers at the origin
                self.counters["zero_markers"] += zeros
        if cfg.unlabelled:
            # The prediction for the next cloud: the latest position of every marker seen.
            if self.last_frame is None:
                if not np.isnan(frame).any():
                    self.last_frame = frame.copy()
            else:
                seen = ~np.isnan(frame[:, 0])
                self.last_frame[seen] = frame[seen]
        return msg.stamp_ns, msg.frame_id, frame

    def frames_many(self, raws: Sequence[bytes]) -> tuple[IntArray, IntArray, list[str], FloatArray]:
        """Parse many marker messages, in order, as :meth:`frame` parses each.

        Parameters
        ----------
        raws : sequence of bytes
            Messages of ``marker_topic``, oldest first.

        Returns
        -------
        index : ndarray, shape (K,), int64
            Positions in ``raws`` of the messages kept, increasing.
        stamps_ns : ndarray, shape (K,), int64
        frame_ids : list of str, length K
        frames : ndarray, shape (K, P, 3)
            In ``marker_names`` order, as :meth:`frame` returns them.

        Notes
        -----
        The same frames, drops, counters and reports as
        :meth:`frame` of each message in turn (:func:`parse_markers`; the
        problems are then counted in message order). Unlabelled clouds
        (``unlabelled``) are labelled against the previous frame, so they go
        through :meth:`frame` one by one.
        """
        parsed = self.parse_block(raws)
        self.counters["label_problems"] += parsed.label_problems
        self.counters["zero_markers"] += parsed.zero_markers
        for problem in parsed.problems:
            self._report(*problem[1:])
        return parsed.index, parsed.stamps_ns, parsed.frame_ids, parsed.frames

    def parse_block(self, raws: Sequence[bytes]) -> ParsedMarkers:
        """:func:`parse_markers`, or unlabelled clouds through :meth:`frame` one by one (which counts their problems)."""
        if not self.cfg.unlabelled:
            return parse_markers(self.cfg, raws)
        got = [(i, self.frame(raw)) for i, raw in enumerate(raws)]
        kept = [(i, g) for i, g in got if g is not None]
        return ParsedMarkers(
            len(raws),
            np.array([i for i, _ in kept], dtype=np.int64),
            np.array([g[0] for _, g in kept], dtype=np.int64),
            [g[1] for _, g in kept],
            np.stack([g[2] for _, g in kept]) if kept else np.zeros((0, len(self.cfg.marker_names), 3)),
            [],
        )
