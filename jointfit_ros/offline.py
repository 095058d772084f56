"""The node's estimators over a whole recording: what ``jointfit fit`` computes.

ROS-free. :func:`run_fit` reads a rosbag2 bag (the node's marker and pose
topics, as raw CDR), a C3D or a TRC file, and feeds every frame, in order, to
one :class:`~jointfit_ros.runner.JointRunner` per configured joint, through
the same :class:`~jointfit_ros.inputs.MessageRouter` the node uses for bag
messages, in blocks (:meth:`MessageRouter.route_many
<jointfit_ros.inputs.MessageRouter.route_many>`,
:meth:`JointRunner.markers_block <jointfit_ros.runner.JointRunner.markers_block>`,
:meth:`OnlineJoint.update_many <jointfit_core.estimator.OnlineJoint.update_many>`):
every joint ends in the state message-by-message routing (the node's) gives
it (counters and frames exactly, sums and estimates to ~1e-13: blocks of
frames are posed with a vectorised eigen-solve) at a fraction of the cost;
joints fed by the marker topic
alone make no per-frame world outputs. With ``whole_recording=True`` (the
default of ``jointfit fit``) every joint keeps the sums of every frame (no
forgetting, O(1) memory), so the final estimate is the batch estimate of all
of it; a node whose window covers the recording ends with the same numbers
to rounding (its ring-buffer window adds in another order).

Along the way it keeps what the report shows: the estimate and its
covariance at evenly spaced checkpoints (the convergence curve, taken
between blocks), the per-frame outputs' constraint residuals of joints fed
frame by frame (pose inputs; the report computes those of marker joints from
the final estimate and the kept frames), and (``keep_frames``) the parsed
marker frames.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
from collections import Counter
from collections.abc import Callable, Generator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from jointfit_core.block_check import snapshots_consistency, window_consistency
from jointfit_core.consistency import BlockConsistency
from jointfit_core.errors import InputError, JointfitError
from jointfit_core.hinge_from_sums import PoseSumsAxis
from jointfit_core.io import METRES_PER_UNIT, MarkerData, marker_name, read_c3d, read_trc
from jointfit_core.segments import PoseSumsCentre

from .bag import iter_selected_messages, select_topics
from .bag_blocks import BagReaderProcess, can_fork, parsed_blocks, split_blocks
from .inputs import MessageRouter, Routed, route_frame
from .params import ConfigError, NodeConfig
from .runner import JointRunner

__all__ = ["Checkpoint", "JointTrace", "FitRun", "input_kind", "read_marker_file", "with_file_marker_names", "run_fit"]

FloatArray = NDArray[np.float64]

#: bag message type of each ``marker_type``.
_MARKER_MSGTYPE = {"pose_array": "geometry_msgs/msg/PoseArray", "pointcloud2": "sensor_msgs/msg/PointCloud2"}
_POSE_MSGTYPE = "geometry_msgs/msg/PoseStamped"

ProgressFn = Callable[[int, int], None]


@dataclass(frozen=True)
class Checkpoint:
    """A joint's estimate part-way through the recording (parent frame).

    Attributes
    ----------
    frames : int
        Frames given to the joint's estimator so far.
    position : ndarray, shape (3,)
        Ball: the centre; hinge: the axis point nearest the parent origin.
        Parent segment frame, input units.
    cov : ndarray, shape (3, 3)
        Its covariance, input units squared.
    direction : ndarray, shape (3,) or None
        Hinge: unit axis direction (parent frame).
    cov_direction : ndarray, shape (3, 3) or None
        Hinge: its covariance (rank 2).
    rms : float
        Rms constraint residual of the window, input units.
    identifiable : bool
    """

    frames: int
    position: FloatArray
    cov: FloatArray
    direction: FloatArray | None
    cov_direction: FloatArray | None
    rms: float
    identifiable: bool


def checkpoint_of(frames: int, sol: PoseSumsCentre | PoseSumsAxis) -> Checkpoint:
    """The :class:`Checkpoint` of an estimate."""
    if isinstance(sol, PoseSumsCentre):
        return Checkpoint(frames, sol.centre_parent, sol.cov_parent, None, None, sol.rms, sol.identifiable)
    return Checkpoint(
        frames,
        sol.point_parent,
        sol.cov_point_parent,
        sol.direction_parent,
        sol.cov_direction_parent,
        sol.rms,
        sol.identifiable,
    )


@dataclass
class JointTrace:
    """One joint's run: its runner (final estimator, counters) and what the report plots.

    Attributes
    ----------
    runner : JointRunner
    checkpoints : list of Checkpoint
    output_stamps : list of float
        Stamp of every per-frame world output, s, of a joint fed frame by
        frame (one that pairs with a pose topic). Empty for joints fed in
        blocks (marker joints), which make no per-frame outputs: the report
        computes their per-frame residual from the final estimate and the
        kept frames (:func:`jointfit_ros.report.segment_geometry`).
    residuals : list of float
        Its constraint residual (input units; NaN when the child was not posed).
    final : PoseSumsCentre or PoseSumsAxis or None
        The estimate from the whole window at the end of the recording; None
        when it could not be made (``runner.last_error`` says why).
    snapshots : list of ndarray
        The estimator's sums vector at every checkpoint (cumulative with
        ``whole_recording``: the movement blocks of the consistency check).
    consistency : BlockConsistency or None
        The consistency check across movement blocks
        (:mod:`jointfit_core.block_check`) of the final estimate; None
        without a final estimate.
    """

    runner: JointRunner
    final: PoseSumsCentre | PoseSumsAxis | None = None
    checkpoints: list[Checkpoint] = field(default_factory=list)
    output_stamps: list[float] = field(default_factory=list)
    residuals: list[float] = field(default_factory=list)
    snapshots: list[FloatArray] = field(default_factory=list)
    consistency: BlockConsistency | None = None


@dataclass
class FitRun:
    """Everything :func:`run_fit` produced.

    Attributes
    ----------
    path : Path
    kind : str
        ``"bag"``, ``"c3d"`` or ``"trc"``.
    cfg : NodeConfig
        The configuration as run (no forgetting with ``whole_recording``,
        calibration files not loaded).
    traces : list of JointTrace
        One per joint, in the configuration's order.
    n_inputs : int
        Messages (bag) or frames (C3D/TRC) read.
    units : str
        The file's length unit where it declares one (C3D, TRC), else ``""``.
    rate : float
        Frame rate the file declares (C3D, TRC), else 0.
    router : MessageRouter or None
        Bag input: the router, with its counters.
    stamps : ndarray, shape (N,)
        Stamp of every marker frame kept, s (``keep_frames``).
    frames : ndarray, shape (N, P, 3) or None
        The marker frames in ``marker_names`` order (``keep_frames`` and marker inputs).
    """

    path: Path
    kind: str
    cfg: NodeConfig
    traces: list[JointTrace]
    n_inputs: int = 0
    units: str = ""
    rate: float = 0.0
    router: MessageRouter | None = None
    stamps: FloatArray = field(default_factory=lambda: np.zeros(0))
    frames: FloatArray | None = None


def input_kind(path: str | os.PathLike[str]) -> str:
    """``"c3d"``, ``"trc"`` or ``"bag"`` from a path (checked to exist).

    Raises
    ------
    InputError
        The path does not exist or is none of these.
    """
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: no such file or directory")
    suffix = p.suffix.lower()
    if suffix in (".c3d", ".trc"):
        return suffix[1:]
    if p.is_dir() or suffix in (".db3", ".mcap") or p.name == "metadata.yaml":
        return "bag"
    raise InputError(f"{p}: expected a rosbag2 bag (a directory, .db3 or .mcap), a .c3d or a .trc file")


def _offline_config(cfg: NodeConfig, whole_recording: bool) -> NodeConfig:
    """Calibration files never loaded (the fit estimates from the recording).

    ``whole_recording``: no forgetting (``half_life_s = inf``): the sums of
    every frame, in O(1) memory, where a frame window as long as the recording
    would keep every frame's record (262 numbers) for removal.
    """
    joints = []
    for j in cfg.joints:
        j = dataclasses.replace(j, calibration_file="")
        if whole_recording:
            j = dataclasses.replace(j, window_s=0.0, half_life_s=math.inf)
        joints.append(j)
    return dataclasses.replace(cfg, joints=tuple(joints))


def read_marker_file(path: str | os.PathLike[str]) -> MarkerData | None:
    """The markers of a C3D or TRC file; None for a bag (checked to exist, :func:`input_kind`).

    Raises
    ------
    InputError
        Missing or unreadable file.
    MissingDependencyError
        ``ezc3d`` missing (C3D).
    """
    file = Path(path)
    kind = input_kind(file)
    if kind == "bag":
        return None
    return read_c3d(file) if kind == "c3d" else read_trc(file)


#: The joint parameters that name markers.
_MARKER_LISTS = ("parent_markers", "child_markers")
_MARKER_NAMES = ("axis_toward_marker", "axis_from_marker")


def with_file_marker_names(values: Mapping[str, Any], labels: Sequence[str], source: str) -> dict[str, Any]:
    """Parameter values whose ``marker_names`` are a C3D/TRC file's labels when the values give none.

    Parameters
    ----------
    values : mapping
        Full parameter names to values (:func:`~jointfit_ros.params.params_from_file`).
    labels : sequence of str
        The file's marker labels, in file order.
    source : str
        The file's name, for the messages.

    Returns
    -------
    dict
        ``values`` unchanged when they give ``marker_names``; else with
        ``marker_names`` = the labels that occur once in the file (empty and
        repeated labels cannot be told apart and are left out), so that the
        joints' ``parent_markers``, ``child_markers``, ``axis_toward_marker``
        and ``axis_from_marker`` and the segments' ``markers`` name file labels
        (or, when some name is no label, the labels without their subject prefix:
        ``RTHI1`` for Vicon's ``Subject:RTHI1``, where that is unique in the file).

    Raises
    ------
    ConfigError
        A joint names a label the file lacks (the message lists the file's
        labels, with the closest one), or one it holds more than once.
    """
    out = dict(values)
    if out.get("marker_names"):
        return out
    counts = Counter(labels)
    names = [label for label in labels if label and counts[label] == 1]
    joints = out.get("joints")
    segments = out.get("segments")
    owners: list[tuple[Any, tuple[str, ...]]] = [
        (j, (*_MARKER_LISTS, *_MARKER_NAMES)) for j in (joints if isinstance(joints, list) else [])
    ]
    owners += [(g, ("markers",)) for g in (segments if isinstance(segments, list) else [])]
    listed: list[tuple[str, list[str]]] = []  # (key, the markers it names)
    for joint, keys in owners:
        for key in keys:
            given = out.get(f"{joint}.{key}")
            wanted = [given] if isinstance(given, str) and given else given
            if isinstance(wanted, list) and all(isinstance(m, str) for m in wanted):  # else node_config says so
                listed.append((f"{joint}.{key}", wanted))
    if any(m not in counts for _, wanted in listed for m in wanted):  # named without the labels' subject prefix?
        plain = Counter(marker_name(label) for label in names)
        names = [marker_name(label) if plain[marker_name(label)] == 1 else label for label in names]
        counts.update({name: 1 for name in names if name not in counts})
    for key, wanted in listed:
        for marker in wanted:
            if counts[marker] > 1:
                raise ConfigError(
                    f"{key}: {source} holds the label {marker!r} {counts[marker]} times; "
                    "markers of one name cannot be told apart"
                )
            if marker not in counts:
                close = difflib.get_close_matches(marker, names, n=1, cutoff=0.5)
                hint = f"did you mean {close[0]!r}? " if close else ""
                raise ConfigError(
                    f"{key}: {marker!r} is not a marker label of {source} ({hint}its labels: {', '.join(names)})"
                )
    out["marker_names"] = names
    return out


def _read_markers(path: Path, kind: str, cfg: NodeConfig, data: MarkerData | None) -> MarkerData:
    if pose_joints := [j.name for j in cfg.joints if j.parent_pose_topic or j.child_pose_topic]:
        raise ConfigError(
            f"joints {pose_joints} read pose topics; a {kind.upper()} file holds markers only "
            "(use a bag, or give these joints parent_markers and child_markers)"
        )
    if data is not None:
        return data
    return read_c3d(path) if kind == "c3d" else read_trc(path)


def _wanted_topics(cfg: NodeConfig) -> dict[str, str]:
    """The topics the configuration reads (as it names them) and their message types."""
    wanted: dict[str, str] = {}
    if any(j.parent_markers or j.child_markers for j in cfg.joints):
        wanted[cfg.marker_topic] = _MARKER_MSGTYPE[cfg.marker_type]
    for j in cfg.joints:
        for topic in (j.parent_pose_topic, j.child_pose_topic):
            if topic:
                wanted[topic] = _POSE_MSGTYPE
    return wanted


def _bag_topics(path: Path, cfg: NodeConfig) -> tuple[list[str], int]:
    """The bag topics the configuration reads (checked for presence and type) and their message count."""
    wanted = _wanted_topics(cfg)
    infos = select_topics(path, list(wanted))
    for (name, msgtype), info in zip(wanted.items(), infos, strict=True):
        if info.msgtype != msgtype:
            raise InputError(
                f"{path}: topic {info.name} holds {info.msgtype}, the configuration reads {name} as {msgtype}"
                + (" (marker_type)" if msgtype in _MARKER_MSGTYPE.values() else "")
            )
    empty = [i.name for i in infos if i.count == 0]
    if empty:
        raise InputError(f"{path}: topic {', '.join(empty)} holds no messages")
    return [i.name for i in infos], max((i.count for i in infos), default=0)


def _check_inputs_read(run: FitRun) -> None:
    """Refuse a bag whose marker messages were all unreadable (e.g. another type's bytes under the topic's type),
    or all stamped 0 (the joints would drop every frame after the first as not increasing).

    Raises
    ------
    InputError
        Naming the topic and the latest problem, instead of a fit that waits for its first frame.
    """
    router = run.router
    if router is None or not router.marker_runners:
        return
    c = router.counters
    dropped = ("malformed", "wrong_frame_id", "oversized_clouds", "invalid_stamps", "stamps_ahead")
    read = c["messages"] - sum(c.get(k, 0) for k in dropped)
    if c["messages"] > 0 and read <= 0:
        last = router.last_problem[1] if router.last_problem is not None else "no message could be read"
        raise InputError(
            f"{run.path}: none of the {c['messages']} messages on {run.cfg.marker_topic} could be read as "
            f"{run.cfg.marker_type} ({last})"
        )
    if read > 1 and c.get("zero_stamps", 0) >= read:
        raise InputError(
            f"{run.path}: every message on {run.cfg.marker_topic} has header.stamp 0 (not set by its publisher): "
            "a recording's frames cannot be put in time order without stamps (replayed into the live node, "
            "jointfit_replay, they take their arrival times); record with the stamps set"
        )


#: Most messages (frames) parsed and given to the estimators at once; blocks also end at every checkpoint.
MAX_BLOCK = 4096
#: Bags from this size on (storage files, bytes) are read in a reader process by default
#: (~7000 PoseArray messages of 40 markers; a fork costs a few ms).
READER_PROCESS_MIN_BYTES = 16_000_000


def _bag_bytes(path: Path) -> int:
    """Size of a bag's files, bytes (a bag directory, its metadata.yaml or one storage file)."""
    folder = path.parent if path.name == "metadata.yaml" else path
    files = list(folder.iterdir()) if folder.is_dir() else [folder]
    return sum(f.stat().st_size for f in files if f.is_file())


def _bag_events(
    run: FitRun, topics: list[str], step: int, reader: BagReaderProcess | None
) -> Generator[int, None, None]:
    """Route every message in blocks; yields the number of messages of each.

    A block ends after ``MAX_BLOCK`` messages or when the message count reaches a multiple of ``step``
    (so that checkpoints fall between blocks, where message-by-message routing would take them).
    Marker messages are parsed a block at a time (:func:`~jointfit_ros.bag_blocks.parsed_blocks`,
    or by ``reader`` in its process) and routed with
    :meth:`MessageRouter.route_parsed`; unlabelled clouds and chain joints, which need the
    previous frame, go through :meth:`MessageRouter.route_many`.
    """
    router = run.router
    assert router is not None
    marker_topic = topics[0] if any(r.uses_marker_topic for r in router.runners) else None
    traces = {id(t.runner): t for t in run.traces}

    def note(routed: list[Routed]) -> None:
        for r in routed:
            t = traces[id(r.runner)]
            t.output_stamps.append(r.stamp_ns * 1e-9)
            t.residuals.append(r.output.residual)

    if not router.blockwise:
        for block in split_blocks(iter_selected_messages(run.path, topics), marker_topic, step, MAX_BLOCK):
            note(router.route_many(block))
            yield len(block)
        return
    if reader is not None:
        blocks = reader.blocks(marker_topic, step)
    else:
        blocks = parsed_blocks(run.path, topics, marker_topic, run.cfg, step, MAX_BLOCK, process=False)
    for parsed, poses in blocks:
        note(router.route_parsed(parsed, poses))
        yield parsed.n + len(poses)


def checked_frame_stamps(stamps: NDArray[np.float64], rate: float, source: str) -> NDArray[np.int64]:
    """Frame stamps of a C3D/TRC file (ns, as floats) as int64, refused when the file's rate cannot give them.

    Parameters
    ----------
    stamps : ndarray, shape (N,)
        ``(first_frame + k) / rate`` (or a given start + ``k / rate``) in ns, rounded.
    rate : float
        The file's frame rate, Hz, for the message.
    source : str
        The file, for the message.

    Returns
    -------
    ndarray of int64, shape (N,)

    Raises
    ------
    InputError
        A stamp that is not finite or beyond int64 nanoseconds (a rate near 0), or two frames
        on one nanosecond (a rate above 1 GHz): every frame after the first would be dropped as
        not increasing, and the fit would report too few frames instead of the rate.
    """
    if stamps.size and not (np.isfinite(stamps).all() and np.abs(stamps).max() < 2.0**63):
        raise InputError(
            f"{source}: the frame rate {rate:g} Hz puts the frames beyond any time stamp (ns in int64; frame k is at "
            "(first frame number - 1 + k) / rate s); check the file's rate and frame numbers"
        )
    if stamps.size > 1 and not (np.diff(stamps) > 0).all():
        raise InputError(
            f"{source}: the frame rate {rate:g} Hz puts frames less than 1 ns apart (stamps are ns); check the file's rate"
        )
    return stamps.astype(np.int64)


def _marker_events(run: FitRun, data: MarkerData, step: int) -> Generator[int, None, None]:
    """Give the frames of a marker file to every joint in blocks; yields the number of frames of each."""
    frames = data.select(run.cfg.marker_names)
    if run.cfg.zero_is_missing:  # TRC exporters write gaps as 0 0 0 too (read_c3d makes them NaN already)
        frames[(frames == 0.0).all(axis=2)] = np.nan
    with np.errstate(over="ignore", invalid="ignore"):
        stamps = np.rint((data.first_frame + np.arange(data.n_frames)) / data.rate * 1e9)
    stamps_ns = checked_frame_stamps(stamps, data.rate, str(run.path))
    run.frames = frames
    run.stamps = stamps_ns.astype(np.float64) * 1e-9
    start = 0
    while start < frames.shape[0]:
        stop = min(frames.shape[0], (start // step + 1) * step, start + MAX_BLOCK)
        if any(t.runner.chained for t in run.traces):
            # Chain joints take this frame's outputs of the joints before them: one frame at a time.
            runners = [t.runner for t in run.traces]
            for k in range(start, stop):
                route_frame(runners, int(stamps_ns[k]), "", frames[k])
        else:
            for t in run.traces:
                t.runner.markers_block(stamps_ns[start:stop], frames[start:stop])
        yield stop - start
        start = stop


def _checkpoint(traces: list[JointTrace]) -> None:
    for t in traces:
        snap = t.runner.estimator.sums_vector()
        if snap is not None:
            t.snapshots.append(snap)
        if t.runner.estimate(force=True) and t.runner.estimator.solution is not None:
            t.checkpoints.append(checkpoint_of(t.runner.counters["frames"], t.runner.estimator.solution))


def _consistency(t: JointTrace, whole_recording: bool, run: FitRun) -> BlockConsistency | None:
    """The check across movement blocks: from the checkpoints' snapshots (no forgetting) or the window's frames."""
    est = t.runner.estimator
    if t.final is None or est.frozen:
        return None
    units = run.units or run.cfg.units
    try:
        if whole_recording:
            return snapshots_consistency(est, t.snapshots, rate_hz=run.rate or t.runner.input_rate(), units=units)
        return window_consistency(est, units=units)
    except JointfitError:  # a block's covariance not positive definite: no verdict (the summary says none)
        return None


def _traces(cfg: NodeConfig) -> list[JointTrace]:
    """A trace per joint, its estimator logging the frames the outlier gate rejects (the report marks them)."""
    traces = [JointTrace(JointRunner(j, cfg)) for j in cfg.joints]
    for t in traces:
        t.runner.estimator.gate_log = []
    return traces


def run_fit(
    path: str | os.PathLike[str],
    cfg: NodeConfig,
    *,
    whole_recording: bool = True,
    n_checkpoints: int = 60,
    keep_frames: bool = True,
    progress: ProgressFn | None = None,
    reader_process: bool | None = None,
    data: MarkerData | None = None,
) -> FitRun:
    """Run every configured joint over a recording, in order, and solve at the end.

    Parameters
    ----------
    path : str or os.PathLike
        A rosbag2 bag (directory, ``.db3``, ``.mcap``), a ``.c3d`` or a ``.trc`` file.
    cfg : NodeConfig
        The node's configuration (:func:`~jointfit_ros.params.node_config`):
        bags are read on its ``marker_topic`` (as ``marker_type``) and pose
        topics; C3D/TRC files give the markers named in ``marker_names``
        (:func:`with_file_marker_names` makes them the file's labels when the
        parameter file gives none).
    whole_recording : bool
        Every joint's estimate from all frames of the recording (default). False
        keeps the configured windows: the result is then what the node holds
        at the end of the recording.
    n_checkpoints : int
        Estimates taken along the way for the convergence curve.
    keep_frames : bool
        Keep the marker frames (``FitRun.frames``) for the report.
    progress : callable, optional
        ``progress(done, total)`` called about every 1 % of the inputs.
    reader_process : bool, optional
        Bags: read and parse in a second process while the estimators run
        (:class:`~jointfit_ros.bag_blocks.BagReaderProcess`; the same results).
        Default: for bags of at least ``READER_PROCESS_MIN_BYTES`` when the
        process may fork (:func:`~jointfit_ros.bag_blocks.can_fork`).
        Unlabelled clouds and chain joints are always read in this process.
    data : MarkerData, optional
        C3D/TRC: the file's markers when already read (:func:`read_marker_file`).

    Returns
    -------
    FitRun
        Each joint's final estimate is ``trace.final`` (None, with
        ``trace.runner.last_error`` saying why, when there is none).

    Raises
    ------
    InputError
        Missing or unreadable input, a bag without the configured topics (or
        with other message types), a C3D/TRC without the configured markers.
    ConfigError
        Pose-topic joints with a C3D/TRC input.
    MissingDependencyError
        ``rosbags`` (bags) or ``ezc3d`` (C3D) missing.
    """
    file = Path(path)
    kind = input_kind(file)
    reader: BagReaderProcess | None = None
    if kind == "bag":
        run_cfg = _offline_config(cfg, whole_recording)
        run = FitRun(file, kind, run_cfg, [])
        run.traces = _traces(run_cfg)
        run.router = MessageRouter(run_cfg, [t.runner for t in run.traces])
        if keep_frames:
            run.router.recorded = []
        if reader_process is None:
            reader_process = _bag_bytes(file) >= READER_PROCESS_MIN_BYTES and can_fork()
        if reader_process and run.router.blockwise:
            # The child opens the bag while this process checks the topics (each open of a sqlite3 bag
            # counts its messages).
            reader = BagReaderProcess(file, list(_wanted_topics(run_cfg)), run_cfg, MAX_BLOCK)
        try:
            topics, total = _bag_topics(file, cfg)
        except BaseException:
            if reader is not None:
                reader.close()
            raise
        step = max(1, total // max(n_checkpoints, 1))
        events = _bag_events(run, topics, step, reader)
    else:
        data = _read_markers(file, kind, cfg, data)
        total = data.n_frames
        run_cfg = _offline_config(cfg, whole_recording)
        if data.units in METRES_PER_UNIT:  # the numbers' unit (workspace is in metres, converted by it)
            run_cfg = dataclasses.replace(run_cfg, units=data.units)
        run = FitRun(file, kind, run_cfg, [], units=data.units, rate=data.rate)
        run.traces = _traces(run_cfg)
        step = max(1, total // max(n_checkpoints, 1))
        events = _marker_events(run, data, step)
    tick = max(1, total // 100)
    done = 0
    try:
        for n in events:
            done += n
            if done % step == 0:
                _checkpoint(run.traces)
            if progress is not None and done // tick > (done - n) // tick:
                progress(done, total)
    finally:  # a reader process stops with the fit, also on an error
        events.close()
        if reader is not None:
            reader.close()
    run.n_inputs = done
    _check_inputs_read(run)
    for t in run.traces:
        if not t.runner.estimate(force=True):
            continue  # no final estimate: an earlier one must not pass for it
        t.final = t.runner.estimator.solution
        if t.final is not None and (not t.checkpoints or t.checkpoints[-1].frames != t.runner.counters["frames"]):
            t.checkpoints.append(checkpoint_of(t.runner.counters["frames"], t.final))
        t.consistency = _consistency(t, whole_recording, run)
    if progress is not None:
        progress(done, total)
    if run.router is not None and run.router.recorded:
        run.stamps = np.array([s for s, _ in run.router.recorded], dtype=np.float64) * 1e-9
        run.frames = np.stack([f for _, f in run.router.recorded])
        run.router.recorded = None
    if not keep_frames:
        run.frames = None
    return run
