"""Skin artefact on every segment of a skeleton: the generator's properties, and the node's covariances on it.

The generator (:mod:`jointfit_core.skeleton_sta`): amplitudes as asked, linear plus quadratic in
the adjacent joints' angles only (so zero in the neutral posture), deterministic by seed, bone
truth untouched. The node (issues 16 + 17): the lower body through its per-message path
(``config/lower_body.yaml``, ``skeleton_runs.run_stream``) on 15 s of skin markers (thigh 10 mm,
shank 5 mm, pelvis and foot 3 mm rms, 0.5 mm noise, 2 % occluded), over three skeleton seeds.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest
from skeleton_runs import JointScore, run_stream, score

from jointfit_core.skeleton_sta import (
    adjacent_joints,
    joint_rotvecs,
    skeleton_artefact,
    skeleton_skin_frames,
    sta_amplitudes,
)
from jointfit_core.skeleton_truth import make_skeleton, skeleton_frames
from jointfit_core.soft_tissue import STA_MODES, _features
from jointfit_ros.params import node_config, params_from_file

LOWER = Path(__file__).resolve().parents[1] / "config" / "lower_body.yaml"


@pytest.mark.parametrize("mode", STA_MODES)
def test_every_segment_moves_by_its_amplitude(mode: str) -> None:
    sk = make_skeleton("full", seed=2)
    t = np.arange(600) / 50.0
    amp = sta_amplitudes(sk, scale=2.0, r_thigh=0.02, shank=0.0)
    assert amp["r_thigh"] == pytest.approx(0.04) and amp["l_thigh"] == pytest.approx(0.02)
    assert amp["r_shank"] == amp["l_shank"] == 0.0 and amp["pelvis"] == pytest.approx(0.006)
    delta = skeleton_artefact(sk, t, np.random.default_rng(3), amp, mode=mode)
    assert delta.shape == (t.size, len(sk.marker_names()), 3)
    start = 0
    for s in sk.segments:
        d = delta[:, start : start + len(s.markers)]
        start += len(s.markers)
        rms = float(np.sqrt((d**2).sum(axis=2).mean()))
        assert rms == pytest.approx(amp[s.name], rel=1e-9, abs=1e-15), s.name


def test_the_artefact_follows_the_adjacent_joints_only_and_is_zero_in_the_neutral_posture() -> None:
    sk = make_skeleton("lower", seed=4)
    t = np.arange(800) / 40.0
    delta = skeleton_artefact(sk, t, np.random.default_rng(5), sta_amplitudes(sk))
    q = joint_rotvecs(sk, t)
    names = [s.name for s in sk.segments]
    assert adjacent_joints(sk)["r_thigh"] == ("r_hip", "r_knee")
    assert adjacent_joints(sk)["pelvis"] == ("r_hip", "l_hip") and adjacent_joints(sk)["r_foot"] == ("r_ankle",)

    def misfit(segment: str, joints: tuple[str, ...]) -> float:
        """Relative residual of the least-squares fit of the segment's displacements on f(q), no intercept."""
        k = names.index(segment)
        d = delta[:, 4 * k : 4 * k + 4].reshape(t.size, -1)
        f = _features(np.concatenate([q[j] for j in joints], axis=1))
        coef = np.linalg.lstsq(f, d, rcond=None)[0]
        return float(np.linalg.norm(f @ coef - d) / np.linalg.norm(d))

    # exactly A f(q) of the adjacent joints' angles: no constant, so zero when every angle is zero
    for s in sk.segments:
        assert misfit(s.name, adjacent_joints(sk)[s.name]) < 1e-9, s.name
    # and it needs both: the thigh's skin follows the knee too, the pelvis's both hips
    assert misfit("r_thigh", ("r_hip",)) > 0.05 and misfit("r_thigh", ("r_knee",)) > 0.05
    assert misfit("pelvis", ("r_hip",)) > 0.05
    # drivers restrict it: the thigh then follows its hip alone
    only_hip = skeleton_artefact(sk, t, np.random.default_rng(5), sta_amplitudes(sk), drivers={"r_thigh": ("r_hip",)})
    k = names.index("r_thigh")
    d = only_hip[:, 4 * k : 4 * k + 4].reshape(t.size, -1)
    f = _features(q["r_hip"])
    assert np.linalg.norm(f @ np.linalg.lstsq(f, d, rcond=None)[0] - d) < 1e-9 * np.linalg.norm(d)


