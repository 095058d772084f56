"""The node's ``<node>: input`` diagnostics status: counters, stamps, recent activity, frames missed.

Pure Python (no rclpy), so that it is tested without ROS: :class:`InputStatus`
keeps what the status needs between two diagnostics ticks (the input's
activity samples and the recent stamp-gap counts) and turns the message
router's counters and stamp gaps into a level, a message and the status's
values; the node adds its own values (graph problems, unexpected errors) and
publishes it with the joints' statuses.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from typing import Any

from .activity import InputActivity
from .frame_load import BUSY_LIMIT, FrameLoad
from .joint_diagnostics import OK, STALE, WARN
from .params import NodeConfig

__all__ = ["MISSED_WARN_MIN", "MISSED_WARN_SHARE", "MISSED_WINDOW_S", "InputStatus"]

#: The input status warns when, over the last :data:`MISSED_WINDOW_S` seconds (at least ``stale_after``),
#: at least this many frames of the marker stream never arrived and they are more than
#: :data:`MISSED_WARN_SHARE` of the stream's frames.
MISSED_WARN_MIN = 10
MISSED_WARN_SHARE = 0.05
MISSED_WINDOW_S = 5.0
#: Counters of messages dropped whole (each is a reason the input status gives).
_DROPPED = ("malformed", "wrong_frame_id", "invalid_stamps", "stamps_ahead", "oversized_clouds", "second_publisher")
#: Counters that make the input status WARN by themselves.
_PROBLEMS = ("malformed", "label_problems", "wrong_frame_id", "oversized_clouds", "second_publisher")


class InputStatus:
    """What the input status keeps between diagnostics ticks, and the status itself (:meth:`status`)."""

    def __init__(self) -> None:
        self._samples: InputActivity | None = None  # the input's activity samples (made at the first tick)
        self._gaps: deque[tuple[float, int, int]] = deque()  # (tick time, frames received, frames missed)

    def status(
        self,
        now: float,
        counters: dict[str, int],
        gaps: Any,
        cfg: NodeConfig,
        values: dict[str, object],
        incompatible: Mapping[str, str] | None = None,
        load: FrameLoad | None = None,
    ) -> tuple[int, str]:
        """The input status's level and message at ``now`` (monotonic s); adds its values to ``values``.

        Parameters
        ----------
        now : float
            Monotonic seconds of this tick.
        counters : dict
            The message router's counters (:attr:`~jointfit_ros.inputs.MessageRouter.counters`).
        gaps : StampGaps
            The router's stamp gaps (frames received and missed; :mod:`jointfit_ros.stamp_gaps`).
        cfg : NodeConfig
            The node's parameters (topic, frame id, ``stale_after``).
        values : dict
            The status's key-value pairs; the counters, the input rate and the frames missed are added.
        incompatible : mapping of str to str, optional
            Input topics with publishers whose QoS their subscription cannot take: the last policy that
            did not match (:attr:`~jointfit_ros.inputs.MessageRouter.incompatible`).
        load : FrameLoad, optional
            The node's input callbacks' times: frames that never arrived are blamed on the node when it
            was busy with frames :data:`~jointfit_ros.frame_load.BUSY_LIMIT` of its time or more, else
            on the network or the driver (without it, on either).

        Returns
        -------
        (int, str)
            OK, WARN (dropped or missed messages, bad stamps, every message since the previous tick
            dropped) or STALE (nothing for ``stale_after`` seconds), and the message.
        """
        c = counters
        values.update({
            "messages": c["messages"],
            "malformed messages": c["malformed"],
            "messages from another frame_id": c["wrong_frame_id"],
            "messages with label problems": c["label_problems"],
            "unassigned markers (unlabelled clouds)": c["unassigned"],
            "oversized clouds dropped": c["oversized_clouds"],
            "frames held back: a second publisher": c["second_publisher"],
            "markers at exactly (0, 0, 0) (zero_is_missing false)": c["zero_markers"],
            "messages with header.stamp 0 (arrival time used)": c["zero_stamps"],
            "publishers not matched: incompatible QoS": c["incompatible_qos"],
        })
        level = WARN if any(c[k] for k in _PROBLEMS) else OK
        message = "receiving" if c["messages"] else f"waiting for {cfg.marker_topic}"
        if c["malformed"]:
            message += f"; {c['malformed']} malformed messages dropped"
        if c["wrong_frame_id"]:
            message += f"; {c['wrong_frame_id']} messages from a frame_id other than {cfg.input_frame_id!r} dropped"
        if c["zero_markers"]:
            level = max(level, WARN)
            message += (
                f"; {c['zero_markers']} markers at exactly (0, 0, 0) taken as positions (zero_is_missing is false): "
                "if the driver sends occluded markers as zeros, set zero_is_missing: true"
            )
        if c["incompatible_qos"]:
            level = max(level, WARN)
            for topic, policy in sorted((incompatible or {}).items()):
                message += (
                    f"; a publisher on {topic} offers a QoS this node's subscription cannot take ({policy} policy; "
                    f"qos_reliability is {cfg.qos_reliability}): none of its messages arrive"
                )
        if c["zero_stamps"]:
            level = max(level, WARN)
            message += (
                f"; {c['zero_stamps']} messages with header.stamp 0 (not set by the publisher): their arrival time "
                "is used, so transport delays enter the time windows and the outputs' stamps; stamp the messages "
                "at capture"
            )
        if c["second_publisher"]:
            message += (
                f"; {c['second_publisher']} frames held back while a second publisher was on the topic (two streams "
                "interleaving, or a copy of each frame): not given to the joints"
            )
        values["messages with an invalid stamp"] = c["invalid_stamps"]
        values["messages stamped too far ahead (max_stamp_jump)"] = c["stamps_ahead"]
        values["timeline restarts"] = c["timeline_restarts"]
        values["frames received again (not added to the windows)"] = c["repeated_frames"]
        dropped = {k: c[k] for k in _DROPPED}
        if self._samples is None:
            self._samples = InputActivity(cfg.stale_after)
        samples = self._samples
        samples.window_s = cfg.stale_after
        act = samples.sample(now, c["messages"], c["messages"] - sum(dropped.values()), dropped)
        if act.rate_hz is not None:
            values["input rate (Hz)"] = round(act.rate_hz, 1)
        if c["stamps_ahead"] or c["invalid_stamps"]:
            level = max(level, WARN)
            message += f"; {c['stamps_ahead'] + c['invalid_stamps']} messages with bad stamps dropped"
        if c["timeline_restarts"]:
            message += f"; the stamps restarted {c['timeline_restarts']} times (looped or restarted recording)"
        if c["repeated_frames"]:
            message += (
                f"; {c['repeated_frames']} frames received again (a looped replay: the same stamps and markers), "
                "published but not added to the windows again"
            )
        level, message = self._missed(now, gaps, cfg, level, message, values, load)
        if act.silent_s is not None and act.silent_s >= cfg.stale_after:
            return STALE, f"no messages for {act.silent_s:.1f} s; {message}"
        if act.all_dropped:
            return max(level, WARN), f"{act.dropped_text('messages')}; {message}"
        return level, message

    def _missed(
        self,
        now: float,
        gaps: Any,
        cfg: NodeConfig,
        level: int,
        message: str,
        values: dict[str, object],
        load: FrameLoad | None,
    ) -> tuple[int, str]:
        """Frames that never arrived (gaps in the stamps), over the last few seconds: a burst lost in one
        stall of the source or the node is not a loss rate. Whose they are: the node's when it was busy."""
        values["frames missed (gaps in the stamps)"] = gaps.missed
        window = max(MISSED_WINDOW_S, cfg.stale_after)
        history = self._gaps
        history.append((now, gaps.received, gaps.missed))
        while len(history) > 2 and history[1][0] <= now - window:
            history.popleft()
        per_frame, busy = (None, None) if load is None else load.sample(now, window)
        if per_frame is not None:
            values["time per input message in the node (ms)"] = round(1e3 * per_frame, 3)
        if busy is not None:
            values["node busy with input messages (%)"] = round(100.0 * busy, 1)
        received, missed = gaps.received - history[0][1], gaps.missed - history[0][2]
        if received + missed:
            values["frames missed, recent (%)"] = round(100.0 * missed / (received + missed), 2)
        if missed >= MISSED_WARN_MIN and missed > MISSED_WARN_SHARE * (received + missed):
            level = max(level, WARN)
            message += (
                f"; {missed} of the last {received + missed} frames never arrived (gaps in the stamps of the "
                f"{1.0 / gaps.period_s:.0f} Hz stream): " + _whose(per_frame, busy, gaps.period_s, len(cfg.joints))
            )
        return level, message


def _whose(per_frame: float | None, busy: float | None, period_s: float, joints: int) -> str:
    """Words for who lost the frames that never arrived: the node (busy), the network or driver (not), or either."""
    if per_frame is None or busy is None:
        return "the node is not keeping up, or the network or the driver drops them"
    if busy >= BUSY_LIMIT:
        return (
            f"the node is not keeping up: a message takes it {1e3 * per_frame:.2f} ms ({joints} joints) and the "
            f"stream sends one every {1e3 * period_s:.2f} ms (busy {100.0 * busy:.0f} % of the time); a node uses one "
            "core: give part of the joints to a second node (its own name and parameter file) if a core is free, or "
            "lower the capture rate"
        )
    return (
        f"the node had time for them (busy with messages {100.0 * busy:.0f} % of the time, {1e3 * per_frame:.2f} ms "
        "each): the network or the driver drops them"
    )
