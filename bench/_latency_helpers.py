"""Child processes of ``bench/node_latency.py``: the marker publisher, the pass-through relay, the measurer.

Run as ``python bench/_latency_helpers.py ROLE ...`` (one process per role; ``make bench`` skips
files starting with ``_``). Each role talks to the benchmark over stdin/stdout, one line per
event, so the benchmark sees what its children do without ROS itself:

``publish``
    Publishes ``geometry_msgs/PoseArray`` CDR bytes (40 markers of the fake mocap rigs, metres,
    :func:`jointfit_ros.conversions.pose_array_bytes` built once, the stamp patched in place) with
    ``header.stamp`` = the wall-clock send time (``time.time_ns()``, the ROS system clock),
    strictly increasing. Warm-up frames at ``--warm-rate`` until the line ``go`` arrives on stdin;
    then, for each rate, a pause (no frames), ``start RATE``, ``--seconds`` of frames, ``end RATE N``.
    Writes the stamps sent in each timed phase to ``--out`` (``.npz``) and prints ``done``.
    Frames are paced by ``time.sleep`` to a fixed schedule; a frame more than two periods late
    restarts the schedule instead of catching up in a burst (counted as ``resyncs``).
``relay``
    Subscribes ``raw=True`` to the marker topic (best effort, depth 10, like the node's default
    input) and republishes the same bytes on ``relay/markers`` (reliable, depth 10, like the node's
    outputs), spun like the node: ``EventsExecutor.spin_once(timeout_sec=0.1)`` in a loop.
``measure``
    Subscribes ``raw=True`` to the given topics (``TOPIC:reliable`` or ``TOPIC:best_effort``),
    records (input stamp, wall-clock receive time) per message, prints ``first TOPIC`` when a topic
    delivers its first message; on ``dump PATH`` writes the records to ``PATH`` (``.npz``) and exits.
"""

from __future__ import annotations

import argparse
import struct
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

#: Extra static markers padding the 16 rig markers to 40.
EXTRA_MARKERS = 24
#: Motion time between consecutive frames of the pool (s): the rigs move as in a 100 Hz capture.
MOTION_STEP_S = 0.01
#: Frames in the pool, cycled (60 s of motion, three 20 s cycles).
POOL_FRAMES = 6000
NOISE_MM = 0.5
RELAY_TOPIC = "relay/markers"
_STAMP = struct.Struct("<iI")  # header.stamp after the 4-byte encapsulation header (little-endian CDR)


def _say(text: str) -> None:
    print(text, flush=True)


def _stdin_lines(handler: Any) -> threading.Thread:
    """Feed every stdin line to ``handler`` from a daemon thread."""

    def run() -> None:
        for line in sys.stdin:
            handler(line.strip())
        handler("eof")

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def _events_executor() -> Any:
    import rclpy

    try:
        from rclpy.experimental import EventsExecutor

        return EventsExecutor()
    except (ImportError, AttributeError, RuntimeError):  # pragma: no cover - other rclpy versions
        return rclpy.executors.SingleThreadedExecutor()


def frame_pool(seed: int = 0) -> list[bytearray]:
    """CDR bytes of ``POOL_FRAMES`` PoseArray frames of the fake mocap (40 markers, m), stamp 0."""
    from jointfit_ros.conversions import pose_array_bytes
    from jointfit_ros.fake_mocap import extra_marker_positions, make_rigs

    rigs = make_rigs(seed)
    t = np.arange(POOL_FRAMES) * MOTION_STEP_S
    parts = []
    for rig in rigs.values():
        parent, child = rig.markers_at(t)
        parts += [parent, child]
    extra = extra_marker_positions(EXTRA_MARKERS, seed)
    parts.append(np.broadcast_to(extra, (POOL_FRAMES, *extra.shape)))
    frames = np.concatenate(parts, axis=1)
    frames = frames + np.random.default_rng([seed, 2]).normal(0.0, NOISE_MM, frames.shape)
    return [bytearray(pose_array_bytes(0, "world", f * 1e-3)) for f in frames]


