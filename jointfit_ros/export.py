"""``jointfit fit --export``: the fitted joints frame by frame, as a CSV and as virtual markers (TRC, C3D).

ROS-free. Every frame's joint in the world (lab) frame is the final estimate
carried by that frame's parent pose, as the node's per-frame outputs
(``<joint>/centre``, ``<joint>/axis``) carry it: ``R_p c_p + d_p``, with the
parent posed from its visible markers on the final template (Stoddart eq. 4,
:func:`~jointfit_core.pose.poses_from_markers`). No value (NaN) where the node
publishes none: the parent not posed (fewer than 3 visible, well-spread
markers), the parent rejected by the outlier gate in that frame, a joint
without an identifiable estimate (unless ``publish_unidentified``).

* ``joints.csv``: one row per marker frame: ``frame`` (the file's frame
  number, 1-based as in TRC; bags: 1, 2, ...), ``time`` (the frame's stamp,
  s), then per joint ``<joint>_x, _y, _z`` (ball: the centre; hinge: the axis
  point nearest the parent template centroid), hinges ``<joint>_dx, _dy,
  _dz`` (unit direction, the sign of the fit's summary), and ``<joint>_sd_x,
  _sd_y, _sd_z`` (standard deviation per world axis: the estimate's
  covariance plus the frame's parent pose noise at the point, as the node's
  per-frame covariance), hinges ``<joint>_dsd_deg`` (the direction's largest
  angular sd, degrees, the same way). Input units; ``NaN`` where there is none.
* ``joints.trc`` / ``joints.c3d``: the markers of ``marker_names`` plus, per
  joint, ``<joint>_JC`` (the centre, or the axis point) and for hinges
  ``<joint>_AX1`` and ``<joint>_AX2``, the points :data:`AXIS_HALF_LENGTH_M`
  (50 mm) before and after it along the axis: how gait software takes
  functional joint centres. Input units and rate (bags: the median stamp
  step); C3D stores float32, as the format does.
"""

from __future__ import annotations

import io
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from jointfit_core.errors import InputError, MissingDependencyError
from jointfit_core.hinge_from_sums import PoseSumsAxis
from jointfit_core.io import MarkerData, trc_text
from jointfit_core.pose import pose_covariance_local, poses_from_markers, skew
from jointfit_core.segments import PoseSumsCentre

from .offline import FitRun, JointTrace
from .params import ConfigError, NodeConfig

__all__ = ["EXPORT_FORMATS", "AXIS_HALF_LENGTH_M", "JointTrack", "check_exportable", "joint_tracks",
           "csv_text", "with_virtual_markers", "c3d_bytes", "export_files"]

FloatArray = NDArray[np.float64]

EXPORT_FORMATS = ("csv", "trc", "c3d")
#: Distance of ``<joint>_AX1`` and ``<joint>_AX2`` from ``<joint>_JC`` along a hinge axis, metres.
AXIS_HALF_LENGTH_M = 0.05
_METRES_PER_UNIT = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}


@dataclass(frozen=True)
class JointTrack:
    """One joint in the world, frame by frame.

    Attributes
    ----------
    name, kind : str
    position : ndarray, shape (N, 3)
        Ball: the centre; hinge: the axis point nearest the parent template
        centroid. World frame, input units; NaN where there is none.
    direction : ndarray, shape (N, 3) or None
        Hinge: the unit axis direction, world frame.
    sd : ndarray, shape (N, 3)
        Standard deviation of ``position`` per world axis, input units: the
        estimate's covariance plus the frame's parent pose noise at the point
        (the node's per-frame covariance).
    direction_sd_deg : ndarray, shape (N,) or None
        Hinge: the direction's largest angular standard deviation (degrees),
        the estimate's and the frame's pose noise.
    """

    name: str
    kind: str
    position: FloatArray
    direction: FloatArray | None
    sd: FloatArray
    direction_sd_deg: FloatArray | None = None


def check_exportable(cfg: NodeConfig) -> None:
    """Refuse joints whose segments come from pose topics (the export poses segments from markers).

    Raises
    ------
    ConfigError
    """
    pose_joints = [j.name for j in cfg.joints if j.parent_pose_topic or j.child_pose_topic]
    if pose_joints:
        raise ConfigError(f"--export: joints {pose_joints} read pose topics; the export covers marker joints only")