def test_frames_are_deterministic_by_seed_and_leave_the_bones_alone() -> None:
    sk = make_skeleton("lower", seed=1)
    t = np.arange(500) / 100.0
    amp = sta_amplitudes(sk)
    a = skeleton_skin_frames(sk, t, np.random.default_rng(7), amp, noise=0.0005, occlusion=0.05)
    b = skeleton_skin_frames(sk, t, np.random.default_rng(7), amp, noise=0.0005, occlusion=0.05)
    c = skeleton_skin_frames(sk, t, np.random.default_rng(8), amp, noise=0.0005, occlusion=0.05)
    assert np.array_equal(a, b, equal_nan=True) and not np.allclose(a, c, equal_nan=True)
    assert a.shape == (t.size, len(sk.marker_names()), 3)
    missing = np.isnan(a).any(axis=2)
    assert np.array_equal(missing, np.isnan(a).all(axis=2)) and 0.03 < missing.mean() < 0.07
    # no artefact: the rigid skeleton's frames exactly; artefact without noise: the bone motion plus delta
    rigid = skeleton_skin_frames(sk, t, np.random.default_rng(7), {})
    assert np.allclose(rigid, skeleton_frames(sk, t, np.random.default_rng(7), 0.0), rtol=0.0, atol=1e-12)
    clean = skeleton_skin_frames(sk, t, np.random.default_rng(7), amp)
    delta = skeleton_artefact(sk, t, np.random.default_rng(7), amp)
    R, _ = sk.poses_at(t)
    seg = np.repeat(np.arange(len(sk.segments)), 4)
    world_delta = np.einsum("npij,npj->npi", R[:, seg], delta)
    assert np.allclose(clean - world_delta, sk.markers_at(t), atol=1e-12)
    noisy = skeleton_skin_frames(sk, t, np.random.default_rng(7), amp, noise=0.0005)
    assert np.std(noisy - clean) == pytest.approx(0.0005, rel=0.05)


def test_bad_arguments_are_refused() -> None:
    sk = make_skeleton("lower")
    t = np.arange(10) / 100.0
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="not segments"):
        skeleton_artefact(sk, t, rng, {"r_upper_arm": 0.01})
    with pytest.raises(ValueError, match=">= 0 m"):
        skeleton_artefact(sk, t, rng, {"r_thigh": -0.01})
    with pytest.raises(ValueError, match="drivers of r_thigh"):
        skeleton_artefact(sk, t, rng, {"r_thigh": 0.01}, drivers={"r_thigh": ("r_elbow",)})
    with pytest.raises(ValueError, match="mode"):
        skeleton_artefact(sk, t, rng, {"r_thigh": 0.01}, mode="slide")
    with pytest.raises(ValueError, match="occlusion"):
        skeleton_skin_frames(sk, t, rng, {}, occlusion=1.5)


SEEDS = (1, 2, 3)
SECONDS, RATE = 20.0, 100.0


@functools.cache
def _lower_body_scores(seed: int) -> dict[str, list[JointScore]]:
    """One skin-marker stream of the lower body through the node's path, with each attachment."""
    sk = make_skeleton("lower", seed=seed)
    t = np.arange(round(SECONDS * RATE)) / RATE
    # 2 % of the markers occluded; solved every 0.1 s of the stream as the node does (its estimate_period):
    frames = skeleton_skin_frames(sk, t, np.random.default_rng(seed), sta_amplitudes(sk), noise=0.0005, occlusion=0.02)
    out = {}
    for attachment in ("skin", "rigid"):
        values = params_from_file(LOWER)
        if attachment == "rigid":
            values.update({f"{j}.attachment": "rigid" for j in sk.joints})
        out[attachment] = [score(sk, r) for r in run_stream(node_config(values), t, frames, estimate_period=0.1)]
    return out


def _indices(scores: list[JointScore]) -> list[float]:
    """Every e/k: ball centres (k = 3), hinge directions and points (off-axis, k = 2)."""
    return [s.e for s in scores] + [s.point_e for s in scores if s.kind == "hinge"]


