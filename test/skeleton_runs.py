"""The node's per-message path over a skeleton stream, and each joint's error against its covariance.

Shared by ``test/test_skeleton_configs.py``, ``test/test_skeleton_sta.py`` and
``bench/skeleton_sta.py``: frames are encoded as PoseArray CDR bytes and fed to
:class:`~jointfit_ros.inputs.MessageRouter` -> :class:`~jointfit_ros.runner.JointRunner` ->
``OnlineJoint`` (no ROS) in blocks of 100, as ``jointfit fit`` does; the truth is mapped into
each joint's own parent template frame (:meth:`Skeleton.joint_in_template`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from helpers import mahalanobis
from numpy.typing import NDArray

from jointfit_core.skeleton_sta import skeleton_skin_frames, sta_amplitudes
from jointfit_core.skeleton_truth import Skeleton, make_skeleton
from jointfit_ros.inputs import MessageRouter
from jointfit_ros.params import NodeConfig, node_config, params_from_file
from jointfit_ros.raw import pose_array_bytes
from jointfit_ros.runner import JointRunner

#: Stamp of motion time 0 (ns).
T0 = 1_000_000_000_000


def run_stream(
    cfg: NodeConfig,
    times: NDArray[np.float64],
    frames: NDArray[np.float64],
    block: int = 100,
    estimate_period: float | None = None,
) -> list[JointRunner]:
    """Feed ``frames`` (N, P, 3) (m) stamped at ``times`` (s) through the node's router; the runners.

    ``estimate_period`` (s of stream time): solve every joint that often, as the node does
    (its ``estimate_period``, 0.1 s by default); the blocks then end there. None: no solve
    during the stream (blocks of ``block`` frames). The outlier gate's limits follow the
    latest estimate, so the two differ on skin markers (see test_skeleton_sta.py).
    """
    raws = [pose_array_bytes(T0 + round(tk * 1e9), "world", f) for tk, f in zip(times, frames, strict=True)]
    runners = [JointRunner(j, cfg) for j in cfg.joints]
    router = MessageRouter(cfg, runners)
    if estimate_period is None:
        starts = list(range(0, len(raws), block))
    else:
        ticks = np.floor((times - times[0]) / estimate_period).astype(np.int64)
        starts = [0, *(np.flatnonzero(np.diff(ticks)) + 1).tolist()]
    for lo, hi in zip(starts, [*starts[1:], len(raws)], strict=True):
        for start in range(lo, hi, block):
            router.markers_many(raws[start : min(start + block, hi)])
        if estimate_period is not None:
            for r in runners:
                r.estimate(force=True)
    assert router.counters["malformed"] == 0
    return runners


@dataclass(frozen=True)
class JointScore:
    """One joint's estimate against the truth.

    Attributes
    ----------
    name, kind : str
    error : float
        Ball: centre error (mm); hinge: direction error (deg).
    sd : float
        Ball: sqrt(tr cov) of the centre (mm); hinge: of the direction (deg).
    e : float
        ``err^T cov^+ err / rank``: the centre's (ball) or the direction's (hinge).
    point_error, point_sd, point_e : float
        Hinge: the point's distance from the true axis (mm), the point covariance's sd and e/2
        in the plane normal to the estimated axis (as bench/sta.py); NaN for a ball.
    point_e_rank : float
        Hinge: the point's ``err^T cov^+ err / rank`` against the axis point nearest the
        template origin (the measure of test_skeleton_configs); NaN for a ball.
    identifiable : bool
    gated : float
        Share of the frames seen in which the outlier gate left out markers or a whole
        segment (parent or child).
    """

    name: str
    kind: str
    error: float
    sd: float
    e: float
    point_error: float
    point_sd: float
    point_e: float
    point_e_rank: float
    identifiable: bool
    gated: float


def score(sk: Skeleton, runner: JointRunner) -> JointScore:
    """Solve ``runner`` now (force) and compare its estimate with the skeleton's truth."""
    assert runner.estimate(force=True), runner.last_error
    sol = runner.estimator.solution
    assert sol is not None, runner.cfg.name
    template = runner.estimator.templates[0]
    assert template is not None
    point, direction = sk.joint_in_template(runner.cfg.name, template)
    nan = float("nan")
    est = runner.estimator
    gated = sum(est.gated_frames) / max(est.n_frames_seen, 1)
    if direction is None:
        err = sol.centre_parent - point
        return JointScore(runner.cfg.name, "ball", 1e3 * float(np.linalg.norm(err)), 1e3 * float(np.sqrt(np.trace(sol.cov_parent))),
                          mahalanobis(err, sol.cov_parent), nan, nan, nan, nan, bool(sol.identifiable), gated)  # fmt: skip
    d = sol.direction_parent * np.sign(sol.direction_parent @ direction)
    off = point - sol.point_parent
    off_perp = off - (off @ d) * d
    basis = np.linalg.svd(np.eye(3) - np.outer(d, d))[0][:, :2]
    cov_perp = basis.T @ sol.cov_point_parent @ basis
    perp = basis.T @ off_perp
    return JointScore(
        runner.cfg.name, "hinge", float(np.degrees(np.arccos(min(1.0, float(d @ direction))))),
        float(np.degrees(np.sqrt(np.trace(sol.cov_direction_parent)))), mahalanobis(d - direction, sol.cov_direction_parent),
        1e3 * float(np.linalg.norm(off_perp)), 1e3 * float(np.sqrt(np.trace(cov_perp))),
        float(perp @ np.linalg.solve(cov_perp, perp)) / 2.0, mahalanobis(sol.point_parent - point, sol.cov_point_parent),
        bool(sol.identifiable), gated,
    )  # fmt: skip


#: The lower body's parameters (``config/lower_body.yaml``).
LOWER_BODY = Path(__file__).resolve().parents[1] / "config" / "lower_body.yaml"


def swapped_thigh_stream(seed: int, swap: bool = True) -> tuple[NodeConfig, list[bytes]]:
    """The skin lower body, 12 s at 100 Hz (1 % occluded), two right-thigh markers swapped in frames 700-899.

    Returns the node's configuration (``config/lower_body.yaml``) and the frames as PoseArray CDR
    bytes stamped from :data:`T0`. ``swap`` False: the same stream without the swap.
    """
    sk = make_skeleton("lower", seed=seed)
    t = np.arange(1200) / 100.0
    frames = skeleton_skin_frames(sk, t, np.random.default_rng(seed), sta_amplitudes(sk), noise=0.0005, occlusion=0.01)
    cfg = node_config(params_from_file(LOWER_BODY))
    if swap:
        names = sk.marker_names()
        hip = next(j for j in cfg.joints if j.name == "r_hip")
        a, b = (names.index(m) for m in hip.child_markers[:2])
        frames[700:900, [a, b]] = frames[700:900, [b, a]]
    return cfg, [pose_array_bytes(T0 + round(tk * 1e9), "world", f) for tk, f in zip(t, frames, strict=True)]
