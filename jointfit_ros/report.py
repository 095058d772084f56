"""What ``jointfit fit`` reports: a JSON-able summary and one figure per joint.

ROS-free. :func:`fit_summary` turns a :class:`~jointfit_ros.offline.FitRun`
into plain types (estimates in the parent and child segment frames, their
covariances and standard deviations, residuals, identifiability verdicts,
counters). :func:`joint_figure` draws, for one joint, from the kept marker
frames and the final templates:

1. the child markers in the parent segment frame, with the fitted sphere
   (ball) or circles and axis (hinge);
2. each marker's distance to its posed template over time (the rigid-body
   residual: label swaps, ghosts and skin motion show up here);
3. the joint constraint residual per frame over time: the distance between
   the joint carried by the parent and by the child (marker joints: with
   the final estimate, from the kept frames; pose inputs: the node's
   per-frame outputs, with the estimate of the time);
4. the estimate minus the final one, with +-2 sd bands, against the frames
   used (the convergence curve);
5. the reported standard deviation against the frames used;
6. the covariance ellipses (1, 2 and 3 sd) of the final estimate, in the
   three coordinate planes of the parent frame.

matplotlib is needed only for the figures (imported by :func:`joint_figure`).
"""

from __future__ import annotations

import io
import math
import multiprocessing
import os
import signal
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from jointfit_core.errors import MissingDependencyError
from jointfit_core.gate import gated_verdict
from jointfit_core.hinge_from_sums import PoseSumsAxis
from jointfit_core.pose import poses_from_markers
from jointfit_core.rom import RangeOfMotion
from jointfit_core.segments import PoseSumsCentre

from .absurd_values import unit_problem
from .anatomy_report import anatomical_summary, joint_rom, rom_summary
from .bag_blocks import can_fork
from .cluster_check import recording_odd_markers
from .geometry import SegmentGeometry, landmark_stat
from .joint_diagnostics import weak_cluster
from .offline import FitRun, JointTrace
from .runner import JointRunner

__all__ = [
    "fit_summary",
    "joint_figure",
    "joint_reports",
    "SegmentGeometry",
    "geometries",
    "segment_geometry",
    "length_unit",
]

FloatArray = NDArray[np.float64]


def _sd(cov: FloatArray) -> list[float]:
    return [float(v) for v in np.sqrt(np.clip(np.diag(cov), 0.0, None))]


def _angle_sd_deg(cov_direction: FloatArray) -> float:
    """Largest angular sd of a unit direction, degrees."""
    return math.degrees(math.sqrt(max(float(np.linalg.eigvalsh(cov_direction)[-1]), 0.0)))


def _list(a: FloatArray) -> list[Any]:
    out: list[Any] = np.asarray(a, dtype=np.float64).tolist()
    return out


