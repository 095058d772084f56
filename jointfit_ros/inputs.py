"""From message bytes to what the joint runners take: shared by the node and the offline tools.

ROS-free: :class:`MessageRouter` parses marker messages (PoseArray or
PointCloud2, labelled, ordered or unlabelled) into ``(P, 3)`` frames in
``marker_names`` order and pose messages into rotations and translations,
hands them to the :class:`~jointfit_ros.runner.JointRunner` of each joint,
and counts what it drops. The node calls it from its subscription callbacks;
``jointfit fit`` calls it for every message of a recording, so that both
compute exactly the same thing.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from jointfit_core.estimator import JointOutput

from .cluster_check import ClusterCheck
from .interleaved_publishers import InterleaveGuard
from .marker_parser import MarkerParser, ParsedMarkers, parse_markers
from .params import NodeConfig
from .raw import ConversionError, parse_pose_stamped, rotation_matrix_from_quaternion
from .repeated_frames import PoseRepeats, RepeatedFrames, window_horizon
from .runner import JointRunner
from .stamp_gaps import StampGaps
from .timeline import Timeline

__all__ = [
    "Message",
    "MessageRouter",
    "ParsedMarkers",
    "PoseMessage",
    "Routed",
    "parse_markers",
    "route_frame",
    "split_block",
]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: A message of a block: ``(None, raw)`` for one of the marker topic, ``(topic, raw)`` for one of a pose topic.
Message = tuple[str | None, bytes]
#: A pose-topic message of a block: ``(position in the block, topic, raw)``.
PoseMessage = tuple[int, str, bytes]


@dataclass(frozen=True)
class Routed:
    """One joint's output for one message: the runner, the stamp, the frame id and the output."""

    runner: JointRunner
    stamp_ns: int
    frame_id: str
    output: JointOutput


def split_block(messages: Sequence[Message]) -> tuple[list[bytes], list[PoseMessage]]:
    """A block's marker messages (their bytes, in order) and its pose messages (with their positions)."""
    return (
        [raw for topic, raw in messages if topic is None],
        [(i, topic, raw) for i, (topic, raw) in enumerate(messages) if topic is not None],
    )


def _isolated(
    runner: JointRunner,
    on_error: Callable[[JointRunner, Exception], None] | None,
    step: Callable[..., JointOutput | None],
    *args: Any,
    **kwargs: Any,
) -> JointOutput | None:
    """``step(*args, **kwargs)``, one joint's step; when it raises and ``on_error`` is set, reported there and None.

    The joints after it then still get the frame (the node); without ``on_error`` the exception propagates.
    """
    try:
        return step(*args, **kwargs)
    except Exception as exc:
        if on_error is None:
            raise
        on_error(runner, exc)
        return None


def route_frame(
    runners: Sequence[JointRunner],
    stamp_ns: int,
    frame_id: str,
    frame: FloatArray,
    time_ns: int | None = None,
    *,
    defer_samples: bool = False,
    replayed: NDArray[np.bool_] | None = None,
    on_error: Callable[[JointRunner, Exception], None] | None = None,
) -> list[Routed]:
    """Give one parsed marker frame (P, 3) to the joints in order; their outputs.

    Each joint's output in this frame becomes a virtual marker of the later
    joints that name it in ``parent_chain`` / ``child_chain``. ``time_ns``:
    the estimators' time of the frame (:class:`~jointfit_ros.timeline.Timeline`),
    when it is not ``stamp_ns``; the outputs carry ``stamp_ns``.
    ``defer_samples``: the joints' live-geometry samples are left for
    :meth:`~jointfit_ros.runner.JointRunner.take_sample`. ``replayed``: per
    runner, the frame is still in its window from before (a looped replay,
    :class:`~jointfit_ros.repeated_frames.RepeatedFrames`): its output, not added again.
    ``on_error``: a joint that raises is reported to it and the frame goes on to
    the joints after it (the node: its callback guard); None: the exception
    propagates (offline, where a bug must stop the fit).
    """
    out = []
    chain: dict[str, FloatArray] = {}
    t = stamp_ns if time_ns is None else time_ns
    for k, runner in enumerate(runners):
        runner.estimator.replayed = replayed is not None and bool(replayed[k])
        try:
            result = _isolated(runner, on_error, runner.markers_frame, t, frame, chain, defer_sample=defer_samples)
        finally:
            runner.estimator.replayed = False
        if result is not None:
            chain[runner.cfg.name] = result.position
            out.append(Routed(runner, stamp_ns, frame_id, result))
    return out


