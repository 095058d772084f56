"""Gamage & Lasenby (2002), section 4: the simulations behind their figures 3-5.

Run with ``python bench/paper_gamage2002.py`` (``--quick`` for 30 trials per
cell, the paper's own count); prints Markdown, writes
``bench/results/paper_gamage2002.md`` and the figures
``bench/results/paper_gamage2002_fig{3,4,5}.png``. Every number comes from
this run (seeded ``np.random.default_rng``; every method sees the same
simulated markers in a trial; means over the trials of a cell).

Set-ups (the paper's, in mm instead of cm)
------------------------------------------
**Axis** (figures 3 and 4): four femur markers at (0, 0, -50), (0, 0, -300),
(0, -50, -150), (0, 50, -150) mm rotate 1 deg per frame for 60 frames about
an axis parallel to y through (0, 0, 50) mm. Figure 3 adds isotropic Gaussian
noise; figure 4 adds a systematic skin-movement error, with and without
1 mm noise (the paper's "variance of 0.01" cm^2).

The paper used the thigh skin movements measured by Cappozzo et al. (1996),
which we do not have. They are replaced by a stylised artefact of the same
kind: each marker slides over the bone by a smooth function of the joint
angle, ``D_p(u) = a_p u + b_p sin(pi u)`` (``u`` the fraction of the
motion, ``a_p, b_p`` random 3-vectors drawn per trial), expressed in the
bone frame and scaled so that its peak is 10 mm at "100 %" (thigh skin
markers move 10-30 mm over the bone in Cappozzo's data). The x axis of
figure 4 is that percentage.

**Centre** (figure 5): markers at (70, -10, 50), (50, -160, 120),
(30, -260, -10), (20, -340, 50) mm about the centre, 100 frames of 1 deg
rotations about an axis that starts along z and takes a random walk
(:func:`jointfit_core.synthetic.gl_random_walk_setup`). As in the paper the
error is relative: |error| / the smallest marker distance from the centre
(86.6 mm).

Methods
-------
- **GL plain**: Gamage-Lasenby eq. (5) / (9) as published
  (``fit_centre(noise_std=0)``, ``fit_axis(noise_std=0)``).
- **jointfit**: the default, bias-compensated fit (``fit_centre()``,
  ``fit_axis()``). For the axis the *direction* is the same eigenvector as
  GL plain (noise adds a multiple of I to A, so it needs no compensation);
  only the axis point differs.
- **Halvorsen d=k** (Halvorsen, Lesser & Lundberg 1999), implemented here:
  marker displacement vectors over a frame difference ``k``,
  ``u = v_{t+k} - v_t``. Axis direction: the unit ``n`` minimising
  ``sum (u . n)^2`` (smallest eigenvector of ``sum u u^T``). Centre: each
  pair lies on a sphere about ``m``, so ``m`` is on the perpendicular
  bisector plane, ``u . m = (|v_{t+k}|^2 - |v_t|^2) / 2``, solved by least
  squares (for the axis point, with the pseudo-inverse orthogonal to ``n``).
- **Silaghi avg** (Silaghi et al. 1998, figure 5 only): one sphere fitted per
  marker (closed form, eq. (5) with P = 1, as Gamage & Lasenby did) and the
  marker centres averaged.

Errors: axis direction angle (deg); axis point: distance from the true axis
line (mm); centre: relative error (% of 86.6 mm). jointfit's reported
covariance is checked with the mean validation index squared (``e/3``
centre, ``e/2`` direction; 1 when calibrated).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from _paper_helpers import (
    angle_deg,
    distance_to_line,
    elapsed_line,
    fmt,
    mahalanobis,
    mahalanobis_rank,
    markdown_table,
    paired_verdict,
    print_and_write,
    pyplot,
    run_header,
    save_figure,
)
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from jointfit_core import fit_axis, fit_centre
from jointfit_core.errors import NotIdentifiableError
from jointfit_core.synthetic import GL_AXIS_MARKERS, GL_CENTRE_MARKERS, gl_random_walk_setup

FloatArray = NDArray[np.float64]

SCRIPT = "paper_gamage2002.py"
SEED = 20020101

AXIS_FRAMES = 60
AXIS_POINT = np.array([0.0, 0.0, 50.0])
AXIS_DIR = np.array([0.0, 1.0, 0.0])
AXIS_NOISE_MM = (0.05, 0.1, 0.25, 0.5, 1.0, 2.0)
AXIS_SWEEP_NOISE_MM = (0.1, 1.0)  # figure 3c/d; 0.1 mm = the paper's 0.01 cm
AXIS_D = (1, 2, 5, 10, 15, 20, 30, 40, 50, 59)
H_SHOWN = (30, 1)  # the paper's figures 3-5 (a) and (b)
SKIN_PERCENT = (0, 25, 50, 75, 100)
SKIN_PEAK_MM = 10.0
SKIN_NOISE_MM = 1.0

CENTRE_FRAMES = 100
CENTRE_NOISE_MM = (0.1, 0.25, 0.5, 1.0, 2.0, 4.0)
CENTRE_SWEEP_NOISE_MM = (0.5, 2.0)
CENTRE_D = (1, 2, 5, 10, 20, 30, 50, 70, 90, 99)
MIN_MARKER_DISTANCE = float(np.min(np.linalg.norm(GL_CENTRE_MARKERS, axis=1)))


# ----------------------------------------------------------------------------- estimators


def halvorsen_axis(markers: FloatArray, d: int) -> tuple[FloatArray, FloatArray]:
    """Halvorsen et al. (1999) axis from displacements over ``d`` frames: ``(direction, point)``."""
    v1, v2 = markers[:-d].reshape(-1, 3), markers[d:].reshape(-1, 3)
    u = v2 - v1
    rhs = 0.5 * (np.einsum("ij,ij->i", v2, v2) - np.einsum("ij,ij->i", v1, v1))
    lam, vecs = np.linalg.eigh(u.T @ u)
    plane = vecs[:, 1:]
    point: FloatArray = plane @ ((plane.T @ (u.T @ rhs)) / lam[1:])
    return vecs[:, 0], point


def halvorsen_centre(markers: FloatArray, d: int) -> FloatArray:
    """Halvorsen et al. (1999) centre: least squares over the bisector planes of ``d``-frame pairs."""
    v1, v2 = markers[:-d].reshape(-1, 3), markers[d:].reshape(-1, 3)
    u = v2 - v1
    rhs = 0.5 * (np.einsum("ij,ij->i", v2, v2) - np.einsum("ij,ij->i", v1, v1))
    out: FloatArray = np.linalg.solve(u.T @ u, u.T @ rhs)
    return out


def silaghi_centre(markers: FloatArray) -> FloatArray:
    """Silaghi et al. (1998) in closed form: one sphere per marker (eq. 5, P = 1), centres averaged."""
    centres = []
    for p in range(markers.shape[1]):
        v = markers[:, p]
        mean = v.mean(axis=0)
        sq = np.einsum("ij,ij->i", v, v)
        a_mat = 2.0 * np.cov(v.T, bias=True)
        b_vec = (sq[:, None] * v).mean(axis=0) - mean * sq.mean()
        centres.append(np.linalg.solve(a_mat, b_vec))
    out: FloatArray = np.mean(centres, axis=0)
    return out


# ----------------------------------------------------------------------------- simulations


def femur_markers(rng: np.random.Generator) -> tuple[FloatArray, FloatArray]:
    """Noise-free axis set-up ``(N, 4, 3)`` and a unit-peak skin pattern ``(N, 4, 3)`` in the bone frame."""
    u = np.arange(AXIS_FRAMES) / (AXIS_FRAMES - 1)
    a, b = rng.normal(size=(2, GL_AXIS_MARKERS.shape[0], 3))
    pattern = a[None] * u[:, None, None] + b[None] * np.sin(np.pi * u)[:, None, None]
    peak = np.linalg.norm(pattern, axis=2).max(axis=0)
    return GL_AXIS_MARKERS - AXIS_POINT, pattern / peak[None, :, None]


def femur_motion(bone: FloatArray, skin: FloatArray) -> FloatArray:
    """Markers (bone coordinates about the axis point, plus skin displacement) rotated 1 deg per frame."""
    angles = np.deg2rad(np.arange(AXIS_FRAMES, dtype=np.float64))
    rots = Rotation.from_rotvec(angles[:, None] * AXIS_DIR[None, :]).as_matrix()
    out: FloatArray = np.einsum("nij,npj->npi", rots, bone[None] + skin) + AXIS_POINT
    return out


@dataclass
class Cell:
    """Per-trial values of each method in one table cell."""

    values: dict[str, list[float]] = field(default_factory=dict)
    refused: int = 0

    def add(self, key: str, value: float) -> None:
        self.values.setdefault(key, []).append(value)

    def mean(self, key: str) -> float:
        """Mean over the trials with a finite value (NaN when there is none)."""
        vals = np.asarray(self.values.get(key, []), dtype=np.float64)
        vals = vals[np.isfinite(vals)]
        return float(np.mean(vals)) if vals.size else float("nan")

    def get(self, key: str) -> list[float]:
        return self.values.get(key, [])


def _axis_methods(markers: FloatArray, cell: Cell, ds: Sequence[int], with_point: bool = True) -> None:
    """Fit every axis method on one trial and record direction angle and point errors."""
    try:
        plain = fit_axis(markers, noise_std=0.0, reference_direction=AXIS_DIR)
        comp = fit_axis(markers, reference_direction=AXIS_DIR)
    except NotIdentifiableError:
        cell.refused += 1
        return
    cell.add("jointfit angle", angle_deg(comp.direction, AXIS_DIR))
    cell.add("GL plain angle", angle_deg(plain.direction, AXIS_DIR))
    delta = comp.direction - AXIS_DIR
    cell.add("jointfit dir e/2", mahalanobis_rank(delta, comp.cov_direction, 2) / 2.0)
    if with_point:
        cell.add("GL plain point", distance_to_line(plain.point, AXIS_POINT, AXIS_DIR))
        cell.add("jointfit point", distance_to_line(comp.point, AXIS_POINT, AXIS_DIR))
        # the reported point is the axis point nearest the centroid of the measured marker means
        centroid = markers.mean(axis=0).mean(axis=0)
        p_true = AXIS_POINT + ((centroid - AXIS_POINT) @ AXIS_DIR) * AXIS_DIR
        cell.add("jointfit point e/3", mahalanobis(comp.point - p_true, comp.cov_point) / 3.0)
        cell.add("jointfit noise", comp.noise_std)
    for d in ds:
        n, m = halvorsen_axis(markers, d)
        cell.add(f"H{d} angle", angle_deg(n, AXIS_DIR))
        if with_point:
            cell.add(f"H{d} point", distance_to_line(m, AXIS_POINT, AXIS_DIR))


def run_axis_noise(seeds: Sequence[np.random.SeedSequence]) -> dict[float, Cell]:
    """Figure 3: Gaussian noise only."""
    ds = sorted(set(AXIS_D) | set(H_SHOWN))
    cells = {s: Cell() for s in AXIS_NOISE_MM}
    for seq in seeds:
        rng = np.random.default_rng(seq)
        bone, _ = femur_markers(rng)
        clean = femur_motion(bone, np.zeros((AXIS_FRAMES, *bone.shape)))
        unit = rng.normal(size=clean.shape)
        for sigma in AXIS_NOISE_MM:
            _axis_methods(clean + sigma * unit, cells[sigma], ds)
    return cells


def run_axis_skin(seeds: Sequence[np.random.SeedSequence]) -> dict[tuple[int, bool], Cell]:
    """Figure 4: systematic skin movement, without and with 1 mm noise."""
    cells = {(pct, noisy): Cell() for pct in SKIN_PERCENT for noisy in (False, True)}
    for seq in seeds:
        rng = np.random.default_rng(seq)
        bone, pattern = femur_markers(rng)
        unit = rng.normal(size=pattern.shape)
        for pct in SKIN_PERCENT:
            clean = femur_motion(bone, (pct / 100.0) * SKIN_PEAK_MM * pattern)
            for noisy in (False, True):
                markers = clean + SKIN_NOISE_MM * unit if noisy else clean
                _axis_methods(markers, cells[(pct, noisy)], H_SHOWN)
    return cells


def run_centre(seeds: Sequence[np.random.SeedSequence]) -> dict[float, Cell]:
    """Figure 5: centre of rotation with Gaussian noise."""
    ds = sorted(set(CENTRE_D) | set(H_SHOWN))
    cells = {s: Cell() for s in CENTRE_NOISE_MM}
    for seq in seeds:
        for sigma, child in zip(CENTRE_NOISE_MM, seq.spawn(len(CENTRE_NOISE_MM)), strict=True):
            rng = np.random.default_rng(child)
            sim = gl_random_walk_setup(rng, sigma, n_frames=CENTRE_FRAMES)
            cell = cells[sigma]
            try:
                plain = fit_centre(sim.markers, noise_std=0.0)
                comp = fit_centre(sim.markers)
            except NotIdentifiableError:
                cell.refused += 1
                continue
            rel = 100.0 / MIN_MARKER_DISTANCE
            cell.add("GL plain", rel * float(np.linalg.norm(plain.centre - sim.centre)))
            cell.add("jointfit", rel * float(np.linalg.norm(comp.centre - sim.centre)))
            cell.add("jointfit e/3", mahalanobis(comp.centre - sim.centre, comp.cov) / 3.0)
            cell.add("jointfit flagged", float(not comp.identifiable))
            cell.add("Silaghi avg", rel * float(np.linalg.norm(silaghi_centre(sim.markers) - sim.centre)))
            for d in ds:
                cell.add(f"H{d}", rel * float(np.linalg.norm(halvorsen_centre(sim.markers, d) - sim.centre)))
    return cells


# ----------------------------------------------------------------------------- tables


def _behind(cell: Cell, ours: str, others: Sequence[str], where: str) -> list[tuple[bool, str]]:
    """Every method whose mean error is lower than jointfit's in a cell: ``(significant, text)``."""
    out = []
    for key in others:
        if cell.mean(key) < cell.mean(ours):
            significant = "BEHIND" in paired_verdict(cell.get(ours), cell.get(key))
            name = key.replace(" angle", "").replace(" point", "")
            out.append(
                (significant, f"{where}: {name} {fmt(cell.mean(key))} < jointfit {fmt(cell.mean(ours))}")
            )
    return out