def test_lower_body_skin_covariances_are_honest_and_rigid_ones_are_not() -> None:
    runs = [_lower_body_scores(seed) for seed in SEEDS]
    skin = [s for run in runs for s in run["skin"]]
    rigid = [s for run in runs for s in run["rigid"]]
    for s, r in zip(skin, rigid, strict=True):
        print(f"{s.name}: error {s.error:.1f} sd {s.sd:.1f} e/k {s.e:.2f} (rigid sd {r.sd:.1f} e/k {r.e:.2f})"
              + (f"; point {s.point_error:.1f} mm sd {s.point_sd:.1f} e/2 {s.point_e:.2f} (rigid {r.point_e:.2f})"
                 if s.kind == "hinge" else ""))

    def confidently_wrong(scores: list[JointScore]) -> bool:
        # One e/k of an honest covariance exceeds 8 with probability 3e-4 (k = 2 or 3, Gaussian): over
        # these 30 indices a false alarm is ~1 %. Their mean is 1 when honest (sd ~0.25 over 30); the skin
        # prior is conservative by design (bench/sta.py: hip 0.54-0.72, knee 0.77-1.04), hence down to 0.2.
        e = _indices(scores)
        return max(e) >= 8.0 or not 0.2 < float(np.mean(e)) < 2.0

    # (a) skin (the default): no joint confidently wrong
    assert not confidently_wrong(skin), [(s.name, round(s.e, 2), round(s.point_e, 2)) for s in skin]
    # (b) the same data with attachment: rigid fails that test (the check can fail). Its hinge points are
    # over-confident (bench/results/skeleton_sta.md: mean e/2 5.6-11); its hips less so since the serial factor
    # is integrated over seconds (mean e/3 1.5-2.4 there, 1.4 on these 6), so no hip-only clause.
    assert confidently_wrong(rigid), [(s.name, round(s.e, 2), round(s.point_e, 2)) for s in rigid]
    rigid_points = [s.point_e for s in rigid if s.kind == "hinge"]
    assert float(np.mean(rigid_points)) > 2.0, rigid_points  # P < 1e-4 for 12 honest e/2 (chi2, 24 dof > 48)
    # (c) a sane physical error and a useful sd: hips within 4x the thigh's 10 mm of artefact
    # (bench/sta.py: ~2x on average); knee and ankle axes within 15 deg, their points within 40 mm.
    for s in skin:
        if s.kind == "ball":
            assert s.error < 40.0 and s.sd < 60.0, s
        else:
            assert s.error < 15.0 and s.point_error < 40.0, s


@pytest.mark.xfail(strict=True, reason="known defect: online skin hinges on a skeleton are far too cautious")
def test_lower_body_hinge_sds_say_something() -> None:
    """The knees' and ankles' direction sd below 25 deg (their errors are 0.4-10 deg here).

    Today the ankles' are 7-16 deg and the knees' 9-50 deg (10-40 deg for all four while the axis-alignment
    reading was an energy ratio). That reading (which removed the confidently wrong tail on
    two-segment knees, bench/sta_online.py) is now projected on the turns that follow the hinge angle,
    but on a skeleton the joints move together: part of the thigh cluster's motion with the hip follows
    the knee angle over the window, is read as the knee's artefact, and the prior adds the invisible
    part (an axis tilt) such motion would carry. ``bench/hinge_readings.py`` shows it on these streams:
    the alignment reading sets the scale of all four hinges above 25 deg (12-25 mm/rad, the point energy
    ratio 3-8), and with the thighs following their knee only those knees read 2.3-12.7. Reading the point
    residual projected on the prior's columns too (tried on branch ptproj, 2026-12-02) leaves these sds as
    they are and makes the knee points over-confident (largest e/2 5.1-12.4). Passing
    (strict xfail fails) means it was fixed: then drop the xfail.
    """
    skin = [s for seed in SEEDS for s in _lower_body_scores(seed)["skin"] if s.kind == "hinge"]
    assert all(s.sd < 25.0 for s in skin), [(s.name, round(s.sd, 1)) for s in skin]


def _occluded_stream(seed: int, estimate_period: float | None) -> dict[str, float]:
    """Share of frames gated per joint: 10 s of the lower body at 50 Hz, skin, 0.5 % of the markers occluded."""
    sk = make_skeleton("lower", seed=seed)
    t = np.arange(500) / 50.0
    frames = skeleton_skin_frames(sk, t, np.random.default_rng(seed), sta_amplitudes(sk), noise=0.0005, occlusion=0.005)
    assert np.isnan(frames).any()
    runners = run_stream(node_config(params_from_file(LOWER)), t, frames, estimate_period=estimate_period)
    return {r.cfg.name: round(score(sk, r).gated, 2) for r in runners}


def test_an_occlusion_does_not_lock_a_skin_marker_out_of_the_node() -> None:
    """Solved every 0.1 s as the node does, a marker missing now and then on a deforming skin cluster comes back.

    The gate's residual test then holds the larger of the window's pooled residual and the
    segment's recent fits' residual (deformation included in both)."""
    gated = _occluded_stream(2, 0.1)
    assert max(gated.values()) < 0.05, gated


def test_an_occlusion_does_not_lock_a_skin_marker_out() -> None:
    """A marker missing in one frame of a deforming skin cluster comes back, even when nothing is solved meanwhile.

    (``OnlineJoint.update_many`` over a whole recording, the node before its first estimate.) Until
    the gate's residual level was read from the segment's recent fits (``GATE_REFRESH_FRAMES``), it
    held the template frames' white noise until the first estimate, which a deforming cluster
    always exceeds: a marker held out once had no recent reference, and ``stale and residual_bad``
    then failed every frame with it (seed 2: 36-65 % of the frames gated, r_knee 6 -> 28 deg).
    """
    gated = _occluded_stream(2, None)
    assert max(gated.values()) < 0.05, gated
