"""Soft-tissue artefact, online: calibration of :class:`~jointfit_core.estimator.OnlineJoint` at 100, 25 and 12.5 Hz.

Run with ``PYTHONPATH=. python bench/sta_online.py`` (``--trials N``, default 20; ``--quick`` 6) from the
repository root; prints Markdown and writes ``bench/results/sta_online.md`` (``--out`` another name).

Data: :func:`jointfit_core.soft_tissue.hip_motion` (pelvis and thigh 4 markers each; 8 star arcs then
4 circumductions of 25 deg, 2.5 s each; 30 s) and :func:`~jointfit_core.soft_tissue.knee_motion` (thigh
and shank 4 markers each, flexion 0-90 deg in 2.5 s cycles; 20 s) with the skin artefact of
:func:`~jointfit_core.soft_tissue.skin_markers_at` (linear plus quadratic in the joint angles, 75 % rigid
cluster motion, rms amplitude as in the case's label) on the thigh (hip) or the shank (knee), and white
noise of 0.5-1 mm per coordinate (uniform per trial). "rigid": no artefact, the estimator told
``attachment="rigid"`` (the control). Each trial is generated once at 100 Hz; the 25 and 12.5 Hz rows
feed the same trial's every 4th and every 8th frame (same seconds of motion, same artefact and noise),
so the rates differ only in the frames the estimator sees.

Estimator: ``OnlineJoint(kind, window=all frames, attachment="skin" or "rigid")`` fed the whole trial
with :meth:`~jointfit_core.estimator.OnlineJoint.update_many` (stamps in seconds), then one
:meth:`~jointfit_core.estimator.OnlineJoint.estimate`.

Measures (truth mapped into the estimator's template frame by Procrustes of template onto template):
e/3 (hip centre, parent frame) and e/2 (knee direction, parent frame, the covariance's two largest
directions) with ``e = delta^T cov^+ delta``: mean, median, and the share of trials above 3 (a
confidently wrong answer: for an honest covariance P(chi2_3 / 3 > 3) = 3 %, P(chi2_2 / 2 > 3) = 5 %).
error: mean distance (mm) or angle (deg); sd: root mean square over trials of sqrt(tr cov) (mm, deg);
factor: median serial factor applied to the statistical covariance; scale: median artefact scale
(mm per rad, skin only).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import selected
from _paper_helpers import (
    angle_deg,
    elapsed_line,
    fmt,
    mahalanobis,
    mahalanobis_rank,
    markdown_table,
    print_and_write,
    rotation_to_estimated_frame,
    run_header,
    to_estimated_frame,
)

from jointfit_core.estimator import OnlineJoint
from jointfit_core.soft_tissue import hip_motion, knee_motion, skin_markers_at

SCRIPT = "sta_online.py"
SEED = 20261202
BASE_HZ = 100.0
#: Rates fed (Hz) and the subsampling step of the 100 Hz trial that gives them.
RATES = ((100.0, 1), (25.0, 4), (12.5, 8))


@dataclass(frozen=True)
class Case:
    label: str
    kind: str  # "ball" (hip) or "hinge" (knee)
    mm: float  # artefact amplitude on the thigh (hip) or the shank (knee); 0: rigid control
    seconds: float


CASES = (
    Case("hip, thigh 5 mm", "ball", 5.0, 30.0),
    Case("hip, thigh 10 mm", "ball", 10.0, 30.0),
    Case("hip, thigh 20 mm", "ball", 20.0, 30.0),
    Case("hip, rigid", "ball", 0.0, 30.0),
    Case("knee, shank 5 mm", "hinge", 5.0, 20.0),
    Case("knee, shank 10 mm", "hinge", 10.0, 20.0),
    Case("knee, shank 20 mm", "hinge", 20.0, 20.0),
    Case("knee, rigid", "hinge", 0.0, 20.0),
)


def _measure(est: OnlineJoint, motion: object, kind: str) -> dict[str, float]:
    sol = est.estimate()
    tp = est.templates[0]
    assert tp is not None
    out: dict[str, float] = {}
    if kind == "ball":
        truth = to_estimated_frame(motion.template_parent, tp, motion.centre_parent)  # type: ignore[attr-defined]
        delta = sol.centre_parent - truth
        out["err"] = float(np.linalg.norm(delta))
        out["e"] = mahalanobis(delta, sol.cov_parent) / 3.0
        out["sd"] = float(np.sqrt(np.trace(sol.cov_parent)))
    else:
        R = rotation_to_estimated_frame(motion.template_parent, tp)  # type: ignore[attr-defined]
        n_true = R @ motion.axis  # type: ignore[attr-defined]
        signed = n_true if float(n_true @ sol.direction_parent) >= 0.0 else -n_true
        out["err"] = angle_deg(sol.direction_parent, n_true)
        out["e"] = mahalanobis_rank(sol.direction_parent - signed, sol.cov_direction_parent, 2) / 2.0
        out["sd"] = float(np.degrees(np.sqrt(np.trace(sol.cov_direction_parent))))
    serial = est.serial_inflation
    out["factor"] = float("nan") if serial is None else serial.factor
    out["scale"] = est.artefact_scale
    out["flagged"] = float(not sol.identifiable)
    return out


def _trial(rng: np.random.Generator, case: Case) -> list[dict[str, float]]:
    """One trial at each of :data:`RATES` (same motion, artefact and noise, subsampled)."""
    noise = float(rng.uniform(0.5, 1.0))
    motion = hip_motion(rng) if case.kind == "ball" else knee_motion(rng)
    t = np.arange(round(case.seconds * BASE_HZ)) / BASE_HZ
    parent, child = skin_markers_at(rng, motion, t, child_mm=case.mm, noise_std=noise)
    rows = []
    for _, step in RATES:
        p, c, s = parent[::step], child[::step], t[::step]
        est = OnlineJoint(case.kind, window=s.size + 10, attachment="rigid" if case.mm == 0.0 else "skin")
        try:
            est.update_many(p, c, s)
            rows.append(_measure(est, motion, case.kind))
        except ValueError:  # InputError / NotIdentifiableError: counted, not averaged
            rows.append({"refused": 1.0})
    return rows


def run(trials: int, seed: int = SEED, cases: Sequence[str] = ()) -> list[tuple[Case, list[dict[str, list[float]]]]]:
    results = []
    for case, seq in zip(CASES, np.random.SeedSequence(seed).spawn(len(CASES)), strict=True):
        if not selected(case.label, cases):
            continue  # its seed is still spawned: a case's trials do not depend on the filter
        acc: list[dict[str, list[float]]] = [{} for _ in RATES]
        for trial_seq in seq.spawn(trials):
            for a, row in zip(acc, _trial(np.random.default_rng(trial_seq), case), strict=True):
                for key, value in row.items():
                    a.setdefault(key, []).append(value)
        results.append((case, acc))
    return results


def _vals(acc: dict[str, list[float]], key: str) -> np.ndarray:
    v = np.asarray(acc.get(key, []), dtype=np.float64)
    return v[np.isfinite(v)]


def _stat(acc: dict[str, list[float]], key: str, how: str) -> float:
    v = _vals(acc, key)
    if not v.size:
        return float("nan")
    if how == "mean":
        return float(v.mean())
    if how == "median":
        return float(np.median(v))
    if how == "rms":
        return float(np.sqrt(np.mean(v**2)))
    return float(np.mean(v > 3.0))  # "over3"


def tables(results: list[tuple[Case, list[dict[str, list[float]]]]]) -> list[str]:
    parts: list[str] = []
    for kind, title, k, unit in (
        ("ball", "Hip (ball joint): centre in the pelvis frame", "e/3", "mm"),
        ("hinge", "Knee (hinge): direction in the thigh frame", "e/2", "deg"),
    ):
        rows = []
        for case, accs in results:
            if case.kind != kind:
                continue
            for (rate, _), a in zip(RATES, accs, strict=True):
                rows.append([
                    case.label, f"{rate:g}", fmt(_stat(a, "e", "mean")), fmt(_stat(a, "e", "median")),
                    fmt(_stat(a, "e", "over3")), fmt(_stat(a, "err", "mean")), fmt(_stat(a, "sd", "rms")),
                    fmt(_stat(a, "factor", "median")), fmt(_stat(a, "scale", "median")),
                    fmt(_stat(a, "flagged", "mean")), str(len(a.get("refused", []))),
                ])
        if not rows:
            continue  # no case of this kind selected (--cases)
        parts += [
            f"## {title}",
            "",
            markdown_table(
                ["case", "Hz", f"mean {k}", f"median {k}", f"share {k} > 3", f"error ({unit})", f"sd ({unit})",
                 "factor", "scale (mm/rad)", "flagged", "refused"],
                rows,
                align="lrrrrrrrrrr",
            ),
            "",
        ]
    parts.append(
        "An honest covariance has mean e/k 1 and a share above 3 of 3 % (ball) or 5 % (hinge). sd: root mean "
        "square over the trials of sqrt(tr cov). factor: median serial factor of the statistical part; scale: "
        "median artefact scale (0 for rigid). flagged: share of estimates reported not identifiable (still "
        "counted); refused: trials the estimator rejected (not averaged)."
    )
    return parts


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="6 trials per case instead of 20")
    parser.add_argument("--trials", type=int, default=None, help="trials per case (overrides --quick)")
    parser.add_argument("--out", default="sta_online.md", help="result file name in bench/results")
    parser.add_argument(
        "--cases", nargs="+", default=(), metavar="TEXT",
        help="run only the cases whose label contains one of these texts (e.g. knee); default all",
    )
    args_list = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(args_list)
    trials = args.trials or (6 if args.quick else 20)
    t0 = time.perf_counter()
    results = run(trials, cases=args.cases)
    parts = run_header(
        "Soft-tissue artefact, online: calibration across frame rates",
        SCRIPT,
        args_list,
        SEED,
        f"{trials} trials per case; the data and the measures are described in the script's docstring.",
    )
    parts += tables(results)
    parts += ["", elapsed_line(t0)]
    print_and_write(args.out, parts)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
