"""Minimal marker sets (Pham et al.) against the two-segment pose methods on the same motion.

Run with ``python bench/minimal.py`` (from the repository root, ``PYTHONPATH=.``); prints
Markdown and writes ``bench/results/minimal.md``. Every number comes from this run (seeded
``np.random.default_rng``).

What is measured
----------------
Random rigs from :func:`jointfit_core.synthetic.minimal_marker_motion`: two links with 3
markers each, 300 mm between a link's farthest markers, the joint 300 mm from each link's
marker centroid, ``N_FRAMES`` frames of a 20 s motion (the parent wanders by ~15 deg and
~100 mm, the child rotates about the joint), isotropic Gaussian noise of sqrt(tr W) = 1.7 mm
(Stoddart's level) or 0.17 mm. Every method sees the same noisy markers of a trial; the
minimal methods use a subset of them.

1. **Ball joint.** S22 (:func:`fit_centre_minimal`, parent markers 0-1 and child markers
   0-1), S31 (3 parent markers + child marker 0) and S32 (3 + 2) with the same distance-model
   fit, and :func:`fit_centre_two_segments` on 3 + 3 (Stoddart's weighted pose method).
   Columns: median over frames and trials of the per-frame world centre error
   ``|c_t - c_true,t|``; median of the reported per-frame ``sqrt(tr cov_world)``; the paper's
   consistency measure ``sqrt(C)``, ``C = sum_k var_t(|c_t - X_k,t|)`` over all 6 markers (the
   paper's section V-A uses it to compare S22 with Gamage-Lasenby, 9.18 vs 9.65 mm on their
   jump data; the true centre's own ``sqrt(C)`` is the noise floor); the fraction of fits
   flagged not identifiable; the median time per fit.
2. **Hinge.** R21 (:func:`fit_axis_minimal`, parent markers 0-1 and child marker 0, with the
   true axis of each frame as ``axis_hint``, so that the discrete ambiguity is resolved in its
   favour), its closed form alone (:func:`r21_closed_form`: the admissible root nearest the
   truth; its error in the pair's DH constants ``d, r, l, rho`` and ``alpha``), and
   :func:`fit_axis_two_segments` on 3 + 3. Columns: median per-frame angle between the
   estimated and the true axis, median distance of the estimated axis point from the true axis
   line, the median reported direction sd, flagged fraction, time per fit.
"""

from __future__ import annotations

import datetime as dt
import platform
import sys
import time
from pathlib import Path

import numpy as np
from _common import save_results
from numpy.typing import NDArray

from jointfit_core import (
    fit_axis_minimal,
    fit_axis_two_segments,
    fit_centre_minimal,
    fit_centre_two_segments,
    r21_closed_form,
)
from jointfit_core.errors import NotIdentifiableError
from jointfit_core.synthetic import TwoSegmentMotion, minimal_marker_motion

FloatArray = NDArray[np.float64]

SEED = 20260611
N_FRAMES = 400
TRIALS = 10
NOISE_TR_MM = (1.7, 0.17)  # sqrt(tr W_y); per coordinate: / sqrt(3)
RESULTS = Path(__file__).resolve().parent / "results" / "minimal.md"
PAPER = "Pham, Ayusawa, Kubota & Nakamura: sqrt(C_S22) = 9.18 mm (2 + 2 markers) vs sqrt(C_GL) = 9.65 mm (Gamage-Lasenby extended to two moving links, 3 + 2 markers), 22 frames of a jump, real data"


def _sqrt_c(centre: FloatArray, markers: FloatArray) -> float:
    """The paper's sqrt(sum_k var_t |c_t - X_k,t|) over the frames where the centre is defined."""
    ok = np.isfinite(centre).all(axis=1)
    dist = np.linalg.norm(markers[ok] - centre[ok, None, :], axis=2)
    return float(np.sqrt(np.sum(np.var(dist, axis=0))))


def _trial(rng: np.random.Generator, kind: str, sigma: float) -> tuple[TwoSegmentMotion, FloatArray, FloatArray, FloatArray]:
    rig = minimal_marker_motion(rng, kind=kind, n_markers=(3, 3))
    times = np.linspace(0.0, 20.0, N_FRAMES)
    yp, yc = rig.markers_at(times)
    return rig, times, yp + rng.normal(0.0, sigma, yp.shape), yc + rng.normal(0.0, sigma, yc.shape)


