"""Peer comparison: jointfit against biobuddy's SCoRE and SARA (Ehrig et al. 2006, 2007).

Run with ``python bench/peers.py`` (``--quick`` for fewer trials) in an
environment that has the bench extras (``pip install -r
requirements-bench.txt``); prints Markdown and writes
``bench/results/peers.md``. Without ``biobuddy`` it prints a skip line, leaves
the result file alone and exits 0.

biobuddy (pyomeca, MIT) implements SCoRE (symmetrical centre of rotation
estimation, Ehrig et al. 2006) and SARA (symmetrical axis of rotation
approach, Ehrig et al. 2007) as ``Score.perform_algorithm`` and
``Sara.perform_algorithm``: both take the world poses of the parent and the
child segment (4x4 per frame), stack ``[R_c, -R_p] [c_c; c_p] = d_p - d_c``
over the frames and solve it by SVD (SARA: the axis is the right singular
vector of the smallest singular value), then drop the frames whose residual
exceeds mean + 1 sd and solve again. Its own pipeline poses each segment per
frame with SLSQP against a static-trial model; here both peers get the
least-squares (SVD) poses of :mod:`jointfit_core.pose` on a template fitted to
the same markers, so that the comparison is of the joint estimators (the
SLSQP pose step is measured separately, see section 3).

jointfit: ``fit_centre_two_segments`` / ``fit_axis_two_segments`` with their
defaults (markers in, covariance and identifiability verdict out).

Cases
-----
1. Real recordings (test/data/biobuddy, biobuddy's own functional trials):
   right hip (pelvis RASIS LASIS RPSIS LPSIS, thigh RTHI1-3): the centre in
   the pelvis frame against the published-methods box of the data README;
   right knee (thigh RTHI1-3, shank RLEG1-3): the axis against the
   epicondyle line RLFE-RMFE (within 15 deg, within 15 mm of their
   midpoint). No ground truth: only plausibility and agreement.
2. Synthetic Stoddart-like rigs with known truth
   (:func:`jointfit_core.synthetic.two_segment_motion`, 3 + 3 markers, 60 Hz):
   20 s and 2.5 s of motion with 1 mm noise, and 20 s with an added smooth
   per-marker artefact (each coordinate a sum of two sinusoids of 0.1-0.5 Hz,
   3 mm peak per sinusoid; the skin-movement kind of model error). Errors are
   those of the parent-frame estimate against the truth mapped into each
   method's local frame.

Time per fit is wall clock, median over the trials, measured in the same run
for both (the peer's includes its pose step and building biobuddy's
``RotoTransMatrixTimeSeries``); ratio = jointfit / peer (below 1: jointfit
faster).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.metadata
import io
import logging
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

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
    rotation_to_estimated_frame,
    run_header,
    to_estimated_frame,
)
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from jointfit_core.frames import pelvis_frame, to_frame
from jointfit_core.io import read_c3d
from jointfit_core.pose import Poses, poses_from_markers, template_from_markers
from jointfit_core.segments import fit_axis_two_segments, fit_centre_two_segments
from jointfit_core.synthetic import two_segment_motion

try:
    import biobuddy
    from biobuddy import RotoTransMatrixTimeSeries, Sara, Score
except ImportError as _exc:  # optional bench dependency
    biobuddy = None
    _IMPORT_ERROR: str = f"{type(_exc).__name__}: {_exc}"
else:
    _IMPORT_ERROR = ""

FloatArray = NDArray[np.float64]

SCRIPT = "peers.py"
SEED = 20060601
DATA = Path(__file__).resolve().parent.parent / "test" / "data" / "biobuddy"
RATE_HZ = 60.0
NOISE_MM = 1.0
ARTEFACT_MM = 3.0
#: Published methods on right_hip.c3d (shared data README), pelvis frame, mm: x, y, z ranges.
HIP_BOX = np.array([[-63.0, -57.0], [-98.0, -72.0], [-95.0, -76.0]])
HIP_MARGIN = 5.0
KNEE_MAX_DEG = 15.0
KNEE_MAX_MM = 15.0
#: (label, seconds of motion, artefact on?)
CASES = (
    ("20 s, 1 mm noise", 20.0, False),
    ("2.5 s, 1 mm noise", 2.5, False),
    ("20 s, 1 mm + 3 mm artefact", 20.0, True),
)
PEER_DISTS = ("biobuddy", "pandas", "lxml", "graphviz")


# ----------------------------------------------------------------------------- the peer


def _rts(poses: Poses) -> Any:
    """biobuddy ``RotoTransMatrixTimeSeries`` from jointfit poses."""
    n = poses.valid.size
    rt = np.zeros((4, 4, n))
    rt[:3, :3] = np.moveaxis(poses.R_world_local, 0, -1)
    rt[:3, 3] = poses.d_world_local.T
    rt[3, 3] = 1.0
    return RotoTransMatrixTimeSeries.from_rt_matrix(rt)


@dataclass
class PeerFit:
    """What the peer returns, in the local frames of ``template_parent`` / ``template_child``."""

    template_parent: FloatArray
    poses_parent: Poses
    poses_child: Poses
    point_parent: FloatArray  # centre (SCoRE) or an axis point (SARA)
    point_child: FloatArray
    direction_parent: FloatArray | None  # SARA only
    frames_kept: int
    residual_rms: float


def _peer(parent: FloatArray, child: FloatArray, kind: str) -> PeerFit:
    tp, tc = template_from_markers(parent), template_from_markers(child)
    pp, pc = poses_from_markers(parent, tp), poses_from_markers(child, tc)
    rt_p, rt_c = _rts(pp), _rts(pc)
    if kind == "ball":
        _, c_p, c_c, kept, _ = Score.perform_algorithm(rt_p, rt_c)
        direction = None
    else:
        _, n_p, _, _, c_p, c_c, kept, _ = Sara.perform_algorithm(rt_p, rt_c)
        direction = np.asarray(n_p, dtype=np.float64)
    c_p, c_c = np.asarray(c_p, dtype=np.float64)[:3], np.asarray(c_c, dtype=np.float64)[:3]
    world_p = np.einsum("nij,j->ni", pp.R_world_local, c_p) + pp.d_world_local
    world_c = np.einsum("nij,j->ni", pc.R_world_local, c_c) + pc.d_world_local
    if direction is not None:  # an axis: the residual is the distance between the two lines' points, off-axis
        n_w = np.einsum("nij,j->ni", pp.R_world_local, direction)
        off = world_c - world_p
        off = off - np.einsum("ni,ni->n", off, n_w)[:, None] * n_w
        residual = np.linalg.norm(off, axis=1)
    else:
        residual = np.linalg.norm(world_p - world_c, axis=1)
    return PeerFit(tp, pp, pc, c_p, c_c, direction, len(kept), float(np.sqrt(np.nanmean(residual**2))))


def _timed(fn: Callable[[], Any]) -> tuple[Any, float]:
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def _quiet(fn: Callable[[], Any]) -> Any:
    """Run ``fn`` with its stdout (biobuddy prints on failure) captured."""
    with contextlib.redirect_stdout(io.StringIO()):
        return fn()


# ----------------------------------------------------------------------------- real recordings


def real_hip() -> tuple[list[list[str]], list[str]]:
    data = read_c3d(DATA / "right_hip.c3d")
    pelvis = data.select(["RASIS", "LASIS", "RPSIS", "LPSIS"])
    thigh = data.select(["RTHI1", "RTHI2", "RTHI3"])
    R_world_pelvis, origin = pelvis_frame(*(pelvis[:, i] for i in range(4)))
    _timed(lambda: fit_centre_two_segments(pelvis[:200], thigh[:200]))  # warm-up
    jf_times, peer_times = [], []
    for _ in range(3):
        jf, dt_j = _timed(lambda: fit_centre_two_segments(pelvis, thigh))
        peer, dt_p = _timed(lambda: _peer(pelvis, thigh, "ball"))
        jf_times.append(dt_j)
        peer_times.append(dt_p)
    c_jf = np.nanmean(to_frame(jf.centre_world, R_world_pelvis, origin), axis=0)
    peer_world = np.einsum("nij,j->ni", peer.poses_parent.R_world_local, peer.point_parent)
    c_peer = np.nanmean(
        to_frame(peer_world + peer.poses_parent.d_world_local, R_world_pelvis, origin), axis=0
    )

    def box_distance(c: FloatArray) -> float:
        below = np.maximum(HIP_BOX[:, 0] - c, 0.0)
        above = np.maximum(c - HIP_BOX[:, 1], 0.0)
        return float(np.linalg.norm(below + above))

    t_j, t_p = float(np.median(jf_times)), float(np.median(peer_times))
    rows = [
        [
            "hip",
            "centre, pelvis frame (mm)",
            _xyz(c_jf),
            _xyz(c_peer),
            "box x -63..-57, y -98..-72, z -95..-76",
            "",
        ],
        [
            "hip",
            "distance outside the box (mm)",
            fmt(box_distance(c_jf)),
            fmt(box_distance(c_peer)),
            f"<= {HIP_MARGIN:g} passes",
            _both_pass(box_distance(c_jf) <= HIP_MARGIN, box_distance(c_peer) <= HIP_MARGIN),
        ],
        [
            "hip",
            "jointfit - SCoRE (mm)",
            fmt(float(np.linalg.norm(c_jf - c_peer))),
            "",
            "published methods: 15-25 mm",
            "",
        ],
        [
            "hip",
            "reported uncertainty",
            f"sd √tr cov {fmt(float(np.sqrt(np.trace(jf.cov_parent))))} mm; identifiable={jf.identifiable}",
            "none",
            "",
            "jointfit reports one; SCoRE does not",
        ],
        ["hip", "joint residual rms (mm)", fmt(jf.rms), fmt(peer.residual_rms), "", ""],
        ["hip", "frames used", str(jf.n_frames), f"{peer.frames_kept} of {pelvis.shape[0]}", "", ""],
        _time_row("hip", t_j, t_p),
    ]
    behind = []
    if box_distance(c_jf) > box_distance(c_peer) + 1.0:
        behind.append(
            f"real hip: jointfit's centre is {fmt(box_distance(c_jf))} mm outside the published box, SCoRE's "
            f"{fmt(box_distance(c_peer))} mm"
        )
    if t_j > t_p:
        behind.append(f"real hip: jointfit is slower ({fmt(1e3 * t_j)} ms against {fmt(1e3 * t_p)} ms)")
    return rows, behind


def real_knee() -> tuple[list[list[str]], list[str]]:
    data = read_c3d(DATA / "right_knee.c3d")
    thigh = data.select(["RTHI1", "RTHI2", "RTHI3"])
    shank = data.select(["RLEG1", "RLEG2", "RLEG3"])
    epi = data.select(["RLFE", "RMFE"])
    line = epi[:, 1] - epi[:, 0]
    line /= np.linalg.norm(line, axis=1, keepdims=True)
    mid = epi.mean(axis=1)
    _timed(lambda: fit_axis_two_segments(thigh[:200], shank[:200]))  # warm-up
    jf_times, peer_times = [], []
    for _ in range(3):
        jf, dt_j = _timed(lambda: fit_axis_two_segments(thigh, shank))
        peer, dt_p = _timed(lambda: _peer(thigh, shank, "hinge"))
        jf_times.append(dt_j)
        peer_times.append(dt_p)

    def checks(direction_world: FloatArray, point_world: FloatArray) -> tuple[float, float]:
        cos = np.abs(np.einsum("ni,ni->n", direction_world, line))
        ang = float(np.nanmean(np.degrees(np.arccos(np.clip(cos, 0.0, 1.0)))))
        off = mid - point_world
        off = off - np.einsum("ni,ni->n", off, direction_world)[:, None] * direction_world
        return ang, float(np.nanmean(np.linalg.norm(off, axis=1)))

    ang_j, dist_j = checks(jf.direction_world, jf.point_world)
    pp = peer.poses_parent
    assert peer.direction_parent is not None
    n_w = np.einsum("nij,j->ni", pp.R_world_local, peer.direction_parent)
    p_w = np.einsum("nij,j->ni", pp.R_world_local, peer.point_parent) + pp.d_world_local
    ang_p, dist_p = checks(n_w, p_w)
    between = angle_deg(jf.direction_parent, peer.direction_parent)
    sd_dir = float(np.degrees(np.sqrt(max(np.linalg.eigvalsh(jf.cov_direction_parent)[-1], 0.0))))
    sd_pt = float(np.sqrt(np.trace(jf.cov_point_parent)))
    t_j, t_p = float(np.median(jf_times)), float(np.median(peer_times))
    rows = [
        [
            "knee",
            "angle to epicondyle line (deg)",
            fmt(ang_j),
            fmt(ang_p),
            f"< {KNEE_MAX_DEG:g}",
            _both_pass(ang_j < KNEE_MAX_DEG, ang_p < KNEE_MAX_DEG),
        ],
        [
            "knee",
            "epicondyle midpoint to axis (mm)",
            fmt(dist_j),
            fmt(dist_p),
            f"< {KNEE_MAX_MM:g}",
            _both_pass(dist_j < KNEE_MAX_MM, dist_p < KNEE_MAX_MM),
        ],
        ["knee", "angle jointfit - SARA (deg)", fmt(between), "", "", ""],
        [
            "knee",
            "reported uncertainty",
            f"direction sd {fmt(sd_dir)} deg, point sd {fmt(sd_pt)} mm; identifiable={jf.identifiable}",
            "none",
            "",
            "jointfit reports one; SARA does not",
        ],
        [
            "knee",
            "residual rms (mm)",
            fmt(jf.rms),
            fmt(peer.residual_rms),
            "off-axis distance of the two carried points",
            "",
        ],
        ["knee", "frames used", str(jf.n_frames), f"{peer.frames_kept} of {thigh.shape[0]}", "", ""],
        _time_row("knee", t_j, t_p),
    ]
    behind = []
    if ang_j > ang_p + 1.0 or dist_j > dist_p + 1.0:
        behind.append(
            f"real knee: jointfit's axis is further from the epicondyle line than SARA's "
            f"({fmt(ang_j)} deg / {fmt(dist_j)} mm against {fmt(ang_p)} deg / {fmt(dist_p)} mm; the epicondyle "
            "line is only a plausibility reference, not the truth)"
        )
    if t_j > t_p:
        behind.append(f"real knee: jointfit is slower ({fmt(1e3 * t_j)} ms against {fmt(1e3 * t_p)} ms)")
    return rows, behind


def _xyz(c: FloatArray) -> str:
    return "(" + ", ".join(f"{v:.1f}" for v in c) + ")"


def _both_pass(ours: bool, theirs: bool) -> str:
    if ours and theirs:
        return "both pass"
    if ours:
        return "**jointfit passes, peer fails**"
    if theirs:
        return "**jointfit FAILS, peer passes**"
    return "both fail"


def _time_row(joint: str, t_j: float, t_p: float) -> list[str]:
    """The table row of the time per fit, jointfit's ``t_j`` against the peer's ``t_p`` (seconds)."""
    return [joint, "time per fit (ms)", fmt(1e3 * t_j), fmt(1e3 * t_p), f"ratio {t_j / t_p:.2f}", _speed_verdict(t_j, t_p)]


def _speed_verdict(ours: float, theirs: float) -> str:
    return (
        f"jointfit {theirs / ours:.1f}x faster"
        if ours < theirs
        else f"**jointfit {ours / theirs:.1f}x SLOWER**"
    )


# ----------------------------------------------------------------------------- synthetic rigs


@dataclass
class CaseStats:
    values: dict[str, list[float]] = field(default_factory=dict)
    refused: int = 0

    def add(self, key: str, value: float) -> None:
        self.values.setdefault(key, []).append(value)

    def get(self, key: str) -> list[float]:
        return self.values.get(key, [])

    def mean(self, key: str) -> float:
        arr = np.asarray(self.get(key), dtype=np.float64)
        arr = arr[np.isfinite(arr)]
        return float(np.mean(arr)) if arr.size else float("nan")

    def median(self, key: str) -> float:
        arr = np.asarray(self.get(key), dtype=np.float64)
        arr = arr[np.isfinite(arr)]
        return float(np.median(arr)) if arr.size else float("nan")


def _artefact(rng: np.random.Generator, t: FloatArray, n_markers: int) -> FloatArray:
    """(N, P, 3) smooth per-marker displacement: two sinusoids of 0.1-0.5 Hz per coordinate, 3 mm each."""
    freq = rng.uniform(0.1, 0.5, (2, n_markers, 3))
    phase = rng.uniform(0.0, 2.0 * np.pi, (2, n_markers, 3))
    waves = np.sin(2.0 * np.pi * freq[:, None] * t[None, :, None, None] + phase[:, None])
    out: FloatArray = ARTEFACT_MM * waves.sum(axis=0)
    return out


def _rig(
    rng: np.random.Generator, kind: str, seconds: float, artefact: bool
) -> tuple[Any, FloatArray, FloatArray]:
    motion = two_segment_motion(rng, kind=kind, n_markers=(3, 3), cycle_s=20.0)
    t = np.arange(round(seconds * RATE_HZ)) / RATE_HZ
    parent, child = motion.markers_at(t)
    parent = parent + rng.normal(0.0, NOISE_MM, parent.shape)
    child = child + rng.normal(0.0, NOISE_MM, child.shape)
    if artefact:
        parent = parent + _artefact(rng, t, parent.shape[1])
        child = child + _artefact(rng, t, child.shape[1])
    return motion, parent, child


def synthetic(kind: str, trials: int, seq: np.random.SeedSequence) -> dict[str, CaseStats]:
    out: dict[str, CaseStats] = {}
    for (label, seconds, artefact), case_seq in zip(CASES, seq.spawn(len(CASES)), strict=True):
        st = out.setdefault(label, CaseStats())
        for trial_seq in case_seq.spawn(trials):
            rng = np.random.default_rng(trial_seq)
            motion, parent, child = _rig(rng, kind, seconds, artefact)
            st.add("N", float(parent.shape[0]))
            try:
                if kind == "ball":
                    jf, dt_j = _timed(lambda p=parent, c=child: fit_centre_two_segments(p, c))
                else:
                    jf, dt_j = _timed(lambda p=parent, c=child: fit_axis_two_segments(p, c))
                peer, dt_p = _timed(lambda p=parent, c=child: _quiet(lambda: _peer(p, c, kind)))
            except (ValueError, np.linalg.LinAlgError):
                st.refused += 1
                continue
            st.add("jf ms", 1e3 * dt_j)
            st.add("peer ms", 1e3 * dt_p)
            st.add("jf flagged", float(not jf.identifiable))
            if kind == "ball":
                c_true_j = to_estimated_frame(
                    motion.template_parent, jf.template_parent, motion.centre_parent
                )
                c_true_p = to_estimated_frame(
                    motion.template_parent, peer.template_parent, motion.centre_parent
                )
                delta = jf.centre_parent - c_true_j
                st.add("jf err", float(np.linalg.norm(delta)))
                st.add("peer err", float(np.linalg.norm(peer.point_parent - c_true_p)))
                st.add("jf sd", float(np.sqrt(np.trace(jf.cov_parent))))
                st.add("jf e", mahalanobis(delta, jf.cov_parent) / 3.0)
            else:
                assert peer.direction_parent is not None
                for who, tpl, n_est, p_est in (
                    ("jf", jf.template_parent, jf.direction_parent, jf.point_parent),
                    ("peer", peer.template_parent, peer.direction_parent, peer.point_parent),
                ):
                    n_true = rotation_to_estimated_frame(motion.template_parent, tpl) @ motion.axis
                    p_true = to_estimated_frame(motion.template_parent, tpl, motion.centre_parent)
                    st.add(f"{who} err", angle_deg(n_est, n_true))
                    # the true centre's distance from the estimated axis line: gauge-free (the distance
                    # of the estimated point from the true axis depends on where along its axis the
                    # point lies, SARA's anywhere: the lines are skew)
                    st.add(f"{who} point", distance_to_line(p_true, p_est, n_est))
                    if who == "jf":
                        signed = n_true if float(n_true @ n_est) >= 0.0 else -n_true
                        st.add("jf e", mahalanobis_rank(n_est - signed, jf.cov_direction_parent, 2) / 2.0)
                        st.add("jf sd", float(np.degrees(np.sqrt(np.trace(jf.cov_direction_parent)))))
    return out


def synthetic_table(kind: str, stats: dict[str, CaseStats], trials: int) -> tuple[str, list[str]]:
    rows: list[list[str]] = []
    behind: list[str] = []
    peer_name = "SCoRE" if kind == "ball" else "SARA"
    unit = "mm" if kind == "ball" else "deg"
    for label, _, _ in CASES:
        st = stats[label]
        v_err = paired_verdict(st.get("jf err"), st.get("peer err"))
        t_j, t_p = st.median("jf ms"), st.median("peer ms")
        row = [label, str(int(st.mean("N"))), fmt(st.mean("jf err")), fmt(st.mean("peer err")), v_err]
        if kind == "hinge":
            v_pt = paired_verdict(st.get("jf point"), st.get("peer point"))
            row += [fmt(st.mean("jf point")), fmt(st.mean("peer point")), v_pt]
            if "BEHIND" in v_pt:
                behind.append(
                    f"synthetic hinge, {label}: axis point {fmt(st.mean('jf point'))} mm against "
                    f"SARA {fmt(st.mean('peer point'))} mm"
                )
            elif "no clear" in v_pt:
                behind.append(
                    f"synthetic hinge, {label}: no clear difference in axis point error from SARA "
                    f"({fmt(st.mean('jf point'))} against {fmt(st.mean('peer point'))} mm)"
                )
        row += [
            fmt(st.mean("jf sd")),
            fmt(st.mean("jf e")),
            fmt(st.mean("jf flagged")),
            "none",
            fmt(t_j),
            fmt(t_p),
            f"{t_j / t_p:.2f}",
            str(st.refused),
        ]
        rows.append(row)
        if "BEHIND" in v_err:
            behind.append(
                f"synthetic {kind}, {label}: error {fmt(st.mean('jf err'))} {unit} against {peer_name} "
                f"{fmt(st.mean('peer err'))} {unit}"
            )
        elif "no clear" in v_err:
            behind.append(
                f"synthetic {kind}, {label}: no clear difference in error from {peer_name} "
                f"({fmt(st.mean('jf err'))} against {fmt(st.mean('peer err'))} {unit})"
            )
        if t_j > t_p:
            behind.append(f"synthetic {kind}, {label}: jointfit slower ({fmt(t_j)} ms against {fmt(t_p)} ms)")
        e_k = st.mean("jf e")
        if e_k > 1.5 or e_k < 0.67:
            what = "over-confident" if e_k > 1 else "under-confident"
            behind.append(
                f"synthetic {kind}, {label}: jointfit's covariance is {what} (mean e/{3 if kind == 'ball' else 2} "
                f"= {fmt(e_k)}); the peer reports no uncertainty at all, so this is a weak spot of jointfit, "
                "not a loss to the peer"
            )
    if kind == "ball":
        header = ["case", "N", "jointfit err (mm)", "SCoRE err (mm)", "error verdict"]
        unc = ["jointfit √tr cov (mm)", "jointfit e/3", "jointfit flagged", "SCoRE uncertainty"]
    else:
        header = [
            "case",
            "N",
            "jointfit angle err (deg)",
            "SARA angle err (deg)",
            "angle verdict",
            "jointfit point err (mm)",
            "SARA point err (mm)",
            "point verdict",
        ]
        unc = ["jointfit direction √tr cov (deg)", "jointfit dir e/2", "jointfit flagged", "SARA uncertainty"]
    header = [*header, *unc, "jointfit ms", f"{peer_name} ms", "time ratio", "refused"]
    return markdown_table(header, rows, align="l" + "r" * (len(header) - 1)), behind


# ----------------------------------------------------------------------------- biobuddy's own pose step


def _slsqp_poses(thigh: FloatArray, tpl: FloatArray, start: Poses) -> tuple[FloatArray, FloatArray, float]:
    """biobuddy's per-frame SLSQP poses of ``thigh`` (metres) against ``tpl``, started at ``start``'s frame 0."""
    markers = np.ones((4, 3, thigh.shape[0]))
    markers[:3] = np.transpose(thigh, (2, 1, 0))
    static = np.ones((4, 3))
    static[:3] = tpl.T
    rt0 = np.eye(4)
    rt0[:3, :3] = start.R_world_local[0]
    rt0[:3, 3] = start.d_world_local[0]
    init = RotoTransMatrixTimeSeries.from_rt_matrix(rt0[:, :, None])
    task = Score.__new__(Score)  # only the pose method is used; it needs no trial or model
    names = ["RTHI1", "RTHI2", "RTHI3"]
    out, dt = _timed(lambda: _quiet(lambda: task.scipy_optimal_rt(markers, static, init, names)))
    R = np.stack([out[i].rotation_matrix.rotation_matrix for i in range(len(out))])
    d = np.stack([np.asarray(out[i].translation, dtype=np.float64)[:3] for i in range(len(out))])
    return R, d, dt / thigh.shape[0]


def slsqp_aside() -> str:
    """biobuddy's own per-frame SLSQP pose step on 60 frames of the hip trial's thigh cluster (metres)."""
    n = 60
    try:
        data = read_c3d(DATA / "right_hip.c3d")
        full = data.select(["RTHI1", "RTHI2", "RTHI3"]) / 1000.0  # biobuddy's thresholds are in metres
        thigh = full[:n]
        results = []
        for label, tpl in (
            ("a template fitted to these frames", template_from_markers(thigh)),
            ("a template fitted to the whole trial", template_from_markers(full)),
        ):
            lsq = poses_from_markers(thigh, tpl)
            R, d, per_frame = _slsqp_poses(thigh, tpl, lsq)
            results.append((label, tpl, lsq, R, d, per_frame))
    except Exception as exc:  # a private method of the peer: report, never crash
        return f"Not measured: biobuddy's pose step could not be called ({type(exc).__name__}: {exc})."

    def rms(tpl: FloatArray, Rs: FloatArray, ds: FloatArray) -> float:
        pred = np.einsum("nij,pj->npi", Rs, tpl) + ds[:, None]
        return 1e3 * float(np.sqrt(np.mean(np.sum((pred - thigh) ** 2, axis=2))))

    pieces = []
    for label, tpl, lsq, R, d, per_frame in results:
        ang = np.degrees(Rotation.from_matrix(np.einsum("nji,njk->nik", R, lsq.R_world_local)).magnitude())
        pieces.append(
            f"with {label}: {1e3 * per_frame:.2f} ms per frame, rotations {np.median(ang):.1f} deg (median) and "
            f"{ang.max():.1f} deg (max) from the least-squares pose, marker rms {rms(tpl, R, d):.2f} mm against "
            f"{rms(tpl, lsq.R_world_local, lsq.d_world_local):.2f} mm"
        )
    return (
        "biobuddy's own pose step (`scipy_optimal_rt`, SLSQP per frame on the 16 entries of the 4x4 matrix with "
        f"orthonormality constraints, each frame started from the previous one), on the first {n} frames of the "
        "hip trial's thigh cluster in metres, started from the exact pose of frame 0: "
        + "; ".join(pieces)
        + ". When the template fits well the cost per frame is ~1e-6 m^2, the size of SLSQP's default "
        "tolerance, and the poses lag the motion. The comparisons above give the peer the least-squares "
        "poses instead, i.e. its best case."
    )


def footprint() -> str:
    parts = []
    total = 0.0
    for name in PEER_DISTS:
        try:
            dist = importlib.metadata.distribution(name)
        except importlib.metadata.PackageNotFoundError:
            continue
        size = sum((f.size or 0) for f in (dist.files or [])) / 1e6
        total += size
        parts.append(f"{name} {dist.version} ({size:.1f} MB)")
    return ", ".join(parts) + f"; {total:.0f} MB installed"


# ----------------------------------------------------------------------------- main


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="8 trials per synthetic case instead of 30")
    parser.add_argument(
        "--trials", type=int, default=None, help="trials per synthetic case (overrides --quick)"
    )
    args_list = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(args_list)
    if biobuddy is None:
        print(
            f"SKIP bench/peers.py: biobuddy is not importable ({_IMPORT_ERROR}); install the bench extras with "
            "`pip install -r requirements-bench.txt`. bench/results/peers.md left unchanged."
        )
        return 0
    logging.getLogger("biobuddy").setLevel(logging.WARNING)
    trials = args.trials or (8 if args.quick else 30)
    t_start = time.perf_counter()
    hip_rows, hip_behind = real_hip()
    knee_rows, knee_behind = real_knee()
    seq_ball, seq_hinge = np.random.SeedSequence(SEED).spawn(2)
    ball_md, ball_behind = synthetic_table("ball", synthetic("ball", trials, seq_ball), trials)
    hinge_md, hinge_behind = synthetic_table("hinge", synthetic("hinge", trials, seq_hinge), trials)
    aside = slsqp_aside()
    version = importlib.metadata.version("biobuddy")
    parts = run_header(
        f"Peer comparison: jointfit against biobuddy {version} (SCoRE, SARA)",
        SCRIPT,
        args_list,
        SEED,
        f"Peer: biobuddy {version} (MIT, PyPI), `Score.perform_algorithm` (SCoRE, Ehrig et al. 2006) and "
        f"`Sara.perform_algorithm` (SARA, Ehrig et al. 2007) with their defaults (one pass of outlier "
        f"removal). Bench extras installed: {footprint()}. What is compared and how: see the script's "
        f"docstring. {trials} trials per synthetic case.",
    )
    parts += [
        "## 1. Real recordings (no ground truth)",
        "",
        "Right hip: jointfit `fit_centre_two_segments` against SCoRE; right knee: `fit_axis_two_segments` "
        "against SARA. Centres and axes are averaged over the frames in the pelvis frame (hip) or checked "
        "per frame against the epicondyles (knee). Times: median of 3 runs.",
        "",
        markdown_table(
            ["joint", "quantity", "jointfit", "biobuddy", "check", "verdict"],
            hip_rows + knee_rows,
            align="llllll",
        ),
        "",
        "## 2. Synthetic rigs with known truth",
        "",
        f"Means over {trials} trials; verdict = paired difference of the per-trial errors beyond 2 standard "
        'errors ("no clear difference" otherwise). e/3, e/2: mean validation index squared of jointfit\'s '
        "covariance (1 when calibrated). flagged = fraction jointfit reports not identifiable. Times: medians.",
        "",
        "### Ball joint: jointfit against SCoRE",
        "",
        ball_md,
        "",
        "### Hinge: jointfit against SARA",
        "",
        "Angle error of the direction, and distance of the true joint centre from the estimated axis line (the same "
        "gauge-free measure for both; until 2026-12-02 the distance of each reported point from the true axis, "
        "which depends on where along its own axis each method puts its point), parent frame.",
        "",
        hinge_md,
        "",
        "## 3. What each reports, and notes on the peer",
        "",
        "- **jointfit**: the estimate in both local frames, its covariance (propagated marker noise, inflated "
        "by the residuals' excess over it by default), an `identifiable` verdict with a reason, the joint "
        "residual per frame and its rms, and the marker noise per segment.",
        "- **SCoRE / SARA (biobuddy)**: the estimate in both local frames and the mean world position (SARA: "
        "the mean axis); no covariance and no identifiability check. The residual's mean and sd go to the "
        "log at INFO level. Frames with a residual above mean + 1 sd are dropped once.",
        "- As read in biobuddy's source (this version): SARA computes its residual from the axis direction "
        "transformed as a *point* (with the segment translation), so its outlier removal is driven by the "
        "segments' positions rather than by the axis misfit; its axis point uses all singular values "
        "(including the near-zero one of a hinge), so the point lies anywhere along the axis (the tables use "
        "the true centre's distance from each estimated axis line, which does not depend on that).",
        f"- {aside}",
        "",
        "## Where jointfit is not ahead",
        "",
    ]
    behind = hip_behind + knee_behind + ball_behind + hinge_behind
    parts += [f"- {line}" for line in behind] if behind else ["- Nowhere in these cases."]
    parts += ["", elapsed_line(t_start)]
    print_and_write("peers.md", parts)
    return 0


if __name__ == "__main__":
    sys.exit(main())
