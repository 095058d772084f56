"""Shared helpers of the paper-reproduction and peer benchmarks (not run by ``make bench``).

``paper_gamage2002.py``, ``paper_stoddart1999.py`` and ``peers.py`` import this
module by name: they are run as ``python bench/<script>.py``, which puts
``bench/`` first on ``sys.path``.
"""

from __future__ import annotations

import datetime as dt
import shlex
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from _common import machine, markdown_table, save_results
from numpy.typing import NDArray

__all__ = ["markdown_table"]  # re-exported for the paper scripts

FloatArray = NDArray[np.float64]
T = TypeVar("T")

BENCH = Path(__file__).resolve().parent
RESULTS = BENCH / "results"


def command_line(script: str, argv: Sequence[str]) -> str:
    """The command that reproduces this run, as written into the result file."""
    return " ".join(["python", f"bench/{script}", *(shlex.quote(a) for a in argv)])


def run_header(title: str, script: str, argv: Sequence[str], seed: int, notes: str = "") -> list[str]:
    """Title, the command that made the file, versions, machine and seed, as Markdown lines."""
    lines = [
        f"# {title}",
        "",
        f"Made by `{command_line(script, argv)}` on {dt.date.today().isoformat()}, seed {seed}.",
        "",
        f"Machine: {machine()}.",
    ]
    if notes:
        lines += ["", notes]
    return [*lines, ""]


def fmt(value: float, digits: int = 3) -> str:
    """Compact number for a table cell (``-`` for NaN)."""
    if not np.isfinite(value):
        return "-"
    if value == 0.0:
        return "0"
    mag = abs(value)
    if mag >= 1000.0:
        return f"{value:,.0f}".replace(",", " ")
    if mag >= 0.01:
        return f"{value:.{digits}g}" if mag < 10**digits else f"{value:.0f}"
    return f"{value:.2e}"


def write_result(name: str, text: str) -> Path:
    """Write ``bench/results/<name>`` and return its path."""
    return save_results(RESULTS / name, text)


def pyplot() -> Any:
    """matplotlib.pyplot with the non-interactive Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, name: str) -> Path:
    """Save a figure as ``bench/results/<name>`` (PNG, 110 dpi) and close it."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / name
    fig.savefig(path, dpi=110)
    fig.clf()
    pyplot().close(fig)
    return path


def mahalanobis(delta: FloatArray, cov: FloatArray) -> float:
    """``delta^T cov^-1 delta`` (full-rank covariance; NaN when it is singular)."""
    if np.linalg.eigvalsh(cov)[0] <= 0.0:
        return float("nan")
    return float(delta @ np.linalg.solve(cov, delta))


def mahalanobis_rank(delta: FloatArray, cov: FloatArray, rank: int) -> float:
    """``delta^T cov^+ delta`` with the pseudo-inverse on the ``rank`` largest eigen-directions."""
    lam, vecs = np.linalg.eigh(cov)
    if lam[-rank] <= 0.0:
        return float("nan")
    proj = vecs[:, -rank:].T @ delta
    return float(np.sum(proj * proj / lam[-rank:]))


def angle_deg(u: FloatArray, v: FloatArray) -> float:
    """Angle between two lines (sign-free), degrees."""
    cos = abs(float(u @ v)) / (float(np.linalg.norm(u)) * float(np.linalg.norm(v)))
    return float(np.degrees(np.arccos(min(cos, 1.0))))


def distance_to_line(point: FloatArray, line_point: FloatArray, line_dir: FloatArray) -> float:
    """Distance of ``point`` from the line through ``line_point`` along ``line_dir``."""
    n = line_dir / np.linalg.norm(line_dir)
    off = point - line_point
    return float(np.linalg.norm(off - (off @ n) * n))


def to_estimated_frame(template_true: FloatArray, template_est: FloatArray, point: FloatArray) -> FloatArray:
    """Map a point of the true local frame into an estimated one (Procrustes of template onto template)."""
    mu_t, mu_e = template_true.mean(axis=0), template_est.mean(axis=0)
    u, _, vt = np.linalg.svd((template_true - mu_t).T @ (template_est - mu_e))
    fix = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(vt.T @ u.T)))])
    R = vt.T @ fix @ u.T
    mapped: FloatArray = R @ (point - mu_t) + mu_e
    return mapped


def rotation_to_estimated_frame(template_true: FloatArray, template_est: FloatArray) -> FloatArray:
    """Rotation taking directions of the true local frame into an estimated one (Procrustes)."""
    mu_t, mu_e = template_true.mean(axis=0), template_est.mean(axis=0)
    u, _, vt = np.linalg.svd((template_true - mu_t).T @ (template_est - mu_e))
    fix = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(vt.T @ u.T)))])
    R: FloatArray = vt.T @ fix @ u.T
    return R


def timed(fn: Callable[[], T]) -> tuple[T, float]:
    """Call ``fn`` once; return its result and the wall-clock seconds."""
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def paired_verdict(ours: Sequence[float], theirs: Sequence[float], *, lower_is_better: bool = True) -> str:
    """Compare paired per-trial values: ahead / behind / no clear difference (2 standard errors)."""
    a, b = np.asarray(ours, dtype=np.float64), np.asarray(theirs, dtype=np.float64)
    ok = np.isfinite(a) & np.isfinite(b)
    a, b = a[ok], b[ok]
    if a.size == 0:
        return "n/a"
    diff = (a - b) if lower_is_better else (b - a)
    se = float(np.std(diff, ddof=1) / np.sqrt(diff.size)) if diff.size > 1 else 0.0
    mean = float(np.mean(diff))
    if mean + 2.0 * se < 0.0:
        return "**jointfit ahead**"
    if mean - 2.0 * se > 0.0:
        return "**jointfit BEHIND**"
    return "no clear difference"


def elapsed_line(t_start: float) -> str:
    return f"Total runtime {time.perf_counter() - t_start:.1f} s (wall clock)."


def print_and_write(name: str, parts: Sequence[str]) -> Path:
    text = "\n".join(parts).rstrip("\n") + "\n"
    print(text, end="")
    sys.stdout.flush()
    return write_result(name, text)
