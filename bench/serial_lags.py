"""How the joint-constraint residual of the real fixtures is correlated in time, lag by lag in milliseconds.

Run with ``PYTHONPATH=. python bench/serial_lags.py`` (repository root; under a minute). Prints
Markdown and writes ``bench/results/serial_lags.md``. Evidence for issue 17's frame-rate question:
the online covariance was inflated by the AR(1) factor ``(1 + rho_1) / (1 - rho_1)`` of the residual's
lag-1 autocorrelation. That factor is the variance ratio of a mean only when the correlation decays
exponentially; this script measures the decay. (The online estimator now uses an integrated factor over
lags in seconds, :func:`jointfit_core.serial.integrated_factor`; ``bench/sta_online.py`` measures it.)

What is measured
----------------
Each fixture is fitted as ``jointfit fit`` does (whole recording, its ``config/offline_*.yaml``).
With the final estimate and the final templates, every frame where both segments are posed gives
the constraint residual in the parent frame (ball: ``c_p - Q c_c - t``; hinge: the same for the axis
points, its component along the axis removed). Its autocorrelation ``rho(l) = sum r_k . r_{k+l} /
sum |r_k|^2`` (frames ``l`` apart, both posed) is listed at lags of 10 ms to 1.28 s, at the
recording's rate and for every 8th frame. For both rates the table gives the AR(1) factor from
lag 1 and the integrated factor ``1 + 2 sum_l (1 - l/L) rho(l)`` over lags up to ``L`` frames
(Bartlett window; L of 1 s and of 3 s), which is the variance ratio of a mean for any correlation
that has died out within ``L``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine, markdown_table, save_results

from jointfit_core.hinge_from_sums import PoseSumsAxis
from jointfit_core.pose import poses_from_markers
from jointfit_ros.offline import read_marker_file, run_fit, with_file_marker_names
from jointfit_ros.params import node_config, params_from_file

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results" / "serial_lags.md"
FIXTURES = {
    "right_hip": ("biobuddy/right_hip.c3d", "offline_right_hip.yaml"),
    "right_knee": ("biobuddy/right_knee.c3d", "offline_right_knee.yaml"),
}
LAGS_MS = (10, 20, 40, 80, 160, 320, 640, 1280)
STEP = 8  # the subsampled rate: every 8th frame


def _residuals(name: str) -> tuple[np.ndarray, float]:
    """Per frame the constraint residual (N, 3) (NaN where a segment is not posed), and the rate (Hz)."""
    fixture, config = FIXTURES[name]
    path = ROOT / "test" / "data" / fixture
    data = read_marker_file(path)
    assert data is not None
    values = with_file_marker_names(params_from_file(ROOT / "config" / config), data.labels, path.name)
    values.update({k: "" for k in values if k.endswith(".calibration_file")})
    run = run_fit(path, node_config(values), reader_process=False, data=data)
    trace = run.traces[0]
    r, sol = trace.runner, trace.final
    assert run.frames is not None and sol is not None
    tp, tc = r.estimator.templates
    with np.errstate(invalid="ignore"):
        pp = poses_from_markers(run.frames[:, r.parent_rows], tp)
        pc = poses_from_markers(run.frames[:, r.child_rows], tc)
    Q = np.swapaxes(pp.R_world_local, 1, 2) @ pc.R_world_local
    t = np.einsum("nji,nj->ni", pp.R_world_local, pc.d_world_local - pp.d_world_local)
    if isinstance(sol, PoseSumsAxis):
        res = sol.point_parent - np.einsum("nij,j->ni", Q, sol.point_child) - t
        u = sol.direction_parent
        res = res - np.outer(res @ u, u)
    else:
        res = sol.centre_parent - np.einsum("nij,j->ni", Q, sol.centre_child) - t
    return res, run.rate


def _rho(res: np.ndarray, lag: int) -> float:
    ok = np.isfinite(res).all(axis=1)
    a, b = res[:-lag], res[lag:]
    both = ok[:-lag] & ok[lag:]
    return float(np.sum(a[both] * b[both]) / np.sum(res[ok] ** 2) * ok.sum() / both.sum())


def _integrated(res: np.ndarray, max_lag: int) -> float:
    L = max(1, max_lag)
    return 1.0 + 2.0 * sum((1.0 - lag / L) * _rho(res, lag) for lag in range(1, L))


def main() -> int:
    rows, lag_rows = [], []
    for name in FIXTURES:
        res, rate = _residuals(name)
        for label, series, hz in ((f"{rate:.0f} Hz", res, rate), (f"every {STEP}th ({rate / STEP:.1f} Hz)", res[::STEP], rate / STEP)):
            rho1 = _rho(series, 1)
            ar1 = (1 + max(rho1, 0.0)) / (1 - min(max(rho1, 0.0), 0.999))
            f1, f3 = _integrated(series, round(hz)), _integrated(series, round(3 * hz))
            n = int(np.isfinite(series).all(axis=1).sum())
            rows.append([name, label, f"{n}", f"{rho1:.3f}", f"{ar1:.1f}", f"{f1:.1f}", f"{f3:.1f}",
                         f"{n / ar1:.0f}", f"{n / max(f3, 1.0):.0f}"])  # fmt: skip
        lag_rows.append([name] + [f"{_rho(res, max(1, round(ms * 1e-3 * rate))):.2f}" for ms in LAGS_MS])
    text = "\n".join([
        "# The constraint residual's correlation in time (issue 17, frame-rate dependence)",
        "",
        "Command: `PYTHONPATH=. python bench/serial_lags.py`.",
        f"Machine: {machine()}.",
        "",
        "Autocorrelation of the residual at the final estimate, by lag:",
        "",
        markdown_table(["fixture"] + [f"{ms} ms" for ms in LAGS_MS], lag_rows),
        "",
        "Variance factors of a mean, and the effective number of independent frames they imply:",
        "",
        markdown_table(["fixture", "rate", "frames", "lag-1 rho", "AR(1) factor", "integrated, 1 s",
                        "integrated, 3 s", "frames / AR(1)", "frames / integrated 3 s"], rows),
        "",
        "Rate-invariant is what the last two columns should be between the two rates of a fixture (the same "
        "seconds of motion hold the same information).",
        "",
    ])
    print(text)
    save_results(RESULTS, text)
    print(f"wrote {RESULTS}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
