"""``joint_angles.csv`` of ``jointfit fit``: each joint's angles per frame, as ``~/joint_states`` gives them live.

Columns: ``frame``, ``time`` (s), then per joint its ``~/joint_states`` names
(:func:`~jointfit_core.urdf.joint_state_names`: ``<joint>`` for a hinge, ``<joint>_x``,
``_y``, ``_z`` for a ball joint), in rad, then the same names with ``_rate`` (rad/s,
backward differences over the stamps, :func:`~jointfit_core.joint_angles.angle_rates`).
The conventions are :mod:`jointfit_core.joint_angles`' (zero at the templates' pose; hinge:
the turn about the calibrated axis; ball: intrinsic X-Y-Z Cardan angles of the child's
rotation in the parent template frame). Both segments are posed on the final templates in
every frame (:func:`~jointfit_core.pose.poses_from_markers`); NaN where a segment cannot be
posed, where the outlier gate or the joint test rejected the frame, or for a joint without an
identifiable estimate, a chain joint (its segments include other joints' centres) or a joint
of pose topics.
"""

from __future__ import annotations

import io

import numpy as np
from numpy.typing import NDArray

from jointfit_core.errors import InputError
from jointfit_core.hinge_from_sums import PoseSumsAxis
from jointfit_core.joint_angles import angle_rates, cardan_xyz, hinge_angle
from jointfit_core.pose import poses_from_markers
from jointfit_core.urdf import joint_state_names

from .offline import FitRun, JointTrace

__all__ = ["joint_angles_csv"]

FloatArray = NDArray[np.float64]


def _rejected(run: FitRun, trace: JointTrace) -> NDArray[np.bool_]:
    """Frames in which the gate rejected a segment or the joint test the frame (the estimator's log, by stamp)."""
    log = trace.runner.estimator.gate_log or []
    stamps = np.array([stamp for _, _, stamp in log], dtype=np.float64)
    if not stamps.size:
        return np.zeros(run.stamps.shape, dtype=bool)
    return np.isin(np.rint(run.stamps * 1e9), np.rint(stamps * 1e9))


def _angles(run: FitRun, trace: JointTrace) -> FloatArray:
    """(N, 1) hinge or (N, 3) ball angles (rad) of one joint; NaN where there are none."""
    assert run.frames is not None
    r = trace.runner
    n = run.frames.shape[0]
    width = 1 if r.cfg.type == "hinge" else 3
    out = np.full((n, width), np.nan)
    sol = trace.final
    tp, tc = r.estimator.templates
    chained = r.cfg.parent_chain or r.cfg.child_chain or r.cfg.parent_pose_topic or r.cfg.child_pose_topic
    if sol is None or not sol.identifiable or tp is None or tc is None or chained:
        return out
    try:
        parent = poses_from_markers(run.frames[:, r.parent_rows], tp)
        child = poses_from_markers(run.frames[:, r.child_rows], tc)
    except InputError:  # no frame poses a segment
        return out
    Q = np.swapaxes(parent.R_world_local, 1, 2) @ child.R_world_local
    good = np.isfinite(Q).all(axis=(1, 2)) & ~_rejected(run, trace)
    if isinstance(sol, PoseSumsAxis):
        out[good, 0] = hinge_angle(Q[good], sol.direction_parent)
    else:
        out[good] = cardan_xyz(Q[good])
    return out


def joint_angles_csv(run: FitRun) -> str:
    """``joint_angles.csv`` of a run that kept its marker frames (see the module notes).

    Raises
    ------
    InputError
        The run kept no marker frames.
    """
    if run.frames is None or not run.frames.shape[0]:
        raise InputError(f"{run.path}: no marker frames for the joint angles")
    names: list[str] = []
    angles: list[FloatArray] = []
    for trace in run.traces:
        names += joint_state_names(trace.runner.cfg.name, trace.runner.cfg.type)
        angles.append(_angles(run, trace))
    table = np.concatenate(angles, axis=1)
    rates = angle_rates(table, run.stamps)
    n = table.shape[0]
    frames = np.arange(1, n + 1, dtype=np.float64)
    out = io.StringIO()
    header = ["frame", "time"] + names + [f"{v}_rate" for v in names]
    np.savetxt(out, np.column_stack([frames, run.stamps, table, rates]),
               fmt=["%d", "%.9f"] + ["%.10g"] * (2 * len(names)), delimiter=",", header=",".join(header), comments="")
    return out.getvalue().replace("nan", "NaN")
