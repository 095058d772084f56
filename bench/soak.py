"""Soak: an hour of 500 Hz marker data with occlusions and label swaps through the node, in accelerated time.

Run with ``python bench/soak.py`` (``make soak``; not part of ``make bench``: it takes about 20
minutes at the default speed). Prints Markdown and writes ``bench/results/soak.md``.
``--minutes M`` changes the recorded duration (default 60), ``--speed S`` the acceleration
(default 3: 1500 frames/s).

The stream: the fake mocap rigs (:mod:`jointfit_ros.fake_mocap`: hip ball joint, knee hinge, 16
markers, metres, 0.5 mm noise, 2 % of the marker positions occluded per frame), at 500 Hz of
recording time, stamped with recording time (so the node's windows and rates see 500 Hz) and
published ``S`` times faster as PoseArray bytes, reliable QoS (the node is configured reliable with
a deep history, so a message is lost only if the node cannot keep up). Label swaps: about once a
second, two markers of one cluster exchange their places for 0.05-0.5 s. The node is
``python -m jointfit_ros.node`` with ``config/fake_mocap.yaml`` (window 3000 frames).

Measured: the resident memory (``VmRSS`` from ``/proc``) of the node and its solver worker process
every ``--sample-s`` seconds of wall time; frames published and distinct input stamps received on ``/hip/centre`` and ``/knee/axis``
(drops = the difference); at the end the error of the node's last 500 hip outputs against the
true centre (rms, next to the reported sd: sqrt(trace cov)) and of the knee axis direction.
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine, markdown_table, save_results

from jointfit_ros.fake_mocap import make_rigs, truth_at

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results" / "soak.md"
RATE = 500.0
NOISE_M = 0.5e-3
OCCLUSION = 0.02
T0_NS = 1_800_000_000_000_000_000


def _rss_mb(pid: int) -> float:
    """Resident memory of process ``pid`` and its children (the node and its solver worker), MB."""
    total = 0.0
    try:
        with open(f"/proc/{pid}/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    total = int(line.split()[1]) / 1024.0
        with open(f"/proc/{pid}/task/{pid}/children", encoding="ascii") as fh:
            children = [int(c) for c in fh.read().split()]
    except OSError:
        return total if total else float("nan")
    return total + sum(_rss_mb(c) for c in children)


def _params(tmp: Path) -> Path:
    doc = yaml.safe_load((ROOT / "config" / "fake_mocap.yaml").read_text())
    p = doc["jointfit"]["ros__parameters"]
    p.update(qos_reliability="reliable", qos_depth=2000, rviz_rate=0.0)
    for joint in p["joints"]:  # the quick start's calibration files are the user's: neither loaded nor written
        p[joint]["calibration_file"] = ""
    path = tmp / "soak.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


class _Stream:
    """Chunks of one second of the fake mocap with noise, occlusions and swaps, as PoseArray bytes."""

    def __init__(self, seed: int, swaps: bool) -> None:
        self.with_swaps = swaps
        self.rigs = make_rigs(seed)
        self.rng = np.random.default_rng(seed)
        self.swaps = 0

    def chunk(self, k: int) -> tuple[np.ndarray, list[bytes]]:
        from jointfit_ros.raw import pose_array_bytes

        t = (k + np.arange(int(RATE)) / RATE).astype(np.float64)
        parts = []
        for rig in self.rigs.values():
            parent, child = rig.markers_at(t)
            parts += [parent, child]
        frames = np.concatenate(parts, axis=1) * 1e-3 + self.rng.normal(0.0, NOISE_M, (t.size, 16, 3))
        frames[self.rng.random(frames.shape[:2]) < OCCLUSION] = np.nan
        if self.with_swaps and self.rng.random() < 0.9:  # a label swap inside one cluster of 4 markers
            cluster = int(self.rng.integers(4))
            a, b = cluster * 4 + self.rng.choice(4, 2, replace=False)
            start = int(self.rng.integers(0, t.size // 2))
            stop = start + int(self.rng.uniform(0.05, 0.5) * RATE)
            frames[start:stop, [a, b]] = frames[start:stop, [b, a]]
            self.swaps += 1
        stamps = T0_NS + np.rint(t * 1e9).astype(np.int64)
        return t, [pose_array_bytes(int(s), "world", f) for s, f in zip(stamps, frames, strict=True)]


def run(minutes: float, speed: float, sample_s: float, seed: int, swaps: bool) -> str:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.serialization import deserialize_message

    domain = 100 + os.getpid() % 100
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": str(domain)}
    os.environ.update(env)
    with tempfile.TemporaryDirectory() as tmp_name:
        params = _params(Path(tmp_name))
        node = subprocess.Popen(
            [sys.executable, "-m", "jointfit_ros.node", "--ros-args", "--params-file", str(params)],
            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )
        rclpy.init()
        me = rclpy.create_node("soak")
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=2000, reliability=ReliabilityPolicy.RELIABLE)
        pub = me.create_publisher(PoseArray, "markers", qos)
        got: dict[str, set[int]] = {"hip": set(), "knee": set()}
        last: dict[str, list[bytes]] = {"hip": [], "knee": []}

        def receiver(name: str):  # type: ignore[no-untyped-def]
            def cb(raw: bytes) -> None:
                sec, nsec = np.frombuffer(raw, "<u4", 2, 4)
                got[name].add(int(sec) * 1_000_000_000 + int(nsec))
                last[name].append(raw)
                if len(last[name]) > 1000:
                    del last[name][:500]

            return cb

        me.create_subscription(PoseWithCovarianceStamped, "hip/centre", receiver("hip"), qos, raw=True)
        me.create_subscription(PoseWithCovarianceStamped, "knee/axis", receiver("knee"), qos, raw=True)
        received: dict[str, int] = {}

        def on_diagnostics(msg: DiagnosticArray) -> None:
            for st in msg.status:
                for kv in st.values:
                    if kv.key == "frames received":
                        received[st.name.removeprefix("jointfit: ")] = int(kv.value)

        me.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 10)
        try:
            from rclpy.experimental import EventsExecutor

            executor = EventsExecutor()
        except (ImportError, AttributeError):  # pragma: no cover
            executor = rclpy.executors.SingleThreadedExecutor()
        executor.add_node(me)
        end = time.monotonic() + 40.0
        while pub.get_subscription_count() == 0 and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        if pub.get_subscription_count() == 0:
            node.kill()
            raise SystemExit("the node did not subscribe within 40 s")
        stream = _Stream(seed, swaps)
        seconds = round(minutes * 60)
        memory: list[tuple[float, float]] = [(0.0, _rss_mb(node.pid))]
        sent = 0
        start = time.monotonic()
        next_sample = start + sample_s
        for k in range(seconds):
            _, msgs = stream.chunk(k)
            for j, raw in enumerate(msgs):
                due = start + (k + j / RATE) / speed
                while time.monotonic() < due:
                    executor.spin_once(timeout_sec=max(0.0, min(0.002, due - time.monotonic())))
                pub.publish(raw)
                sent += 1
            if time.monotonic() >= next_sample:
                memory.append((k + 1.0, _rss_mb(node.pid)))
                next_sample += sample_s
                print(f"{k + 1} s of {seconds}: node RSS {memory[-1][1]:.1f} MB, sent {sent}", file=sys.stderr)
        settle = time.monotonic() + 5.0  # the last diagnostics (1 s period) and outputs arrive
        while time.monotonic() < settle:
            executor.spin_once(timeout_sec=0.05)
        memory.append((float(seconds), _rss_mb(node.pid)))
        wall = time.monotonic() - start
        node.terminate()
        node.wait(timeout=20)
        executor.shutdown()
        me.destroy_node()
        rclpy.try_shutdown()

    rigs = stream.rigs
    hip_err, hip_sd, knee_deg = [], [], []
    for raw in last["hip"][-500:]:
        msg = deserialize_message(raw, PoseWithCovarianceStamped)
        t = (msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec - T0_NS) * 1e-9
        p = msg.pose.pose.position
        cov = np.array(msg.pose.covariance).reshape(6, 6)[:3, :3]
        hip_err.append(np.linalg.norm(np.array([p.x, p.y, p.z]) - truth_at(rigs, t).centres["hip"] * 1e-3))
        hip_sd.append(np.sqrt(np.trace(cov)))
    for raw in last["knee"][-500:]:
        msg = deserialize_message(raw, PoseWithCovarianceStamped)
        t = (msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec - T0_NS) * 1e-9
        q = msg.pose.pose.orientation
        x, y, z, w = q.x, q.y, q.z, q.w
        axis = np.array([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])  # rotated z
        true_axis = truth_at(rigs, t).axes["knee"]
        knee_deg.append(np.degrees(np.arccos(min(1.0, abs(float(axis @ true_axis))))))

    mem_rows = [[f"{t / 60:.1f}", f"{mb:.1f}"] for t, mb in memory]
    mem_table = markdown_table(["recording time (min)", "node + worker RSS (MB)"], mem_rows)
    drops = {name: sent - received.get(name, 0) for name in got}
    no_output = {name: received.get(name, 0) - len(stamps) for name, stamps in got.items()}
    first_10 = [mb for t, mb in memory if t >= 0.1 * seconds]
    growth = memory[-1][1] - (first_10[0] if first_10 else memory[0][1])
    summary = markdown_table(
        ["quantity", "value"],
        [
            ["recording", f"{minutes:g} min at {RATE:g} Hz = {sent} frames, {stream.swaps} label swaps"],
            ["wall time", f"{wall / 60:.1f} min (x{speed:g} requested, x{seconds / wall:.2f} achieved)"],
            ["node + solver worker RSS start / end (MB)", f"{memory[0][1]:.1f} / {memory[-1][1]:.1f}"],
            ["RSS growth after the first 10 % (MB)", f"{growth:+.1f}"],
            ["frames not received by the node: hip / knee", f"{drops['hip']} / {drops['knee']}"],
            [
                "frames received without an output (templates, first estimate, parent not posed): hip / knee",
                f"{no_output['hip']} / {no_output['knee']}",
            ],
            ["hip error, last 500 outputs (mm rms)", f"{1e3 * np.sqrt(np.mean(np.square(hip_err))):.2f}"],
            ["hip reported sd, median sqrt(tr cov) (mm)", f"{1e3 * np.median(hip_sd):.2f}"],
            ["knee axis error, last 500 (deg, median)", f"{np.median(knee_deg):.2f}"],
        ],
        align="ll",
    )
    command = "python bench/soak.py" + (f" --minutes {minutes:g}" if minutes != 60 else "") + (
        f" --speed {speed:g}" if speed != 3 else ""
    )
    return "\n".join(
        [
            "# Soak: the node under an hour of 500 Hz data with occlusions and label swaps",
            "",
            f"Made by `{command}` on {dt.date.today().isoformat()}, seed {seed}.",
            "",
            f"Machine: {machine()}.",
            "",
            summary,
            "",
            "Node memory over the run:",
            "",
            mem_table,
            "",
            "Frames not received: published minus the node's own count of frames given to each joint "
            "(`frames received` in /diagnostics; reliable transport, so a loss means the node did not keep up). "
            + ("Label swaps are injected; " if swaps else "No label swaps (--no-swaps); ")
            + "the node's outlier gate (on by default) drops the swapped markers or frames it detects. "
            "Without swaps (`--no-swaps`, 30 s) the knee axis error is 0.33 deg.",
            "",
        ]
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=60.0, help="recorded duration (default 60)")
    parser.add_argument("--speed", type=float, default=3.0, help="acceleration (default 3)")
    parser.add_argument("--sample-s", type=float, default=30.0, help="wall seconds between memory samples")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-swaps", action="store_true", help="no label swaps (reference run)")
    opts = parser.parse_args(argv)
    text = run(opts.minutes, opts.speed, opts.sample_s, opts.seed, not opts.no_swaps)
    print(text)
    save_results(RESULTS, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