def _gated_parent_frames(run: FitRun, trace: JointTrace) -> NDArray[np.bool_]:
    """The frames in which the outlier gate rejected the parent (the estimator's gate log, matched by stamp)."""
    log = trace.runner.estimator.gate_log or []
    gated = np.array([stamp for _, side, stamp in log if side == 0], dtype=np.float64)
    if not gated.size:
        return np.zeros(run.stamps.shape, dtype=bool)
    return np.isin(np.rint(run.stamps * 1e9), np.rint(gated * 1e9))


def _no_track(name: str, kind: str, n: int) -> JointTrack:
    nan = np.full((n, 3), np.nan)
    hinge = kind == "hinge"
    return JointTrack(name, kind, nan, nan.copy() if hinge else None, nan.copy(), np.full(n, np.nan) if hinge else None)


def _track(run: FitRun, trace: JointTrace, earlier: dict[str, JointTrack]) -> JointTrack:
    assert run.frames is not None
    n = run.frames.shape[0]
    r = trace.runner
    sol = trace.final
    template = r.estimator.templates[0]
    if sol is None or template is None or not (sol.identifiable or r.cfg.publish_unidentified):
        return _no_track(r.cfg.name, r.cfg.type, n)
    parent = run.frames[:, r.parent_rows]
    if r.cfg.parent_chain:  # earlier joints' per-frame positions as virtual markers, as the node adds them
        parent = np.concatenate([parent, np.stack([earlier[j].position for j in r.cfg.parent_chain], axis=1)], axis=1)
    try:
        poses = poses_from_markers(parent, template)
    except InputError:  # e.g. no frame with the parent's markers
        return _no_track(r.cfg.name, r.cfg.type, n)
    R, d = poses.R_world_local, poses.d_world_local
    R = np.where(_gated_parent_frames(run, trace)[:, None, None], np.nan, R)
    # The node's per-frame covariance: the estimate's plus this frame's parent pose noise at the point
    # (Pennec & Thirion, the visible markers' pose covariance carried by J = [-[p]x, I]), into the world.
    W = pose_covariance_local(template, r.estimator.noise_std[0], ~np.isnan(parent[..., 0]))
    direction = direction_sd = None
    if isinstance(sol, PoseSumsCentre):
        local, cov = sol.centre_parent, sol.cov_parent
    else:
        assert isinstance(sol, PoseSumsAxis)
        local, cov = sol.point_parent, sol.cov_point_parent
        direction = R @ sol.direction_parent
        Nx = skew(sol.direction_parent)
        cov_direction = sol.cov_direction_parent + Nx @ W[:, :3, :3] @ Nx.T  # (N, 3, 3), rotation invariant
        good = np.isfinite(cov_direction).all(axis=(1, 2)) & ~np.isnan(R[:, 0, 0])
        direction_sd = np.full(n, np.nan)
        direction_sd[good] = np.degrees(np.sqrt(np.clip(np.linalg.eigvalsh(cov_direction[good])[:, -1], 0.0, None)))
    position = R @ local + d
    J = np.concatenate([-skew(local), np.eye(3)], axis=1)
    cov_local = cov + J @ W @ J.T  # (N, 3, 3)
    with np.errstate(invalid="ignore"):
        sd = np.sqrt(np.clip(np.einsum("nij,njk,nik->ni", R, cov_local, R), 0.0, None))
    return JointTrack(r.cfg.name, r.cfg.type, position, direction, sd, direction_sd)


def joint_tracks(run: FitRun) -> list[JointTrack]:
    """Every configured joint's :class:`JointTrack` over the kept marker frames, in configuration order.

    Raises
    ------
    InputError
        The run kept no marker frames (``keep_frames=False``, or a bag of pose topics only).
    """
    if run.frames is None or not run.frames.shape[0]:
        raise InputError(f"{run.path}: no marker frames to export")
    tracks: dict[str, JointTrack] = {}
    for trace in run.traces:
        tracks[trace.runner.cfg.name] = _track(run, trace, tracks)
    return list(tracks.values())


def _rate(run: FitRun) -> float:
    if run.rate > 0.0:
        return run.rate
    steps = np.diff(run.stamps)
    step = float(np.median(steps)) if steps.size else 0.0
    return 1.0 / step if step > 0.0 else 1.0


