"""The outlier gate on skin-marker clusters (issue 15, item 3): skin deformation passes, swaps, ghosts and jumps do not.

The failure this guards against: a real 12 Hz knee trial with 3-marker clusters and ~4 mm of
smooth skin deformation in flexion, where the white-noise gate dropped the flexed frames
(122 of 216 thigh frames), the templates waited for "consistent" frames, and ``jointfit fit``
said nothing. The data here are :func:`jointfit_core.soft_tissue.skin_markers_at` on a hinge
whose subject pauses at extension between flexions (as ``bench/skin_gate.py``); the pre-fix
gate dropped 22-57 % of such frames and built its templates after 66-108 frames.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

from jointfit_core.estimator import OnlineJoint
from jointfit_core.gate import GATE_WARN_SHARE
from jointfit_core.io import MarkerData, write_trc
from jointfit_core.soft_tissue import skin_markers_at
from jointfit_core.synthetic import TwoSegmentMotion, two_segment_motion
from jointfit_ros.cli import fit_main
from jointfit_ros.params import node_config, params_from_file
from jointfit_ros.runner import WARN, JointRunner

FloatArray = NDArray[np.float64]
RATE = 12.0
PAUSE_S = 2.0
NAMES = ["THI1", "THI2", "THI3", "SHK1", "SHK2", "SHK3"]


def _paused(motion: TwoSegmentMotion, t: FloatArray) -> FloatArray:
    """The motion's clock: it stops for PAUSE_S at every most extended posture of the hinge."""
    period = 1.0 / float(motion.freq[6])
    t0 = ((1.5 * np.pi - float(motion.phase[6])) / (2.0 * np.pi) % 1.0) * period
    k, u = np.divmod(t, period + PAUSE_S)
    out: FloatArray = t0 + k * period + np.clip(u - PAUSE_S, 0.0, period)
    return out


