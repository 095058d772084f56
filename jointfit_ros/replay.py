"""``jointfit replay``: publish a rosbag2 recording's marker and pose topics into ROS 2, with their timing.

Usage::

    jointfit replay BAG [--rate R] [--loop] [--topics T ...] [--reliable]
                        [--start-delay S] [--wait-subscribers N] [--wait-timeout S]
                        [--ros-args ...]
    python -m jointfit_ros.replay BAG ...

A small ``ros2 bag play`` for the message types jointfit reads
(``geometry_msgs/msg/PoseArray``, ``sensor_msgs/msg/PointCloud2``,
``geometry_msgs/msg/PoseStamped``), that needs no rosbag2 install: the bag is
read with ``rosbags`` (:mod:`jointfit_ros.bag`) and every message is published
as the CDR bytes stored in the bag (``Publisher.publish(bytes)``), never
deserialized.

* **Topics**: the bag's names (``--ros-args -r /markers:=/mocap/markers``
  remaps them); by default every topic of a supported type that holds
  messages, or the ``--topics`` given.
* **Timing**: message k is published ``(log_k - log_0) / R`` seconds after
  the first, where ``log`` is the bag's log (receive) time; ``--rate 0`` or
  ``--rate max`` publishes as fast as possible. A late message is published
  at once, never skipped.
* **Header stamps are not rewritten**: the messages carry the stamps of the
  recording. The jointfit node matches and orders its inputs by header stamp,
  so its results do not depend on the replay rate as long as no message is
  lost (its output stamps are the recording's, not the wall clock's). With
  ``--loop`` the stamps jump back at each new pass; the node drops stamps that
  go backwards, so call its ``~/reset`` service between passes (or restart it).
* **QoS**: by default the sensor-data profile (best effort, keep last 5,
  volatile), like a mocap driver. ``--reliable`` publishes reliable, keep-all,
  volatile: the middleware resends what a reliable subscriber has not
  acknowledged, and the replay waits (up to 10 s) for every acknowledgement
  after the last message before it exits (a warning on stderr when some are
  missing). A best-effort subscriber is still served best effort.
* **Exact round trips** (every message reaches the subscriber) need: a
  reliable subscriber that exists before the first message
  (``--wait-subscribers``; durability is volatile), a history deep enough
  for the messages it has not taken yet (keep-all, or keep-last with a depth
  such as the node's ``qos_depth`` larger than any backlog: a keep-last
  reader drops the oldest unread message even when reliable), and a finite
  ``--rate``. At ``--rate max`` the whole bag arrives in a burst; a reader
  whose history is full rejects samples, which are resent only at the next
  heartbeat (Fast DDS: every 3 s) and may still be lost.
* **Output**: one line on stdout at the end (messages published, duration);
  errors as one line on stderr. Exit status 0 when done; 1 on a bad bag, a
  missing dependency or a timeout waiting for subscribers
  (``--wait-timeout``); 2 on bad arguments; 130 after Ctrl-C (or SIGTERM),
  which stops cleanly and still prints the summary.

ROS (``rclpy``, the message packages) is imported only by :func:`replay_main`
once the bag has been checked, so this module imports without ROS.
"""

from __future__ import annotations

import argparse
import importlib
import math
import signal
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NoReturn

from jointfit_core.errors import InputError, MissingDependencyError

from .bag import SUPPORTED_MSGTYPES, BagTopic, bag_topics, iter_bag_messages, select_topics, supported_topics

__all__ = ["parse_args", "replay_main", "main"]

PROG = "jointfit replay"
#: rosbag2 message type -> (Python module, class) of the rclpy message.
_MSG_CLASSES: dict[str, tuple[str, str]] = {
    "geometry_msgs/msg/PoseArray": ("geometry_msgs.msg", "PoseArray"),
    "sensor_msgs/msg/PointCloud2": ("sensor_msgs.msg", "PointCloud2"),
    "geometry_msgs/msg/PoseStamped": ("geometry_msgs.msg", "PoseStamped"),
}
_NS_PER_S = 1e9
_ACK_TIMEOUT_S = 10.0


class _UsageError(Exception):
    """Bad command-line arguments (one line)."""