class MessageRouter:
    """Parse messages and route them to the joints that use them.

    Parameters
    ----------
    cfg : NodeConfig
    runners : iterable of JointRunner
    clock : callable returning int, optional
        Arrival time of a message in ns (the node: ``time.monotonic_ns``), for
        the :attr:`timeline`; None for recordings.
    stamp_clock : callable returning int, optional
        The time (ns, the node's ROS clock) that stands in for a message's ``header.stamp`` when
        that is exactly 0 (a driver that leaves it unset: every frame after the first was dropped
        as not increasing, and no joint ever estimated); counted as ``zero_stamps``. None
        (recordings): such messages keep their stamp 0 and are counted.

    Attributes
    ----------
    counters : dict of str to int
        ``messages``, ``malformed`` (unparsable or inconsistent messages),
        ``wrong_frame_id`` (messages whose ``header.frame_id`` is not
        ``input_frame_id``, when that is set),
        ``label_problems`` (labelled clouds with out-of-range or duplicated
        labels), ``unassigned`` (markers of unlabelled clouds left without a
        point), ``oversized_clouds`` (unlabelled clouds of more than
        ``max_cloud_points`` points, dropped), ``zero_markers`` (markers at exactly (0, 0, 0) taken as
        positions: ``zero_is_missing`` false), ``zero_stamps`` (messages whose ``header.stamp`` is 0:
        unset; live, their arrival time stands in), ``second_publisher`` (frames held back while two publishers'
        frames interleave, :attr:`interleave`), and the :attr:`timeline`'s ``invalid_stamps``,
        ``stamps_ahead`` (dropped) and ``timeline_restarts``; ``repeated_frames``:
        marker frames received again (the same stamp and markers: a looped
        replay), published but not added to the joints' windows (:attr:`repeats`).
    timeline : Timeline
        Checks every message's stamp and gives the joints increasing times
        (``max_stamp_jump``); the outputs carry the input stamps.
    last_problem : tuple of (str, str) or None
        ``(key, text)`` of the latest dropped message, for a one-time log line.
    frame_id : str
        frame_id of the latest message.
    recorded : list of (int, ndarray) or None
        When set to a list (the offline fit does, for its report), every
        parsed marker frame is appended as ``(stamp_ns, frame (P, 3))``.
    chained : bool
        Some joint takes chain markers: it needs this frame's outputs of the
        joints before it, so messages are routed one at a time.
    blockwise : bool
        Marker messages can be parsed a block at a time, apart from the
        routing (:func:`parse_markers`, :meth:`route_parsed`): not
        ``chained`` and not ``unlabelled`` (labelled against the previous frame).
    defer_bookkeeping : bool
        False (default): :meth:`markers` does everything. True (the node, so
        that it publishes a frame's outputs first): what does not change the
        outputs (the stamp-gap count, the joints' live-geometry samples) is
        left for :meth:`after_outputs`, which must follow before the next
        message (else the frame's sample and stamp gap are lost, never wrong).
    """

    def __init__(
        self,
        cfg: NodeConfig,
        runners: Iterable[JointRunner],
        clock: Callable[[], int] | None = None,
        stamp_clock: Callable[[], int] | None = None,
    ) -> None:
        self.cfg = cfg
        self.stamp_clock = stamp_clock
        self.runners = list(runners)
        self.marker_runners = [r for r in self.runners if r.uses_marker_topic]
        self.chained = any(r.chained for r in self.marker_runners)
        self.blockwise = not (self.chained or cfg.unlabelled)
        self.pose_topics: dict[str, list[tuple[JointRunner, int]]] = {}
        for r in self.runners:
            for source, topic in ((0, r.cfg.parent_pose_topic), (1, r.cfg.child_pose_topic)):
                if topic:
                    self.pose_topics.setdefault(topic, []).append((r, source))
        self.counters = {
            "messages": 0, "malformed": 0, "wrong_frame_id": 0, "label_problems": 0, "unassigned": 0,
            "oversized_clouds": 0, "repeated_frames": 0, "second_publisher": 0, "zero_markers": 0,
            "zero_stamps": 0, "incompatible_qos": 0,
        }
        #: Per input topic with publishers whose QoS its subscription cannot take, the last policy that did not
        #: match (:meth:`set_incompatible`).
        self.incompatible: dict[str, str] = {}
        self._incompatible_totals: dict[str, int] = {}
        #: Per input topic, its matched publishers and whether frames of two of them interleave (the node sets
        #: the counts from its subscriptions' matched events: :meth:`set_publishers`).
        self.interleave: dict[str, InterleaveGuard] = {
            t: InterleaveGuard() for t in ([cfg.marker_topic] if self.marker_runners else []) + list(self.pose_topics)
        }
        #: The marker frames received (stamp and markers), to tell a looped replay's frames from new ones.
        self.repeats = RepeatedFrames(len(self.marker_runners))
        #: The poses received on each pose topic (stamp, position and orientation): a looped replay of rigid bodies.
        self.pose_repeats = PoseRepeats({
            topic: [(r.cfg.window, r.cfg.window_s, r.cfg.half_life_s) for r, _ in pairs]
            for topic, pairs in self.pose_topics.items()
        })
        self._horizons = (-1.0, np.zeros(0))  # (frame period they were taken at, ns; per marker joint, ns)
        self.last_problem: tuple[str, str] | None = None
        self.frame_id = ""
        #: The stamp (ns) of the frame the latest :meth:`markers` gave to the joints; None when it gave none.
        self.routed_stamp_ns: int | None = None
        #: Frames of the marker topic that never arrived (gaps in its stamps), for ``/diagnostics``.
        self.gaps = StampGaps()
        self._gap_stamp_ns: int | None = None  # the stamp a deferred markers() left for after_outputs()
        self.defer_bookkeeping = False
        #: When set (the node: its callback guard), a joint that raises on a frame is reported here and the
        #: frame goes on to the other joints; None: the exception propagates.
        self.on_joint_error: Callable[[JointRunner, Exception], None] | None = None
        #: Marker messages into frames; the unlabelled clouds' prediction (:attr:`MarkerParser.last_frame`).
        self.parser = MarkerParser(cfg, self.counters, self._problem)
        self.recorded: list[tuple[int, FloatArray]] | None = None
        self.timeline = Timeline(round(cfg.max_stamp_jump * 1e9), clock=clock, counters=self.counters)
        #: The marker-topic segments' pair distances: a marker that does not move with its segment (each marker
        #: joint's status names it, :meth:`JointRunner.odd_markers <jointfit_ros.runner.JointRunner.odd_markers>`).
        self.clusters = ClusterCheck(cfg, [r.cfg for r in self.marker_runners])
        for r in self.marker_runners:
            r.cluster_check = self.clusters

    def reset(self) -> None:
        """Forget the unlabelled-cloud prediction and the frames received (after a reset of the joints)."""
        self.parser.reset()
        self.repeats.clear()
        self.pose_repeats.clear()
        self.clusters.clear()

    def _horizons_ns(self) -> NDArray[np.float64]:
        """How long a frame may stay in each marker joint's window (ns): :meth:`RepeatedFrames.fresh`'s horizons.

        Taken again only when the stream's measured frame period changes (windows in frames need it).
        """
        period_ns = self.gaps.spacing_s * 1e9  # the frames the joints get (not the stream's, when most are lost)
        if period_ns != self._horizons[0]:
            windows = [(r.cfg.window, r.cfg.window_s, r.cfg.half_life_s) for r in self.marker_runners]
            self._horizons = (period_ns, window_horizon(windows, period_ns))
        return self._horizons[1]

    def set_incompatible(self, topic: str, total: int, policy: str) -> None:
        """``total`` publishers on ``topic`` offer a QoS its subscription cannot take (its incompatible-QoS event).

        ``policy``: the last QoS policy that did not match (e.g. RELIABILITY). None of their messages can
        arrive; counted over the input topics (``incompatible_qos``) and said once in the log.
        """
        seen = self._incompatible_totals.get(topic, 0)
        self._incompatible_totals[topic] = total
        self.counters["incompatible_qos"] += max(total - seen, 0)
        self.incompatible[topic] = policy
        self.last_problem = (
            f"incompatible_qos:{topic}",
            f"a publisher on {topic} offers a QoS this subscription cannot take ({policy} policy): "
            "none of its messages arrive",
        )

    def set_publishers(self, topic: str, n: int) -> None:
        """``topic`` has ``n`` matched publishers now (its subscription's matched event)."""
        guard = self.interleave.get(topic)
        if guard is not None:
            guard.set_publishers(n)

    def _second_publisher(self, topic: str, frame: FloatArray, runners: Sequence[JointRunner]) -> bool:
        """Whether a frame of ``topic`` is held back because a second publisher's frames interleave with it."""
        guard = self.interleave.get(topic)
        if guard is None or guard.publishers <= 1:
            return False
        why = guard.admit(frame)
        if not why:
            return False
        self._problem(
            f"second_publisher:{topic}",
            f"{topic} has {guard.publishers} publishers: frames held back until only one sends "
            + ("(this one a copy of a recent frame)" if why == "copy" else "(their frames interleave)"),
            "second_publisher",
        )
        _note_dropped(runners, 1)
        return True

    def _problem(self, key: str, text: str, counter: str = "malformed") -> None:
        if counter:  # "": counted where it was found (the timeline)
            self.counters[counter] += 1
        self.last_problem = (key, text)

    def _time(self, stamp_ns: int, topic: str, runners: Sequence[JointRunner]) -> int | None:
        """The timeline's time of a message's stamp; None when dropped (reported, and noted by ``runners``)."""
        t = self.timeline.time_of(stamp_ns, topic)
        event = self.timeline.last_event
        if event is not None:
            self.last_problem = event
            self.timeline.last_event = None
        if t is None:
            _note_dropped(runners, 1)
        return t

    def _times(self, parsed: ParsedMarkers) -> tuple[ParsedMarkers, IntArray]:
        """A block's marker messages kept by the timeline, with its times as stamps, and their real stamps.

        The messages the timeline drops become problems (counted by it), at their positions.
        """
        timeline = self.timeline
        kept, times = timeline.times_of(parsed.stamps_ns, self.cfg.marker_topic)
        event = timeline.last_event
        timeline.last_event = None
        dropped = parsed.n - parsed.index.size
        if bool(kept.all()):
            if event is not None and parsed.index.size:  # a restart confirmed in the block: its log line
                at = (int(parsed.index[-1]), *event, "")
                parsed = dataclasses.replace(parsed, problems=sorted([*parsed.problems, at], key=lambda p: p[0]))
            _note_dropped(self.marker_runners, dropped)
            return dataclasses.replace(parsed, stamps_ns=times), parsed.stamps_ns
        gone = np.flatnonzero(~kept)
        text = ("stamp_ahead", f"dropped messages on {self.cfg.marker_topic} with bad stamps (see the counters)")
        problems = sorted([*parsed.problems, *((int(parsed.index[i]), *(event or text), "") for i in gone)],
                          key=lambda p: p[0])
        _note_dropped(self.marker_runners, dropped + gone.size)
        kept_parsed = ParsedMarkers(
            parsed.n,
            parsed.index[kept],
            times[kept],
            [f for f, k in zip(parsed.frame_ids, kept.tolist(), strict=True) if k],
            parsed.frames[kept],
            problems,
            parsed.label_problems,
        )
        return kept_parsed, parsed.stamps_ns[kept]

    def markers_many(self, raws: Sequence[bytes]) -> list[Routed]:
        """Many messages of ``marker_topic``, oldest first: :meth:`markers` of each (see :meth:`route_many`)."""
        return self.route_many([(None, raw) for raw in raws])

    def route_many(self, messages: Sequence[Message]) -> list[Routed]:
        """Messages in arrival order: :meth:`markers` or :meth:`pose` of each, the marker frames in one block.

        Parameters
        ----------
        messages : sequence of (str or None, bytes)
            ``(None, raw)`` for a message of ``marker_topic``, ``(topic, raw)``
            for one of a pose topic.

        Returns
        -------
        list of Routed
            The per-frame outputs of the joints fed one message at a time
            (those that pair with a pose topic), in message order. Joints fed
            by the marker topic alone make none: they take the block's kept
            frames at once (:meth:`~jointfit_ros.runner.JointRunner.markers_block`).

        Notes
        -----
        Every joint, the counters, :attr:`last_problem`, :attr:`frame_id`
        and :attr:`recorded` end up as after :meth:`markers` and :meth:`pose`
        of each message in turn: the marker messages are parsed at once
        (:meth:`MarkerParser.parse_block <jointfit_ros.marker_parser.MarkerParser.parse_block>`) and the marker-only joints, which never see a
        pose message, take their frames as one block; then the messages are
        walked in order for the rest (joints pairing markers with a pose
        topic, pose topics, problems and frame ids), unless there are none.
        """
        if self.chained:
            # Chain joints need this frame's outputs of the joints before them: one message at a time.
            out: list[Routed] = []
            for topic, raw in messages:
                out.extend(self.markers(raw) if topic is None else self.pose(topic, raw))
            return out
        raws, poses = split_block(messages)
        return self.route_parsed(self.parser.parse_block(raws), poses)

    def route_parsed(self, parsed: ParsedMarkers, poses: Sequence[PoseMessage] = ()) -> list[Routed]:
        """:meth:`route_many` of a block whose marker messages are already parsed.

        Parameters
        ----------
        parsed : ParsedMarkers
            The block's marker messages (:func:`parse_markers`).
        poses : sequence of (int, str, bytes)
            The block's pose-topic messages: ``(position in the block, topic, raw)``,
            by position; the marker messages fill the other positions, in order.

        Returns
        -------
        list of Routed
            As :meth:`route_many`.

        Raises
        ------
        ValueError
            A joint takes chain markers (those go through :meth:`route_many`, one message at a time).
        """
        if self.chained:
            raise ValueError("chain joints are routed one message at a time (route_many)")
        self.counters["messages"] += parsed.n
        self.counters["label_problems"] += parsed.label_problems
        self.counters["zero_markers"] += parsed.zero_markers
        self.counters["zero_stamps"] += int(np.count_nonzero(parsed.stamps_ns == 0))  # blocks: recordings, kept as 0
        parsed, real_stamps = self._times(parsed)  # stamps_ns: the timeline's times from here on
        index, stamps, frame_ids, frames, problems = (
            parsed.index, parsed.stamps_ns, parsed.frame_ids, parsed.frames, parsed.problems
        )
        replayed = ~self.repeats.fresh_many(real_stamps, frames, stamps, self._horizons_ns())  # (K, marker joints)
        self._count_repeats()
        column = {id(r): j for j, r in enumerate(self.marker_runners)}
        if index.size:
            self.clusters.add(stamps, frames)
            if self.recorded is not None:
                self.recorded.extend(zip(stamps.tolist(), frames, strict=True))
            unpaired = [r for r in self.marker_runners if r.matcher is None]
            if replayed.any():  # frames received before (a loop): no new data, frame by frame as markers() gives them
                cols = [column[id(r)] for r in unpaired]
                for k in range(index.size):
                    route_frame(unpaired, int(real_stamps[k]), frame_ids[k], frames[k], time_ns=int(stamps[k]),
                                replayed=replayed[k, cols])
            else:
                for runner in unpaired:
                    runner.markers_block(stamps, frames)
        paired = [r for r in self.marker_runners if r.matcher is not None]
        paired_cols = [column[id(r)] for r in paired]
        out: list[Routed] = []
        if not paired and not poses:
            for problem in problems:
                self._problem(*problem[1:])
            if index.size:
                self.frame_id = frame_ids[-1]
            return out
        row_of = dict(zip(index.tolist(), range(index.size), strict=True))
        next_problem = 0
        next_pose = 0
        j = 0  # position among the marker messages
        for position in range(parsed.n + len(poses)):
            if next_pose < len(poses) and poses[next_pose][0] == position:
                out.extend(self.pose(*poses[next_pose][1:]))
                next_pose += 1
                continue
            while next_problem < len(problems) and problems[next_problem][0] == j:
                self._problem(*problems[next_problem][1:])
                next_problem += 1
            row = row_of.get(j)
            j += 1
            if row is None:
                continue
            self.frame_id = frame_ids[row]
            out.extend(route_frame(paired, int(real_stamps[row]), frame_ids[row], frames[row], time_ns=int(stamps[row]),
                                   replayed=replayed[row, paired_cols]))
        return out

    def markers(self, raw: bytes) -> list[Routed]:
        """A message of ``marker_topic``: the outputs of the joints it produced one for.

        With :attr:`defer_bookkeeping`, what does not change the outputs is
        left for :meth:`after_outputs`.
        """
        defer_bookkeeping = self.defer_bookkeeping
        self.counters["messages"] += 1
        self.routed_stamp_ns = None
        self._gap_stamp_ns = None
        got = self.parser.frame(raw)
        if got is None:
            _note_dropped(self.marker_runners, 1)
            return []
        stamp_ns, frame_id, frame = got
        stamp_ns = self._stamp(stamp_ns)
        if self._second_publisher(self.cfg.marker_topic, frame, self.marker_runners):
            return []
        if defer_bookkeeping:
            self._gap_stamp_ns = stamp_ns
        else:
            self.gaps.add(stamp_ns)
        t = self._time(stamp_ns, self.cfg.marker_topic, self.marker_runners)
        if t is None:
            return []
        self.frame_id = frame_id
        self.routed_stamp_ns = stamp_ns
        if self.recorded is not None:
            self.recorded.append((t, frame))
        self.clusters.add(np.array([t]), frame[None])
        fresh = self.repeats.fresh(stamp_ns, frame, t, self._horizons_ns())
        self._count_repeats()
        return route_frame(
            self.marker_runners, stamp_ns, frame_id, frame, time_ns=t, defer_samples=defer_bookkeeping,
            replayed=None if fresh.all() else ~fresh, on_error=self.on_joint_error,
        )

    def after_outputs(self) -> None:
        """The bookkeeping :meth:`markers` left with :attr:`defer_bookkeeping`: stamp gaps, live-geometry samples.

        Nothing when there is none left (calling it twice does it once).
        """
        if self._gap_stamp_ns is not None:
            self.gaps.add(self._gap_stamp_ns)
            self._gap_stamp_ns = None
        for runner in self.marker_runners:
            runner.take_sample()

    def pose(self, topic: str, raw: bytes) -> list[Routed]:
        """A message of a pose topic: the outputs of the joints it produced one for."""
        self.counters["messages"] += 1
        pairs = self.pose_topics.get(topic, [])
        runners = [r for r, _ in pairs]
        try:
            msg = parse_pose_stamped(raw)
            R = rotation_matrix_from_quaternion(msg.quaternion)
        except ConversionError as exc:
            self._problem(f"malformed:{topic}", f"dropped a malformed message on {topic}: {exc}")
            _note_dropped(runners, 1)
            return []
        if not np.isfinite(msg.position).all():
            self._problem(f"nan:{topic}", f"dropped a pose with a non-finite position on {topic}")
            _note_dropped(runners, 1)
            return []
        if not self.parser.frame_id_ok(msg.frame_id, topic):
            _note_dropped(runners, 1)
            return []
        if self._second_publisher(topic, msg.position.reshape(1, 3), runners):
            return []
        stamp_ns = self._stamp(msg.stamp_ns)
        t = self._time(stamp_ns, topic, runners)
        if t is None:
            return []
        self.frame_id = self.frame_id or msg.frame_id
        values = np.concatenate([msg.position, msg.quaternion])
        fresh = self.pose_repeats.fresh(topic, stamp_ns, values, t, self.gaps.spacing_s * 1e9)
        self._count_repeats()
        out = []
        for k, (runner, source) in enumerate(pairs):
            # a pose received before and still in the joint's window (a looped replay): published, not added again
            # (it completes a pair only with its partner of the same stamp, which came round with it)
            runner.estimator.replayed = not fresh[k]
            try:
                result = _isolated(runner, self.on_joint_error, runner.pose, source, t, R, msg.position)
            finally:
                runner.estimator.replayed = False
            if result is not None:
                out.append(Routed(runner, stamp_ns, msg.frame_id, result))
        return out

    def _count_repeats(self) -> None:
        """``repeated_frames``: the marker frames and the poses some joint did not take again."""
        self.counters["repeated_frames"] = self.repeats.count + self.pose_repeats.count

    def _stamp(self, stamp_ns: int) -> int:
        """A message's stamp; exactly 0 (unset) is counted and, live, replaced by the :attr:`stamp_clock`'s time."""
        if stamp_ns != 0:
            return stamp_ns
        self.counters["zero_stamps"] += 1
        return stamp_ns if self.stamp_clock is None else int(self.stamp_clock())


def _note_dropped(runners: Iterable[JointRunner], n: int) -> None:
    """Tell the joints a message meant for them was dropped before it reached them (their status counts it)."""
    if n:
        for runner in runners:
            runner.note_dropped(n)

