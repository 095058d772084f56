"""The synthetic skeletons of jointfit_core.skeleton_truth: rigid geometry, plausible sizes, motions that identify every joint."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jointfit_core.skeleton_truth import SKELETONS, Skeleton, make_skeleton, skeleton_frames

TIMES = np.linspace(0.0, 10.0, 501)


def _segment_rows(sk: Skeleton, name: str) -> list[int]:
    names = sk.marker_names()
    return [names.index(n) for n in sk.segment(name).marker_names]


def test_names_and_layout() -> None:
    lower, full = make_skeleton("lower"), make_skeleton("full")
    assert lower.joints == SKELETONS["lower"] and len(full.joints) == 12
    assert len(lower.segments) == 7 and len(full.segments) == 14
    names = full.marker_names()
    assert len(names) == 56 == len(set(names)) and names[:28] == lower.marker_names()
    assert all(len(s.markers) == 4 for s in full.segments)
    kinds = {j: full.joint_segment(j).kind for j in full.joints}
    assert {j for j, k in kinds.items() if k == "ball"} == {"r_hip", "l_hip", "r_shoulder", "l_shoulder", "r_wrist", "l_wrist"}
    for s in full.segments[1:]:  # parents come first
        assert [x.name for x in full.segments].index(s.parent or "") < [x.name for x in full.segments].index(s.name)
    with pytest.raises(ValueError, match="skeleton"):
        make_skeleton("upper")
    with pytest.raises(ValueError, match="cycle_s"):
        make_skeleton("lower", cycle_s=0.0)
    with pytest.raises(KeyError, match="no such joint"):
        full.joint_segment("neck")


def test_segments_are_rigid_and_joints_hold() -> None:
    sk = make_skeleton("full", seed=3)
    markers = sk.markers_at(TIMES)
    world = sk.joints_world_at(TIMES)
    for j in sk.joints:
        child = sk.joint_segment(j)
        point, direction = world[j]
        for seg in (child.parent or "", child.name):
            rel = markers[:, _segment_rows(sk, seg)] - point[:, None]
            if direction is None:  # ball: every marker of both segments keeps its distance to the centre
                assert np.ptp(np.linalg.norm(rel, axis=2), axis=0).max() < 1e-12, (j, seg)
            else:  # hinge: distance to the axis line and position along it are constant
                along = np.einsum("npi,ni->np", rel, direction)
                radial = np.linalg.norm(rel - along[..., None] * direction[:, None], axis=2)
                assert np.ptp(along, axis=0).max() < 1e-12 and np.ptp(radial, axis=0).max() < 1e-12, (j, seg)
    R, _ = sk.poses_at(TIMES)
    assert np.allclose(np.einsum("nsji,nsjk->nsik", R, R), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)


def test_anatomical_dimensions_in_metres() -> None:
    sk = make_skeleton("full")
    world = sk.joints_world_at(TIMES)
    lengths = {
        "thigh": ("r_hip", "r_knee", 0.38, 0.46),
        "shank": ("r_knee", "r_ankle", 0.36, 0.44),
        "upper arm": ("r_shoulder", "r_elbow", 0.27, 0.33),
        "forearm": ("r_elbow", "r_wrist", 0.23, 0.29),
        "pelvis width": ("r_hip", "l_hip", 0.15, 0.20),
        "shoulder width": ("r_shoulder", "l_shoulder", 0.32, 0.40),
    }
    for what, (a, b, low, high) in lengths.items():
        dist = np.linalg.norm(world[a][0] - world[b][0], axis=1)
        assert low < dist.min() and dist.max() < high, (what, dist.min(), dist.max())
    markers = sk.markers_at(TIMES)
    assert 0.0 < markers[..., 2].min() and markers[..., 2].max() < 2.0  # above the floor, below 2 m
    for s in sk.segments:  # clusters of a few centimetres to ~0.3 m, well spread (not collinear)
        x = s.markers - s.markers.mean(axis=0)
        sv = np.linalg.svd(x, compute_uv=False)
        assert 0.02 < np.sqrt((x**2).sum(axis=1).mean()) < 0.3 and sv[1] > 0.2 * sv[0], s.name


def test_every_joint_moves_enough_to_be_identified_within_a_cycle() -> None:
    sk = make_skeleton("full")
    R, _ = sk.poses_at(TIMES)
    index = {s.name: k for k, s in enumerate(sk.segments)}
    for j in sk.joints:
        child = sk.joint_segment(j)
        rel = np.einsum("nji,njk->nik", R[:, index[child.parent or ""]], R[:, index[child.name]])
        rotvec = np.degrees(Rotation.from_matrix(rel).as_rotvec())
        spread = np.linalg.svd(rotvec - rotvec.mean(axis=0), compute_uv=False) / np.sqrt(len(TIMES))
        if child.kind == "ball":  # about at least two axes, several degrees rms each
            assert spread[1] > 4.0, (j, spread)
        else:  # about the hinge axis only, through a range of tens of degrees
            assert spread[1] < 1e-9 and np.ptp(rotvec @ child.axis) > 30.0, (j, spread)


def test_joints_local_is_the_template_frame_of_the_node() -> None:
    sk = make_skeleton("lower", seed=1)
    t_ref = 2.0
    local = sk.joints_local(t_ref)
    world = sk.joints_world_at(TIMES)
    markers = sk.markers_at(TIMES)
    k_ref = int(np.argmin(np.abs(TIMES - t_ref)))
    assert TIMES[k_ref] == t_ref
    for j, truth in local.items():
        rows = _segment_rows(sk, truth.parent)
        y = markers[:, rows]
        template = y[k_ref] - y[k_ref].mean(axis=0)  # the node's template: centroid origin, world axes at t_ref
        for k in (0, 100, 400):
            H = template.T @ (y[k] - y[k].mean(axis=0))
            U, _, Vt = np.linalg.svd(H)
            R = Vt.T @ np.diag([1.0, 1.0, np.linalg.det(Vt.T @ U.T)]) @ U.T
            point_world, direction_world = world[j]
            np.testing.assert_allclose(R @ truth.point + y[k].mean(axis=0), point_world[k], atol=1e-12)
            if truth.direction is not None:
                assert direction_world is not None
                np.testing.assert_allclose(R @ truth.direction, direction_world[k], atol=1e-12)
                # the hinge point is the axis point nearest the parent markers' centroid
                assert abs(truth.point @ truth.direction) < 1e-12


def test_skeleton_frames_noise_and_occlusion() -> None:
    sk = make_skeleton("lower")
    rng = np.random.default_rng(0)
    clean = sk.markers_at(TIMES)
    frames = skeleton_frames(sk, TIMES, rng, 0.0005, 0.1)
    missing = np.isnan(frames).any(axis=2)
    assert (np.isnan(frames).all(axis=2) == missing).all()
    assert abs(missing.mean() - 0.1) < 5.0 * np.sqrt(0.09 / missing.size)
    err = (frames - clean)[~missing]
    assert abs(err.std() - 0.0005) < 1e-5 and abs(err.mean()) < 1e-5
    with pytest.raises(ValueError, match="noise"):
        skeleton_frames(sk, TIMES, rng, -1.0)