def ball_table(rng: np.random.Generator) -> list[str]:
    rows = [
        "| noise sqrt(tr W) (mm) | method | markers | centre error (mm) | sqrt(tr cov_world) (mm) | sqrt(C) (mm) | sqrt(C) truth (mm) | flagged | time/fit (s) |",
        "|---:|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    methods = ("S22", "S31", "S32", "two-segment poses")
    for noise in NOISE_TR_MM:
        sigma = noise / np.sqrt(3.0)
        stats: dict[str, dict[str, list[float]]] = {m: {"err": [], "sd": [], "c": [], "c0": [], "flag": [], "t": []} for m in methods}
        for _ in range(TRIALS):
            rig, times, yp, yc = _trial(rng, "ball", sigma)
            truth = rig.centre_world_at(times)
            all_markers = np.concatenate([yp, yc], axis=1)
            c0 = _sqrt_c(truth, all_markers)
            for method in methods:
                t0 = time.perf_counter()
                try:
                    if method == "S22":
                        fit = fit_centre_minimal(yp[:, :2], yc[:, :2])
                    elif method == "S31":
                        fit = fit_centre_minimal(yp, yc[:, :1])
                    elif method == "S32":
                        fit = fit_centre_minimal(yp, yc[:, :2])
                    else:
                        fit = fit_centre_two_segments(yp, yc)  # type: ignore[assignment]
                except NotIdentifiableError:
                    stats[method]["flag"].append(1.0)
                    continue
                stats[method]["t"].append(time.perf_counter() - t0)
                centre, cov = fit.centre_world, fit.cov_world
                stats[method]["err"].append(float(np.nanmedian(np.linalg.norm(centre - truth, axis=1))))
                stats[method]["sd"].append(float(np.nanmedian(np.sqrt(np.trace(cov, axis1=1, axis2=2)))))
                stats[method]["c"].append(_sqrt_c(centre, all_markers))
                stats[method]["c0"].append(c0)
                stats[method]["flag"].append(0.0 if fit.identifiable else 1.0)
        for method, count in zip(methods, ("2 + 2", "3 + 1", "3 + 2", "3 + 3"), strict=True):
            s = stats[method]
            rows.append(
                f"| {noise:g} | {method} | {count} | {np.median(s['err']):.2f} | {np.median(s['sd']):.2f} | "
                f"{np.median(s['c']):.2f} | {np.median(s['c0']):.2f} | {np.mean(s['flag']):.2f} | {np.median(s['t']):.2f} |"
            )
    return rows


def _true_dh(rig: TwoSegmentMotion) -> FloatArray:
    """DH constants (d, r, alpha, l, rho) of the true hinge vs parent markers 0-1 and child marker 0 (cos alpha >= 0)."""
    a0, a1 = rig.template_parent[:2]
    u = (a1 - a0) / np.linalg.norm(a1 - a0)
    n = rig.axis if u @ rig.axis >= 0 else -rig.axis
    w0 = a0 - rig.centre_parent
    b, du, dn = u @ n, u @ w0, n @ w0
    s = (b * dn - du) / (1 - b * b)
    t = (dn - b * du) / (1 - b * b)
    r = np.linalg.norm(rig.centre_parent + t * n - (a0 + s * u))
    x_b = rig.template_child[0] - rig.centre_child
    return np.array([s, r, np.arccos(b), x_b @ n - t, np.linalg.norm(x_b - (x_b @ n) * n)])


def hinge_table(rng: np.random.Generator) -> list[str]:
    rows = [
        "| noise sqrt(tr W) (mm) | method | markers | axis angle error (deg) | axis point off-axis (mm) | direction sd (deg) | DH length error (mm) | alpha error (deg) | flagged | time/fit (s) |",
        "|---:|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    methods = ("R21 closed form", "R21 refined", "two-segment poses")
    for noise in NOISE_TR_MM:
        sigma = noise / np.sqrt(3.0)
        stats: dict[str, dict[str, list[float]]] = {m: {"ang": [], "off": [], "sd": [], "dh": [], "alpha": [], "flag": [], "t": []} for m in methods}
        for _ in range(TRIALS):
            rig, times, yp, yc = _trial(rng, "hinge", sigma)
            R_p, d_p, _, _ = rig.poses_at(times)
            point = np.einsum("nij,j->ni", R_p, rig.centre_parent) + d_p
            direction = np.einsum("nij,j->ni", R_p, rig.axis)
            dh_true = _true_dh(rig)
            t0 = time.perf_counter()
            rows_cf = r21_closed_form(yp[:, :2], yc[:, :1])
            stats["R21 closed form"]["t"].append(time.perf_counter() - t0)
            best = rows_cf[np.argmin(np.max(np.abs(rows_cf[:, [0, 1, 3, 4]] - dh_true[[0, 1, 3, 4]]), axis=1))]
            stats["R21 closed form"]["dh"].append(float(np.max(np.abs(best[[0, 1, 3, 4]] - dh_true[[0, 1, 3, 4]]))))
            stats["R21 closed form"]["alpha"].append(float(np.rad2deg(abs(best[2] - dh_true[2]))))
            for method in methods[1:]:
                t0 = time.perf_counter()
                try:
                    if method == "R21 refined":
                        fit = fit_axis_minimal(yp[:, :2], yc[:, :1], axis_hint=direction)
                    else:
                        fit = fit_axis_two_segments(yp, yc)  # type: ignore[assignment]
                except NotIdentifiableError:
                    stats[method]["flag"].append(1.0)
                    continue
                stats[method]["t"].append(time.perf_counter() - t0)
                ang = np.rad2deg(np.arccos(np.clip(np.abs(np.einsum("ni,ni->n", fit.direction_world, direction)), 0.0, 1.0)))
                w = fit.point_world - point
                off = np.linalg.norm(w - np.einsum("ni,ni->n", w, direction)[:, None] * direction, axis=1)
                cov_dir = fit.cov_direction_world if method == "R21 refined" else None
                stats[method]["ang"].append(float(np.nanmedian(ang)))
                stats[method]["off"].append(float(np.nanmedian(off)))
                if cov_dir is not None:
                    stats[method]["sd"].append(float(np.rad2deg(np.nanmedian(np.sqrt(np.linalg.eigvalsh(cov_dir)[:, -1])))))
                    dh = fit.dh.copy()
                    if np.cos(dh[2]) < 0:  # fold to the closed form's convention
                        dh[2], dh[3] = np.pi - dh[2], -dh[3]
                    stats[method]["dh"].append(float(np.max(np.abs(dh[[0, 1, 3, 4]] - dh_true[[0, 1, 3, 4]]))))
                    stats[method]["alpha"].append(float(np.rad2deg(abs(abs(dh[2]) - dh_true[2]))))
                stats[method]["flag"].append(0.0 if fit.identifiable else 1.0)
        for method, count in zip(methods, ("2 + 1", "2 + 1", "3 + 3"), strict=True):
            s = stats[method]

            def med(key: str, fmt: str = ".2f", s: dict[str, list[float]] = s) -> str:
                return format(float(np.median(s[key])), fmt) if s[key] else "-"

            flagged = f"{np.mean(s['flag']):.2f}" if s["flag"] else "-"
            rows.append(
                f"| {noise:g} | {method} | {count} | {med('ang')} | {med('off')} | {med('sd')} | {med('dh', '.1f')} | "
                f"{med('alpha', '.1f')} | {flagged} | {med('t', '.3f')} |"
            )
    return rows


def main() -> None:
    rng = np.random.default_rng(SEED)
    start = time.perf_counter()
    ball = ball_table(rng)
    hinge = hinge_table(rng)
    elapsed = time.perf_counter() - start
    lines = [
        "# Minimal marker sets (Pham et al.) vs the two-segment pose methods",
        "",
        f"Made by `PYTHONPATH=. python bench/minimal.py` on {dt.date.today().isoformat()}, seed {SEED}, "
        f"{TRIALS} random rigs per noise level, {N_FRAMES} frames each; {platform.platform()}, numpy {np.__version__}; "
        f"total {elapsed:.0f} s. Medians over the frames, then over the trials.",
        "",
        "## 1. Ball joint",
        "",
        *ball,
        "",
        f"Paper's reference (section V-A): {PAPER}. Their sqrt(C) mixes the centre's error with the marker",
        "noise and skin motion of a real jump; here the truth's own sqrt(C) (the noise floor of this measure) is",
        "given next to each row. S22 needs no link frame; its per-frame centre carries that frame's noise",
        "through the elongated 4-sphere intersection, hence its larger per-frame error.",
        "",
        "## 2. Hinge",
        "",
        *hinge,
        "",
        "R21 refined is given the true per-frame axis as axis_hint (the 2 + 1 data fit four hinges equally",
        "well: two roots of eq. 13, each with its mirror image). The DH columns compare the pair-relative",
        "constants (d, r, l, rho: largest absolute error; alpha) with the truth; two-segment fits have no DH",
        "constants. With 2 + 1 markers the hinge constants are very sensitive to noise (a 5-parameter curve",
        "fitted to the arc that the single marker traces in the pair's meridian plane), which the flagged",
        "column and the direction sd show.",
    ]
    text = "\n".join(lines) + "\n"
    sys.stdout.write(text)
    save_results(RESULTS, text)


if __name__ == "__main__":
    main()
