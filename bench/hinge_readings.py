"""Which reading sets an online skin hinge's artefact scale on the lower body, and why it is so cautious (issue 17).

Run with ``python bench/hinge_readings.py`` (repository root; ``--seeds 1,2,3``); prints Markdown and
writes ``bench/results/hinge_readings.md``.

Data: the streams of ``test/test_skeleton_sta.py`` (``lower`` skeleton, seeds as given, 20 s at 100 Hz,
skin artefact on every segment, 0.5 mm noise, 2 % occluded) through the node's path
(``config/lower_body.yaml``, solved every 0.1 s), once with every segment's skin following its adjacent
joints (the thigh's the hip and the knee) and once with the thighs following their knee only (no thigh
motion with the hip).

Measures, per hinge, at the final solve: the artefact scale (mm per rad) of
:func:`~jointfit_core.artefact_sums.artefact_from_sums` (what the node publishes), the scale its point
reading alone gives (the energy ratio of the joint residual's smooth part: the call without
``directions``), so that a total above it was set by the axis-alignment reading; the direction's
error (deg), sd (deg, sqrt of the covariance's trace) and e/2 against the truth.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _paper_helpers import elapsed_line, fmt, mahalanobis_rank, markdown_table, print_and_write, run_header
from skeleton_runs import run_stream

from jointfit_core.artefact_sums import SumsArtefact, artefact_from_sums
from jointfit_core.estimator import solve_window
from jointfit_core.hinge_from_sums import PoseSumsAxis
from jointfit_core.skeleton_sta import skeleton_skin_frames, sta_amplitudes
from jointfit_core.skeleton_truth import make_skeleton
from jointfit_ros.params import node_config, params_from_file

SCRIPT = "hinge_readings.py"
SEED = 0  # the streams are seeded by --seeds, as test_skeleton_sta.py
SECONDS, RATE = 20.0, 100.0
CONFIG = Path(__file__).resolve().parents[1] / "config" / "lower_body.yaml"
#: The module whose solve_window calls artefact_from_sums (estimator.py, or the module it moved to).
SOLVER_MODULE = sys.modules[solve_window.__module__]
HEADER = ("skin follows", "seed", "hinge", "scale (mm/rad)", "point reading (mm/rad)", "set by", "error (deg)", "sd (deg)", "e/2")
DRIVERS: dict[str, dict[str, tuple[str, ...]] | None] = {
    "adjacent joints": None,
    "thighs with the knee only": {"r_thigh": ("r_knee",), "l_thigh": ("l_knee",)},
}


def _recording(calls: list[tuple[float, float]]) -> Callable[..., SumsArtefact]:
    """``artefact_from_sums`` that also records ``(its scale, the point reading's scale)`` of each call."""

    def wrapped(*args: Any, **kwargs: Any) -> SumsArtefact:
        out = artefact_from_sums(*args, **kwargs)
        point = artefact_from_sums(*args[:10], None) if len(args) > 10 and args[10] is not None else out
        calls.append((out.scale, point.scale))
        return out

    return wrapped


def run(seeds: Sequence[int]) -> list[list[str]]:
    """One row per (drivers, seed, hinge)."""
    rows = []
    calls: list[tuple[float, float]] = []
    SOLVER_MODULE.artefact_from_sums = _recording(calls)  # type: ignore[attr-defined]
    try:
        for label, drivers in DRIVERS.items():
            for seed in seeds:
                sk = make_skeleton("lower", seed=seed)
                t = np.arange(round(SECONDS * RATE)) / RATE
                frames = skeleton_skin_frames(sk, t, np.random.default_rng(seed), sta_amplitudes(sk), noise=0.0005,
                                              occlusion=0.02, drivers=drivers)  # fmt: skip
                for r in run_stream(node_config(params_from_file(CONFIG)), t, frames, estimate_period=0.1):
                    est = r.estimator
                    if est.kind != "hinge":
                        continue
                    calls.clear()
                    res = solve_window(est.request_for(est._entered_sums().copy()))
                    total, point = calls[-1]
                    template = est.templates[0]
                    assert template is not None
                    _, direction = sk.joint_in_template(r.cfg.name, template)
                    assert direction is not None
                    sol = res.solution
                    assert isinstance(sol, PoseSumsAxis)
                    d = sol.direction_parent * np.sign(sol.direction_parent @ direction)
                    err = float(np.degrees(np.arccos(min(1.0, float(d @ direction)))))
                    sd = float(np.degrees(np.sqrt(np.trace(sol.cov_direction_parent))))
                    e = mahalanobis_rank(d - direction, sol.cov_direction_parent, 2) / 2.0
                    rows.append([label, str(seed), r.cfg.name, fmt(1e3 * total), fmt(1e3 * point),
                                 "alignment" if total > point * (1.0 + 1e-9) else "point", fmt(err), fmt(sd), fmt(e)])  # fmt: skip
    finally:
        SOLVER_MODULE.artefact_from_sums = artefact_from_sums  # type: ignore[attr-defined]
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="1,2,3", help="skeleton and stream seeds (default 1,2,3: test_skeleton_sta)")
    parser.add_argument("--out", default="hinge_readings.md", help="result file name in bench/results")
    args_list = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(args_list)
    t0 = time.perf_counter()
    rows = run([int(s) for s in args.seeds.split(",")])
    parts = run_header(
        "Online skin hinges on the lower body: which reading sets the artefact scale",
        SCRIPT,
        args_list,
        SEED,
        "The streams of test/test_skeleton_sta.py; the data and the measures are described in the script's docstring.",
    )
    parts += [
        "",
        markdown_table(HEADER, rows),
        "",
        "scale: the artefact scale published (the larger of the two readings, the alignment one times nu / (nu - 2)); "
        "point reading: the energy ratio alone; set by: which of the two gave the scale.",
        "",
        elapsed_line(t0),
    ]
    print_and_write(args.out, parts)
    return 0


if __name__ == "__main__":
    sys.exit(main())