def axis_tables(
    noise: dict[float, Cell], skin: dict[tuple[int, bool], Cell]
) -> tuple[str, list[tuple[bool, str]]]:
    parts: list[str] = []
    behind: list[tuple[bool, str]] = []
    # Figure 3 (a), (b)
    rows = []
    for sigma in AXIS_NOISE_MM:
        c = noise[sigma]
        rows.append(
            [
                fmt(sigma),
                fmt(c.mean("jointfit angle")),
                fmt(c.mean("jointfit dir e/2")),
                fmt(c.mean("H30 angle")),
                fmt(c.mean("H1 angle")),
                fmt(c.mean("GL plain point")),
                fmt(c.mean("jointfit point")),
                fmt(c.mean("jointfit point e/3")),
                fmt(c.mean("H30 point")),
                fmt(c.mean("H1 point")),
            ]
        )
        behind += _behind(c, "jointfit angle", ["H30 angle", "H1 angle"], f"fig. 3 angle, noise {sigma:g} mm")
        behind += _behind(
            c,
            "jointfit point",
            ["GL plain point", "H30 point", "H1 point"],
            f"axis point, noise {sigma:g} mm",
        )
        if not np.allclose(c.get("jointfit angle"), c.get("GL plain angle")):
            behind.append((True, f"noise {sigma:g} mm: jointfit and GL plain directions differ (unexpected)"))
    parts += [
        "### Figure 3 (a), (b): axis direction error vs noise",
        "",
        "Angle error (deg) of the axis direction; jointfit = GL plain for the direction (identical "
        "eigenvector, checked every trial). Point: distance of the reported axis point from the true axis (mm).",
        "",
        markdown_table(
            [
                "noise (mm)",
                "jointfit / GL angle",
                "jointfit dir e/2",
                "Halvorsen d=30 angle",
                "Halvorsen d=1 angle",
                "GL plain point",
                "jointfit point",
                "jointfit point e/3",
                "Halvorsen d=30 point",
                "Halvorsen d=1 point",
            ],
            rows,
        ),
        "",
    ]
    # Figure 3 (c), (d)
    rows = []
    for d in AXIS_D:
        rows.append([str(d)] + [fmt(noise[s].mean(f"H{d} angle")) for s in AXIS_SWEEP_NOISE_MM])
    rows.append(["jointfit (no d)"] + [fmt(noise[s].mean("jointfit angle")) for s in AXIS_SWEEP_NOISE_MM])
    parts += [
        "### Figure 3 (c), (d): Halvorsen's frame difference",
        "",
        "Angle error (deg) of Halvorsen's direction against the frame difference d (60 frames), "
        "and jointfit's (which has no d) for reference.",
        "",
        markdown_table(["d (frames)", *(f"noise {s:g} mm" for s in AXIS_SWEEP_NOISE_MM)], rows),
        "",
    ]
    for s in AXIS_SWEEP_NOISE_MM:
        best_d = min(AXIS_D, key=lambda d, s=s: noise[s].mean(f"H{d} angle"))
        c = noise[s]
        parts.append(
            f"- noise {s:g} mm: best Halvorsen d = {best_d} ({fmt(c.mean(f'H{best_d} angle'))} deg), "
            f"worst d = 1 ({fmt(c.mean('H1 angle'))} deg); jointfit {fmt(c.mean('jointfit angle'))} deg = "
            f"{c.mean('jointfit angle') / c.mean(f'H{best_d} angle'):.2f} x Halvorsen's best d."
        )
        behind += _behind(c, "jointfit angle", [f"H{best_d} angle"], f"fig. 3 best d, noise {s:g} mm")
    parts.append("")
    # Figure 4
    rows = []
    for pct in SKIN_PERCENT:
        row = [str(pct)]
        for noisy in (False, True):
            c = skin[(pct, noisy)]
            row += [fmt(c.mean("jointfit angle")), fmt(c.mean("H30 angle")), fmt(c.mean("H1 angle"))]
            tag = "skin + noise" if noisy else "skin only"
            if pct > 0:
                behind += _behind(c, "jointfit angle", ["H30 angle", "H1 angle"], f"fig. 4 {tag} {pct} %")
        c = skin[(pct, True)]
        row += [
            fmt(c.mean("GL plain point")),
            fmt(c.mean("jointfit point")),
            fmt(c.mean("jointfit point e/3")),
            fmt(c.mean("jointfit noise")),
        ]
        behind += _behind(
            c, "jointfit point", ["GL plain point", "H30 point"], f"axis point, skin + noise {pct} %"
        )
        rows.append(row)
    parts += [
        "### Figure 4: axis direction error with systematic skin movement",
        "",
        f"Angle error (deg); skin movement in % of a {SKIN_PEAK_MM:g} mm peak (see the module docstring), "
        f"(a)/(b) without noise, (c)/(d) with {SKIN_NOISE_MM:g} mm noise; last four columns, with skin + "
        "noise: axis point error (mm), jointfit's e/3 for its point and the marker noise sd jointfit "
        f"estimates from the out-of-plane scatter (true random part: {SKIN_NOISE_MM:g} mm).",
        "",
        markdown_table(
            [
                "skin (%)",
                "(a,b) jointfit",
                "(a) Halvorsen d=30",
                "(b) Halvorsen d=1",
                "(c,d) jointfit",
                "(c) Halvorsen d=30",
                "(d) Halvorsen d=1",
                "GL plain point",
                "jointfit point",
                "jointfit point e/3",
                "jointfit noise est (mm)",
            ],
            rows,
        ),
        "",
    ]
    return "\n".join(parts), behind


