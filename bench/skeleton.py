"""CPU per frame of the node's per-message path for 1, 2, 6 and 12 joints of the fake skeleton.

Run with ``python bench/skeleton.py`` (repository root, ``PYTHONPATH=.:test``; ``--quick`` for a
shorter run, about two minutes). Prints Markdown and writes ``bench/results/skeleton.md``. This is the
"before" of issue 16's segment-centric redesign: the results name the commit they were measured at.

What is measured
----------------
The stream: the ``full`` skeleton of :mod:`jointfit_core.skeleton_truth` (14 segments of 4 markers,
56 markers per frame, metres, 0.5 mm white noise, 2 % occluded markers) at 100 Hz, encoded as
``geometry_msgs/PoseArray`` CDR bytes before timing (what the node's subscription hands it).
The joints: the first 1 (``r_hip``), 2 (+ ``r_knee``), 6 (the lower body) and 12 (the full body)
of ``config/full_body.yaml`` (:func:`jointfit_ros.skeleton_params.skeleton_parameters`), on that
same 56-marker stream, so only the joint count changes. Shared segments are repeated marker lists
(each joint poses and gates its own copy of the thigh, as the node does today).

**path**: the node's whole per-message path, in this process, without rclpy: what
``JointfitNode._on_markers`` runs per message: :meth:`MessageRouter.markers` (parse, stamp checks,
route, every joint's :class:`~jointfit_ros.runner.JointRunner` and ``OnlineJoint.update``), then
each output encoded as CDR (``pose_with_covariance_bytes`` / ``axis_pose_bytes``), then the
frame's ``~/segments`` (:class:`~jointfit_ros.segment_output.SegmentOutput`: the segment poses
gathered and encoded; its share is given apart), then the bookkeeping that does not change the
outputs (:meth:`MessageRouter.after_outputs`: stamp gaps, live-geometry samples), in the node's
order; **to the outputs** is the CPU from the message to its joints' outputs encoded. Every
``READ_EVERY`` (10) messages every joint's sums are read, inside the timed span, as the node's
estimate tick reads them for its solve requests every 0.1 s: since 2026-12-03 that sums the frames
queued since (:mod:`jointfit_core.frame_queue`), work that used to be in each message. Solves are not
in it (the node runs them in its worker process): every 50 messages one joint is solved in turn,
outside the timed spans. Before timing, ``WARM`` frames build the templates and the gate's history
and every joint is solved, so that every frame of the timed part has an output per joint
(checked: the outputs are counted).

**baseline**: parsing the same messages alone (:meth:`MarkerParser.frame <jointfit_ros.marker_parser.MarkerParser.frame>`: CDR to a (56, 3) frame
with the node's checks), measured in the same run, interleaved with the paths round by round. The
ratio path / baseline is what the joints add to reading the message.

CPU time is ``time.process_time`` (this process, all threads) over the timed messages; each
configuration is timed in ``ROUNDS`` rounds (baseline, then 1, 2, 6, 12 joints, repeated), and the
table gives the median round. The slope is the least-squares line through the four medians.
"""

from __future__ import annotations

import argparse
import datetime as dt
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine, markdown_table, save_results

from jointfit_core.skeleton_truth import make_skeleton, skeleton_frames
from jointfit_ros.conversions import axis_pose_bytes, pose_with_covariance_bytes
from jointfit_ros.inputs import MessageRouter
from jointfit_ros.params import NodeConfig, node_config
from jointfit_ros.raw import pose_array_bytes
from jointfit_ros.runner import JointRunner
from jointfit_ros.segment_output import SegmentOutput
from jointfit_ros.skeleton_params import skeleton_parameters

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results" / "skeleton.md"
RATE = 100.0
T0 = 1_000_000_000_000
WARM = 300
SOLVE_EVERY = 50
#: Frames between two reads of every joint's sums, inside the timed span: the node's estimate tick every
#: estimate_period (0.1 s, 10 frames at 100 Hz) reads them for the solve requests, which sums the frames
#: queued since (jointfit_core.frame_queue); the solves themselves run in the worker process.
READ_EVERY = 10
COUNTS = (1, 2, 6, 12)


class _Path:
    """One joint configuration's runners and router, warmed up, fed messages as the node does."""

    def __init__(self, cfg: NodeConfig, warm: Sequence[bytes]) -> None:
        self.runners = [JointRunner(j, cfg) for j in cfg.joints]
        self.router = MessageRouter(cfg, self.runners)
        self.segments = SegmentOutput(self.runners)
        self.turn = 0
        self.frames = 0
        self.outputs = 0
        self.segment_cpu = 0.0
        self.to_outputs_cpu = 0.0
        for raw in warm:
            self.router.markers(raw)
        self.router.defer_bookkeeping = True  # as the node: the bookkeeping after the outputs (after_outputs)
        for r in self.runners:
            if not r.estimate(force=True):
                raise RuntimeError(f"{r.cfg.name}: no estimate after the warm-up: {r.last_error}")

    def run(self, messages: Sequence[bytes]) -> float:
        """CPU seconds of the per-message path over ``messages`` (solves between the timed spans)."""
        total = 0.0
        for start in range(0, len(messages), SOLVE_EVERY):
            chunk = messages[start : start + SOLVE_EVERY]
            c0 = time.process_time()
            for raw in chunk:
                f0 = time.process_time()
                for routed in self.router.markers(raw):
                    out = routed.output
                    if out.direction is None:
                        pose_with_covariance_bytes(routed.stamp_ns, routed.frame_id, out.position, out.cov)
                    else:
                        assert out.cov_direction is not None
                        axis_pose_bytes(
                            routed.stamp_ns, routed.frame_id, out.position, out.direction, out.cov, out.cov_direction
                        )
                    self.outputs += 1
                c1 = time.process_time()
                self.to_outputs_cpu += c1 - f0
                R, t = self.segments.poses()  # ~/segments, as the node encodes it after the joints
                self.segments.pose_array(T0, "world", R, t)
                self.segment_cpu += time.process_time() - c1
                self.router.after_outputs()  # as the node: after the frame's outputs
                self.frames += 1
                if self.frames % READ_EVERY == 0:  # the node's estimate tick reads every joint's sums (flushes its queue)
                    for r in self.runners:
                        _ = r.estimator.n_window
            total += time.process_time() - c0
            self.runners[self.turn].estimate(force=True)
            self.turn = (self.turn + 1) % len(self.runners)
        return total


