"""Input-to-output latency and drops of the jointfit node at 100, 500 and 1000 Hz, against a relay.

Run with ``python bench/node_latency.py`` (from the repository root); prints Markdown and writes
``bench/results/node_latency.md``. Takes about 2 minutes. Every number comes from this run on
this machine; the header names the machine and the load on it.

What is measured
----------------
A marker stream of 40 markers (the two rigs of :mod:`jointfit_ros.fake_mocap`, a ball-joint hip
and a hinge knee, 16 markers, plus 24 static ``EXTRA`` markers; metres, 0.5 mm noise, no
occlusions so that every input frame has an output) is published as ``geometry_msgs/PoseArray``
CDR bytes, best-effort QoS (sensor data, as a mocap driver), at 100, 500 and 1000 Hz for
``SECONDS`` each, with ``header.stamp`` = the wall-clock send time (ns, strictly increasing).
Three systems under test, one after the other, each with fresh processes (direct once, then
relay, node, relay, node: ``ROUNDS`` alternating rounds, so that a change of the background
load during the run falls on both; the summary pools the rounds and shows the ratio per round):

* **direct**: no node; the measuring process subscribes to the marker topic itself. One hop:
  the floor of a bare rclpy subscriber.
* **relay**: a minimal rclpy node (``bench/_latency_helpers.py relay``) subscribing ``raw=True``
  to the markers and republishing the same bytes, spun like the jointfit node
  (``EventsExecutor.spin_once(timeout_sec=0.1)`` in a loop, same input QoS). Two hops.
* **node**: ``python -m jointfit_ros.node`` with ``config/fake_mocap.yaml`` extended by the 24
  extra marker names (hip ball, knee hinge, window 3000, estimate every 0.1 s in its solver worker
  process, local outputs at 10 Hz and RViz markers at 5 Hz as configured). Its per-frame outputs ``/hip/centre`` and
  ``/knee/axis`` carry the input stamp. Two hops plus the node's work.

Processes: the publisher, the system under test and the measuring process are three separate
processes (``bench/_latency_helpers.py``), so neither publishing nor receiving shares an
interpreter (and a GIL) with the system under test, and the receive time is taken in a process
that does nothing else; the relay's and the node's numbers contain the same publisher and
measurer, so their ratio isolates the node's work. All processes get
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` and ``ROS_DOMAIN_ID`` = 100 + pid % 100.

Sequence per system: start it, start the measurer and the publisher; the publisher sends
warm-up frames at ``WARM_RATE`` Hz until the measurer has received on every output topic
(discovery, and for the node its segment templates and first estimate), then ``SETTLE_S`` more;
then for each rate a ``PAUSE_S`` pause without frames (queues drain) and ``SECONDS`` of frames.
``SETTLE_S`` after the last frame the measurer writes what it received.

**Latency** = receive time in the measurer's callback (``time.time_ns()``) minus the input stamp
(the same wall clock on this host): p50, p99 and max over the frames of the timed phase, first
receipt of each stamp. **Drops** = frames sent in the phase minus distinct input stamps that
reached the output (per output topic for the node). **CPU** of the system under test =
(utime + stime) / wall time during the phase from ``/proc/PID/stat``, the node's solver worker
process included (100 % = one core; divided by the rate, the CPU time per frame);
**machine busy** = non-idle time of all cores from ``/proc/stat`` (100 % = all cores) and
**others** = the part of it not used by the three benchmark processes (the load that is not
ours, e.g. other jobs on a shared VM). Target: 1000 Hz sustained without drops and node p99
within 1.5x of the relay's p99 at every rate.

Known artefact: in about 4 of 10 node runs the measurer receives ~25 consecutive outputs of the
100 Hz phase ~250 ms late, then all at once (never a drop). It is not the node: instrumented, the
node received those frames within 10 ms of their stamps and no callback took over 5 ms; and an
independent subscriber process on ``/hip/centre`` through five such runs received every output
on time while the measurer saw the stall in one of them. Such a stall sets the p99 of the round
it falls in (5 frames are 1 % of a 100 Hz phase); the per-round ratios show which round it was.

``--nice N`` starts the three child processes at nice value N (e.g. -10, as root) to measure on a
machine shared with CPU-bound jobs; the results file records the value. Default 0.
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import platform
import queue
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

import numpy as np
import yaml
from _common import cpu_name, markdown_table, save_results

ROOT = Path(__file__).resolve().parent.parent
HELPERS = Path(__file__).resolve().parent / "_latency_helpers.py"
RESULTS = Path(__file__).resolve().parent / "results" / "node_latency.md"
CONFIG = ROOT / "config" / "fake_mocap.yaml"

RATES = (100.0, 500.0, 1000.0)
SECONDS = 5.0
PAUSE_S = 1.0
WARM_RATE = 200.0
SETTLE_S = 1.0
READY_TIMEOUT_S = 40.0
EXTRA_MARKERS = 24
P99_TARGET = 1.5
#: Other jobs' share of the machine (% of all cores) above which the results carry a warning.
OTHERS_WARN = 20.0
ROUNDS = 2
#: Run order: the direct reference once, then relay and node alternately, so that a change in the
#: machine's background load during the run falls on both.
SEQUENCE = [("direct", 1)] + [(system, r) for r in range(1, ROUNDS + 1) for system in ("relay", "node")]
OUTPUTS = {
    "direct": ["/markers:pose_array:best_effort"],
    "relay": ["/relay/markers:pose_array:reliable"],
    "node": ["/hip/centre:pose_cov:reliable", "/knee/axis:pose_cov:reliable"],
}
_CLK_TCK = os.sysconf("SC_CLK_TCK")


# ----------------------------------------------------------------------------- processes


def _proc_seconds(pid: int) -> float:
    """CPU time (user + system, s) of process ``pid`` and its live children (the node's solver worker); NaN when gone."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
    except OSError:
        return float("nan")
    try:
        with open(f"/proc/{pid}/task/{pid}/children", encoding="ascii") as fh:
            children = [int(c) for c in fh.read().split()]
    except OSError:
        children = []
    own = (int(fields[11]) + int(fields[12])) / _CLK_TCK
    return own + sum(t for t in (_proc_seconds(c) for c in children) if t == t)


def _machine_seconds() -> tuple[float, float]:
    """(busy, total) CPU seconds of all cores from ``/proc/stat``."""
    with open("/proc/stat", encoding="ascii") as fh:
        values = [int(v) for v in fh.readline().split()[1:]]
    idle = values[3] + values[4]  # idle + iowait
    total = sum(values[:8])  # guest time is already in user
    return (total - idle) / _CLK_TCK, total / _CLK_TCK


class Child:
    """A child process with its stdout lines in a queue and stderr in a file; stopped reliably."""

    def __init__(
        self, name: str, args: Sequence[str], env: dict[str, str], logdir: Path, nice: int = 0
    ) -> None:
        self.name = name
        if nice:
            args = ["nice", "-n", str(nice), *args]  # nice execs the program: same pid
        self.log = logdir / f"{name}.stderr"
        self._err: IO[str] = open(self.log, "w", encoding="utf-8")  # closed in stop()
        self.proc = subprocess.Popen(
            list(args),
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self._err,
            env=env,
            cwd=ROOT,
            text=True,
            bufsize=1,
            start_new_session=True,  # a Ctrl-C of the benchmark reaches it only through stop()
        )
        self.lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line.strip())
        self.lines.put("<eof>")

    def expect(self, prefix: str, timeout: float) -> str:
        """The next stdout line starting with ``prefix`` (others are skipped); RuntimeError on timeout."""
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            try:
                line = self.lines.get(timeout=max(left, 0.0))
            except queue.Empty:
                raise RuntimeError(
                    f"{self.name}: no '{prefix}' within {timeout:g} s; {self.tail()}"
                ) from None
            if line.startswith(prefix):
                return line
            if line == "<eof>":
                raise RuntimeError(f"{self.name}: exited before '{prefix}'; {self.tail()}")

    def send(self, line: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def cpu(self) -> float:
        return _proc_seconds(self.proc.pid)

    def tail(self, n: int = 5) -> str:
        self._err.flush()
        lines = self.log.read_text(encoding="utf-8", errors="replace").splitlines()
        return "stderr: " + (" | ".join(lines[-n:]) if lines else "(empty)")

    def stop(self, grace: float = 5.0) -> str:
        """SIGINT (rclpy's clean shutdown), then SIGKILL after ``grace`` s; how it ended, in words."""
        how = "exited by itself"
        if self.proc.poll() is None:
            how = "stopped by SIGINT"
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(grace)
            except subprocess.TimeoutExpired:
                how = f"ignored SIGINT for {grace:g} s, killed"
                self.proc.kill()
                self.proc.wait()
        for pipe in (self.proc.stdin, self.proc.stdout):
            if pipe is not None:
                try:
                    pipe.close()
                except OSError:
                    pass
        self._err.close()
        return how


# ----------------------------------------------------------------------------- one system


@dataclass
class Window:
    """CPU snapshots at the start and end of one timed phase."""

    wall: list[float] = field(default_factory=list)
    sut: list[float] = field(default_factory=list)
    ours: list[float] = field(default_factory=list)
    machine: list[tuple[float, float]] = field(default_factory=list)

    def snap(self, sut: Child | None, children: Sequence[Child]) -> None:
        self.wall.append(time.monotonic())
        self.sut.append(sut.cpu() if sut is not None else float("nan"))
        self.ours.append(sum(c.cpu() for c in children))
        self.machine.append(_machine_seconds())

    def loads(self) -> tuple[float, float, float]:
        """(SUT % of one core, machine busy % of all cores, others % of all cores)."""
        wall = self.wall[1] - self.wall[0]
        total = self.machine[1][1] - self.machine[0][1]
        busy = self.machine[1][0] - self.machine[0][0]
        ours = self.ours[1] - self.ours[0]
        return (
            100.0 * (self.sut[1] - self.sut[0]) / wall,
            100.0 * busy / total,
            100.0 * max(busy - ours, 0.0) / total,
        )


@dataclass
class Phase:
    rate: float
    sent: np.ndarray
    elapsed: float
    resyncs: int
    window: Window


@dataclass
class SystemRun:
    system: str
    round: int
    ready_s: float
    phases: list[Phase]
    received: dict[str, tuple[np.ndarray, np.ndarray]]  # topic -> (stamps, receive times), ns
    stopped: str


def _node_params(tmp: Path) -> Path:
    """config/fake_mocap.yaml with marker_names extended by the extra markers."""
    from jointfit_ros.fake_mocap import marker_names

    doc = yaml.safe_load(CONFIG.read_text(encoding="utf-8"))
    p = doc["jointfit"]["ros__parameters"]
    p["marker_names"] = marker_names(EXTRA_MARKERS)
    for joint in p["joints"]:  # the quick start's calibration files are the user's: neither loaded nor written
        p[joint]["calibration_file"] = ""
    path = tmp / "node_latency_params.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return path


def run_system(
    system: str, round_: int, env: dict[str, str], tmp: Path, params: Path, nice: int = 0
) -> SystemRun:
    py = sys.executable
    topics = OUTPUTS[system]
    name = f"{system}{round_}"
    sent_path, recv_path = tmp / f"{name}_sent.npz", tmp / f"{name}_recv.npz"
    children: list[Child] = []
    sut: Child | None = None
    stopped = ""
    try:
        if system == "relay":
            sut = Child(name, [py, str(HELPERS), "relay"], env, tmp, nice)
        elif system == "node":
            node_args = [py, "-m", "jointfit_ros.node", "--ros-args", "--params-file", str(params)]
            sut = Child(name, node_args, env, tmp, nice)
        if sut is not None:
            children.append(sut)
        meas = Child(f"{name}_measure", [py, str(HELPERS), "measure", *topics], env, tmp, nice)
        children.append(meas)
        meas.expect("ready", READY_TIMEOUT_S)
        pub = Child(
            f"{name}_publish",
            [
                py,
                str(HELPERS),
                "publish",
                "--rates",
                *(f"{r:g}" for r in RATES),
                "--seconds",
                f"{SECONDS:g}",
                "--pause",
                f"{PAUSE_S:g}",
                "--warm-rate",
                f"{WARM_RATE:g}",
                "--out",
                str(sent_path),
            ],
            env,
            tmp,
            nice,
        )
        children.append(pub)
        t0 = time.monotonic()
        for _ in topics:
            meas.expect("first", READY_TIMEOUT_S)
        ready_s = time.monotonic() - t0
        time.sleep(SETTLE_S)
        pub.send("go")
        windows = []
        for rate in RATES:
            w = Window()
            pub.expect(f"start {rate:g}", READY_TIMEOUT_S)
            w.snap(sut, children)
            pub.expect(f"end {rate:g}", SECONDS + READY_TIMEOUT_S)
            w.snap(sut, children)
            windows.append(w)
        pub.expect("done", READY_TIMEOUT_S)
        time.sleep(SETTLE_S)
        meas.send(f"dump {recv_path}")
        meas.expect("dumped", READY_TIMEOUT_S)
    finally:
        for child in reversed(children):
            how = child.stop()
            if child is sut:
                stopped = how
    sent = np.load(sent_path)
    got = np.load(recv_path)
    phases = [
        Phase(
            rate,
            sent[f"stamps_{rate:g}"],
            float(sent[f"elapsed_{rate:g}"]),
            int(sent[f"resyncs_{rate:g}"]),
            w,
        )
        for rate, w in zip(RATES, windows, strict=True)
    ]
    received = {spec.split(":")[0]: (got[f"stamp_{i}"], got[f"recv_{i}"]) for i, spec in enumerate(topics)}
    return SystemRun(system, round_, ready_s, phases, received, stopped or "none")


# ----------------------------------------------------------------------------- statistics


@dataclass(frozen=True)
class Sample:
    """One output topic during one timed phase (``round`` 0: pooled over the rounds)."""

    system: str
    round: int
    topic: str
    rate: float
    sent: int
    achieved_hz: float
    lat_ms: np.ndarray  # first receipt of each stamp sent in the phase
    sut_cpu: float  # % of one core
    busy: float  # % of all cores
    others: float  # % of all cores

    @property
    def drops(self) -> int:
        return self.sent - self.lat_ms.size

    def q(self, pct: float) -> float:
        return float(np.percentile(self.lat_ms, pct)) if self.lat_ms.size else float("nan")


def samples_of(run: SystemRun) -> list[Sample]:
    out = []
    for ph in run.phases:
        sut_cpu, busy, others = ph.window.loads()
        for topic, (stamps, recv) in run.received.items():
            keep = np.isin(stamps, ph.sent)
            uniq, first = np.unique(stamps[keep], return_index=True)
            lat_ms = (recv[keep][first] - uniq) / 1e6
            achieved = ph.sent.size / ph.elapsed
            out.append(
                Sample(
                    run.system,
                    run.round,
                    topic,
                    ph.rate,
                    ph.sent.size,
                    achieved,
                    lat_ms,
                    sut_cpu,
                    busy,
                    others,
                )
            )
    return out


def pooled(samples: Sequence[Sample], system: str, rate: float, topic: str) -> Sample:
    """The rounds of one system, rate and topic together (CPU and load: mean over the rounds)."""
    sel = [s for s in samples if s.system == system and s.rate == rate and s.topic == topic]
    return Sample(
        system,
        0,
        topic,
        rate,
        sum(s.sent for s in sel),
        min(s.achieved_hz for s in sel),
        np.concatenate([s.lat_ms for s in sel]),
        float(np.mean([s.sut_cpu for s in sel])),
        float(np.mean([s.busy for s in sel])),
        float(np.mean([s.others for s in sel])),
    )


def _pct(part: int, whole: int) -> str:
    return f"{part} ({100.0 * part / whole:.1f} %)" if whole else f"{part}"


def detail_table(samples: Sequence[Sample]) -> str:
    header = [
        "rate (Hz)",
        "system",
        "round",
        "output",
        "sent",
        "achieved (Hz)",
        "drops",
        "p50 (ms)",
        "p99 (ms)",
        "max (ms)",
        "SUT CPU (% core)",
        "machine busy (%)",
        "others (%)",
    ]
    order = {name: k for k, name in enumerate(OUTPUTS)}
    body = [
        [
            f"{s.rate:g}",
            s.system,
            f"{s.round}",
            f"`{s.topic}`",
            f"{s.sent}",
            f"{s.achieved_hz:.0f}",
            _pct(s.drops, s.sent),
            f"{s.q(50):.1f}",
            f"{s.q(99):.1f}",
            f"{s.q(100):.1f}",
            "" if np.isnan(s.sut_cpu) else f"{s.sut_cpu:.0f}",
            f"{s.busy:.0f}",
            f"{s.others:.0f}",
        ]
        for s in sorted(samples, key=lambda s: (s.rate, order[s.system], s.round, s.topic))
    ]
    return markdown_table(header, body)


def _topics(system: str) -> list[str]:
    return [spec.split(":")[0] for spec in OUTPUTS[system]]


def summary(samples: Sequence[Sample], rounds: int) -> tuple[str, list[str]]:
    """Per rate, pooled over the rounds: direct, relay and node (worse joint output), p99 ratio, verdicts."""
    table = []
    ratios = {}
    worst_top: Sample | None = None
    for rate in RATES:
        direct = pooled(samples, "direct", rate, _topics("direct")[0])
        relay = pooled(samples, "relay", rate, _topics("relay")[0])
        node = [pooled(samples, "node", rate, t) for t in _topics("node")]
        worst = max(node, key=lambda s: (s.drops, s.q(99)))
        ratio = worst.q(99) / relay.q(99)
        ratios[rate] = ratio
        per_round = []
        for r in range(1, rounds + 1):
            rel = [s for s in samples if s.system == "relay" and s.rate == rate and s.round == r]
            nod = [s for s in samples if s.system == "node" and s.rate == rate and s.round == r]
            per_round.append(f"{max(s.q(99) for s in nod) / rel[0].q(99):.2f}")
        worst_top = worst
        table.append(
            [
                f"{rate:g}",
                f"{direct.q(50):.1f} / {direct.q(99):.1f}",
                f"{relay.q(50):.1f} / {relay.q(99):.1f}",
                f"{worst.q(50):.1f} / {worst.q(99):.1f}",
                f"**{ratio:.2f}**",
                " / ".join(per_round),
                "yes" if ratio <= P99_TARGET else "no",
                _pct(relay.drops, relay.sent),
                _pct(worst.drops, worst.sent),
                f"{worst.sut_cpu:.0f} / {relay.sut_cpu:.0f}",
                f"{1e4 * worst.sut_cpu / rate:.0f} / {1e4 * relay.sut_cpu / rate:.0f}",
                f"{worst.others:.0f}",
            ]
        )
    header = [
        "rate (Hz)",
        "direct p50 / p99 (ms)",
        "relay p50 / p99 (ms)",
        "node p50 / p99 (ms, worse joint)",
        "node p99 / relay p99",
        "per round",
        f"<= {P99_TARGET:g}",
        "relay drops",
        "node drops (worse joint)",
        "CPU node / relay (% core)",
        "CPU per frame node / relay (us)",
        "others, node phases (%)",
    ]
    assert worst_top is not None
    met_ratio = all(v <= P99_TARGET for v in ratios.values())
    met_drops = worst_top.drops == 0
    verdict = [
        f"- **{worst_top.rate:g} Hz sustained without drops: {'met' if met_drops else 'not met'}** "
        f"(node: {worst_top.drops} of {worst_top.sent} frames missing on the worse joint output over "
        f"{rounds} rounds; publisher achieved at least {worst_top.achieved_hz:.0f} Hz).",
        f"- **Node p99 within {P99_TARGET:g}x of the relay's: {'met' if met_ratio else 'not met'}** ("
        + ", ".join(f"{r:g} Hz {v:.2f}x" for r, v in ratios.items())
        + ").",
    ]
    others = max(s.others for s in samples if s.system in ("relay", "node"))
    if others > OTHERS_WARN:
        verdict.append(
            f"- **Warning: the machine was not quiet.** Processes other than the benchmark's used up to "
            f"{others:.0f} % of all cores during the relay and node phases. On an overloaded machine a woken "
            "process can wait for another job's time slice (a few ms), and such waits set the p99s and cause "
            "the drops; compare the rounds, and re-run on a quiet machine (or with `--nice -10`) for the "
            "node's own numbers. p50 and CPU per frame are little affected."
        )
    return markdown_table(header, table), verdict


# ----------------------------------------------------------------------------- main


def _machine() -> str:
    from importlib.metadata import PackageNotFoundError, version

    from rclpy.utilities import get_rmw_implementation_identifier

    try:
        rclpy_version = version("rclpy")
    except PackageNotFoundError:
        rclpy_version = "unknown"
    return (
        f"{platform.platform()}, {cpu_name()}, {os.cpu_count()} CPUs; Python {platform.python_version()}, "
        f"numpy {np.__version__}, rclpy {rclpy_version}, "
        f"RMW {get_rmw_implementation_identifier()}; "
        f"load average at start {', '.join(f'{x:.2f}' for x in os.getloadavg())}"
    )


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--nice",
        type=int,
        default=0,
        help="run the three child processes at this nice value (negative needs root); default 0. "
        "For a machine shared with CPU-bound jobs; the results file records it",
    )
    opts = p.parse_args(argv)
    # SIGTERM (e.g. `timeout`) unwinds like Ctrl-C, so that the children are stopped in `finally`.
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))
    t_start = time.perf_counter()
    machine = _machine()
    print(f"Machine: {machine}", flush=True)
    domain = 100 + os.getpid() % 100
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(domain))
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH", "")) if p)
    runs: list[SystemRun] = []
    with tempfile.TemporaryDirectory(prefix="jointfit_latency_") as tmp_name:
        tmp = Path(tmp_name)
        params = _node_params(tmp)
        for system, round_ in SEQUENCE:
            print(f"== {system} (round {round_})", flush=True)
            run = run_system(system, round_, env, tmp, params, opts.nice)
            print(f"   ready after {run.ready_s:.1f} s; stopped: {run.stopped}", flush=True)
            runs.append(run)
    samples = [s for run in runs for s in samples_of(run)]
    summary_md, verdict = summary(samples, ROUNDS)
    ready = ", ".join(f"{run.system} {run.round}: {run.ready_s:.1f} s" for run in runs)
    stops = ", ".join(f"{run.system} {run.round}: {run.stopped}" for run in runs if run.system != "direct")
    resyncs = sum(ph.resyncs for run in runs for ph in run.phases)
    parts = [
        "# jointfit node: input-to-output latency and drops",
        "",
        f"Made by `python bench/node_latency.py` on {dt.date.today().isoformat()}.",
        "",
        f"Machine: {machine}.",
        "",
        f"40 markers (16 on the hip and knee rigs + {EXTRA_MARKERS} static), PoseArray CDR bytes, "
        f"best effort, {SECONDS:g} s per rate; publisher, system under test and measurer in three "
        f"processes (ROS_DOMAIN_ID {domain}, localhost discovery), nice {opts.nice}"
        f"{' (default priority)' if opts.nice == 0 else ' (raised above other jobs on this machine)'}. "
        "Latency = receive time in the measurer - input stamp (send time). "
        "direct = measurer subscribed to the markers (1 hop); relay = pass-through rclpy node "
        "(2 hops); node = jointfit node, outputs `/hip/centre` (ball) and `/knee/axis` (hinge) "
        "(2 hops + work). "
        "See the docstring of `bench/node_latency.py` for the method.",
        "",
        "## Summary",
        "",
        summary_md,
        "",
        *verdict,
        "",
        "## Every output",
        "",
        "SUT CPU: the relay's process, or the node's with its solver worker (100 % = one core); machine busy: all "
        f"{os.cpu_count()} cores; others: busy time not used by the benchmark's processes.",
        "",
        detail_table(samples),
        "",
        "Time from the publisher's start (imports and frame pool included) to the first output on every "
        f"topic (discovery, and "
        f"for the node its templates and first estimate; warm-up at {WARM_RATE:g} Hz): {ready}. "
        f"Schedule restarts of the publisher (a frame > 2 periods late): {resyncs}. "
        f"Shutdown: {stops}.",
        "",
    ]
    parts.append(f"Total runtime {time.perf_counter() - t_start:.0f} s.")
    text = "\n".join(parts) + "\n"
    print(text, end="")
    save_results(RESULTS, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
