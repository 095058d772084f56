"""A marker that does not move with its segment (a label on the wrong segment) is named, and only then.

Ground truth: the skin skeleton of :mod:`jointfit_core.skeleton_sta` (the literature's artefact and
twice it) and the rigid one, with one marker swapped between two segments for the whole session;
the real hip recording, with and without such a swap.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jointfit_core.cluster_rigidity import ClusterPairs, ClusterRigidity, odd_markers
from jointfit_core.io import read_c3d
from jointfit_core.skeleton_sta import skeleton_skin_frames, sta_amplitudes
from jointfit_core.skeleton_truth import make_skeleton, skeleton_frames
from jointfit_ros.cluster_check import ODD_FLOOR_MM, recording_odd_markers
from jointfit_ros.inputs import MessageRouter
from jointfit_ros.joint_diagnostics import WARN
from jointfit_ros.params import node_config, params_from_file
from jointfit_ros.raw import pose_array_bytes
from jointfit_ros.runner import JointRunner

ROOT = Path(__file__).resolve().parent.parent
DATA = Path(__file__).resolve().parent / "data"
RATE = 100.0
T0 = 1_000_000_000_000


def _skin(seed: int, seconds: float = 30.0, scale: float = 1.0) -> tuple[list[str], list[list[int]], np.ndarray]:
    rng = np.random.default_rng(seed)
    sk = make_skeleton("lower", seed=int(rng.integers(2**31)))
    names = sk.marker_names()
    t = np.arange(round(seconds * RATE)) / RATE
    frames = skeleton_skin_frames(sk, t, rng, sta_amplitudes(sk, scale), noise=0.0005)
    segments = [[names.index(m) for m in s.marker_names] for s in sk.segments]
    return names, segments, frames


def _swapped(frames: np.ndarray, names: list[str], a: str, b: str) -> np.ndarray:
    out = frames.copy()
    i, j = names.index(a), names.index(b)
    out[:, [i, j]] = out[:, [j, i]]
    return out


def _named(names: list[str], segments: list[list[int]], frames: np.ndarray, floor: float) -> set[str]:
    pairs = ClusterPairs(segments)
    return {names[segments[o.segment][o.marker]] for o in odd_markers(pairs, pairs.spread(pairs.distances(frames)), floor)}


SKIN_FLOOR = ODD_FLOOR_MM["skin"] / 1000.0


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize(("a", "b"), [("PELV1", "RTHI1"), ("RTHI2", "RSHK1"), ("LTHI1", "RTHI1"), ("RSHK3", "RFOO1")])
def test_a_marker_swapped_across_segments_is_named(seed: int, a: str, b: str) -> None:
    """Named in each segment where its distances vary beyond the skin's deformation; at least in one.

    A shank marker near the knee moves ~9 mm (sd) in the thigh cluster, within the thigh's own
    deformation: the shank names the thigh's marker it holds (its label ``b``), the thigh does not
    name the shank's. So for a foot marker near the ankle in the shank cluster.
    """
    names, segments, frames = _skin(seed)
    named = _named(names, segments, _swapped(frames, names, a, b), SKIN_FLOOR)
    assert named == ({b} if (a, b) in {("RTHI2", "RSHK1"), ("RSHK3", "RFOO1")} else {a, b})


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("scale", [1.0, 2.0, 3.0])
def test_skin_clusters_deformation_names_no_marker(seed: int, scale: float) -> None:
    names, segments, frames = _skin(seed, scale=scale)
    assert _named(names, segments, frames, SKIN_FLOOR) == set()


def test_rigid_clusters_name_a_swap_at_the_rigid_floor_and_nothing_without() -> None:
    rng = np.random.default_rng(3)
    sk = make_skeleton("full", seed=3)
    names = sk.marker_names()
    frames = skeleton_frames(sk, np.arange(3000) / RATE, rng, 0.0005, 0.02)
    segments = [[names.index(m) for m in s.marker_names] for s in sk.segments]
    floor = ODD_FLOOR_MM["rigid"] / 1000.0
    assert _named(names, segments, frames, floor) == set()
    assert _named(names, segments, _swapped(frames, names, "RUPA2", "RFRA2"), floor) == {"RUPA2", "RFRA2"}


@pytest.mark.parametrize("kind", ["corrupt", "ghost"])
def test_glitches_of_one_marker_name_nothing_and_hide_no_swap(kind: str) -> None:
    """A marker's rare glitches are not its segment's spread: nothing named, and a real swap still is.

    Before 2026-12-07, one frame in a hundred with a corrupt coordinate (a driver's 2e7) named that marker as
    not moving with its segment ("on another segment, or its label swapped"), on rigid and skin clusters
    alike; so did a ghost 60 mm away in 3 % of the frames on a rigid cluster.
    """
    rng = np.random.default_rng(3)
    sk = make_skeleton("lower", seed=3)
    names = sk.marker_names()
    frames = skeleton_frames(sk, np.arange(2000) / RATE, rng, 0.0005, 0.02)
    segments = [[names.index(m) for m in s.marker_names] for s in sk.segments]
    bad = frames.copy()
    row = names.index("RTHI2")
    if kind == "corrupt":
        at = np.arange(7, 2000, 100)
        bad[at, row, 1] = 2.4e7
    else:
        at = rng.choice(2000, 60, replace=False)
        bad[at, row] += rng.normal(0.0, 1.0, (at.size, 3)) * 0.06 / np.sqrt(3.0)
    for floor in (ODD_FLOOR_MM["rigid"] / 1000.0, SKIN_FLOOR):
        assert _named(names, segments, bad, floor) == set()
    floor = ODD_FLOOR_MM["rigid"] / 1000.0
    assert _named(names, segments, _swapped(bad, names, "PELV1", "RTHI1"), floor) == {"PELV1", "RTHI1"}


def test_a_still_stance_names_nothing() -> None:
    names, segments, frames = _skin(0)
    still = np.repeat(frames[:1], 1500, axis=0) + np.random.default_rng(0).normal(0.0, 0.0005, (1500, *frames.shape[1:]))
    assert _named(names, segments, _swapped(still, names, "PELV1", "RTHI1"), SKIN_FLOOR) == set()


def test_the_verdict_ignores_the_world_frame_the_units_and_the_marker_order() -> None:
    names, segments, frames = _skin(1)
    frames = _swapped(frames, names, "PELV1", "RTHI1")
    R = Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix()
    moved = (frames @ R.T + np.array([2.0, -1.0, 0.5])) * 1000.0  # another world frame, in mm
    order = [list(reversed(s)) for s in segments]
    assert _named(names, order, moved, SKIN_FLOOR * 1000.0) == {"PELV1", "RTHI1"}


def test_fed_a_frame_at_a_time_or_in_blocks_the_samples_and_the_verdict_are_the_same() -> None:
    names, segments, frames = _skin(0, seconds=40.0, scale=1.0)
    frames = _swapped(frames, names, "PELV1", "RTHI1")
    frames[::7, 2] = np.nan  # occluded markers leave their pairs out of those frames
    stamps = T0 + np.round(np.arange(frames.shape[0]) / RATE * 1e9).astype(np.int64)
    one, block = ClusterRigidity(segments, SKIN_FLOOR, samples=600), ClusterRigidity(segments, SKIN_FLOOR, samples=600)
    for k in range(frames.shape[0]):
        one.add(stamps[k : k + 1], frames[k : k + 1])
    for start in range(0, frames.shape[0], 333):
        block.add(stamps[start : start + 333], frames[start : start + 333])
    # 40 s at 50 samples per second: 2000 samples through a ring of 600 (the last 12 s kept)
    np.testing.assert_array_equal(one._ring, block._ring)
    assert one._rows == block._rows == 2000
    assert one.odd_markers() == block.odd_markers()
    assert {names[segments[o.segment][o.marker]] for o in one.odd_markers()} == {"PELV1", "RTHI1"}
    one.clear()
    assert one.odd_markers() == []


def _lower_body_run(frames: np.ndarray) -> list[JointRunner]:
    cfg = node_config(params_from_file(ROOT / "config" / "lower_body.yaml"))
    runners = [JointRunner(j, cfg) for j in cfg.joints]
    router = MessageRouter(cfg, runners)
    for k, f in enumerate(frames):
        router.markers(pose_array_bytes(T0 + round(k / RATE * 1e9), "world", f))
        if k % 500 == 499:
            for r in runners:
                r.estimate(force=True)
    return runners


def test_the_joints_of_both_segments_warn_with_the_marker_named() -> None:
    names, _, frames = _skin(0, seconds=25.0)
    runners = {r.cfg.name: r for r in _lower_body_run(_swapped(frames, names, "PELV1", "RTHI1"))}
    for name in ("r_hip", "l_hip", "r_knee"):
        status = runners[name].status()
        assert status.level == WARN, (name, status.message)
    assert "marker PELV1 does not move with the other markers of segment pelvis" in runners["l_hip"].status().message
    assert "marker RTHI1 does not move" in runners["r_knee"].status().message
    assert runners["r_hip"].status().message.count("does not move") == 2  # both its segments hold a foreign marker
    for name in ("l_knee", "l_ankle"):
        assert "does not move" not in runners[name].status().message


def test_without_a_swap_no_joint_names_a_marker() -> None:
    _, _, frames = _skin(0, seconds=25.0)
    for r in _lower_body_run(frames):
        assert r.odd_markers() == "", r.cfg.name
        assert "does not move" not in r.status().message


def test_the_real_hip_recording_names_a_swapped_asis_and_nothing_without() -> None:
    data = read_c3d(DATA / "biobuddy" / "right_hip.c3d")
    cfg = node_config(params_from_file(ROOT / "config" / "offline_right_hip.yaml"))
    frames = data.select(cfg.marker_names)
    assert recording_odd_markers(cfg, cfg.joints[0], frames) == ""
    names = list(cfg.marker_names)
    text = recording_odd_markers(cfg, cfg.joints[0], _swapped(frames, names, "RASIS", "RTHI1"))
    assert "marker RASIS does not move" in text and "marker RTHI1 does not move" in text


@pytest.mark.parametrize("keep_frames", [True, False])
def test_a_bag_fitted_with_or_without_its_frames_names_the_marker(tmp_path: Path, keep_frames: bool) -> None:
    """``jointfit fit`` of a bag: from the kept frames, or (``--no-report``) from what its router sampled."""
    from bagtools import write_marker_bag

    from jointfit_ros.offline import run_fit
    from jointfit_ros.report import fit_summary

    names, _, frames = _skin(0, seconds=25.0)
    stamps = T0 + np.round(np.arange(frames.shape[0]) / RATE * 1e9).astype(np.int64)
    bag = write_marker_bag(tmp_path / "swapped", _swapped(frames, names, "PELV1", "RTHI1"), stamps)
    cfg = node_config(params_from_file(ROOT / "config" / "lower_body.yaml"))
    run = run_fit(bag, cfg, keep_frames=keep_frames)
    assert (run.frames is None) != keep_frames
    joints = {j["name"]: j for j in fit_summary(run, elapsed_s=0.0, version="test")["joints"]}
    assert "marker PELV1 does not move with the other markers of segment pelvis" in joints["l_hip"]["label_warning"]
    assert joints["l_ankle"]["label_warning"] == ""
