"""The estimate tick's cost for the 12 joints of the full skeleton: one batched request to the solver worker against 12 single ones.

Run with ``python bench/solver_batch.py`` (repository root, ``PYTHONPATH=.:test``; ``--quick`` for a
short run, under a minute). Prints Markdown and writes ``bench/results/solver_batch.md``.

What is measured
----------------
The node solves its joints' windows in a worker process
(:class:`~jointfit_ros.solver_process.SolverProcess`). Since issue 16 item 6 it sends every due
joint's window in one request per estimate tick; before, it sent one joint's window per request
and installed its answer at the next tick. Both are measured here in the same run, on the same
worker process, round by round (the order alternating):

- **batched**: the 12 joints' :meth:`~jointfit_ros.runner.JointRunner.solve_request` snapshots,
  one :meth:`~jointfit_ros.solver_process.SolverProcess.submit`, the wait, one
  :meth:`~jointfit_ros.solver_process.SolverProcess.collect` and the 12
  :meth:`~jointfit_ros.runner.JointRunner.install` (what the node's two estimate ticks do);
- **12 single**: the same for one joint at a time, 12 times in a row (back to back here; the node
  spread them over 24 timer ticks, so there a joint's answer waited up to a whole ``estimate_period``);
- **in-process**: the 12 solves on the calling thread (:meth:`~jointfit_ros.runner.JointRunner.estimate`),
  what the node does when it has no worker (there one joint per tick), for scale.

Each configuration has its own 12 runners, fed the same frames (the full skeleton of
:mod:`jointfit_core.skeleton_truth`: 56 markers, metres, 0.5 mm noise, 2 % occluded, 100 Hz;
``config/full_body.yaml``'s joints), ``FRAMES_PER_ROUND`` new frames per round (one
``estimate_period`` of 0.1 s), so every joint has a window to solve in every round; the answers of
the three are checked equal bit for bit.

Columns: **executor CPU** is ``time.thread_time`` of the calling thread (what the node's executor
thread spends: snapshots, pickling, sending, unpickling, installing; the waits block in ``poll``
without CPU); **longest tick** the longest of its steps that the node runs in one estimate tick
(a send, an install; in-process: one joint's solve), how long a tick holds up the frames;
**worker CPU** is the worker's own CPU time (``/proc/<pid>/schedstat``; empty where
that does not exist); **wall** is from the first snapshot to the last install; **messages** the
requests sent per round. Medians over the rounds, and the 90th percentile of the wall time.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine, markdown_table, save_results
from skeleton import _commit

from jointfit_core.skeleton_truth import make_skeleton, skeleton_frames
from jointfit_ros.inputs import MessageRouter
from jointfit_ros.params import NodeConfig, node_config
from jointfit_ros.raw import pose_array_bytes
from jointfit_ros.runner import JointRunner
from jointfit_ros.skeleton_params import skeleton_parameters
from jointfit_ros.solver_process import SolverProcess

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results" / "solver_batch.md"
RATE = 100.0
T0 = 1_000_000_000_000
WARM = 300
FRAMES_PER_ROUND = 10
#: Seconds to wait for an answer (the worker's first start imports numpy and scipy).
WAIT_S = 60.0


@dataclasses.dataclass
class _Sample:
    executor_s: float
    longest_tick_s: float  # the longest send or install step (one estimate tick's work in the node)
    worker_s: float
    wall_s: float
    messages: int


def _worker_cpu_s(sp: SolverProcess) -> float:
    """The worker's CPU time so far (s) from /proc/<pid>/schedstat; NaN where unavailable."""
    proc = sp._proc
    if proc is None:
        return float("nan")
    try:
        return int(Path(f"/proc/{proc.pid}/schedstat").read_text().split()[0]) * 1e-9
    except (OSError, ValueError, IndexError):
        return float("nan")