class _WaitTimeoutError(Exception):
    """The subscribers did not appear in time (one line)."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        raise _UsageError(message)


def _rate(text: str) -> float:
    if text.strip().lower() in ("max", "inf"):
        return 0.0
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number >= 0 or 'max', got {text!r}") from None
    if math.isinf(value) and value > 0:
        return 0.0
    if not (math.isfinite(value) and value >= 0.0):
        raise argparse.ArgumentTypeError(f"expected a number >= 0 or 'max', got {text!r}")
    return value


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds >= 0, got {text!r}") from None
    if not (math.isfinite(value) and value >= 0.0):
        raise argparse.ArgumentTypeError(f"expected seconds >= 0, got {text!r}")
    return value


def _count(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}")
    return value


def _split_ros_args(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """(jointfit arguments, ``--ros-args ...`` part for rclpy) of a command line."""
    args = list(argv)
    if "--ros-args" in args:
        k = args.index("--ros-args")
        return args[:k], args[k:]
    return args, []


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """Options of ``jointfit replay`` (the module docstring says what they do).

    Parameters
    ----------
    argv : sequence of str, optional
        Arguments without the program name; default ``sys.argv[1:]``.
        Everything from ``--ros-args`` on goes to rclpy (``ros_args``).

    Returns
    -------
    argparse.Namespace
        ``bag`` (str), ``rate`` (float, 0 = as fast as possible), ``loop``
        (bool), ``topics`` (list of str or None), ``reliable`` (bool),
        ``start_delay`` (s), ``wait_subscribers`` (int), ``wait_timeout`` (s),
        ``ros_args`` (list of str).

    Raises
    ------
    _UsageError
        On bad arguments (one line, argparse's message).
    SystemExit
        For ``--help`` (code 0).
    """
    own, ros_args = _split_ros_args(sys.argv[1:] if argv is None else argv)
    parser = _Parser(
        prog=PROG,
        description="Publish the marker and pose topics of a rosbag2 bag (sqlite3 or mcap) into ROS 2, "
        "with the recorded timing and the original header stamps.",
        epilog="Arguments from --ros-args on go to rclpy, e.g. --ros-args -r /markers:=/mocap/markers.",
    )
    parser.add_argument("bag", help="bag directory (with metadata.yaml), or a .db3 / .mcap file")
    parser.add_argument(
        "--rate",
        type=_rate,
        default=1.0,
        metavar="R",
        help="speed factor: log-time gaps are divided by R; 0 or 'max': as fast as possible (default 1)",
    )
    parser.add_argument("--loop", action="store_true", help="start again at the end, until Ctrl-C")
    parser.add_argument(
        "--topics",
        nargs="+",
        metavar="T",
        help="topics to publish (default: every topic of a supported type that has messages)",
    )
    parser.add_argument(
        "--reliable",
        action="store_true",
        help="publish reliable, keep-all (default: best effort, keep last 5, the sensor-data profile)",
    )
    parser.add_argument(
        "--start-delay",
        type=_seconds,
        default=0.0,
        metavar="S",
        help="wait S seconds before the first message",
    )
    parser.add_argument(
        "--wait-subscribers",
        type=_count,
        default=0,
        metavar="N",
        help="before starting, wait until every topic has at least N subscribers (default 0: do not wait)",
    )
    parser.add_argument(
        "--wait-timeout",
        type=_seconds,
        default=10.0,
        metavar="S",
        help="give up (exit status 1) when the subscribers have not appeared after S seconds (default 10)",
    )
    opts = parser.parse_args(own)
    opts.ros_args = ros_args
    return opts


@dataclass
class _Tally:
    published: int = 0
    passes: int = 0
    first_wall: float | None = None
    last_wall: float | None = None
    span_ns: int = 0

    def summary(self, topics: Sequence[str], rate: float, interrupted: bool) -> str:
        wall = 0.0
        if self.first_wall is not None and self.last_wall is not None:
            wall = self.last_wall - self.first_wall
        speed = "as fast as possible" if rate == 0.0 else f"rate {rate:g}"
        text = (
            f"{PROG}: published {self.published} messages on {len(topics)} "
            f"topic{'s' if len(topics) != 1 else ''} in {wall:.3f} s "
            f"(bag span {self.span_ns / _NS_PER_S:.3f} s, {speed}"
        )
        if self.passes > 1:
            text += f", {self.passes} passes"
        return text + (", interrupted)" if interrupted else ")")


def _message_classes(msgtypes: dict[str, str]) -> dict[str, Any]:
    """Topic -> rclpy message class; :class:`MissingDependencyError` without the message packages."""
    out = {}
    for topic, msgtype in msgtypes.items():
        module, name = _MSG_CLASSES[msgtype]
        try:
            out[topic] = getattr(importlib.import_module(module), name)
        except ImportError:
            raise MissingDependencyError(
                f"publishing {msgtype} needs the ROS 2 message package {module.split('.')[0]} "
                "(source a ROS 2 Jazzy install, or pip install the ros-jazzy-common-interfaces wheels)"
            ) from None
    return out


def _wait_for_subscribers(pubs: dict[str, Any], n: int, timeout_s: float, context: Any) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        counts = {topic: pub.get_subscription_count() for topic, pub in pubs.items()}
        if all(c >= n for c in counts.values()):
            return
        if time.monotonic() >= deadline or not context.ok():
            have = ", ".join(f"{topic}: {c}" for topic, c in counts.items())
            raise _WaitTimeoutError(
                f"timed out after {timeout_s:g} s waiting for {n} subscriber(s) per topic (have {have})"
            )
        time.sleep(0.02)


def _play(
    bag: str, topics: list[str], pubs: dict[str, Any], opts: argparse.Namespace, tally: _Tally, context: Any
) -> None:
    """Publish the bag once or (``--loop``) until interrupted, updating ``tally`` as it goes."""
    rate_ns = opts.rate * _NS_PER_S  # bag ns per wall second
    pass_start = time.monotonic()
    while context.ok():
        first_log: int | None = None
        last_log = 0
        count = 0
        for msg in iter_bag_messages(bag, topics):
            if first_log is None:
                first_log = msg.log_time_ns
            if rate_ns > 0.0:
                target = pass_start + (msg.log_time_ns - first_log) / rate_ns
                delay = target - time.monotonic()
                if delay > 0.0:
                    time.sleep(delay)
            if not context.ok():
                return
            pubs[msg.topic].publish(msg.raw)
            now = time.monotonic()
            if tally.first_wall is None:
                tally.first_wall = now
            tally.last_wall = now
            tally.published += 1
            last_log = msg.log_time_ns
            count += 1
        tally.passes += 1
        if first_log is None:
            return
        tally.span_ns += last_log - first_log
        if not opts.loop:
            return
        # next pass: one mean message period after the last message of this one
        gap_ns = (last_log - first_log) / max(count - 1, 1)
        last_wall = tally.last_wall if tally.last_wall is not None else time.monotonic()
        pass_start = last_wall + (gap_ns / rate_ns if rate_ns > 0.0 else 0.0)


def _on_sigterm(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt  # SIGTERM stops like Ctrl-C


def replay_main(argv: Sequence[str] | None = None) -> int:
    """Run ``jointfit replay`` (see the module docstring).

    Parameters
    ----------
    argv : sequence of str, optional
        Arguments without the program name; default ``sys.argv[1:]``.

    Returns
    -------
    int
        Exit status: 0 done, 1 bad bag / missing dependency / subscriber
        timeout, 2 bad arguments, 130 interrupted (Ctrl-C or SIGTERM).
    """
    try:
        opts = parse_args(argv)
    except _UsageError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    except SystemExit as exc:  # --help
        return exc.code if isinstance(exc.code, int) else 0

    try:
        chosen = _choose_topics(opts.bag, opts.topics)
        return _run(opts, [t.name for t in chosen], {t.name: t.msgtype for t in chosen})
    except (InputError, MissingDependencyError, _WaitTimeoutError) as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # while the bag is being checked, before ROS starts
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130


def _choose_topics(bag: str, wanted: list[str] | None) -> list[BagTopic]:
    """The bag topics to publish: ``wanted`` (checked) or every supported topic with messages."""
    if wanted is None:
        wanted = supported_topics(bag)
        if not wanted:
            topics = bag_topics(bag).values()
            listing = ", ".join(f"{t.name} ({t.msgtype}, {t.count} messages)" for t in topics)
            raise InputError(
                f"{bag}: no messages of a supported type ({', '.join(SUPPORTED_MSGTYPES)}); "
                f"the bag has {listing or 'no topics'}"
            )
    return select_topics(bag, wanted)


def _run(opts: argparse.Namespace, topics: list[str], msgtypes: dict[str, str]) -> int:
    try:
        import rclpy
        from rclpy.duration import Duration
        from rclpy.node import Node
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    except ImportError:
        raise MissingDependencyError(
            "replaying a bag into ROS needs rclpy: source a ROS 2 Jazzy install "
            "(or pip install the ros-jazzy-rclpy wheels)"
        ) from None
    classes = _message_classes(msgtypes)
    if opts.reliable:
        qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
    else:
        qos = qos_profile_sensor_data

    in_main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _on_sigterm) if in_main else None
    context = rclpy.Context()
    tally = _Tally()
    interrupted = False
    node = None
    try:
        rclpy.init(args=[PROG, *opts.ros_args], context=context)
        node = Node("jointfit_replay", context=context, start_parameter_services=False)
        pubs = {topic: node.create_publisher(classes[topic], topic, qos) for topic in topics}
        if opts.wait_subscribers > 0:
            _wait_for_subscribers(pubs, opts.wait_subscribers, opts.wait_timeout, context)
        if opts.start_delay > 0.0:
            time.sleep(opts.start_delay)
        _play(opts.bag, topics, pubs, opts, tally, context)
        if opts.reliable:  # let the middleware repair what a subscriber has not acknowledged yet
            unacked = [
                topic
                for topic, pub in pubs.items()
                if not pub.wait_for_all_acked(Duration(seconds=_ACK_TIMEOUT_S))
            ]
            if unacked:
                print(
                    f"{PROG}: warning: not every reliable subscriber acknowledged every message within "
                    f"{_ACK_TIMEOUT_S:g} s after the last one ({', '.join(unacked)}); some may be lost",
                    file=sys.stderr,
                )
    except KeyboardInterrupt:
        interrupted = True
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown(context=context)
        if in_main:
            signal.signal(signal.SIGTERM, previous)
    print(tally.summary(topics, opts.rate, interrupted), flush=True)
    return 130 if interrupted else 0


def main(argv: Sequence[str] | None = None) -> None:
    """Console entry point: :func:`replay_main`, then exit with its status."""
    sys.exit(replay_main(argv))


if __name__ == "__main__":
    main()
