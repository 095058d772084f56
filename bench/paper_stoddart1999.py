"""Stoddart et al. (1999), Table 1: predicted uncertainty and validation index against the number of frames.

Run with ``python bench/paper_stoddart1999.py`` (``--quick`` for fewer
trials); prints Markdown and writes ``bench/results/paper_stoddart1999.md``.
Every number comes from this run (seeded ``np.random.default_rng``).

Stoddart's experiment: a hand-held two-segment mechanical rig swung like a
pendulum for 20 s (1200 frames at 60 Hz), 3 markers per segment, clusters
100-200 mm wide, the two clusters ~1 m apart with the joint halfway, marker
noise ``sqrt(tr W_y) = 1.7 mm``. For the first N = 4 ... 1200 frames they
list the predicted ``sqrt(tr W_c)`` and the validation index
``v = sqrt(e / 3)``, ``e = (c - c_true)^T W_c^-1 (c - c_true)``, with the
1200-frame estimate standing in for the truth (one trial, so each v is a
single draw).

Here: the same kind of rig, simulated (:func:`jointfit_core.synthetic.two_segment_motion`,
``kind="ball"``, 3 + 3 markers, sinusoidal motion with periods of 2-6.7 s:
the parent wanders ~15 deg and ~100 mm, the child swings 40/30/20 deg about
three axes), isotropic Gaussian noise of 1.7 / sqrt(3) mm per coordinate,
sampled at 60 Hz. For each N the first N frames are fitted with
``fit_centre_two_segments`` (default: Stoddart's weighted Gauss-Markov
solution, eq. 22-23, bias-compensated, with the model-error inflation) and
with ``model_error=False`` (the pure eq. 23 covariance, as in the paper).
Since the truth is known, v is computed against it as well as, like the
paper, against the trial's own 1200-frame estimate. Errors are those of
``centre_parent`` against the true centre mapped into the estimated local
frame (Procrustes of the true onto the estimated template).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from _paper_helpers import (
    elapsed_line,
    fmt,
    mahalanobis,
    markdown_table,
    print_and_write,
    run_header,
    to_estimated_frame,
)
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from jointfit_core import fit_centre_two_segments
from jointfit_core.errors import InputError, NotIdentifiableError
from jointfit_core.results import SegmentsCentreFit
from jointfit_core.synthetic import two_segment_motion

FloatArray = NDArray[np.float64]

SCRIPT = "paper_stoddart1999.py"
SEED = 19990913
RATE_HZ = 60.0
FRAMES = (4, 8, 16, 32, 75, 150, 300, 600, 1200)
NOISE_TR_MM = 1.7  # sqrt(tr W_y)
#: Stoddart et al. 1999, Table 1: N -> (sqrt(tr W_c) mm, v); v at 1200 is undefined (it is the reference).
PAPER = {
    4: (1872.02, 0.46),
    8: (96.04, 2.62),
    16: (76.60, 3.18),
    32: (35.93, 2.97),
    75: (3.04, 1.82),
    150: (1.10, 3.05),
    300: (0.50, 2.99),
    600: (0.30, 1.38),
    1200: (0.20, float("nan")),
}
VARIANTS = (("default", {}), ("eq. 23", {"model_error": False}))
#: Mean of v = sqrt(e/3) when e is chi-square with 3 degrees of freedom: sqrt(2/3) / Gamma(3/2).
V_CALIBRATED = float(np.sqrt(2.0 / 3.0) * 2.0 / np.sqrt(np.pi))


@dataclass
class Row:
    """Per-trial values of one N."""

    spread: dict[str, list[float]] = field(default_factory=dict)
    e3_truth: dict[str, list[float]] = field(default_factory=dict)
    e3_ref: dict[str, list[float]] = field(default_factory=dict)
    e3_identifiable: list[float] = field(default_factory=list)
    err: list[float] = field(default_factory=list)
    rom: list[float] = field(default_factory=list)
    flagged: int = 0
    refused: int = 0
    seconds: float = 0.0


def _rom_deg(motion: object, t: FloatArray) -> float:
    """Largest relative rotation (child in parent) from the first frame, over ``t``, in degrees."""
    R_p, _, R_c, _ = motion.poses_at(t)  # type: ignore[attr-defined]
    rel = np.einsum("nji,njk->nik", R_p, R_c)
    delta = Rotation.from_matrix(np.einsum("ij,njk->nik", rel[0].T, rel))
    return float(np.degrees(np.max(delta.magnitude())))


def _fit(parent: FloatArray, child: FloatArray, kwargs: dict[str, object]) -> SegmentsCentreFit | None:
    try:
        return fit_centre_two_segments(parent, child, **kwargs)  # type: ignore[arg-type]
    except (InputError, NotIdentifiableError):
        return None


def run(trials: int) -> dict[int, Row]:
    rows = {n: Row() for n in FRAMES}
    sigma = NOISE_TR_MM / np.sqrt(3.0)
    n_max = max(FRAMES)
    t = np.arange(n_max) / RATE_HZ
    for seq in np.random.SeedSequence(SEED).spawn(trials):
        rng = np.random.default_rng(seq)
        motion = two_segment_motion(rng, kind="ball", n_markers=(3, 3), cycle_s=20.0)
        parent, child = motion.markers_at(t)
        parent = parent + rng.normal(0.0, sigma, parent.shape)
        child = child + rng.normal(0.0, sigma, child.shape)
        fits: dict[int, dict[str, SegmentsCentreFit | None]] = {}
        for n in FRAMES:
            t0 = time.perf_counter()
            fits[n] = {label: _fit(parent[:n], child[:n], kw) for label, kw in VARIANTS}
            rows[n].seconds += time.perf_counter() - t0
            rows[n].rom.append(_rom_deg(motion, t[:n]))
        ref = fits[n_max]["default"]
        for n in FRAMES:
            row = rows[n]
            fit = fits[n]["default"]
            if fit is None:
                row.refused += 1
                continue
            row.flagged += int(not fit.identifiable)
            c_true = to_estimated_frame(motion.template_parent, fit.template_parent, motion.centre_parent)
            row.err.append(float(np.linalg.norm(fit.centre_parent - c_true)))
            for label, _ in VARIANTS:
                f = fits[n][label]
                if f is None:
                    continue
                row.spread.setdefault(label, []).append(float(np.sqrt(np.trace(f.cov_parent))))
                row.e3_truth.setdefault(label, []).append(
                    mahalanobis(f.centre_parent - c_true, f.cov_parent) / 3.0
                )
                if label == "default" and f.identifiable:
                    row.e3_identifiable.append(row.e3_truth[label][-1])
                if ref is not None and n < n_max:
                    c_ref = to_estimated_frame(ref.template_parent, f.template_parent, ref.centre_parent)
                    row.e3_ref.setdefault(label, []).append(
                        mahalanobis(f.centre_parent - c_ref, f.cov_parent) / 3.0
                    )
    return rows


def _median(values: Sequence[float]) -> float:
    arr = np.asarray(values, dtype=np.float64)
    arr = arr[np.isfinite(arr)]
    return float(np.median(arr)) if arr.size else float("nan")


def _mean(values: Sequence[float]) -> float:
    arr = np.asarray(values, dtype=np.float64)
    arr = arr[np.isfinite(arr)]
    return float(np.mean(arr)) if arr.size else float("nan")


def _v(values: Sequence[float]) -> float:
    """Mean of the per-trial validation index ``v = sqrt(e/3)``."""
    return _mean(np.sqrt(np.asarray(values, dtype=np.float64)).tolist())


def tables(rows: dict[int, Row], trials: int) -> tuple[str, str]:
    out = []
    for n in FRAMES:
        r = rows[n]
        paper_w, paper_v = PAPER[n]
        out.append(
            [
                str(n),
                fmt(n / RATE_HZ),
                fmt(_mean(r.rom)),
                fmt(paper_w),
                fmt(paper_v),
                fmt(_median(r.spread.get("default", []))),
                fmt(_median(r.err)),
                fmt(float(np.sqrt(_mean(np.square(r.err).tolist())))),
                fmt(_v(r.e3_truth.get("default", []))),
                fmt(_v(r.e3_ref.get("default", []))),
                fmt(_mean(r.e3_truth.get("default", []))),
                fmt(_mean(r.e3_identifiable)),
                fmt(_median(r.spread.get("eq. 23", []))),
                fmt(_v(r.e3_truth.get("eq. 23", []))),
                f"{r.flagged}/{trials - r.refused}",
                str(r.refused),
                fmt(1e3 * r.seconds / trials / len(VARIANTS), 3),
            ]
        )
    header = [
        "N",
        "s",
        "rel. rotation range (deg)",
        "paper √tr W (mm)",
        "paper v",
        "√tr W (mm, median)",
        "error (mm, median)",
        "error (mm, rms)",
        "v vs truth",
        "v vs own N=1200",
        "e/3 vs truth",
        "e/3, identifiable fits",
        "eq. 23 √tr W (mm)",
        "eq. 23 v vs truth",
        "flagged",
        "refused",
        "ms/fit",
    ]
    # conclusion from the numbers
    big = [n for n in FRAMES if n >= 150]
    v_big = [_v(rows[n].e3_truth.get("default", [])) for n in big]
    ratio = [
        _median(rows[n].err) / _median(rows[n].spread.get("default", []))
        for n in big
        if rows[n].spread.get("default")
    ]
    w_1200 = _median(rows[max(FRAMES)].spread.get("default", []))
    rms_1200 = float(np.sqrt(_mean(np.square(rows[max(FRAMES)].err).tolist())))
    small = [n for n in FRAMES if rows[n].flagged + rows[n].refused > 0.5 * trials]
    v_ref = {n: _v(rows[n].e3_ref.get("default", [])) for n in (300, 600)}
    v_tru = {n: _v(rows[n].e3_truth.get("default", [])) for n in (300, 600)}
    lines = [
        f"- N = 1200 (20 s): predicted √tr W {fmt(w_1200)} mm (paper 0.20 mm), actual rms error {fmt(rms_1200)} mm.",
        f"- N >= 150: mean v against the truth {', '.join(fmt(v) for v in v_big)} (a calibrated covariance gives "
        f"a mean v of {V_CALIBRATED:.2f}, the mean of sqrt(chi2_3 / 3); the paper's single-trial v were 1.4-3.1, "
        f"i.e. its covariance was 1.4-3x too small); median error / median √tr W = "
        f"{', '.join(fmt(x) for x in ratio)}.",
        "- Short windows: "
        + (
            f"for N <= {max(small)} most fits are flagged not identifiable or refused (rotation range "
            f"<= {fmt(_mean(rows[max(small)].rom))} deg); there the linearised covariance is too small "
            f"(e/3 up to {fmt(max(_mean(rows[n].e3_truth.get('default', [])) for n in small))}), which the "
            "verdict says. The paper reports 1872 mm at N = 4 with no such verdict. Fits that jointfit calls "
            f"identifiable have a mean e/3 of {fmt(_mean([e for n in FRAMES for e in rows[n].e3_identifiable]))} "
            "over all N."
            if small
            else "no N had a majority of flagged or refused fits."
        ),
        f"- v against the trial's own 1200-frame estimate (the paper's protocol): {fmt(v_ref[300])} at N = 300 "
        f"and {fmt(v_ref[600])} at N = 600, against {fmt(v_tru[300])} and {fmt(v_tru[600])} with the truth: "
        "the reference shares frames (and their errors) with the window, so this protocol under-states v.",
    ]
    weak = [
        f"N = {n} ({len(rows[n].e3_identifiable)} fits called identifiable, mean e/3 "
        f"{fmt(_mean(rows[n].e3_identifiable))})"
        for n in FRAMES
        if len(rows[n].e3_identifiable) >= 3 and _mean(rows[n].e3_identifiable) > 1.5
    ]
    lines.append(
        "- **Weak spot**: fits that jointfit calls identifiable but whose covariance is too small by more than "
        f"1.5x in e/3: {'; '.join(weak)}. The verdict lets through some short, small-range windows "
        "where the linearisation does not hold yet."
        if weak
        else "- Every N where jointfit calls fits identifiable has a mean e/3 within 1.5 of 1 for them."
    )
    return markdown_table(header, out), "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="20 trials instead of 100")
    parser.add_argument(
        "--trials", type=int, default=None, help="number of simulated trials (overrides --quick)"
    )
    args_list = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(args_list)
    trials = args.trials or (20 if args.quick else 100)
    t_start = time.perf_counter()
    rows = run(trials)
    table, conclusion = tables(rows, trials)
    parts = run_header(
        "Stoddart et al. (1999) Table 1, simulated",
        SCRIPT,
        args_list,
        SEED,
        f"{trials} simulated trials of a Stoddart-like rig (see the script's docstring): 3 + 3 markers, "
        f"sqrt(tr W_y) = {NOISE_TR_MM} mm, {RATE_HZ:g} Hz, the first N frames of a 20 s motion. "
        "Default = `fit_centre_two_segments` as shipped (weighted, bias-compensated, model-error inflation); "
        "eq. 23 = the same with `model_error=False` (Stoddart's own covariance). v = mean over trials of "
        f"sqrt(e/3) (the paper's v is one trial; {V_CALIBRATED:.2f} when calibrated); e/3 = mean of e/3 (1 when calibrated). flagged = fits "
        "reported not identifiable / fits returned; refused = fits that raised. ms/fit = mean time of one "
        "fit (both variants timed, divided by 2).",
    )
    parts += ["## Table 1", "", table, "", conclusion, "", elapsed_line(t_start)]
    print_and_write("paper_stoddart1999.md", parts)
    return 0


if __name__ == "__main__":
    sys.exit(main())
