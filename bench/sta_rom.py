"""Soft-tissue artefact, online, by range of motion: where do the published covariances stop holding?

Run with ``PYTHONPATH=. python bench/sta_rom.py`` (``--trials N``, default 40; ``--quick`` 8) from the
repository root; prints Markdown and writes ``bench/results/sta_rom.md`` (``--out`` another name).
Issue 17.

Data: as ``bench/sta_online.py`` at 100 Hz (:func:`jointfit_core.soft_tissue.hip_motion`, 30 s of
star arcs and circumductions; :func:`~jointfit_core.soft_tissue.knee_motion`, 20 s of flexion cycles;
4 markers a cluster; 0.5-1 mm of white noise), with 10 mm rms of skin artefact on the thigh (hip) or
the shank (knee) (:func:`~jointfit_core.soft_tissue.skin_markers_at`: linear plus quadratic in the
joint angles, 75 % rigid cluster motion), at several ranges of motion: the movement's amplitude is
the row's (hip: star arcs and circumductions of that many degrees; knee: flexion from 0 to that
many degrees). The artefact keeps its 10 mm at every range, so a small range is an artefact large
against the motion (a pessimistic case: real skin moves less when the joint moves less).

Estimator: ``OnlineJoint(kind, window=all frames, attachment="skin")``, one estimate at the end.

Measures: e/k as ``bench/sta_online.py`` (hip centre k = 3, knee direction k = 2); its mean and
median over all trials; the share above 3 over all trials and over those the estimator did not
flag as not identifiable (an honest covariance: 3 % for k = 3, 5 % for k = 2); the largest e/k
of an unflagged trial (a confidently wrong answer when large); the flagged share; the mean error
and the rms sd (mm or deg).
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

from _paper_helpers import elapsed_line, fmt, markdown_table, print_and_write, run_header
from sta_online import _measure

from jointfit_core.estimator import OnlineJoint
from jointfit_core.soft_tissue import hip_motion, knee_motion, skin_markers_at

SCRIPT = "sta_rom.py"
SEED = 20261203
RATE_HZ = 100.0
ARTEFACT_MM = 10.0


@dataclass(frozen=True)
class Regime:
    kind: str  # "ball" (hip) or "hinge" (knee)
    amplitude_deg: float
    seconds: float


REGIMES = (
    Regime("ball", 8.0, 30.0),
    Regime("ball", 12.0, 30.0),
    Regime("ball", 15.0, 30.0),
    Regime("ball", 25.0, 30.0),
    Regime("hinge", 20.0, 20.0),
    Regime("hinge", 30.0, 20.0),
    Regime("hinge", 45.0, 20.0),
    Regime("hinge", 90.0, 20.0),
)


def _trial(rng: np.random.Generator, regime: Regime) -> dict[str, float]:
    noise = float(rng.uniform(0.5, 1.0))
    make = hip_motion if regime.kind == "ball" else knee_motion
    motion = make(rng, amplitude_deg=regime.amplitude_deg)
    t = np.arange(round(regime.seconds * RATE_HZ)) / RATE_HZ
    parent, child = skin_markers_at(rng, motion, t, child_mm=ARTEFACT_MM, noise_std=noise)
    est = OnlineJoint(regime.kind, window=t.size + 10, attachment="skin")
    try:
        est.update_many(parent, child, t)
        return _measure(est, motion, regime.kind)
    except ValueError:  # InputError / NotIdentifiableError: counted, not averaged
        return {"refused": 1.0}


def run(trials: int, seed: int = SEED) -> list[tuple[Regime, list[dict[str, float]]]]:
    out = []
    for regime, seq in zip(REGIMES, np.random.SeedSequence(seed).spawn(len(REGIMES)), strict=True):
        out.append((regime, [_trial(np.random.default_rng(s), regime) for s in seq.spawn(trials)]))
    return out


def _row(regime: Regime, rows: list[dict[str, float]]) -> list[str]:
    ok = [r for r in rows if "e" in r]
    e = np.array([r["e"] for r in ok])
    flagged = np.array([r["flagged"] for r in ok]) > 0.5
    clear = e[~flagged]
    return [
        "hip" if regime.kind == "ball" else "knee",
        f"{regime.amplitude_deg:g}",
        fmt(float(e.mean())) if e.size else "-",
        fmt(float(np.median(e))) if e.size else "-",
        fmt(float(np.mean(e > 3.0))) if e.size else "-",
        str(int(clear.size)),
        fmt(float(np.mean(clear > 3.0))) if clear.size else "-",
        fmt(float(clear.max())) if clear.size else "-",
        fmt(float(flagged.mean())) if e.size else "-",
        fmt(float(np.mean([r["err"] for r in ok]))) if ok else "-",
        fmt(float(np.sqrt(np.mean([r["sd"] ** 2 for r in ok])))) if ok else "-",
        str(len(rows) - len(ok)),
    ]


def tables(results: list[tuple[Regime, list[dict[str, float]]]]) -> list[str]:
    rows = [_row(regime, trial_rows) for regime, trial_rows in results]
    return [
        "## Hip centre (mm, e/3) and knee direction (deg, e/2), 10 mm of skin artefact, by range of motion",
        "",
        markdown_table(
            ["joint", "range (deg)", "mean e/k", "median e/k", "share e/k > 3", "unflagged", "unflagged share > 3",
             "unflagged max e/k", "flagged", "error", "sd (rms)", "refused"],
            rows,
            align="lrrrrrrrrrrr",
        ),
        "",
        "e/k = delta^T cov^+ delta / k for the published covariance; an honest one has mean 1 and a share above 3 "
        "of 3 % (k = 3) or 5 % (k = 2). unflagged: trials the estimator did not call not identifiable; their "
        "largest e/k is the worst confidently wrong answer. error: mean over the trials (hip mm, knee deg); "
        "sd (rms): root mean square of sqrt(tr cov).",
    ]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="8 trials per range instead of 40")
    parser.add_argument("--trials", type=int, default=None, help="trials per range (overrides --quick)")
    parser.add_argument("--out", default="sta_rom.md", help="result file name in bench/results")
    args_list = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(args_list)
    trials = args.trials or (8 if args.quick else 40)
    t0 = time.perf_counter()
    results = run(trials)
    parts = run_header(
        "Soft-tissue artefact, online, by range of motion",
        SCRIPT,
        args_list,
        SEED,
        f"{trials} trials per range; the data and the measures are described in the script's docstring.",
    )
    parts += tables(results)
    parts.append(elapsed_line(t0))
    print_and_write(args.out, parts)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
