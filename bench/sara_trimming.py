"""SARA's frame trimming on the knee of bench/sta.py: the closed form without it, and its dependence on the lab origin.

Run with ``python bench/sara_trimming.py`` (``--trials N``, default 10) in an
environment with the bench extras (biobuddy); prints Markdown and writes
``bench/results/sara_trimming.md``.

Data: the "knee, shank 5 mm" case of ``bench/sta.py`` (its seeds, so its first
trials). Each trial is fitted by biobuddy's SARA with and without its one pass
of frame trimming (``recursive_outlier_removal``) on the same least-squares
poses as ``bench/peers.py``, and by ``fit_axis_two_segments`` (skin: the
closed form), once with the markers as generated and once with every marker
moved by the same lab offset. Errors as in ``bench/sta.py``: the direction's
angle to the true axis (deg) and the true knee centre's distance from the
estimated axis line (mm), each in the method's own parent frame.

biobuddy's trimming keeps the frames whose angle between ``R_p n_p + d_p`` and
``R_c n_c + d_c`` (the axis directions carried as homogeneous points, so with
the segments' translations) is below its mean plus 1 sd: which frames it keeps
depends on where the lab origin is, while the fit itself does not.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections.abc import Sequence

import numpy as np
from _paper_helpers import (
    angle_deg,
    distance_to_line,
    elapsed_line,
    fmt,
    markdown_table,
    print_and_write,
    rotation_to_estimated_frame,
    run_header,
    to_estimated_frame,
)
from peers import Sara, _quiet, _rts, biobuddy
from sta import CASES, SEED

from jointfit_core.pose import poses_from_markers, template_from_markers
from jointfit_core.segments import fit_axis_two_segments
from jointfit_core.soft_tissue import knee_motion, skin_markers_at

SCRIPT = "sara_trimming.py"
CASE = "knee, shank 5 mm"
#: The lab offset (mm) every marker is moved by in the second half of each trial (as bench/online.py's).
OFFSET = np.array([2500.0, -1800.0, 1000.0])


def _errors(motion: object, template: np.ndarray, direction: np.ndarray, point: np.ndarray) -> tuple[float, float]:
    """Direction error (deg) and the true centre's distance from the axis line (mm), in the template's frame."""
    R = rotation_to_estimated_frame(motion.template_parent, template)  # type: ignore[attr-defined]
    centre = to_estimated_frame(motion.template_parent, template, motion.centre_parent)  # type: ignore[attr-defined]
    return angle_deg(direction, R @ motion.axis), distance_to_line(centre, point, direction)  # type: ignore[attr-defined]


def _sara(parent: np.ndarray, child: np.ndarray, trim: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """SARA's parent-frame direction and point, the parent template and the frames it kept."""
    tp, tc = template_from_markers(parent), template_from_markers(child)
    rt_p = _rts(poses_from_markers(parent, tp))
    rt_c = _rts(poses_from_markers(child, tc))
    out = _quiet(lambda: Sara.perform_algorithm(rt_p, rt_c, recursive_outlier_removal=trim))
    n_p = np.asarray(out[1], dtype=np.float64)
    c_p = np.asarray(out[4], dtype=np.float64)[:3]
    return n_p, c_p, tp, len(out[6])


def _trial(rng: np.random.Generator, mm: float) -> dict[str, float]:
    noise = float(rng.uniform(0.5, 1.0))  # the same draws, in the same order, as bench/sta.py's _trial
    motion = knee_motion(rng)
    t = np.arange(2000) / 100.0
    parent, child = skin_markers_at(rng, motion, t, child_mm=mm, mode="angle", noise_std=noise)
    out: dict[str, float] = {}
    for where, shift in (("as generated", np.zeros(3)), ("moved", OFFSET)):
        p, c = parent + shift, child + shift
        for trim in (True, False):
            n_p, c_p, tp, kept = _sara(p, c, trim)
            out[f"SARA trim={trim} {where} dir"], out[f"SARA trim={trim} {where} point"] = _errors(motion, tp, n_p, c_p)
            out[f"SARA trim={trim} {where} kept"] = float(kept)
        jf = fit_axis_two_segments(p, c)
        out[f"jointfit {where} dir"], out[f"jointfit {where} point"] = _errors(
            motion, jf.template_parent, jf.direction_parent, jf.point_parent
        )
        out[f"jointfit {where} kept"] = float(jf.n_frames)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=10, help="trials (the first of bench/sta.py's case)")
    parser.add_argument("--out", default="sara_trimming.md", help="result file name in bench/results")
    args_list = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(args_list)
    if biobuddy is None:
        print("SKIP bench/sara_trimming.py: biobuddy is not importable; install the bench extras.")
        return 0
    logging.getLogger("biobuddy").setLevel(logging.WARNING)
    t0 = time.perf_counter()
    index = [c.label for c in CASES].index(CASE)
    seq = np.random.SeedSequence(SEED).spawn(len(CASES))[index]
    rows: dict[str, list[float]] = {}
    for trial_seq in seq.spawn(args.trials):
        for key, value in _trial(np.random.default_rng(trial_seq), CASES[index].mm).items():
            rows.setdefault(key, []).append(value)
    table = []
    for method in ("SARA trim=True", "SARA trim=False", "jointfit"):
        for where in ("as generated", "moved"):
            label = {"SARA trim=True": "SARA (trimming)", "SARA trim=False": "SARA (no trimming)"}.get(method, method)
            table.append([
                label, where, fmt(float(np.mean(rows[f"{method} {where} dir"])), 4),
                fmt(float(np.mean(rows[f"{method} {where} point"])), 4), fmt(float(np.mean(rows[f"{method} {where} kept"]))),
            ])
    same = max(
        float(np.max(np.abs(np.subtract(rows[f"SARA trim=False {w} {k}"], rows[f"jointfit {w} {k}"]))))
        for w in ("as generated", "moved")
        for k in ("dir", "point")
    )
    parts = run_header(
        "SARA's frame trimming: the closed form without it, and the lab origin",
        SCRIPT,
        args_list,
        SEED,
        f"{args.trials} trials of bench/sta.py's '{CASE}' case; markers as generated and moved by "
        f"{tuple(OFFSET.tolist())} mm. The data and the measures are described in the script's docstring.",
    )
    parts += [
        markdown_table(
            ["method", "lab origin", "direction error (deg)", "point error (mm)", "frames used (of 2000)"],
            table,
            align="llrrr",
        ),
        "",
        f"Largest per-trial difference between SARA without trimming and jointfit (deg or mm): {same:.2g}.",
        "",
        elapsed_line(t0),
    ]
    print_and_write(args.out, parts)
    return 0


if __name__ == "__main__":
    sys.exit(main())