def centre_tables(cells: dict[float, Cell]) -> tuple[str, list[tuple[bool, str]]]:
    parts: list[str] = []
    behind: list[tuple[bool, str]] = []
    rows = []
    others = ["GL plain", "H30", "H1", "Silaghi avg"]
    for sigma in CENTRE_NOISE_MM:
        c = cells[sigma]
        rows.append(
            [
                fmt(sigma),
                fmt(c.mean("GL plain")),
                fmt(c.mean("jointfit")),
                fmt(c.mean("jointfit e/3")),
                fmt(c.mean("jointfit flagged")),
                fmt(c.mean("H30")),
                fmt(c.mean("H1")),
                fmt(c.mean("H50")),
                fmt(c.mean("Silaghi avg")),
                str(c.refused),
            ]
        )
        behind += _behind(c, "jointfit", [*others, "H50"], f"fig. 5 centre, noise {sigma:g} mm")
    parts += [
        "### Figure 5 (a), (b): centre error vs noise",
        "",
        f"Relative error = |c - c_true| / {MIN_MARKER_DISTANCE:.1f} mm, in %; jointfit e/3 = mean validation "
        "index squared of its covariance; flagged = fraction it reports not identifiable; refused = "
        "trials where a fit raised (excluded).",
        "",
        markdown_table(
            [
                "noise (mm)",
                "GL plain",
                "jointfit",
                "jointfit e/3",
                "jointfit flagged",
                "Halvorsen d=30",
                "Halvorsen d=1",
                "Halvorsen d=50",
                "Silaghi avg",
                "refused",
            ],
            rows,
        ),
        "",
    ]
    rows = []
    for d in CENTRE_D:
        rows.append([str(d)] + [fmt(cells[s].mean(f"H{d}")) for s in CENTRE_SWEEP_NOISE_MM])
    for key in ("jointfit", "GL plain", "Silaghi avg"):
        rows.append([f"{key} (no d)"] + [fmt(cells[s].mean(key)) for s in CENTRE_SWEEP_NOISE_MM])
    parts += [
        "### Figure 5 (c), (d): Halvorsen's frame difference",
        "",
        "Relative centre error (%) of Halvorsen's method against d (100 frames); the methods without d below.",
        "",
        markdown_table(["d (frames)", *(f"noise {s:g} mm" for s in CENTRE_SWEEP_NOISE_MM)], rows),
        "",
    ]
    for s in CENTRE_SWEEP_NOISE_MM:
        c = cells[s]
        best_d = min(CENTRE_D, key=lambda d, c=c: c.mean(f"H{d}"))
        parts.append(
            f"- noise {s:g} mm: best Halvorsen d = {best_d} ({fmt(c.mean(f'H{best_d}'))} %); jointfit "
            f"{fmt(c.mean('jointfit'))} % = {c.mean('jointfit') / c.mean(f'H{best_d}'):.2f} x Halvorsen's best, "
            f"{c.mean('jointfit') / c.mean('GL plain'):.2f} x GL plain, "
            f"{c.mean('jointfit') / c.mean('Silaghi avg'):.2f} x Silaghi avg."
        )
        behind += _behind(c, "jointfit", [f"H{best_d}"], f"fig. 5 best d, noise {s:g} mm")
    parts.append("")
    return "\n".join(parts), behind


