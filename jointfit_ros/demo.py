"""Live demo: the fake mocap and the node as separate processes, the estimate converging on the truth.

Run with ``make demo`` (or ``python -m jointfit_ros.demo [--duration 20] [--out DIR]``). It starts
``jointfit_fake_mocap`` (a ball-joint hip and a hinge knee with known truth, 200 Hz, 0.5 mm noise,
2 % occlusions) and ``jointfit_node`` with ``config/fake_mocap.yaml``, listens to both, prints every
two seconds the error of the node's per-frame outputs against the truth next to the uncertainty the
node reports, and writes a PNG of both over time. ROS traffic stays on this machine
(``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, a domain id of its own).
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["main"]

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "config" / "fake_mocap.yaml"


@dataclass
class _Series:
    """Per-output samples: time since start (s), error and reported sd."""

    t: list[float] = field(default_factory=list)
    err: list[float] = field(default_factory=list)
    sd: list[float] = field(default_factory=list)
    e3: list[float] = field(default_factory=list)
    t_local: list[float] = field(default_factory=list)
    sd_local: list[float] = field(default_factory=list)


def _env(domain: int) -> dict[str, str]:
    return {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": str(domain)}


def _stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _rolling_rms(values: list[float], k: int) -> np.ndarray:
    """Root mean square of the last ``k`` values at every index."""
    c = np.concatenate([[0.0], np.cumsum(np.square(values))])
    idx = np.arange(1, len(values) + 1)
    lo = np.maximum(idx - k, 0)
    out: np.ndarray = np.sqrt((c[idx] - c[lo]) / (idx - lo))
    return out


def _plot(series: dict[str, _Series], path: Path) -> bool:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not installed: no plot written")
        return False
    fig, axes = plt.subplots(2, 1, figsize=(8, 6.5), sharex=True)
    labels = {"hip": ("hip centre (ball)", "mm"), "knee": ("knee axis direction (hinge)", "deg")}
    for ax, (name, s) in zip(axes, series.items(), strict=True):
        title, unit = labels[name]
        t = np.asarray(s.t)
        ax.plot(t, s.err, ".", ms=1.5, alpha=0.3, color="tab:blue", label="error of each output")
        k = 100
        ax.plot(t, _rolling_rms(s.err, k), color="tab:blue", lw=1.5, label=f"rms error (last {k} outputs)")
        ax.plot(t, _rolling_rms(s.sd, k), color="tab:orange", lw=1.5, label=f"rms reported sd (last {k} outputs)")
        ax.plot(s.t_local, s.sd_local, color="tab:green", lw=1.5, label="reported sd of the estimate (parent frame)")
        ax.set_ylabel(f"{title} [{unit}]")
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("time since the node started [s]")
    fig.suptitle("jointfit live demo: per-frame outputs against the truth")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


def main(argv: Sequence[str] | None = None) -> int:
    """Run the demo; returns a process exit code (0 when the estimates converged)."""
    ap = argparse.ArgumentParser(prog="python -m jointfit_ros.demo", description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=20.0, help="seconds of streaming (default 20)")
    ap.add_argument("--out", type=Path, default=ROOT / "demo_output", help="directory of the PNG")
    ap.add_argument("--domain", type=int, default=57 + os.getpid() % 40, help="ROS_DOMAIN_ID to use")
    opts = ap.parse_args(argv)
    os.environ.update(_env(opts.domain))

    import rclpy
    from geometry_msgs.msg import PointStamped, PoseWithCovarianceStamped, Vector3Stamped
    from rclpy.node import Node

    env = _env(opts.domain)
    mocap = subprocess.Popen(
        [sys.executable, "-m", "jointfit_ros.fake_mocap", "--rate", "200", "--duration", str(opts.duration + 8)],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    opts.out.mkdir(parents=True, exist_ok=True)
    override = opts.out / "demo_params_override.yaml"  # the demo starts from scratch: no calibration files
    override.write_text(
        "jointfit:\n  ros__parameters:\n    hip: {calibration_file: ''}\n    knee: {calibration_file: ''}\n",
        encoding="utf-8",
    )
    node_proc = subprocess.Popen(
        [sys.executable, "-m", "jointfit_ros.node", "--ros-args", "--params-file", str(CONFIG),
         "--params-file", str(override)],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.STDOUT,
    )
    rclpy.init()
    listener = Node("jointfit_demo")
    truth_c: dict[int, np.ndarray] = {}
    truth_a: dict[int, np.ndarray] = {}
    series = {"hip": _Series(), "knee": _Series()}
    start = time.monotonic()

    def key(msg: object) -> int:
        st = msg.header.stamp  # type: ignore[attr-defined]
        return int(st.sec) * 1_000_000_000 + int(st.nanosec)

    def on_truth_hip(msg: PointStamped) -> None:
        truth_c[key(msg)] = np.array([msg.point.x, msg.point.y, msg.point.z])

    def on_truth_knee(msg: Vector3Stamped) -> None:
        truth_a[key(msg)] = np.array([msg.vector.x, msg.vector.y, msg.vector.z])

    pending: list[tuple[str, PoseWithCovarianceStamped]] = []
    listener.create_subscription(PointStamped, "truth/hip/centre", on_truth_hip, 1000)
    listener.create_subscription(Vector3Stamped, "truth/knee/axis", on_truth_knee, 1000)
    listener.create_subscription(PoseWithCovarianceStamped, "hip/centre", lambda m: pending.append(("hip", m)), 1000)
    listener.create_subscription(PoseWithCovarianceStamped, "knee/axis", lambda m: pending.append(("knee", m)), 1000)

    def on_local(name: str, msg: PoseWithCovarianceStamped) -> None:
        cov6 = np.array(msg.pose.covariance).reshape(6, 6)
        s = series[name]
        s.t_local.append(time.monotonic() - start)
        if name == "hip":
            s.sd_local.append(float(np.sqrt(np.trace(cov6[:3, :3])) * 1000.0))
        else:
            s.sd_local.append(float(np.degrees(np.sqrt(cov6[3, 3] + cov6[4, 4]))))

    listener.create_subscription(PoseWithCovarianceStamped, "hip/centre_local", lambda m: on_local("hip", m), 100)
    listener.create_subscription(PoseWithCovarianceStamped, "knee/axis_local", lambda m: on_local("knee", m), 100)

    from jointfit_ros.conversions import rotation_matrix_from_quaternion

    def consume() -> None:
        keep = []
        for name, msg in pending:
            k = key(msg)
            cov6 = np.array(msg.pose.covariance).reshape(6, 6)
            s = series[name]
            if name == "hip":
                if k not in truth_c:
                    keep.append((name, msg))
                    continue
                p = msg.pose.pose.position
                e = (np.array([p.x, p.y, p.z]) - truth_c[k]) * 1000.0
                cov = cov6[:3, :3] * 1e6
                s.err.append(float(np.linalg.norm(e)))
                s.sd.append(float(np.sqrt(np.trace(cov))))
                s.e3.append(float(e @ np.linalg.solve(cov, e)) / 3.0)
            else:
                if k not in truth_a:
                    keep.append((name, msg))
                    continue
                q = msg.pose.pose.orientation
                n = rotation_matrix_from_quaternion([q.x, q.y, q.z, q.w])[:, 2]
                angle = float(np.degrees(np.arccos(np.clip(abs(n @ truth_a[k]), -1.0, 1.0))))
                s.err.append(angle)
                s.sd.append(float(np.degrees(np.sqrt(cov6[3, 3] + cov6[4, 4]))))
            s.t.append(time.monotonic() - start)
        pending[:] = keep[-2000:]

    print(f"jointfit demo: fake mocap (hip ball + knee hinge, 200 Hz) and the node for {opts.duration:g} s")
    print(
        "Per-frame outputs (world, carried by this frame's parent pose) against the truth: rms error over the last "
        "200 outputs, the sd the node reports for them, mean e/3 (1 = honest); and the sd of the estimate itself "
        "(parent frame, <joint>/*_local), which shrinks as frames accumulate."
    )
    print(
        f"{'t [s]':>6} {'hip err [mm]':>13} {'hip sd [mm]':>12} {'hip e/3':>8} {'estimate sd':>12} "
        f"{'knee err [deg]':>15} {'knee sd [deg]':>14} {'estimate sd':>12}"
    )
    next_print = 1.0
    try:
        while time.monotonic() - start < opts.duration + 4.0:
            rclpy.spin_once(listener, timeout_sec=0.01)
            consume()
            now = time.monotonic() - start
            if now >= next_print:
                next_print += 1.0 if now < 6.0 else 2.0
                h, kn = series["hip"], series["knee"]
                if h.err and kn.err:
                    n = 200
                    hl = f"{h.sd_local[-1]:12.3f}" if h.sd_local else f"{'-':>12}"
                    kl = f"{kn.sd_local[-1]:12.4f}" if kn.sd_local else f"{'-':>12}"
                    print(
                        f"{now:6.1f} {np.sqrt(np.mean(np.square(h.err[-n:]))):13.2f} {np.median(h.sd[-n:]):12.2f} "
                        f"{np.mean(h.e3[-n:]):8.2f} {hl} {np.sqrt(np.mean(np.square(kn.err[-n:]))):15.3f} "
                        f"{np.median(kn.sd[-n:]):14.3f} {kl}"
                    )
                else:
                    print(f"{now:6.1f} waiting for the node's first estimates (discovery, templates) ...")
                if now > opts.duration + 2.0:
                    break
    finally:
        listener.destroy_node()
        rclpy.try_shutdown()
        _stop(node_proc)
        _stop(mocap)
    h, kn = series["hip"], series["knee"]
    if not h.err or not kn.err:
        print("no estimates received: is something else using this ROS_DOMAIN_ID? (try --domain N)")
        return 1
    png = opts.out / "jointfit_demo.png"
    if _plot(series, png):
        print(f"plot: {png}")
    hip_rms = float(np.sqrt(np.mean(np.square(h.err[-500:]))))
    knee_rms = float(np.sqrt(np.mean(np.square(kn.err[-500:]))))
    print(
        f"last 500 outputs: hip rms error {hip_rms:.2f} mm (reported sd {np.median(h.sd[-500:]):.2f} mm, "
        f"mean e/3 {np.mean(h.e3[-500:]):.2f}); knee axis rms error {knee_rms:.3f} deg "
        f"(reported sd {np.median(kn.sd[-500:]):.3f} deg); {len(h.err)} + {len(kn.err)} outputs checked"
    )
    return 0 if hip_rms < 10.0 and knee_rms < 5.0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