def _knee(seed: int, n: int, deformation_mm: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(stamps, thigh (N, 3, 3), shank): 3-marker clusters at 12 Hz, skin deformation ``deformation_mm`` rms, 0.2 mm noise."""
    rng = np.random.default_rng(seed)
    motion = two_segment_motion(rng, kind="hinge", n_markers=(3, 3))
    t = np.arange(n) / RATE
    amp = deformation_mm / np.sqrt(1.0 - 0.75**2)  # the deformation part of the artefact is deformation_mm
    thigh, shank = skin_markers_at(rng, motion, _paused(motion, t), parent_mm=amp, child_mm=amp, mode="angle", noise_std=0.2)
    return t, thigh, shank


def _corrupt(seed: int, thigh: FloatArray, shank: FloatArray, share: float, sides: tuple[int, ...] = (0, 1)) -> NDArray[np.bool_]:
    """Swaps, ghosts (20-80 mm) and jumps (two markers, N(0, 30 mm)) in ``share`` of the frames from 60 on; (N, 2) mask."""
    rng = np.random.default_rng([seed, 7])
    bad = np.zeros((thigh.shape[0], 2), dtype=bool)
    for k in 60 + np.flatnonzero(rng.random(thigh.shape[0] - 60) < share):
        side = sides[int(rng.integers(len(sides)))]
        seg = (thigh, shank)[side]
        a, b = rng.choice(3, 2, replace=False)
        kind = int(rng.integers(3))
        if kind == 0:
            seg[k, [a, b]] = seg[k, [b, a]]
        elif kind == 1:
            direction = rng.normal(size=3)
            seg[k, a] += rng.uniform(20.0, 80.0) * direction / np.linalg.norm(direction)
        else:
            seg[k, a] += rng.normal(0.0, 30.0, 3)
            seg[k, b] += rng.normal(0.0, 30.0, 3)
        bad[k, side] = True
    return bad


def _fit(thigh: FloatArray, shank: FloatArray, t: FloatArray, blocks: bool = True) -> OnlineJoint:
    """As jointfit fit: blocks of len/60 frames (or frame by frame), an estimate after each."""
    est = OnlineJoint("hinge", half_life=float("inf"))
    est.gate_log = []
    step = max(1, t.size // 60)
    for lo in range(0, t.size, step):
        if blocks:
            est.update_many(thigh[lo : lo + step], shank[lo : lo + step], t[lo : lo + step])
        else:
            for k in range(lo, min(lo + step, t.size)):
                est.update(thigh[k], shank[k], t[k])
        if est.templates_ready and est.n_window >= 3:
            est.estimate()
    return est


def _knee_50hz(seed: int, deformation_mm: float) -> tuple[TwoSegmentMotion, FloatArray, FloatArray, FloatArray]:
    """(motion, stamps, thigh (N, 4, 3), shank): 4-marker skin clusters at 50 Hz, 30 s from a 2 s still start, 0.2 mm noise."""
    rng = np.random.default_rng(seed)
    motion = two_segment_motion(rng, kind="hinge", n_markers=(4, 4))
    t = np.arange(1500) / 50.0
    amp = deformation_mm / np.sqrt(1.0 - 0.75**2)
    thigh, shank = skin_markers_at(rng, motion, _paused(motion, t), parent_mm=amp, child_mm=amp, mode="angle", noise_std=0.2)
    return motion, t, thigh, shank


def _frame_and_block(thigh: FloatArray, shank: FloatArray, t: FloatArray) -> tuple[OnlineJoint, OnlineJoint]:
    """The same stream frame by frame and in one block, nothing solved, gate logs kept."""
    one = OnlineJoint("hinge", half_life=float("inf"))
    many = OnlineJoint("hinge", half_life=float("inf"))
    one.gate_log, many.gate_log = [], []
    for k in range(t.size):
        one.update(thigh[k], shank[k], t[k])
    many.update_many(thigh, shank, t)
    return one, many


def _gated(est: OnlineJoint, n: int) -> NDArray[np.bool_]:
    out = np.zeros((n, 2), dtype=bool)
    assert est.gate_log is not None
    for number, side, _ in est.gate_log:
        out[number - 1, slice(None) if side == 2 else side] = True  # 2: the joint test, both segments lost
    return out


@pytest.mark.parametrize("deformation_mm", [2.0, 4.0, 6.0])
def test_skin_deformation_at_12_hz_is_not_gated(deformation_mm: float) -> None:
    """216 frames, as the real trial: no more than 2 % of either cluster's frames gated (the old gate: 22-57 %)."""
    for seed in range(3):
        t, thigh, shank = _knee(seed, 216, deformation_mm)
        est = _fit(thigh, shank, t)
        assert max(est.gated_frames) <= 0.02 * t.size, (seed, est.gated_frames, est.dropped)


def test_swaps_ghosts_and_jumps_among_skin_motion_are_gated() -> None:
    """5 % of the frames corrupted over 60 s at 12 Hz: at least 95 % of them caught, at most 2 % of the clean ones gated.

    (bench/skin_gate.py measures the rates over more trials and rates; the misses are
    corruptions that move a 3-marker cluster almost rigidly: distances change by a few mm.)
    """
    caught = bad_n = wrong = clean_n = 0
    for seed, deformation in enumerate((2.0, 4.0, 6.0)):
        t, thigh, shank = _knee(10 + seed, 720, deformation)
        bad = _corrupt(seed, thigh, shank, 0.05)
        g = _gated(_fit(thigh, shank, t), t.size)
        caught += int((g & bad).sum())
        bad_n += int(bad.sum())
        wrong += int((g & ~bad).sum())
        clean_n += int((~bad).sum())
    assert caught >= 0.95 * bad_n, (caught, bad_n)
    assert wrong <= 0.02 * clean_n, (wrong, clean_n)


def test_block_path_gates_skin_clusters_as_the_frame_path() -> None:
    t, thigh, shank = _knee(21, 720, 6.0)
    _corrupt(21, thigh, shank, 0.1)
    thigh[300:310, 1] = np.nan  # a marker occluded: too few markers, the segment is not posed
    one, many = _fit(thigh, shank, t, blocks=False), _fit(thigh, shank, t)
    assert one.dropped == many.dropped and one.gated_frames == many.gated_frames and sum(one.gated_frames) > 30
    assert one.gate_log == many.gate_log
    a, b = one.estimate(), many.estimate()
    np.testing.assert_allclose(b.direction_parent, a.direction_parent, rtol=0, atol=1e-9)  # type: ignore[union-attr]


@pytest.mark.parametrize("deformation_mm", [4.0, 6.0])
def test_templates_are_built_promptly_on_a_deforming_cluster(deformation_mm: float) -> None:
    """The templates take the first template_frames (50) fully visible frames: deformation is no inconsistency."""
    for seed in range(3):
        t, thigh, shank = _knee(seed, 120, deformation_mm)
        est = OnlineJoint("hinge", half_life=float("inf"))
        for k in range(t.size):
            est.update(thigh[k], shank[k], t[k])
            if est.templates_ready:
                break
        assert k + 1 == est.template_frames, (seed, k)


def _gated_recording(tmp_path: Path) -> tuple[Path, Path, FloatArray, FloatArray]:
    """A TRC of a 12 Hz knee whose thigh cluster has ghosts and jumps in ~25 % of its frames, and its config."""
    _, thigh, shank = _knee(5, 720, 4.0)
    _corrupt(5, thigh, shank, 0.25, sides=(0,))
    frames = np.concatenate([thigh, shank], axis=1)
    trc = tmp_path / "knee.trc"
    write_trc(trc, MarkerData(np.round(frames, 5), tuple(NAMES), RATE, "mm"))
    config = tmp_path / "knee.yaml"
    config.write_text(
        f"""jointfit:
  ros__parameters:
    joints: [knee]
    marker_names: [{", ".join(NAMES)}]
    knee:
      type: hinge
      parent_markers: [THI1, THI2, THI3]
      child_markers: [SHK1, SHK2, SHK3]
      window: 3000
"""
    )
    return trc, config, thigh, shank


def test_fit_exits_3_when_the_gate_rejects_over_10_percent(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("matplotlib")
    trc, config, _, _ = _gated_recording(tmp_path)
    code = fit_main([str(trc), "--config", str(config), "--out", str(tmp_path / "out")])  # the figure marks the frames
    out = capsys.readouterr().out
    assert code == 3
    assert (tmp_path / "out" / "knee.png").stat().st_size > 10_000
    assert "the outlier gate rejected" in out and "of the parent (THI1, THI2, THI3) frames" in out, out
    assert "not a hinge" not in out and "NOT identifiable" not in out
    joint = json.loads((tmp_path / "out" / "summary.json").read_text())["joints"][0]
    share = joint["gated"]
    assert share["parent"]["percent"] > 100 * GATE_WARN_SHARE and share["child"]["percent"] < 2.0, share
    assert joint["status"] == "outlier gate" and joint["gate_warning"].startswith("the outlier gate rejected")
    assert joint["identifiable"]


def test_fit_reports_the_gated_share_and_exits_0_on_clean_skin_data(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _, thigh, shank = _knee(6, 216, 4.0)
    trc = tmp_path / "clean.trc"
    write_trc(trc, MarkerData(np.round(np.concatenate([thigh, shank], axis=1), 5), tuple(NAMES), RATE, "mm"))
    _, config, _, _ = _gated_recording(tmp_path)
    code = fit_main([str(trc), "--config", str(config), "--out", str(tmp_path / "clean"), "--no-report"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "gated 0 % parent, 0 % child" in out, out
    joint = json.loads((tmp_path / "clean" / "summary.json").read_text())["joints"][0]
    none = {"frames": 0, "percent": 0.0}
    assert joint["gated"] == {"parent": none, "child": none, "joint": none}
    assert joint["status"] == "ok" and joint["gate_warning"] == ""


def test_runner_status_warns_when_the_gate_rejects_over_10_percent(tmp_path: Path) -> None:
    _, config, thigh, shank = _gated_recording(tmp_path)
    cfg = node_config(params_from_file(config))
    runner = JointRunner(cfg.joints[0], cfg)
    frames = np.concatenate([thigh, shank], axis=1)
    stamps = (np.arange(frames.shape[0]) / RATE * 1e9).astype(np.int64)
    for k in range(frames.shape[0]):
        runner.markers_frame(int(stamps[k]), frames[k])
        if k % 50 == 49:
            runner.estimate(force=True)
    runner.estimate(force=True)
    status = runner.status()
    assert status.level == WARN
    assert status.message.startswith("the outlier gate rejected") and "parent (THI1, THI2, THI3)" in status.message
    assert status.values["parent gated (%)"] > 100 * GATE_WARN_SHARE
    assert status.values["child gated (%)"] < 2.0


@pytest.mark.parametrize("seed", [5, 6, 7])
def test_a_marker_back_from_an_occlusion_passes_without_any_estimate(seed: int) -> None:
    """4-marker skin clusters at 50 Hz after a still start, a thigh marker occluded for 15 frames every 2 s, nothing solved.

    Since the residual test's level follows the segment's recent frames (GATE_RESIDUAL_RECENT) this
    holds from the first movement on; before, the first movement was left out of the check.

    The gate's residual level is the window's pooled residual, read every ``GATE_REFRESH_FRAMES``
    frames. Held at the still template frames' noise until a first estimate (whole-recording
    ``update_many``, the node's first seconds), a returning marker of a deforming cluster failed
    the residual test with no recent reference (older than 10 frames) and was left out for good:
    on these seeds 297-630 clean segment frames after the first movement were gated (now none).
    Swaps, ghosts and jumps are still caught; one block and frame by frame judge alike.
    """
    _, t, thigh, shank = _knee_50hz(seed, 6.0)
    for start in range(400, t.size, 100):
        thigh[start : start + 15, start // 100 % 4] = np.nan
    bad = _corrupt(seed, thigh, shank, 0.02)
    one, many = _frame_and_block(thigh, shank, t)
    assert one.solution is None and many.solution is None
    assert one.gate_log == many.gate_log and one.gated_frames == many.gated_frames
    g = _gated(one, t.size)  # from the first movement after the still start on (GATE_RESIDUAL_RECENT)
    caught, wrong = int((g & bad).sum()), int((g & ~bad).sum())
    assert caught >= 0.95 * bad.sum() and wrong <= 0.02 * (~bad).sum(), (caught, int(bad.sum()), wrong)


@pytest.mark.parametrize("deformation_mm", [6.0, 15.0])
@pytest.mark.parametrize("seed", [5, 6, 7])
def test_the_first_movement_after_a_still_stance_passes(seed: int, deformation_mm: float) -> None:
    """4-marker skin clusters at 50 Hz: 2 s still at extension, then flexions (with 2 s pauses); no corruption.

    During the stance the window's pooled residual and the gate's normal jump are the noise's
    (0.2 mm). When the knee starts to flex the clusters deform (a 6-15 mm artefact): the pose-fit
    residual grows ~1000 times within a second. Judged against the stance's pooled level, the
    first movement failed the residual test, one marker was left out, and with its reference
    gone stale it was kept out until the pooled level caught up: 29-53 segment-frames lost at
    6 mm, 36-774 at 15 mm (whole segments included) on these seeds. The residual test now holds
    at least ``gate^2`` times the segment's last few frames that passed whole and moved as
    usual (:data:`~jointfit_core.gate.GATE_RESIDUAL_RECENT`): none is lost. Frame by frame and
    in one block alike.
    """
    motion, t, thigh, shank = _knee_50hz(seed, deformation_mm)
    one, many = _frame_and_block(thigh, shank, t)
    assert one.gate_log == many.gate_log and one.dropped == many.dropped
    assert one.dropped == {}, one.dropped
    # not vacuous: the clusters deformed far beyond the stance's noise, and the stance came first
    noise = one.statistics.noise_sums()
    assert noise is not None
    pooled_mm = np.sqrt(noise[0] / noise[1])  # per segment, the window's pooled pose-fit residual
    assert pooled_mm.min() > 5 * 0.2, pooled_mm
    assert np.ptp(_paused(motion, t[:100])) == 0.0