def run_publisher(opts: argparse.Namespace) -> int:
    import rclpy
    from geometry_msgs.msg import PoseArray
    from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

    pool = frame_pool(opts.seed)
    rclpy.init()
    node = rclpy.create_node("latency_publisher")
    qos = (
        qos_profile_sensor_data
        if opts.qos == "best_effort"
        else QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    )
    pub = node.create_publisher(PoseArray, opts.topic, qos)
    go = threading.Event()
    _stdin_lines(lambda line: go.set() if line in ("go", "eof") else None)
    state = {"k": 0, "last": 0}

    def send() -> int:
        stamp = max(time.time_ns(), state["last"] + 1)
        state["last"] = stamp
        buf = pool[state["k"] % len(pool)]
        state["k"] += 1
        _STAMP.pack_into(buf, 4, *divmod(stamp, 1_000_000_000))
        pub.publish(bytes(buf))
        return stamp

    def paced(rate: float, seconds: float | None, until: threading.Event | None) -> tuple[list[int], int]:
        period = round(1e9 / rate)
        stamps: list[int] = []
        resyncs = 0
        start = time.perf_counter_ns()
        k = 0
        end = None if seconds is None else start + round(seconds * 1e9)
        while True:
            target = start + k * period
            if end is not None and target >= end:
                break
            if until is not None and until.is_set():
                break
            now = time.perf_counter_ns()
            if target > now:
                time.sleep((target - now) / 1e9)
            elif now - target > 2 * period:  # descheduled: restart the schedule, no burst
                start, k, resyncs = now, 0, resyncs + 1
                if end is not None and now >= end:
                    break
            stamps.append(send())
            k += 1
        return stamps, resyncs

    try:
        paced(opts.warm_rate, None, go)
        sent: dict[str, Any] = {}
        for rate in opts.rates:
            time.sleep(opts.pause)
            _say(f"start {rate:g}")
            t0 = time.perf_counter()
            stamps, resyncs = paced(rate, opts.seconds, None)
            elapsed = time.perf_counter() - t0
            _say(f"end {rate:g} {len(stamps)} {elapsed:.3f} {resyncs}")
            sent[f"stamps_{rate:g}"] = np.asarray(stamps, dtype=np.int64)
            sent[f"elapsed_{rate:g}"] = np.float64(elapsed)
            sent[f"resyncs_{rate:g}"] = np.int64(resyncs)
        np.savez(opts.out, **sent)
        _say("done")
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def run_relay(opts: argparse.Namespace) -> int:
    import rclpy
    from geometry_msgs.msg import PoseArray
    from rclpy.executors import ExternalShutdownException
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    rclpy.init()
    node = rclpy.create_node("latency_relay")
    try:
        qos_in = QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.BEST_EFFORT
        )
        pub = node.create_publisher(PoseArray, RELAY_TOPIC, 10)
        node.create_subscription(PoseArray, opts.topic, pub.publish, qos_in, raw=True)
        executor = _events_executor()
        executor.add_node(node)
        _say("ready")
        while rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def run_measure(opts: argparse.Namespace) -> int:
    import rclpy
    from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    types = {"pose_array": PoseArray, "pose_cov": PoseWithCovarianceStamped}
    rclpy.init()
    node = rclpy.create_node("latency_measure")
    stop = threading.Event()
    dump_to: list[str] = []

    def on_line(line: str) -> None:
        if line.startswith("dump "):
            dump_to.append(line[5:])
            stop.set()
        elif line == "eof":
            stop.set()

    records: dict[str, tuple[list[int], list[int]]] = {}
    try:
        for spec in opts.topics:
            topic, kind, reliability = spec.split(":")
            stamps: list[int] = []
            recv: list[int] = []
            records[topic] = (stamps, recv)
            qos = QoSProfile(
                history=HistoryPolicy.KEEP_LAST,
                depth=1000,
                reliability=ReliabilityPolicy.RELIABLE
                if reliability == "reliable"
                else ReliabilityPolicy.BEST_EFFORT,
            )

            def callback(
                raw: bytes, topic: str = topic, stamps: list[int] = stamps, recv: list[int] = recv
            ) -> None:
                now = time.time_ns()
                sec, nsec = _STAMP.unpack_from(raw, 4)
                if not stamps:
                    _say(f"first {topic}")
                stamps.append(sec * 1_000_000_000 + nsec)
                recv.append(now)

            node.create_subscription(types[kind], topic, callback, qos, raw=True)
        executor = _events_executor()
        executor.add_node(node)
        _stdin_lines(on_line)
        _say("ready")
        while rclpy.ok() and not stop.is_set():
            executor.spin_once(timeout_sec=0.1)
        if dump_to:
            out = {}
            for i, (stamps, recv) in enumerate(records.values()):
                out[f"stamp_{i}"] = np.asarray(stamps, dtype=np.int64)
                out[f"recv_{i}"] = np.asarray(recv, dtype=np.int64)
            np.savez(dump_to[0], **out)
            _say("dumped")
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="_latency_helpers.py")
    sub = p.add_subparsers(dest="role", required=True)
    pp = sub.add_parser("publish")
    pp.add_argument("--rates", type=float, nargs="+", required=True)
    pp.add_argument("--seconds", type=float, default=5.0)
    pp.add_argument("--pause", type=float, default=1.0)
    pp.add_argument("--warm-rate", type=float, default=200.0)
    pp.add_argument("--topic", default="markers")
    pp.add_argument("--qos", choices=("best_effort", "reliable"), default="best_effort")
    pp.add_argument("--seed", type=int, default=0)
    pp.add_argument("--out", required=True)
    pr = sub.add_parser("relay")
    pr.add_argument("--topic", default="markers")
    pm = sub.add_parser("measure")
    pm.add_argument("topics", nargs="+", help="TOPIC:pose_array|pose_cov:reliable|best_effort")
    opts = p.parse_args(argv)
    return {"publish": run_publisher, "relay": run_relay, "measure": run_measure}[opts.role](opts)


if __name__ == "__main__":
    sys.exit(main())