# ----------------------------------------------------------------------------- figures


def _panel(
    ax: object,
    x: Sequence[float],
    series: dict[str, Sequence[float]],
    xlabel: str,
    ylabel: str,
    title: str,
    logx: bool = False,
    logy: bool = True,
) -> None:
    styles = {"jointfit": "-o", "GL plain": "--s"}
    for label, y in series.items():
        ax.plot(x, y, styles.get(label.split(" (")[0], ":^"), label=label, markersize=4)  # type: ignore[attr-defined]
    if logx:
        ax.set_xscale("log")  # type: ignore[attr-defined]
    if logy:
        ax.set_yscale("log")  # type: ignore[attr-defined]
    ax.set_xlabel(xlabel)  # type: ignore[attr-defined]
    ax.set_ylabel(ylabel)  # type: ignore[attr-defined]
    ax.set_title(title, fontsize=9)  # type: ignore[attr-defined]
    ax.grid(True, which="both", alpha=0.3)  # type: ignore[attr-defined]
    ax.legend(fontsize=7)  # type: ignore[attr-defined]


def figures(
    noise: dict[float, Cell], skin: dict[tuple[int, bool], Cell], centre: dict[float, Cell]
) -> list[str]:
    plt = pyplot()
    names = []
    ang = "axis direction error (deg)"
    # Figure 3
    fig, axes = plt.subplots(2, 2, figsize=(10, 7.5))
    xs = list(AXIS_NOISE_MM)
    for ax, d, tag in ((axes[0, 0], 30, "(a)"), (axes[0, 1], 1, "(b)")):
        _panel(
            ax,
            xs,
            {
                "jointfit (= GL plain)": [noise[s].mean("jointfit angle") for s in xs],
                f"Halvorsen d={d}": [noise[s].mean(f"H{d} angle") for s in xs],
            },
            "marker noise sd (mm)",
            ang,
            f"{tag} vs noise, Halvorsen d = {d}",
            logx=True,
        )
    for ax, s, tag in (
        (axes[1, 0], AXIS_SWEEP_NOISE_MM[0], "(c)"),
        (axes[1, 1], AXIS_SWEEP_NOISE_MM[1], "(d)"),
    ):
        _panel(
            ax,
            list(AXIS_D),
            {
                "jointfit (= GL plain)": [noise[s].mean("jointfit angle")] * len(AXIS_D),
                "Halvorsen": [noise[s].mean(f"H{d} angle") for d in AXIS_D],
            },
            "frame difference d (frames)",
            ang,
            f"{tag} vs frame difference, noise {s:g} mm",
        )
    fig.suptitle("Gamage & Lasenby 2002 fig. 3: axis, 4 femur markers, 60 frames at 1 deg/frame")
    fig.tight_layout()
    names.append(save_figure(fig, "paper_gamage2002_fig3.png").name)
    # Figure 4
    fig, axes = plt.subplots(2, 2, figsize=(10, 7.5))
    xs = list(SKIN_PERCENT)
    for ax, noisy, d, tag in (
        (axes[0, 0], False, 30, "(a)"),
        (axes[0, 1], False, 1, "(b)"),
        (axes[1, 0], True, 30, "(c)"),
        (axes[1, 1], True, 1, "(d)"),
    ):
        extra = f" + {SKIN_NOISE_MM:g} mm noise" if noisy else ""
        _panel(
            ax,
            xs,
            {
                "jointfit (= GL plain)": [skin[(p, noisy)].mean("jointfit angle") for p in xs],
                f"Halvorsen d={d}": [skin[(p, noisy)].mean(f"H{d} angle") for p in xs],
            },
            f"skin movement (% of {SKIN_PEAK_MM:g} mm peak)",
            ang,
            f"{tag} skin movement{extra}, Halvorsen d = {d}",
            logy=False,
        )
    fig.suptitle("Gamage & Lasenby 2002 fig. 4: axis with systematic skin movement")
    fig.tight_layout()
    names.append(save_figure(fig, "paper_gamage2002_fig4.png").name)
    # Figure 5
    fig, axes = plt.subplots(2, 2, figsize=(10, 7.5))
    xs = list(CENTRE_NOISE_MM)
    rel = f"centre error / {MIN_MARKER_DISTANCE:.1f} mm (%)"
    for ax, d, tag in ((axes[0, 0], 30, "(a)"), (axes[0, 1], 1, "(b)")):
        _panel(
            ax,
            xs,
            {
                "jointfit": [centre[s].mean("jointfit") for s in xs],
                "GL plain": [centre[s].mean("GL plain") for s in xs],
                f"Halvorsen d={d}": [centre[s].mean(f"H{d}") for s in xs],
                "Silaghi avg": [centre[s].mean("Silaghi avg") for s in xs],
            },
            "marker noise sd (mm)",
            rel,
            f"{tag} vs noise, Halvorsen d = {d}",
            logx=True,
        )
    for ax, s, tag in (
        (axes[1, 0], CENTRE_SWEEP_NOISE_MM[0], "(c)"),
        (axes[1, 1], CENTRE_SWEEP_NOISE_MM[1], "(d)"),
    ):
        n = len(CENTRE_D)
        _panel(
            ax,
            list(CENTRE_D),
            {
                "jointfit": [centre[s].mean("jointfit")] * n,
                "GL plain": [centre[s].mean("GL plain")] * n,
                "Halvorsen": [centre[s].mean(f"H{d}") for d in CENTRE_D],
                "Silaghi avg": [centre[s].mean("Silaghi avg")] * n,
            },
            "frame difference d (frames)",
            rel,
            f"{tag} vs frame difference, noise {s:g} mm",
        )
    fig.suptitle("Gamage & Lasenby 2002 fig. 5: centre, 4 markers, 100 frames, random-walk axis")
    fig.tight_layout()
    names.append(save_figure(fig, "paper_gamage2002_fig5.png").name)
    return names