class _Joints:
    """12 runners and their router, fed the same frames as the other configurations."""

    def __init__(self, cfg: NodeConfig, warm: Sequence[bytes]) -> None:
        self.runners = [JointRunner(j, cfg) for j in cfg.joints]
        self.router = MessageRouter(cfg, self.runners)
        self.router.markers_many(list(warm))
        for r in self.runners:
            if not r.estimate(force=True):
                raise RuntimeError(f"{r.cfg.name}: no estimate after the warm-up: {r.last_error}")

    def feed(self, messages: Sequence[bytes]) -> None:
        self.router.markers_many(list(messages))

    def solutions(self) -> list[object]:
        return [r.estimator.solution for r in self.runners]


def _round_trip(sp: SolverProcess, joints: _Joints, sizes: Sequence[int]) -> _Sample:
    """Snapshot, send, wait, collect and install every joint, in requests of ``sizes`` joints."""
    by_name = {r.cfg.name: r for r in joints.runners}
    ticks: list[float] = []
    w0, t0 = _worker_cpu_s(sp), time.perf_counter()
    start = 0
    for size in sizes:
        c0 = time.thread_time()
        batch = []
        for r in joints.runners[start : start + size]:
            request = r.solve_request(force=True)
            if request is None:
                raise RuntimeError(f"{r.cfg.name}: nothing to solve after new frames")
            batch.append((r.cfg.name, request))
        if not sp.submit(batch):
            raise RuntimeError(f"the solver process took no request: {sp.problem or 'busy'}")
        ticks.append(time.thread_time() - c0)
        if not sp.ready(WAIT_S):
            raise RuntimeError(f"no answer in {WAIT_S:g} s")
        c0 = time.thread_time()
        answers = sp.collect()
        requests = dict(batch)
        for name, answer in answers:
            if not by_name[name].install(answer, requests[name]):
                raise RuntimeError(f"{name}: the answer was not installed ({answer!r})")
        ticks.append(time.thread_time() - c0)
        if len(answers) != size:
            raise RuntimeError(f"{len(answers)} answers to a request of {size}: {sp.problem}")
        start += size
    return _Sample(sum(ticks), max(ticks), _worker_cpu_s(sp) - w0, time.perf_counter() - t0, len(sizes))


def _in_process(joints: _Joints) -> _Sample:
    ticks = []
    t0 = time.perf_counter()
    for r in joints.runners:
        c0 = time.thread_time()
        if not r.estimate(force=True):
            raise RuntimeError(f"{r.cfg.name}: {r.last_error}")
        ticks.append(time.thread_time() - c0)
    return _Sample(sum(ticks), max(ticks), 0.0, time.perf_counter() - t0, 0)