def _residuals(markers: FloatArray, template: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    poses = poses_from_markers(markers, template)
    fitted = poses.R_world_local @ template.T + poses.d_world_local[:, :, None]  # (N, 3, P)
    return np.linalg.norm(np.swapaxes(fitted, 1, 2) - markers, axis=2), poses.R_world_local, poses.d_world_local


def segment_geometry(run: FitRun, trace: JointTrace) -> SegmentGeometry | None:
    """Poses and residuals of a marker joint (None for pose inputs, without frames or templates)."""
    r = trace.runner
    tp, tc = r.estimator.templates
    if run.frames is None or tp is None or tc is None or not len(r.parent_rows) or not len(r.child_rows):
        return None
    if r.chained:
        return None  # virtual markers are not in the frames
    parent = run.frames[:, r.parent_rows]
    child = run.frames[:, r.child_rows]
    with np.errstate(invalid="ignore"):
        rp, R_p, d_p = _residuals(parent, tp)
        rc, R_c, d_c = _residuals(child, tc)
        cip = (child - d_p[:, None, :]) @ R_p  # R_p^T (y - d_p) of every child marker
        joint = None if trace.final is None else _joint_residual(trace.final, R_p, d_p, R_c, d_c)
        R_rel = np.swapaxes(R_p, 1, 2) @ R_c
        landmarks = _landmarks_parent(run, r.cfg.anatomical, R_p, d_p)
    return SegmentGeometry(run.stamps - run.stamps[0], rp, rc, cip, joint, R_rel, landmarks)


def _landmarks_parent(
    run: FitRun, anatomical: tuple[tuple[str, str], ...], R_p: FloatArray, d_p: FloatArray
) -> dict[str, tuple[FloatArray, float, int]]:
    """Each landmark marker in the parent frame: median over the frames, rms scatter about it, frames used."""
    assert run.frames is not None
    out: dict[str, tuple[FloatArray, float, int]] = {}
    for _, marker in anatomical:
        if marker in out:
            continue
        stat = landmark_stat(np.einsum("nji,nj->ni", R_p, run.frames[:, run.cfg.marker_index(marker)] - d_p))
        if stat is not None:
            out[marker] = stat
    return out


def geometries(run: FitRun) -> dict[str, SegmentGeometry | None]:
    """:func:`segment_geometry` of every joint, by name (computed once for the summary and the figures)."""
    return {t.runner.cfg.name: segment_geometry(run, t) for t in run.traces}


def _geometry(run: FitRun, trace: JointTrace, geos: Mapping[str, SegmentGeometry | None] | None) -> SegmentGeometry | None:
    name = trace.runner.cfg.name
    return geos[name] if geos is not None and name in geos else segment_geometry(run, trace)


def _joint_residual(
    sol: PoseSumsCentre | PoseSumsAxis, R_p: FloatArray, d_p: FloatArray, R_c: FloatArray, d_c: FloatArray
) -> FloatArray:
    """Distance between the joint carried by the parent and by the child in every frame (N,) (NaN where unposed)."""
    if isinstance(sol, PoseSumsCentre):
        local_p, local_c = sol.centre_parent, sol.centre_child
    else:
        local_p, local_c = sol.point_parent, sol.point_child
    diff = (R_p @ local_p + d_p) - (R_c @ local_c + d_c)
    if isinstance(sol, PoseSumsAxis):
        axis_c = R_c @ sol.direction_child
        diff = diff - axis_c * np.sum(diff * axis_c, axis=1, keepdims=True)
    out: FloatArray = np.linalg.norm(diff, axis=1)
    return out


def _joint_summary(run: FitRun, trace: JointTrace, geos: Mapping[str, SegmentGeometry | None] | None) -> dict[str, Any]:
    r = trace.runner
    est = r.estimator
    sol = trace.final
    out: dict[str, Any] = {
        "name": r.cfg.name,
        "type": r.cfg.type,
        "parent": list(r.cfg.parent_markers) or r.cfg.parent_pose_topic,
        "child": list(r.cfg.child_markers) or r.cfg.child_pose_topic,
        "frames_received": r.counters["frames"],
        "frames_in_window": est.n_window,
        "outputs": r.counters["outputs"],
        "malformed_frames": r.counters["malformed"],
        "unmatched_inputs": r.counters["unmatched"],
        "dropped": dict(sorted(est.dropped.items())),
        "absurd_markers": r.counters["absurd_markers"],
    }
    out["gated"] = gated_share(r)
    out["relabelled"] = dict(zip(("parent", "child"), est.relabelled_frames, strict=True))
    out["joint_breaks"] = list(est.joint_breaks)  # frames where the joint broke for good and the window restarted
    out["joint_drifts"] = list(est.joint_drifts)  # frames where a cluster moved on its bone and the window restarted
    if r.cfg.type == "hinge":
        out["axis_points"] = r.axis_words()
    if sol is None:
        out["status"] = "no estimate"
        out["message"] = (r.last_error or r.waiting() or "too few frames").removeprefix("no estimate: ")
        return out
    warning = gate_warning(r)
    out["status"] = ("outlier gate" if warning else "ok") if sol.identifiable else "not identifiable"
    out["identifiable"] = bool(sol.identifiable)
    out["reason"] = sol.reason
    out["message"] = sol.reason if not sol.identifiable else warning
    out["gate_warning"] = warning
    out["units_warning"] = units_warning(run, r)
    # the whole recording's frames when kept, else the last 20 s its router sampled (a bag fitted without the report)
    out["label_warning"] = r.odd_markers() if run.frames is None else recording_odd_markers(run.cfg, r.cfg, run.frames)
    out["cluster_warning"] = weak_cluster(r) if sol.identifiable else ""  # markers nearly on a line: cov under-states
    out["rms_residual"] = float(sol.rms)
    out["noise_sd"] = {"parent": est.noise_std[0], "child": est.noise_std[1]}
    out["lever_ratio"] = r.lever_ratios()  # the joint's distance from each marker cluster, in cluster radii
    white = est.white_noise_std  # skin: the markers' noise alone (noise_sd holds the deformation too)
    out["white_noise_sd"] = None if white is None else {"parent": white[0], "child": white[1]}
    if isinstance(sol, PoseSumsCentre):
        out["centre_parent"] = _list(sol.centre_parent)
        out["sd_parent"] = _sd(sol.cov_parent)
        out["cov_parent"] = _list(sol.cov_parent)
        out["centre_child"] = _list(sol.centre_child)
        out["sd_child"] = _sd(sol.cov_child)
        out["cov_child"] = _list(sol.cov_child)
    elif isinstance(sol, PoseSumsAxis):
        out["direction_parent"] = _list(sol.direction_parent)
        out["direction_sd_deg_parent"] = _angle_sd_deg(sol.cov_direction_parent)
        out["cov_direction_parent"] = _list(sol.cov_direction_parent)
        out["point_parent"] = _list(sol.point_parent)
        out["point_sd_parent"] = _sd(sol.cov_point_parent)
        out["cov_point_parent"] = _list(sol.cov_point_parent)
        out["direction_child"] = _list(sol.direction_child)
        out["direction_sd_deg_child"] = _angle_sd_deg(sol.cov_direction_child)
        out["point_child"] = _list(sol.point_child)
        out["point_sd_child"] = _sd(sol.cov_point_child)
    out.update(_artefact_summary(est, sol))
    out["consistency"] = consistency_summary(trace)
    out["consistency_warning"] = out["consistency"]["message"] if out["consistency"]["consistent"] is False else ""
    geo = _geometry(run, trace, geos)
    if geo is not None:
        rms: dict[str, float | None] = {}
        for names, res in ((r.cfg.parent_markers, geo.residual_parent), (r.cfg.child_markers, geo.residual_child)):
            for k, name in enumerate(names):
                col = res[:, k]
                col = col[np.isfinite(col)]
                rms[name] = float(np.sqrt(np.mean(col**2))) if col.size else None
        out["marker_residual_rms"] = rms
    out["range_of_motion"] = rom_summary(joint_rom(sol, geo))
    if r.cfg.anatomical:
        out["anatomical"] = anatomical_summary(r.cfg, sol, geo, length_unit(run))
    return out


def length_unit(run: FitRun) -> str:
    """The length unit of a run's numbers: the file's (C3D, TRC), else the configured ``units`` (bags)."""
    return run.units or run.cfg.units


def _artefact_summary(est: Any, sol: PoseSumsCentre | PoseSumsAxis) -> dict[str, Any]:
    """``attachment`` and, for skin markers, the statistical part of each sd beside the total (with-artefact) one."""
    out: dict[str, Any] = {"attachment": list(est.attachment)}
    stat = est.statistical_solution
    if stat is None:
        return out
    out["artefact_scale_per_rad"] = float(est.artefact_scale)
    if isinstance(stat, PoseSumsCentre):
        out["sd_parent_statistical"] = _sd(stat.cov_parent)
        out["cov_parent_statistical"] = _list(stat.cov_parent)
        out["sd_child_statistical"] = _sd(stat.cov_child)
    elif isinstance(stat, PoseSumsAxis):
        out["direction_sd_deg_parent_statistical"] = _angle_sd_deg(stat.cov_direction_parent)
        out["point_sd_parent_statistical"] = _sd(stat.cov_point_parent)
        out["direction_sd_deg_child_statistical"] = _angle_sd_deg(stat.cov_direction_child)
        out["point_sd_child_statistical"] = _sd(stat.cov_point_child)
    return out


def consistency_summary(trace: JointTrace) -> dict[str, Any]:
    """The consistency check across movement blocks (:meth:`BlockConsistency.to_dict
    <jointfit_core.consistency.BlockConsistency.to_dict>`), or why there is none."""
    if trace.consistency is None:
        return {"consistent": None, "message": "no consistency check: no block could be solved"}
    return trace.consistency.to_dict()


def gated_share(r: JointRunner) -> dict[str, dict[str, float]]:
    """Per segment (``parent``, ``child``) and the joint test (``joint``): the frames rejected, their number and percent of the frames taken."""
    est = r.estimator
    seen = est.n_frames_seen
    counts = (*est.gated_frames, est.joint_gated_frames)
    return {
        side: {"frames": n, "percent": round(100.0 * n / seen, 2) if seen else 0.0}
        for side, n in zip(("parent", "child", "joint"), counts, strict=True)
    }


def gate_warning(r: JointRunner) -> str:
    """:func:`~jointfit_core.gate.gated_verdict` of a joint (empty when no segment lost more than 10 % of its frames)."""
    est = r.estimator
    return gated_verdict(est.gated_frames, est.n_frames_seen, r.cfg.segment_names(), est.joint_gated_frames)


def units_warning(run: FitRun, r: JointRunner) -> str:
    """Why the joint's marker clusters are implausibly large or small for the run's length unit (empty when not).

    Parameters
    ----------
    run : FitRun
    r : JointRunner
        The joint, with its templates.

    Returns
    -------
    str
        :func:`~jointfit_ros.absurd_values.unit_problem` for :func:`length_unit` (e.g. a C3D in
        millimetres that declares metres, or a bag in millimetres fitted with ``units: m``),
        saying where that unit came from; empty when plausible or unknown.
    """
    unit = length_unit(run)
    problem = unit_problem(r.estimator.length_scale, unit)
    if not problem:
        return ""
    if run.units:
        source = f"the file declares {unit!r}"
    elif run.kind in ("c3d", "trc"):
        source = f"the file declares no unit, {unit!r} is the units parameter's"
    else:
        source = f"{unit!r} is the units parameter's"
    problem = problem.split("; check the driver")[0].replace("the stream looks like", "the recording looks like")
    return f"{problem} ({source}); every length of the fit, the calibrations and subject.urdf are off by that factor"


def fit_summary(
    run: FitRun, *, elapsed_s: float, version: str, geos: Mapping[str, SegmentGeometry | None] | None = None
) -> dict[str, Any]:
    """The summary of a fit as JSON-able plain types.

    Parameters
    ----------
    run : FitRun
    elapsed_s : float
        Wall time of the fit, s.
    version : str
        jointfit's version.
    geos : mapping, optional
        :func:`geometries` of the run, when already computed.

    Returns
    -------
    dict
        ``input``, ``input_kind``, ``units`` (as the file declares them;
        ``""`` for bags), ``length_unit`` (the unit of every length: the
        file's, else the configured ``units``), ``inputs_read``, ``elapsed_s``, ``router`` (bag
        message counters) and ``joints``: per joint its estimate in the
        parent and the child segment frames (the frames of the templates the
        calibration file stores) with covariances (units squared) and
        standard deviations, the rms residuals, the verdict, the counters and
        ``gated``: per segment the frames the outlier gate rejected (number
        and percent); above 10 % of a segment's frames ``status`` is
        ``"outlier gate"`` and ``gate_warning`` says which; ``consistency``:
        the check across movement blocks (the blocks' estimates, chi-square,
        dof, p-value, ratio, spread, verdict; see
        :mod:`jointfit_core.consistency`), and ``consistency_warning`` its
        "skin artefact dominates" message when it fails (empty otherwise);
        ``units_warning``: :func:`units_warning` (empty when the clusters' size fits the length unit);
        ``label_warning``: a marker of the joint's segments that does not keep its distances to the others
        (on another segment, its label swapped, or on soft tissue: :func:`~jointfit_ros.cluster_check.recording_odd_markers`;
        empty when none); ``cluster_warning``: a segment whose markers lie so nearly on a line that the
        covariance under-states (:func:`~jointfit_ros.joint_diagnostics.weak_cluster`; empty when none).
    """
    return {
        "jointfit_version": version,
        "input": str(run.path),
        "input_kind": run.kind,
        "units": run.units,
        "length_unit": length_unit(run),
        "rate_hz": run.rate,
        "inputs_read": run.n_inputs,
        "elapsed_s": round(elapsed_s, 3),
        "router": dict(run.router.counters) if run.router is not None else {},
        "joints": [_joint_summary(run, t, geos) for t in run.traces],
    }


# --------------------------------------------------------------------------- figures


def _pyplot() -> Any:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise MissingDependencyError("the report figures need matplotlib: pip install 'jointfit[plot]'") from None
    return plt


def _subsample(n: int, at_most: int) -> NDArray[np.intp]:
    return np.unique(np.linspace(0, n - 1, min(n, at_most)).astype(np.intp)) if n else np.zeros(0, np.intp)


#: Time series longer than four times this many points are drawn in this many bins (median line,
#: maximum dots); shorter ones (e.g. 40 s at 100 Hz) frame by frame.
PLOT_BINS = 1000


def _run_length(n: int, bins: int = PLOT_BINS) -> int:
    """Samples per run when ``n`` samples are cut into at most ``bins`` runs."""
    return -(-n // bins)


def binned(t: FloatArray, y: FloatArray, bins: int = PLOT_BINS) -> tuple[FloatArray, FloatArray, FloatArray] | None:
    """A long series summarised in ``bins`` runs of consecutive samples, for plotting.

    Parameters
    ----------
    t, y : ndarray, shape (N,)
        Times (increasing) and values (NaN where undefined).
    bins : int
        Most runs; ``None`` is returned for series of at most ``4 * bins`` points (drawn as they are).

    Returns
    -------
    t : ndarray, shape (B,)
        Each run's middle time.
    median, maximum : ndarray, shape (B,)
        Of the run's finite values (NaN where it has none): the typical level, and the
        peak, so that a one-sample spike (a label swap) stays as tall as it is.
    """
    n = y.shape[0]
    if n <= 4 * bins:
        return None
    size = _run_length(n, bins)
    rows = -(-n // size)
    padded = np.full(rows * size, np.nan)
    padded[:n] = y
    runs = np.sort(padded.reshape(rows, size), axis=1)  # NaN last
    k = np.isfinite(runs).sum(axis=1)
    r = np.arange(rows)
    lo, hi = np.maximum((k - 1) // 2, 0), np.maximum(k // 2, 0)
    median = np.where(k > 0, 0.5 * (runs[r, lo] + runs[r, hi]), np.nan)
    peak = np.where(k > 0, runs[r, np.maximum(k - 1, 0)], np.nan)
    mid = t[np.minimum(r * size + size // 2, n - 1)]
    return mid, median, peak


def _plot_series(
    ax: Any, t: FloatArray, y: FloatArray, raw: dict[str, Any], median: dict[str, Any], peak: dict[str, Any]
) -> int:
    """``y`` against ``t``: as it is (``raw`` line properties), or for a long series (:func:`binned`) the
    per-run medians (``median``) and maxima (``peak``; the medians' colour unless given).

    Returns the samples per run drawn (1: every sample).
    """
    b = binned(t, y)
    if b is None:
        ax.plot(t, y, **raw)
        return 1
    line = ax.plot(b[0], b[1], **median)[0]
    ax.plot(b[0], b[2], **{"color": line.get_color(), **peak})
    return _run_length(y.shape[0])


def _draw_trajectories(ax: Any, geo: SegmentGeometry, sol: PoseSumsCentre | PoseSumsAxis, names: tuple[str, ...], unit: str) -> None:
    pts = geo.child_in_parent
    keep = _subsample(pts.shape[0], 1500)
    u = np.linspace(0, 2 * np.pi, 40)
    for k, name in enumerate(names):
        p = pts[keep, k]
        p = p[np.isfinite(p).all(axis=1)]
        line = ax.plot(p[:, 0], p[:, 1], p[:, 2], ".", ms=1.5, label=name)[0]
        allp = pts[:, k][np.isfinite(pts[:, k]).all(axis=1)]
        if not allp.size:
            continue
        if isinstance(sol, PoseSumsCentre):
            c = sol.centre_parent
            rad = float(np.median(np.linalg.norm(allp - c, axis=1)))
            v = np.linspace(0, np.pi, 20)
            xs = c[0] + rad * np.outer(np.cos(u), np.sin(v))
            ys = c[1] + rad * np.outer(np.sin(u), np.sin(v))
            zs = c[2] + rad * np.outer(np.ones_like(u), np.cos(v))
            ax.plot_wireframe(xs, ys, zs, color=line.get_color(), alpha=0.12, linewidth=0.5)
        else:
            a, q = sol.direction_parent, sol.point_parent
            rel = allp - q
            along = rel @ a
            centre = q + float(np.median(along)) * a
            radial = rel - np.outer(along, a)
            rad = float(np.median(np.linalg.norm(radial, axis=1)))
            e1 = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(a, e1)
            circle = centre + rad * (np.outer(np.cos(u), e1) + np.outer(np.sin(u), e2))
            ax.plot(circle[:, 0], circle[:, 1], circle[:, 2], "-", color=line.get_color(), lw=1)
    if isinstance(sol, PoseSumsCentre):
        c = sol.centre_parent
        ax.plot([c[0]], [c[1]], [c[2]], "k*", ms=10, label="centre")
        ax.set_title("child markers in the parent frame\nand their fitted spheres", fontsize=9)
    else:
        a, q = sol.direction_parent, sol.point_parent
        flat = pts[np.isfinite(pts).all(axis=2)]
        span = float(np.ptp((flat - q) @ a)) if flat.size else 1.0
        extent = float(np.max(np.ptp(flat, axis=0))) if flat.size else 1.0
        half = max(0.75 * span, 0.35 * extent, 1e-9)
        ends = q + np.outer([-half, half], a) + float(np.median((flat - q) @ a)) * a
        ax.plot(ends[:, 0], ends[:, 1], ends[:, 2], "k-", lw=2, label="axis")
        ax.set_title("child markers in the parent frame\nwith their fitted circles and the axis", fontsize=9)
    # Equal scales, so that spheres look round and circles circular; the fitted centre (axis point) inside.
    flat = pts[np.isfinite(pts).all(axis=2)]
    joint_point = sol.centre_parent if isinstance(sol, PoseSumsCentre) else sol.point_parent
    if np.isfinite(joint_point).all():
        flat = np.concatenate([flat, joint_point[None]]) if flat.size else joint_point[None]
    if flat.size:
        lo, hi = flat.min(axis=0), flat.max(axis=0)
        mid, half = (lo + hi) / 2, max(float(np.max(hi - lo)) / 2, 1e-9)
        ax.set_xlim(mid[0] - half, mid[0] + half)
        ax.set_ylim(mid[1] - half, mid[1] + half)
        ax.set_zlim(mid[2] - half, mid[2] + half)
        ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel(f"x ({unit})")
    ax.set_ylabel(f"y ({unit})")
    ax.set_zlabel(f"z ({unit})")
    legend = ax.legend(fontsize=7, loc="upper left")
    for handle in legend.legend_handles:
        if hasattr(handle, "set_markersize"):
            handle.set_markersize(6)


def gated_times(run: FitRun, trace: JointTrace) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Times (s from the first frame) of the frames in which the parent, the child and the joint failed the gate."""
    log = trace.runner.estimator.gate_log or []
    t0 = float(run.stamps[0]) if run.stamps.size else 0.0
    out = []
    for side in (0, 1, 2):
        out.append(np.array([stamp for _, k, stamp in log if k == side], dtype=np.float64) - t0)
    return out[0], out[1], out[2]


def _draw_marker_residuals(ax: Any, geo: SegmentGeometry, trace: JointTrace, unit: str, run_: FitRun) -> None:
    cfg = trace.runner.cfg
    run = 1
    for res, names, style in ((geo.residual_parent, cfg.parent_markers, "-"), (geo.residual_child, cfg.child_markers, "--")):
        for k, name in enumerate(names):
            line = {"linestyle": style, "lw": 0.8, "label": name}
            run = _plot_series(ax, geo.t, res[:, k], line, line, {"linestyle": "none", "marker": ".", "ms": 2})
    share = gated_share(trace.runner)
    for side, times, y, colour in zip(
        ("parent", "child", "joint"), gated_times(run_, trace), (0.02, 0.06, 0.10), ("C3", "C1", "C4"), strict=True
    ):
        if times.size:  # rug of the gated frames along the bottom of the panel
            ax.plot(times, np.full(times.size, y), "|", color=colour, ms=6, transform=ax.get_xaxis_transform(),
                    label=f"{side} gated ({share[side]['percent']:.1f} %)")
    shown = "every frame" if run == 1 else f"median (lines) and maximum (dots) of every {run} frames"
    ax.set_xlabel("time (s)")
    ax.set_ylabel(f"marker to posed template ({unit})")
    ax.set_title(f"rigid-body residual per marker (parent solid, child dashed)\n{shown}", fontsize=9)
    ax.legend(fontsize=7, ncol=2, loc="upper right")


def _draw_joint_residual(ax: Any, trace: JointTrace, geo: SegmentGeometry | None, t0: float, unit: str) -> None:
    what = "centres carried by parent and child" if trace.runner.cfg.type == "ball" else "parent axis point to child axis"
    if trace.output_stamps or geo is None or geo.joint_residual is None:
        t, y = np.asarray(trace.output_stamps, dtype=np.float64) - t0, np.asarray(trace.residuals, dtype=np.float64)
    else:
        t, y = geo.t, geo.joint_residual
        what += ", final estimate"
    run = _plot_series(
        ax,
        t,
        y,
        {"linestyle": "none", "marker": ".", "ms": 1.5, "color": "C0"},
        {"linestyle": "-", "lw": 1, "color": "C0", "label": "median"},
        {"linestyle": "none", "marker": ".", "ms": 2, "color": "C3", "label": "maximum"},
    )
    if run > 1:
        ax.legend(fontsize=7, loc="upper right")
    shown = "every frame" if run == 1 else f"median and maximum of every {run} frames"
    ax.set_xlabel("time (s)")
    ax.set_ylabel(f"distance ({unit})")
    ax.set_title(f"per-frame joint residual: {what}\n{shown}", fontsize=9)


def _draw_convergence(ax_est: Any, ax_sd: Any, trace: JointTrace, unit: str) -> None:
    cps = trace.checkpoints
    n = np.array([c.frames for c in cps], dtype=np.float64)
    pos = np.array([c.position for c in cps])
    sd = np.sqrt(np.clip(np.array([np.diag(c.cov) for c in cps]), 0.0, None))
    final = pos[-1]
    for k, axis in enumerate("xyz"):
        line = ax_est.plot(n, pos[:, k] - final[k], "-", label=axis)[0]
        ax_est.fill_between(n, pos[:, k] - final[k] - 2 * sd[:, k], pos[:, k] - final[k] + 2 * sd[:, k], color=line.get_color(), alpha=0.15)
    what = "centre" if trace.runner.cfg.type == "ball" else "axis point"
    ax_est.set_xlabel("frames used")
    ax_est.set_ylabel(f"{what} minus final ({unit})")
    ax_est.set_title(f"convergence of the {what} (bands: +-2 sd)", fontsize=9)
    ax_est.legend(fontsize=7)
    big = np.nanmax(np.abs(pos[len(pos) // 4 :] - final) + 2 * sd[len(pos) // 4 :], initial=0.0)
    if big > 0:
        ax_est.set_ylim(-1.2 * big, 1.2 * big)
    sd_max = np.sqrt(np.clip([np.linalg.eigvalsh(c.cov)[-1] for c in cps], 0.0, None))
    ax_sd.loglog(n, sd_max, "C0-", label=f"{what}: largest sd ({unit})")
    ax_sd.set_xlabel("frames used")
    ax_sd.set_ylabel(f"sd ({unit})")
    if cps[0].cov_direction is not None:
        deg = [_angle_sd_deg(c.cov_direction) for c in cps if c.cov_direction is not None]
        ax2 = ax_sd.twinx()
        ax2.loglog(n, deg, "C1--", label="direction: largest sd (deg)")
        ax2.set_ylabel("direction sd (deg)")
        ax2.legend(fontsize=7, loc="upper right")
    ax_sd.legend(fontsize=7, loc="lower left")
    ax_sd.set_title("reported uncertainty vs frames used", fontsize=9)
    plain_log_ticks(ax_sd.xaxis)
    plain_log_ticks(ax_sd.yaxis)
    if cps[0].cov_direction is not None:
        plain_log_ticks(ax2.yaxis)


def _plain(value: float, _pos: Any = None) -> str:
    return f"{value:.6g}"


def plain_log_ticks(axis: Any) -> None:
    """Decimal labels (``20``, ``0.5``; never ``2x10^1``) on a log axis, at most ~6, minor ticks unlabelled.

    Spans of less than a decade get evenly spaced ticks (a log locator would label every minor tick there, as
    overlapping ``2.04x10^2 2.06x10^2 ...``).
    """
    from matplotlib.ticker import LogLocator, MaxNLocator, NullFormatter

    lo, hi = sorted(axis.get_view_interval())
    if lo > 0 and hi / lo < 10.0:
        axis.set_major_locator(MaxNLocator(nbins=4, steps=[1, 2, 2.5, 5, 10]))
    elif lo > 0 and hi / lo < 300.0:
        axis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0), numticks=7))
    else:
        axis.set_major_locator(LogLocator(base=10.0, subs=(1.0,), numticks=7))
    axis.set_major_formatter(_plain)
    axis.set_minor_formatter(NullFormatter())


def _draw_ellipses(ax: Any, cov: FloatArray, unit: str, title: str) -> None:
    u = np.linspace(0, 2 * np.pi, 100)
    circle = np.stack([np.cos(u), np.sin(u)])
    for (i, j), colour in zip(((0, 1), (0, 2), (1, 2)), ("C0", "C1", "C2"), strict=True):
        c2 = cov[np.ix_((i, j), (i, j))]
        w, v = np.linalg.eigh(c2)
        root = v @ np.diag(np.sqrt(np.clip(w, 0.0, None)))
        for s, style in ((1, "-"), (2, "--"), (3, ":")):
            e = s * root @ circle
            ax.plot(e[0], e[1], style, color=colour, lw=1, label=f"{'xyz'[i]}-{'xyz'[j]} plane" if s == 1 else None)
    ax.set_aspect("equal", adjustable="datalim")
    ax.yaxis.tick_right()
    ax.yaxis.set_label_position("right")
    ax.axhline(0, color="0.8", lw=0.5)
    ax.axvline(0, color="0.8", lw=0.5)
    ax.set_xlabel(f"first coordinate of the plane ({unit})")
    ax.xaxis.get_offset_text().set_x(1.04)  # a "1e-5" multiplier beside the axis, not on its label
    ax.set_ylabel(f"second coordinate ({unit})")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)


def _draw_rom(ax: Any, geo: SegmentGeometry | None, rom: RangeOfMotion | None) -> None:
    """The joint angles over time: a hinge's flexion about its axis, a ball's rotations about their principal axes."""
    if geo is None or rom is None:
        ax.axis("off")
        ax.text(0.5, 0.5, "no range of motion (needs the marker frames of both segments)", ha="center")
        return
    if rom.flexion_deg is not None:
        series = [(rom.flexion_deg, f"about the hinge axis (range {rom.flexion_range_deg:.0f} deg)")]
    else:
        series = [(rom.angles_deg[:, k], f"about principal axis {k + 1} (range {rom.ranges_deg[k]:.0f} deg)")
                  for k in range(3)]
    run = 1
    for k, (y, label) in enumerate(series):
        style = {"linestyle": "-", "lw": 1, "color": f"C{k}", "label": label}
        run = _plot_series(ax, geo.t, y, style, style, {"linestyle": "none", "marker": ".", "ms": 1.5})
    shown = "every frame" if run == 1 else f"median and maximum of every {run} frames"
    ax.set_xlabel("time (s)")
    ax.set_ylabel("angle from the mean orientation (deg)")
    ax.set_title(f"range of motion: the child's rotation in the parent frame\n{shown}", fontsize=9)
    ax.legend(fontsize=7, loc="upper right")


def anatomy_lines(anatomy: Mapping[str, Any], rom: Mapping[str, Any]) -> list[str]:
    """The anatomical results and the range of motion in words, one line each (figure, one-line summary)."""
    lines = []
    if rom:
        if "flexion_range_deg" in rom:
            lines.append(f"flexion range about the axis: {rom['flexion_range_deg']:.0f} deg")
        ranges = ", ".join(f"{v:.0f}" for v in rom["principal_ranges_deg"])
        lines.append(f"rotation ranges about the principal axes: {ranges} deg")
    pelvis = anatomy.get("pelvis")
    if pelvis and "error" not in pelvis:
        u = pelvis["unit"]
        c, sd = pelvis["centre"], pelvis["sd"]
        lines.append(f"{pelvis['side']} hip centre, ISB pelvis axes (origin mid-ASIS,")
        lines.append("x anterior, y superior, z right):")
        lines.append("  (" + ", ".join(f"{v:.0f}" for v in c) + ") +- (" + ", ".join(f"{v:.0f}" for v in sd) + f") {u}")
        pw = pelvis["percent_width"]
        lines.append(f"  = {pw[0]:.0f} %, {pw[1]:.0f} %, {pw[2]:.0f} % (lateral) of the")
        lines.append(f"  inter-ASIS width {pelvis['width']:.0f} {u} (depth {pelvis['depth']:.0f} {u})")
        for name, reg in pelvis["regressions"].items():
            title = name.replace("_", " ").capitalize()
            lines.append(f"  {title}: (" + ", ".join(f"{v:.0f}" for v in reg["centre"]) + f") {u}, "
                         f"{reg['distance']:.0f} {u} away")
    epi = anatomy.get("epicondyles")
    if epi and "error" not in epi:
        u = epi["unit"]
        lines.append(f"axis to the epicondyle line: {epi['angle_to_epicondyle_line_deg']:.1f} deg "
                     f"(direction sd {epi['direction_sd_deg']:.1f} deg)")
        lines.append(f"epicondyle midpoint to the axis: {epi['distance_to_epicondyle_midpoint']:.1f} {u} "
                     f"(width {epi['epicondyle_width']:.0f} {u})")
    for key in ("error",):
        if key in anatomy:
            lines.append(f"anatomical results: {anatomy[key]}")
    for part in ("pelvis", "epicondyles"):
        if isinstance(anatomy.get(part), Mapping) and "error" in anatomy[part]:
            lines.append(f"{part}: {anatomy[part]['error']}")
    return lines


def _draw_anatomy_text(ax: Any, lines: list[str]) -> None:
    ax.axis("off")
    text = "\n".join(lines) if lines else "no anatomical landmarks configured (<joint>.anatomical.*)"
    ax.text(0.0, 1.0, text, ha="left", va="top", fontsize=8, family="monospace", transform=ax.transAxes)
    ax.set_title("anatomical terms and range of motion", fontsize=9, loc="left")


def _headline(trace: JointTrace, unit: str) -> str:
    r = trace.runner
    sol = trace.final
    head = f"{r.cfg.name} ({r.cfg.type})"
    if sol is None:
        return f"{head}: no estimate: {(r.last_error or r.waiting()).removeprefix('no estimate: ')}"
    verdict = "identifiable" if sol.identifiable else f"NOT identifiable: {sol.reason}"
    share = gated_share(r)
    frames = (
        f"{sol.n_frames} frames, rms constraint residual {sol.rms:.3g} {unit}, outlier gate: parent "
        f"{share['parent']['percent']:.1f} %, child {share['child']['percent']:.1f} %, joint test "
        f"{share['joint']['percent']:.1f} % of the frames"
    )
    warning = gate_warning(r)
    if warning:
        verdict += f"\nWARNING: {warning.split(': the estimate')[0]}"
    if trace.consistency is not None and trace.consistency.warns:
        verdict += f"\nWARNING: {trace.consistency.message.split(' (chi2')[0]}"
    if isinstance(sol, PoseSumsCentre):
        c, s = sol.centre_parent, _sd(sol.cov_parent)
        est = "centre (parent frame) = (" + ", ".join(f"{v:.4g}" for v in c) + ") +- (" + ", ".join(f"{v:.2g}" for v in s) + f") {unit}"
    else:
        d = sol.direction_parent
        est = "axis direction (parent frame) = (" + ", ".join(f"{v:.3f}" for v in d) + f") +- {_angle_sd_deg(sol.cov_direction_parent):.2g} deg"
    stat = r.estimator.statistical_solution
    if isinstance(stat, PoseSumsCentre):
        est += " (statistical +- (" + ", ".join(f"{v:.2g}" for v in _sd(stat.cov_parent)) + "); skin: with artefact)"
    elif isinstance(stat, PoseSumsAxis):
        est += f" (statistical {_angle_sd_deg(stat.cov_direction_parent):.2g} deg; skin: with artefact)"
    levers = r.lever_ratios()  # the joint's distance from each marker cluster, in cluster radii (jointfit_core.lever)
    if levers:
        frames += "; lever / cluster radius " + ", ".join(f"{side} {v:.2g}" for side, v in levers.items())
    return f"{head}: {est}\n{frames}; {verdict}"


def joint_figure(run: FitRun, trace: JointTrace, geos: Mapping[str, SegmentGeometry | None] | None = None) -> bytes:
    """One joint's report figure as PNG bytes (see the module docstring for the panels).

    ``geos``: :func:`geometries` of the run, when already computed.

    Raises
    ------
    MissingDependencyError
        matplotlib is not installed.
    """
    plt = _pyplot()
    unit = length_unit(run)
    fig = plt.figure(figsize=(17, 13.5))
    try:
        grid = fig.add_gridspec(3, 3, hspace=0.42, wspace=0.45, height_ratios=(1.0, 1.0, 0.85))
        geo = _geometry(run, trace, geos)
        sol = trace.final
        if geo is not None and sol is not None:
            _draw_trajectories(fig.add_subplot(grid[0, 0], projection="3d"), geo, sol, trace.runner.cfg.child_markers, unit)
            _draw_marker_residuals(fig.add_subplot(grid[0, 1]), geo, trace, unit, run)
        else:
            for k in range(2):
                ax = fig.add_subplot(grid[0, k])
                ax.axis("off")
                ax.text(0.5, 0.5, "no marker frames (pose inputs)" if sol is not None else "no estimate", ha="center")
        t0 = float(run.stamps[0]) if run.stamps.size else (trace.output_stamps[0] if trace.output_stamps else 0.0)
        _draw_joint_residual(fig.add_subplot(grid[0, 2]), trace, geo, t0, unit)
        if trace.checkpoints:
            _draw_convergence(fig.add_subplot(grid[1, 0]), fig.add_subplot(grid[1, 1]), trace, unit)
        if sol is not None:
            if isinstance(sol, PoseSumsCentre):
                _draw_ellipses(fig.add_subplot(grid[1, 2]), sol.cov_parent, unit, "centre covariance (parent frame): 1, 2, 3 sd")
            else:
                _draw_ellipses(fig.add_subplot(grid[1, 2]), sol.cov_point_parent, unit, "axis point covariance (parent frame): 1, 2, 3 sd")
        rom = joint_rom(sol, geo)
        _draw_rom(fig.add_subplot(grid[2, 0:2]), geo, rom)
        anatomy = anatomical_summary(trace.runner.cfg, sol, geo, unit)
        _draw_anatomy_text(fig.add_subplot(grid[2, 2]), anatomy_lines(anatomy, rom_summary(rom)))
        fig.suptitle(_headline(trace, unit), fontsize=11)
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=90)
    finally:
        plt.close(fig)
    return buf.getvalue()


def _one_joint_report(index: int) -> tuple[SegmentGeometry | None, bytes]:
    """In a forked process: the geometry and the figure of the run's ``index``-th joint (the run inherited)."""
    run = _FORKED_RUN[0]
    assert run is not None
    trace = run.traces[index]
    geo = segment_geometry(run, trace)
    return geo, joint_figure(run, trace, {trace.runner.cfg.name: geo})


def _ignore_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)


#: The run that :func:`joint_reports` hands to its forked processes (set only while they run).
_FORKED_RUN: list[FitRun | None] = [None]


def joint_reports(run: FitRun, *, parallel: bool | None = None) -> tuple[dict[str, SegmentGeometry | None], dict[str, bytes]]:
    """Every joint's geometry (:func:`geometries`) and figure (:func:`joint_figure`).

    Parameters
    ----------
    run : FitRun
    parallel : bool, optional
        One forked process per joint (at most one per CPU), which inherits the
        run: drawing takes ~1 s per joint for a long recording. Default: when
        there are several joints and the process may fork
        (:func:`~jointfit_ros.bag_blocks.can_fork`).

    Returns
    -------
    geometries : dict
        By joint name, as :func:`geometries`.
    figures : dict
        By joint name, PNG bytes.

    Raises
    ------
    MissingDependencyError
        matplotlib is not installed.
    """
    names = [t.runner.cfg.name for t in run.traces]
    if parallel is None:
        parallel = len(names) > 1 and can_fork()
    if not parallel:
        geos = geometries(run)
        return geos, {t.runner.cfg.name: joint_figure(run, t, geos) for t in run.traces}
    _pyplot()  # imported once, here: the processes inherit it (and a missing matplotlib is said here)
    _FORKED_RUN[0] = run
    try:
        processes = min(len(names), os.cpu_count() or 1)
        # Ctrl-C is this process's to handle: leaving the block terminates the workers
        with multiprocessing.get_context("fork").Pool(processes, initializer=_ignore_sigint) as pool:
            results = pool.map(_one_joint_report, range(len(names)), chunksize=1)
    finally:
        _FORKED_RUN[0] = None
    return {n: g for n, (g, _) in zip(names, results, strict=True)}, {n: f for n, (_, f) in zip(names, results, strict=True)}