def _baseline(cfg: NodeConfig, messages: Sequence[bytes]) -> float:
    router = MessageRouter(cfg, [])
    c0 = time.process_time()
    for raw in messages:
        router.parser.frame(raw)
    return time.process_time() - c0


def _commit() -> str:
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True,
                               text=True, check=True)  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head.stdout.strip() + (" (with uncommitted changes)" if dirty.stdout.strip() else "")


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="2 rounds of 1000 frames (about two minutes; fewer frames leave too many of them before the first skin estimates, which the check of the outputs refuses)")
    p.add_argument("--frames", type=int, default=1000, help="timed frames per round (default 1000)")
    p.add_argument("--rounds", type=int, default=3, help="rounds (default 3)")
    p.add_argument("--out", type=Path, default=RESULTS, help=f"results file (default {RESULTS.relative_to(ROOT)})")
    opts = p.parse_args(argv)
    frames_per_round, rounds = (1000, 2) if opts.quick else (opts.frames, opts.rounds)
    started = dt.datetime.now().astimezone()
    commit = _commit()  # the code measured: before the run, in case of commits meanwhile
    sk = make_skeleton("full", seed=0)
    n = WARM + frames_per_round * rounds
    t = np.arange(n) / RATE
    frames = skeleton_frames(sk, t, np.random.default_rng(0), 0.0005, 0.02)
    messages = [pose_array_bytes(T0 + round(tk * 1e9), "world", f) for tk, f in zip(t, frames, strict=True)]
    warm, timed = messages[:WARM], messages[WARM:]
    configs = {k: node_config(skeleton_parameters(sk, sk.joints[:k])) for k in COUNTS}
    paths = {k: _Path(cfg, warm) for k, cfg in configs.items()}
    base: list[float] = []
    cpu: dict[int, list[float]] = {k: [] for k in COUNTS}
    for r in range(rounds):
        chunk = timed[r * frames_per_round : (r + 1) * frames_per_round]
        base.append(_baseline(configs[1], chunk) / len(chunk))
        for k in COUNTS:
            cpu[k].append(paths[k].run(chunk) / len(chunk))
    for k in COUNTS:
        expected = k * frames_per_round * rounds
        if paths[k].outputs < 0.95 * expected:
            raise RuntimeError(f"{k} joints: {paths[k].outputs} outputs of {expected} expected")
    base_us = 1e6 * float(np.median(base))
    med = {k: 1e6 * float(np.median(cpu[k])) for k in COUNTS}
    slope, intercept = np.polyfit(np.array(COUNTS, dtype=float), [med[k] for k in COUNTS], 1)
    seg_us = {k: 1e6 * paths[k].segment_cpu / (frames_per_round * rounds) for k in COUNTS}
    out_us = {k: 1e6 * paths[k].to_outputs_cpu / (frames_per_round * rounds) for k in COUNTS}
    rows = [
        [f"{k}", f"{len(paths[k].segments.names)}", f"{med[k]:.0f}", f"{med[k] / k:.0f}", f"{med[k] / base_us:.1f}",
         f"{out_us[k]:.0f}", f"{seg_us[k]:.0f}", f"{100.0 * paths[k].outputs / (k * frames_per_round * rounds):.0f}"]
        for k in COUNTS
    ]  # fmt: skip
    table = markdown_table(
        ["joints", "segments", "CPU per frame (us)", "per joint (us)", "path / baseline", "to the outputs (us)",
         "of which ~/segments (us)", "frames with output (%)"],
        rows,
    )
    text = "\n".join([
        "# Per-message CPU of the node's path on the fake skeleton (issue 16)",
        "",
        f"Command: `python bench/skeleton.py{' --quick' if opts.quick else ''}`; commit {commit}; "
        f"{started:%Y-%m-%d %H:%M %Z}.",
        f"Machine: {machine()}.",
        "",
        f"Stream: the full skeleton (56 markers, PoseArray CDR, 0.5 mm noise, 2 % occluded), {rounds} round(s) of "
        f"{frames_per_round} frames after {WARM} warm-up frames; median round. Baseline (parse alone, same "
        f"messages, same run): **{base_us:.0f} us per frame**.",
        "",
        table,
        "",
        f"Per-joint slope (least squares over 1, 2, 6, 12 joints): **{slope:.0f} us per joint**, "
        f"intercept {intercept:.0f} us ({slope / base_us:.1f}x and {intercept / base_us:.1f}x the baseline).",
        "Issue 16's targets (<= 150 us for 12 joints, <= 90 us for 6) are for the redesign; compare by the "
        "ratios to the baseline when machines differ.",
        "",
    ])  # fmt: skip
    print(text)
    save_results(opts.out, text)
    print(f"wrote {opts.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