def _same(a: Sequence[object], b: Sequence[object]) -> bool:
    """Whether two lists of solutions are equal bit for bit (NaN equals NaN)."""
    for x, y in zip(a, b, strict=True):
        for f in dataclasses.fields(x):  # type: ignore[arg-type]
            u, v = getattr(x, f.name), getattr(y, f.name)
            if isinstance(u, np.ndarray):
                if not np.array_equal(u, v, equal_nan=True):
                    return False
            elif not (u == v or (u != u and v != v)):
                return False
    return True


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="30 rounds (under a minute)")
    p.add_argument("--rounds", type=int, default=150, help="rounds (default 150)")
    p.add_argument("--out", type=Path, default=RESULTS, help=f"results file (default {RESULTS.relative_to(ROOT)})")
    opts = p.parse_args(argv)
    rounds = 30 if opts.quick else opts.rounds
    started = dt.datetime.now().astimezone()
    commit = _commit()
    sk = make_skeleton("full", seed=0)
    n = WARM + FRAMES_PER_ROUND * rounds
    t = np.arange(n) / RATE
    frames = skeleton_frames(sk, t, np.random.default_rng(0), 0.0005, 0.02)
    messages = [pose_array_bytes(T0 + round(tk * 1e9), "world", f) for tk, f in zip(t, frames, strict=True)]
    cfg = node_config(skeleton_parameters(sk))
    k = len(cfg.joints)
    names = ("batched", f"{k} single", "in-process")
    paths = {name: _Joints(cfg, messages[:WARM]) for name in names}
    sp = SolverProcess()
    try:
        starter = _Joints(cfg, messages[:WARM])
        starter.feed(messages[WARM : WARM + FRAMES_PER_ROUND])
        _round_trip(sp, starter, [k])  # start the worker (not timed)
        runs: dict[str, Callable[[], _Sample]] = {
            "batched": lambda: _round_trip(sp, paths["batched"], [k]),
            f"{k} single": lambda: _round_trip(sp, paths[f"{k} single"], [1] * k),
            "in-process": lambda: _in_process(paths["in-process"]),
        }
        samples: dict[str, list[_Sample]] = {name: [] for name in names}
        for rd in range(rounds):
            chunk = messages[WARM + rd * FRAMES_PER_ROUND : WARM + (rd + 1) * FRAMES_PER_ROUND]
            order = list(names) if rd % 2 == 0 else list(reversed(names))
            for name in order:
                paths[name].feed(chunk)
                samples[name].append(runs[name]())
            reference = paths["in-process"].solutions()
            for name in names[:2]:
                if not _same(paths[name].solutions(), reference):
                    raise RuntimeError(f"round {rd}: the {name} answers differ from the in-process solves")
    finally:
        sp.close()

    def med(name: str, field: str) -> float:
        return float(np.median([getattr(s, field) for s in samples[name]]))

    rows = []
    for name in names:
        wall = np.array([s.wall_s for s in samples[name]])
        worker = med(name, "worker_s")
        rows.append([
            name,
            f"{samples[name][0].messages}",
            f"{1e6 * med(name, 'executor_s'):.0f}",
            f"{1e6 * med(name, 'longest_tick_s'):.0f}",
            "" if name == "in-process" or not np.isfinite(worker) else f"{1e6 * worker:.0f}",
            f"{1e3 * float(np.median(wall)):.2f}",
            f"{1e3 * float(np.percentile(wall, 90)):.2f}",
        ])  # fmt: skip
    table = markdown_table(
        ["solving", "messages", "executor CPU (us)", "longest tick (us)", "worker CPU (us)", "wall, median (ms)",
         "wall, p90 (ms)"],
        rows,
        align="lrrrrrr",
    )
    ratio = med(f"{k} single", "executor_s") / med("batched", "executor_s")
    text = "\n".join([
        f"# The estimate tick's cost for {k} joints: one batched request against {k} single ones",
        "",
        f"Command: `python bench/solver_batch.py{' --quick' if opts.quick else ''}`; commit {commit}; "
        f"{started:%Y-%m-%d %H:%M %Z}.",
        f"Machine: {machine()}.",
        "",
        f"The {k} joints of `config/full_body.yaml` on the full skeleton (56 markers), {rounds} rounds of "
        f"{FRAMES_PER_ROUND} new frames each (one estimate_period at 100 Hz), every joint re-solved in every "
        "round; medians over the rounds. The batched and single answers equal the in-process solves bit for bit "
        "in every round.",
        "",
        table,
        "",
        f"Executor-thread CPU per re-solve of all {k} joints: batched {1e6 * med('batched', 'executor_s'):.0f} us "
        f"against {1e6 * med(f'{k} single', 'executor_s'):.0f} us in {k} requests ({ratio:.1f}x), and one round "
        f"trip instead of {k}. But that CPU now falls in two estimate ticks instead of {2 * k}: the longest "
        f"(installing the {k} answers) holds the frames' thread {1e6 * med('batched', 'longest_tick_s'):.0f} us, "
        f"against {1e6 * med(f'{k} single', 'longest_tick_s'):.0f} us for one joint's. Wall times are back to back "
        "here; in the node the single requests took a timer tick each way, so the last joint of a cycle waited a "
        "whole estimate_period. The worker runs at idle priority (SCHED_IDLE): on a busy machine (the load average "
        "above) its wall time stretches beyond its CPU time.",
        "",
    ])  # fmt: skip
    print(text)
    save_results(opts.out, text)
    print(f"wrote {opts.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