# ----------------------------------------------------------------------------- main


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick", action="store_true", help="30 trials per cell (the paper's count) instead of 200"
    )
    parser.add_argument("--trials", type=int, default=None, help="trials per cell (overrides --quick)")
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    args_list = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(args_list)
    trials = args.trials or (30 if args.quick else 200)
    t_start = time.perf_counter()
    s_noise, s_skin, s_centre = np.random.SeedSequence(SEED).spawn(3)
    noise = run_axis_noise(s_noise.spawn(trials))
    skin = run_axis_skin(s_skin.spawn(trials))
    centre = run_centre(s_centre.spawn(trials))
    axis_md, behind_axis = axis_tables(noise, skin)
    centre_md, behind_centre = centre_tables(centre)
    pngs = [] if args.no_plots else figures(noise, skin, centre)
    behind = behind_axis + behind_centre
    parts = run_header(
        "Gamage & Lasenby (2002) section 4, reproduced",
        SCRIPT,
        args_list,
        SEED,
        f"{trials} trials per cell (the paper: 30). Set-ups, methods and the stylised skin movement are "
        "described in the script's docstring. Plain = Gamage-Lasenby as published; jointfit = the default "
        "bias-compensated fit; Halvorsen d = Halvorsen et al. 1999 with a frame difference of d frames; "
        "Silaghi avg = per-marker sphere centres averaged (Silaghi et al. 1998 in closed form).",
    )
    parts += [
        "## Axis of rotation (figures 3 and 4)",
        "",
        axis_md,
        "## Centre of rotation (figure 5)",
        "",
        centre_md,
    ]
    parts += ["## Where jointfit is not ahead", ""]
    significant = [text for sig, text in behind if sig]
    close = [text for sig, text in behind if not sig]
    if not behind:
        parts += ["Nowhere: jointfit has the lowest mean error in every cell of every table above.", ""]
    if significant:
        parts += ["**Behind** (paired difference over the trials larger than 2 standard errors):", ""]
        parts += [f"- {line}" for line in significant]
        parts.append("")
    if close:
        parts += ["Lower mean error than jointfit but within 2 standard errors (no clear difference):", ""]
        parts += [f"- {line}" for line in close]
        parts.append("")
    parts += [
        "The paper's qualitative claims, to be read against the numbers above: (1) Halvorsen's method depends strongly "
        "on d and is worst at d = 1; (2) Gamage-Lasenby needs no d and is close to Halvorsen's best d; "
        "(3) averaging per-marker sphere centres (Silaghi) is worse than one fit to all markers. jointfit's "
        "bias compensation leaves the axis direction unchanged and lowers the centre and axis-point error "
        "where noise is large relative to the range of motion.",
        "",
    ]
    if pngs:
        parts += ["Figures: " + ", ".join(f"[{n}]({n})" for n in pngs) + ".", ""]
    parts.append(elapsed_line(t_start))
    print_and_write("paper_gamage2002.md", parts)
    return 0


if __name__ == "__main__":
    sys.exit(main())