def _first_frame(run: FitRun) -> int:
    """The file's 0-based first frame (C3D/TRC stamps are ``(first_frame + k) / rate``); 0 for bags."""
    return round(float(run.stamps[0]) * run.rate) if run.rate > 0.0 and run.stamps.size else 0


def csv_text(run: FitRun, tracks: list[JointTrack]) -> str:
    """``joints.csv`` (see the module docstring)."""
    n = run.stamps.shape[0]
    names = ["frame", "time"]
    columns: list[FloatArray] = [(_first_frame(run) + 1 + np.arange(n)).astype(np.float64), run.stamps]
    for t in tracks:
        names += [f"{t.name}_{a}" for a in "xyz"]
        columns.append(t.position)
        if t.direction is not None:
            names += [f"{t.name}_d{a}" for a in "xyz"]
            columns.append(t.direction)
        names += [f"{t.name}_sd_{a}" for a in "xyz"]
        columns.append(t.sd)
        if t.direction_sd_deg is not None:
            names.append(f"{t.name}_dsd_deg")
            columns.append(t.direction_sd_deg)
    table = np.column_stack(columns)
    out = io.StringIO()
    fmt = ["%d", "%.9f"] + ["%.17g"] * (table.shape[1] - 2)
    np.savetxt(out, table, fmt=fmt, delimiter=",", header=",".join(names), comments="")
    return out.getvalue().replace("nan", "NaN")


def with_virtual_markers(run: FitRun, tracks: list[JointTrack]) -> MarkerData:
    """The markers of ``marker_names`` plus ``<joint>_JC`` (and ``_AX1``, ``_AX2`` for hinges).

    Raises
    ------
    InputError
        A virtual marker's name is already a marker's, or hinge axis points
        in a unit other than m, cm, mm.
    """
    assert run.frames is not None
    units = run.units or run.cfg.units
    labels = list(run.cfg.marker_names)
    parts = [run.frames]
    for t in tracks:
        labels.append(f"{t.name}_JC")
        parts.append(t.position[:, None, :])
        if t.direction is not None:
            if units not in _METRES_PER_UNIT:
                raise InputError(f"{run.path}: units {units!r}: cannot place the axis points 50 mm apart")
            half = AXIS_HALF_LENGTH_M / _METRES_PER_UNIT[units]
            labels += [f"{t.name}_AX1", f"{t.name}_AX2"]
            parts += [(t.position - half * t.direction)[:, None, :], (t.position + half * t.direction)[:, None, :]]
    taken = sorted({lab for lab in labels if labels.count(lab) > 1})
    if taken:
        raise InputError(f"--export: the virtual markers {taken} would repeat a marker label of the recording")
    return MarkerData(np.concatenate(parts, axis=1), tuple(labels), _rate(run), units, _first_frame(run))


def c3d_bytes(data: MarkerData) -> bytes:
    """A C3D file of ``data`` (POINT data, LABELS, RATE, UNITS; float32, as the format stores it).

    Raises
    ------
    MissingDependencyError
        ``ezc3d`` missing.
    """
    try:
        import ezc3d
    except ImportError:
        raise MissingDependencyError("writing C3D needs ezc3d: pip install 'jointfit[c3d]'") from None
    c3d = ezc3d.c3d()
    points = np.ones((4, len(data.labels), data.n_frames))
    points[:3] = data.markers.transpose(2, 1, 0)
    c3d["parameters"]["POINT"]["RATE"]["value"] = [data.rate]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = list(data.labels)
    c3d.add_parameter("POINT", "UNITS", [data.units])
    c3d["data"]["points"] = points
    c3d["header"]["points"]["first_frame"] = data.first_frame  # the input's frame numbers (0-based; ezc3d writes +1)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "joints.c3d"
        c3d.write(os.fspath(path))
        return path.read_bytes()


def export_files(run: FitRun, formats: tuple[str, ...]) -> dict[str, bytes | str]:
    """The export files by name (``joints.csv``, ``joints.trc``, ``joints.c3d``) of the formats asked for."""
    tracks = joint_tracks(run)
    files: dict[str, bytes | str] = {}
    if "csv" in formats:
        files["joints.csv"] = csv_text(run, tracks)
    if "trc" in formats or "c3d" in formats:
        data = with_virtual_markers(run, tracks)
        if "trc" in formats:
            files["joints.trc"] = trc_text(data, "joints.trc")
        if "c3d" in formats:
            files["joints.c3d"] = c3d_bytes(data)
    return files
