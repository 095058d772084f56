"""Consistency across movement blocks: false-alarm and detection rates of "skin artefact dominates".

Run with ``python bench/consistency.py`` (``--trials N``, default 30;
``--quick`` 6); prints Markdown and writes ``bench/results/consistency.md``.

Each trial is an :class:`~jointfit_core.estimator.OnlineJoint` over a whole
trial (its window holds every frame), checked by
:func:`~jointfit_core.block_check.window_consistency` (4 blocks):

- rigid rigs: :func:`jointfit_core.synthetic.two_segment_motion`, 40 s at
  60 Hz, 0.5 mm noise (the estimator told ``rigid`` and ``skin``): every WARN
  is a false alarm; "still start": the same, but the first 1160 frames
  (19 s) stand still in the start posture, so that the second block holds
  the end of the stance and the first 40 frames (0.7 s) of movement;
- a steady artefact: :func:`~jointfit_core.soft_tissue.hip_motion` /
  :func:`~jointfit_core.soft_tissue.knee_motion` (30 s at 100 Hz) with the
  same artefact field throughout (linear plus quadratic in the angles,
  :func:`~jointfit_core.soft_tissue.skin_markers_at`), 0.7 mm noise;
- an artefact that changes between movements: a new field (``mode`` as
  given) every 7.5 s (a re-seated cluster, tissue loaded differently).

Columns: the share of trials with the WARN, the mean and median of
``ratio = sqrt(chi2 / dof)`` (~1 when the covariances are honest), the mean
spread of the blocks (mm; hinge: deg) and the blocks compared.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence

import numpy as np
from _paper_helpers import elapsed_line, markdown_table, print_and_write, run_header

from jointfit_core.block_check import window_consistency
from jointfit_core.estimator import OnlineJoint
from jointfit_core.soft_tissue import hip_motion, knee_motion, skin_markers_by_block
from jointfit_core.synthetic import two_segment_motion

SCRIPT = "consistency.py"
SEED = 20261201


def _rigid(rng: np.random.Generator, kind: str, attachment: str, still: int = 0) -> OnlineJoint:
    motion = two_segment_motion(rng, kind=kind)
    t = np.arange(2400) / 60.0
    yp, yc = motion.markers_at(np.concatenate([np.zeros(still), t[: t.size - still]]))
    est = OnlineJoint(kind, window=t.size + 10, attachment=attachment)
    est.update_many(yp + rng.normal(0.0, 0.5, yp.shape), yc + rng.normal(0.0, 0.5, yc.shape), t)
    return est


def _skin(rng: np.random.Generator, kind: str, mm: float, attachment: str, per_block: bool, mode: str) -> OnlineJoint:
    motion = hip_motion(rng) if kind == "ball" else knee_motion(rng)
    t = np.arange(3000) / 100.0
    parent_mm = mm if kind == "hinge" else 0.0
    parent, child = skin_markers_by_block(
        rng, motion, t, 4 if per_block else 1, child_mm=mm, parent_mm=parent_mm, mode=mode, noise_std=0.7
    )
    est = OnlineJoint(kind, window=t.size + 10, attachment=attachment)
    est.update_many(parent, child, t)
    return est


CASES: list[tuple[str, str, str, float, str, bool, str]] = [
    # (label, source, kind, mm, attachment, per_block, mode)
    ("rigid rig", "rigid", "ball", 0.0, "rigid", False, ""),
    ("rigid rig", "rigid", "ball", 0.0, "skin", False, ""),
    ("rigid rig", "rigid", "hinge", 0.0, "rigid", False, ""),
    ("rigid rig", "rigid", "hinge", 0.0, "skin", False, ""),
    ("rigid rig, still start", "still", "ball", 0.0, "rigid", False, ""),
    ("rigid rig, still start", "still", "hinge", 0.0, "rigid", False, ""),
    ("rigid rig, still start", "still", "hinge", 0.0, "skin", False, ""),
    ("steady artefact", "skin", "ball", 10.0, "skin", False, "angle"),
    ("steady artefact", "skin", "ball", 10.0, "rigid", False, "angle"),
    ("steady artefact", "skin", "hinge", 10.0, "skin", False, "angle"),
    ("artefact per block", "skin", "ball", 10.0, "rigid", True, "rigid"),
    ("artefact per block", "skin", "ball", 10.0, "skin", True, "rigid"),
    ("artefact per block", "skin", "ball", 20.0, "skin", True, "angle"),
    ("artefact per block", "skin", "hinge", 10.0, "skin", True, "angle"),
    ("artefact per block", "skin", "hinge", 20.0, "skin", True, "rigid"),
]


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trials", type=int, default=30)
    p.add_argument("--quick", action="store_true", help="6 trials per case")
    args = p.parse_args(argv)
    trials = 6 if args.quick else args.trials
    t_start = time.perf_counter()
    rows = []
    for label, source, kind, mm, attachment, per_block, mode in CASES:
        rng = np.random.default_rng([SEED, len(rows)])
        warns, ratios, spreads, blocks = 0, [], [], []
        for _ in range(trials):
            if source == "skin":
                est = _skin(rng, kind, mm, attachment, per_block, mode)
            else:
                est = _rigid(rng, kind, attachment, 1160 if source == "still" else 0)
            est.estimate()
            c = window_consistency(est, units="mm")
            if c is None or c.consistent is None:
                continue
            warns += c.warns
            ratios.append(c.ratio)
            spreads.append(c.spread if kind == "ball" else c.spread_deg)
            blocks.append(c.n_blocks)
        n = len(ratios)
        rows.append([
            label, kind, f"{mm:g}" + (f" ({mode})" if mode else ""), attachment, f"{n}/{trials}",
            f"{100.0 * warns / max(n, 1):.0f} %", f"{np.mean(ratios):.2f}", f"{np.median(ratios):.2f}",
            f"{np.mean(spreads):.3g} {'mm' if kind == 'ball' else 'deg'}", f"{np.mean(blocks):.1f}",
        ])
    parts = run_header("Consistency across movement blocks", SCRIPT, sys.argv[1:] if argv is None else argv, SEED,
                       __doc__.split("\n\n", 2)[2])
    parts += ["", markdown_table(
        ["case", "kind", "artefact mm", "attachment", "checked", "WARN", "mean ratio", "median ratio", "spread",
         "blocks"], rows, "llllrrrrrr"), "", elapsed_line(t_start)]
    print_and_write("consistency.md", parts)
    return 0


if __name__ == "__main__":
    sys.exit(main())
