"""Joints between two moving segments (jointfit_core.segments; Stoddart et al. 1999).

The synthetic rig follows Stoddart's experiment: two rigid clusters of 3-4
markers, 100-200 mm wide, about 1 m apart with the joint halfway; the parent
wanders (rotations of ~15 deg and translations) while the child rotates about
the joint; isotropic noise with sqrt(tr W_y) = 1.7 mm.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from jointfit_core.errors import InputError, NotIdentifiableError
from jointfit_core.pose import pose_covariance_local, poses_from_markers
from jointfit_core.segments import (
    PoseSums,
    centre_from_pose_sums,
    fit_axis_two_segments,
    fit_centre_two_segments,
    noise_bias_matrices,
    pose_sums_from_relative,
    relative_poses,
)
from jointfit_core.synthetic import random_cluster

FloatArray = NDArray[np.float64]

# These rigs are rigid clusters with white noise: the fits are told so (the skin default adds a soft-tissue prior).
fit_centre_two_segments = functools.partial(fit_centre_two_segments, attachment="rigid")
fit_axis_two_segments = functools.partial(fit_axis_two_segments, attachment="rigid")

SIGMA = 1.7 / np.sqrt(3.0)  # per coordinate: sqrt(tr W_y) = 1.7 mm
HINGE_AXIS = np.array([1.0, 0.0, 0.0])  # true hinge direction in both true local frames


@dataclass
class Rig:
    parent: FloatArray  # (N, Pa, 3) noisy markers
    child: FloatArray
    template_parent: FloatArray  # true local coordinates
    template_child: FloatArray
    centre_parent: FloatArray  # true joint, true local frames
    centre_child: FloatArray
    R_parent: FloatArray  # true poses
    d_parent: FloatArray


def _rig(
    rng: np.random.Generator,
    n_frames: int = 1200,
    *,
    sigma: float = SIGMA,
    motion: str = "ball",
    n_markers: tuple[int, int] = (3, 3),
) -> Rig:
    """Stoddart-like rig; ``motion`` is "ball" (three axes), "hinge" (about x) or "none"."""
    xp = random_cluster(rng, n_markers[0])
    xc = random_cluster(rng, n_markers[1])
    c_p = np.array([0.0, 0.0, -500.0]) + rng.normal(0.0, 30.0, 3)
    c_c = np.array([0.0, 0.0, 500.0]) + rng.normal(0.0, 30.0, 3)
    time = np.arange(n_frames) / 60.0
    phase = rng.uniform(0.0, 2.0 * np.pi, 9)
    freq = rng.uniform(0.15, 0.5, 9) * 1200.0 / n_frames  # same number of cycles for any N
    wave = np.sin(2.0 * np.pi * freq * time[:, None] + phase)
    R_p = Rotation.from_rotvec(np.deg2rad(15.0) * wave[:, :3]).as_matrix()
    d_p = 100.0 * wave[:, 3:6] + np.array([100.0, 200.0, 900.0])
    if motion == "ball":
        rotvec = np.deg2rad(np.array([40.0, 30.0, 20.0])) * wave[:, 6:9]
    elif motion == "hinge":
        rotvec = np.deg2rad(30.0 + 50.0 * wave[:, 6:7]) * HINGE_AXIS
    else:
        rotvec = np.zeros((n_frames, 3))
    R_c = R_p @ Rotation.from_rotvec(rotvec).as_matrix()
    joint = np.einsum("nij,j->ni", R_p, c_p) + d_p
    d_c = joint - np.einsum("nij,j->ni", R_c, c_c)
    yp = np.einsum("nij,pj->npi", R_p, xp) + d_p[:, None, :]
    yc = np.einsum("nij,pj->npi", R_c, xc) + d_c[:, None, :]
    yp = yp + rng.normal(0.0, sigma, yp.shape)
    yc = yc + rng.normal(0.0, sigma, yc.shape)
    return Rig(yp, yc, xp, xc, c_p, c_c, R_p, d_p)


def _to_estimated_frame(template_est: FloatArray, template_true: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Rigid (R, d) mapping true local coordinates into the estimated template's frame (Procrustes)."""
    ca, cb = template_est.mean(axis=0), template_true.mean(axis=0)
    U, _, Vt = np.linalg.svd((template_true - cb).T @ (template_est - ca))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, ca - R @ cb


def _mahalanobis(err: FloatArray, cov: FloatArray, rank: int) -> float:
    """``err^T cov^+ err`` over the ``rank`` largest eigen-directions of ``cov``."""
    lam, V = np.linalg.eigh(cov)
    z = V.T @ err
    return float(np.sum(z[-rank:] ** 2 / lam[-rank:]))


def _centre_errors(fit: object, rig: Rig) -> tuple[FloatArray, FloatArray]:
    R, d = _to_estimated_frame(fit.template_parent, rig.template_parent)  # type: ignore[attr-defined]
    Rc, dc = _to_estimated_frame(fit.template_child, rig.template_child)  # type: ignore[attr-defined]
    return (
        fit.centre_parent - (R @ rig.centre_parent + d),  # type: ignore[attr-defined]
        fit.centre_child - (Rc @ rig.centre_child + dc),  # type: ignore[attr-defined]
    )


def _axis_errors(fit: object, rig: Rig) -> dict[str, FloatArray]:
    out = {}
    for side, template_true, centre_true in (
        ("parent", rig.template_parent, rig.centre_parent),
        ("child", rig.template_child, rig.centre_child),
    ):
        R, d = _to_estimated_frame(getattr(fit, f"template_{side}"), template_true)
        n_true = R @ HINGE_AXIS
        if n_true @ getattr(fit, f"direction_{side}") < 0:
            n_true = -n_true
        c_true = R @ centre_true + d
        point_true = c_true - n_true * (n_true @ c_true)  # nearest the local origin (template centroid)
        out[f"direction_{side}"] = getattr(fit, f"direction_{side}") - n_true
        out[f"point_{side}"] = getattr(fit, f"point_{side}") - point_true
    return out


# --------------------------------------------------------------------------- accuracy on Stoddart's rig


@pytest.fixture(scope="module")
def stoddart_rig() -> Rig:
    return _rig(np.random.default_rng(1999))


@pytest.mark.parametrize(
    "kwargs",
    [{"weighted": True}, {"weighted": False}, {"method": "sphere"}],
    ids=["weighted", "closed", "sphere"],
)
def test_stoddart_rig_centre(stoddart_rig: Rig, kwargs: dict[str, object]) -> None:
    fit = fit_centre_two_segments(stoddart_rig.parent, stoddart_rig.child, **kwargs)  # type: ignore[arg-type]
    err_p, err_c = _centre_errors(fit, stoddart_rig)
    assert fit.identifiable, fit.reason
    assert fit.reason == ""
    assert fit.n_frames == 1200
    assert fit.noise_std_parent == pytest.approx(SIGMA, rel=0.1)
    assert fit.noise_std_child == pytest.approx(SIGMA, rel=0.1)
    assert fit.method == kwargs.get("method", "poses")
    # Stoddart: 0.20 mm predicted for 1200 frames on his rig; here about 0.4-0.6 mm (see the report).
    assert np.sqrt(np.trace(fit.cov_parent)) < 1.0
    if fit.method == "poses":
        assert _mahalanobis(err_p, fit.cov_parent, 3) < 16.3  # chi2(3) 99.9 %
        assert _mahalanobis(err_c, fit.cov_child, 3) < 16.3
    else:  # the sphere method's covariance is over-confident here; only a plausibility bound
        assert np.linalg.norm(err_p) < 10.0 and np.linalg.norm(err_c) < 10.0
    # Per-frame outputs.
    poses = poses_from_markers(stoddart_rig.parent, fit.template_parent)
    expected_world = np.einsum("nij,j->ni", poses.R_world_local, fit.centre_parent) + poses.d_world_local
    np.testing.assert_allclose(fit.centre_world, expected_world, atol=1e-9)
    np.testing.assert_allclose(fit.cov_world, np.swapaxes(fit.cov_world, -1, -2), atol=1e-12)
    assert np.all(np.linalg.eigvalsh(fit.cov_world) > 0)
    assert fit.rms == pytest.approx(np.sqrt(np.mean(fit.residual**2)))
    assert 2.0 < fit.rms < 20.0  # parent + child pose noise carried 0.5 m: several mm per frame


def test_weighted_beats_closed_form(stoddart_rig: Rig) -> None:
    weighted = fit_centre_two_segments(stoddart_rig.parent, stoddart_rig.child)
    closed = fit_centre_two_segments(stoddart_rig.parent, stoddart_rig.child, weighted=False)
    assert np.trace(weighted.cov_parent) < np.trace(closed.cov_parent)
    assert np.trace(weighted.cov_child) < np.trace(closed.cov_child)


def test_stoddart_rig_hinge() -> None:
    rig = _rig(np.random.default_rng(2000), motion="hinge")
    fit = fit_axis_two_segments(rig.parent, rig.child)
    assert fit.identifiable, fit.reason
    err = _axis_errors(fit, rig)
    for side in ("parent", "child"):
        assert _mahalanobis(err[f"direction_{side}"], getattr(fit, f"cov_direction_{side}"), 2) < 13.8
        assert _mahalanobis(err[f"point_{side}"], getattr(fit, f"cov_point_{side}"), 3) < 16.3
        direction = getattr(fit, f"direction_{side}")
        assert np.linalg.norm(direction) == pytest.approx(1.0)
        assert abs(getattr(fit, f"cov_direction_{side}") @ direction).max() < 1e-12  # rank 2, orthogonal
        assert abs(getattr(fit, f"point_{side}") @ direction) < 1e-9  # nearest the template centroid
    np.testing.assert_allclose(np.linalg.norm(fit.direction_world, axis=1), 1.0)
    assert 1.0 < fit.rms < 20.0
    # Q n_c ~ n_p in every frame.
    pp = poses_from_markers(rig.parent, fit.template_parent)
    pc = poses_from_markers(rig.child, fit.template_child)
    Q, _, _ = relative_poses(pp, pc)
    cos = np.einsum("i,nij,j->n", fit.direction_parent, Q, fit.direction_child)
    assert cos.min() > 0.99  # the pose noise tilts Q by ~1 deg


# --------------------------------------------------------------------------- Monte-Carlo calibration


def test_centre_covariance_calibration() -> None:
    """Mean of e/3 over 200 seeded trials, truth mapped into the estimated local frames."""
    rng = np.random.default_rng(42)
    e = {"weighted": [], "closed": []}  # type: dict[str, list[tuple[float, float]]]
    for _ in range(200):
        rig = _rig(rng, 200)
        for name, weighted in (("weighted", True), ("closed", False)):
            fit = fit_centre_two_segments(rig.parent, rig.child, weighted=weighted)
            err_p, err_c = _centre_errors(fit, rig)
            e[name].append(
                (_mahalanobis(err_p, fit.cov_parent, 3) / 3, _mahalanobis(err_c, fit.cov_child, 3) / 3)
            )
    for name, values in e.items():
        mean_p, mean_c = np.mean(values, axis=0)
        assert 0.8 < mean_p < 1.25, (name, mean_p)
        assert 0.8 < mean_c < 1.25, (name, mean_c)


def test_centre_covariance_calibration_with_occlusions() -> None:
    """15 % of the markers and some whole frames missing (4 markers per segment): still calibrated."""
    rng = np.random.default_rng(44)
    e: dict[str, list[float]] = {"weighted": [], "closed": []}
    for _ in range(150):  # an extra check beyond the 200-trial ones: fewer trials to keep the file fast
        rig = _rig(rng, 150, n_markers=(4, 4))
        parent, child = rig.parent.copy(), rig.child.copy()
        parent[rng.random(parent.shape[:2]) < 0.15] = np.nan
        child[rng.random(child.shape[:2]) < 0.15] = np.nan
        child[rng.integers(0, 150, 5)] = np.nan
        for name, weighted in (("weighted", True), ("closed", False)):
            fit = fit_centre_two_segments(parent, child, weighted=weighted)
            err_p, _ = _centre_errors(fit, rig)
            e[name].append(_mahalanobis(err_p, fit.cov_parent, 3) / 3)
    for name, values in e.items():
        assert 0.8 < np.mean(values) < 1.25, (name, np.mean(values))


def test_badly_posed_frames_are_not_used() -> None:
    """Frames whose visible markers are nearly collinear are posed but left out of the joint fit."""
    rng = np.random.default_rng(17)
    rig = _rig(rng, 300, n_markers=(4, 3))
    # Same true parent frame, new cluster: three markers nearly on a line, the fourth well off it.
    x = np.array([[-90.0, 0.0, 0.0], [0.0, 3.0, 0.0], [90.0, 0.0, 0.0], [0.0, 80.0, 10.0]])
    x -= x.mean(axis=0)
    parent = np.einsum("nij,pj->npi", rig.R_parent, x) + rig.d_parent[:, None, :]
    parent += rng.normal(0.0, SIGMA, parent.shape)
    parent[::3, 3] = np.nan  # every third frame: the 3 nearly collinear markers (posed, but degrees off)
    fit = fit_centre_two_segments(parent, rig.child)
    poses = poses_from_markers(parent, fit.template_parent)
    assert poses.valid[::3].all()
    assert np.isnan(fit.residual[::3]).all()
    assert np.isfinite(fit.centre_world[::3]).all()  # the parent still carries the centre there
    assert fit.n_frames == 200
    assert fit.identifiable, fit.reason
    rig_x = Rig(
        parent,
        rig.child,
        x,
        rig.template_child,
        rig.centre_parent,
        rig.centre_child,
        rig.R_parent,
        rig.d_parent,
    )
    err_p, err_c = _centre_errors(fit, rig_x)
    assert _mahalanobis(err_p, fit.cov_parent, 3) < 16.3
    assert _mahalanobis(err_c, fit.cov_child, 3) < 16.3


def test_hinge_covariance_calibration() -> None:
    """Mean of e/2 (directions, rank 2) and e/3 (points) over 200 seeded trials."""
    rng = np.random.default_rng(43)
    e: dict[str, list[float]] = {
        "direction_parent": [],
        "direction_child": [],
        "point_parent": [],
        "point_child": [],
    }
    for _ in range(200):
        rig = _rig(rng, 200, motion="hinge")
        fit = fit_axis_two_segments(rig.parent, rig.child)
        err = _axis_errors(fit, rig)
        for key in e:
            rank = 2 if key.startswith("direction") else 3
            e[key].append(_mahalanobis(err[key], getattr(fit, f"cov_{key}"), rank) / rank)
    for key, values in e.items():
        assert 0.8 < np.mean(values) < 1.25, (key, np.mean(values))


# --------------------------------------------------------------------------- running sums


def test_sums_add_and_subtract_to_the_batch_closed_form(stoddart_rig: Rig) -> None:
    fit = fit_centre_two_segments(stoddart_rig.parent, stoddart_rig.child, weighted=False, model_error=False)
    pp = poses_from_markers(stoddart_rig.parent, fit.template_parent)
    pc = poses_from_markers(stoddart_rig.child, fit.template_child)
    Q, t, both = relative_poses(pp, pc)
    W_p = pose_covariance_local(fit.template_parent, fit.noise_std_parent)
    W_c = pose_covariance_local(fit.template_child, fit.noise_std_child)
    # A long random sequence of single-frame additions and removals, ending on frames 100..1099.
    rng = np.random.default_rng(3)
    sums = PoseSums.zeros()
    window: set[int] = set()
    for k in rng.permutation(1200)[:700]:
        sums = sums + pose_sums_from_relative(Q[k : k + 1], t[k : k + 1])
        window.add(int(k))
    for k in sorted(window):
        sums = sums - pose_sums_from_relative(Q[k : k + 1], t[k : k + 1])
    for k in range(100, 1100):
        sums = sums + pose_sums_from_relative(Q[k : k + 1], t[k : k + 1])
    online = centre_from_pose_sums(sums, W_p, W_c)
    direct = centre_from_pose_sums(pose_sums_from_relative(Q[100:1100], t[100:1100]), W_p, W_c)
    np.testing.assert_allclose(online.centre_parent, direct.centre_parent, atol=1e-8)
    np.testing.assert_allclose(online.cov, direct.cov, rtol=1e-6, atol=1e-14)
    assert online.n_frames == 1000
    # The whole batch closed form is the sums solution.
    full = centre_from_pose_sums(pose_sums_from_relative(Q[both], t[both]), W_p, W_c)
    np.testing.assert_allclose(full.centre_parent, fit.centre_parent, atol=1e-10)
    np.testing.assert_allclose(full.cov_child, fit.cov_child, rtol=1e-10)
    assert full.rms == pytest.approx(fit.rms, rel=1e-6)
    # The sandwich with K equals the explicit per-frame sum.
    a = np.concatenate([full.centre_parent, full.centre_child])
    Jp = np.concatenate([-_skew(a[:3]), np.eye(3)], axis=1)
    Jc = np.concatenate([-_skew(a[3:]), np.eye(3)], axis=1)
    Wt = Jp @ W_p @ Jp.T + Q[both] @ (Jc @ W_c @ Jc.T) @ np.swapaxes(Q[both], -1, -2)
    M = np.concatenate([np.broadcast_to(np.eye(3), Q[both].shape), -Q[both]], axis=2)
    B = (np.swapaxes(M, -1, -2) @ Wt @ M).sum(axis=0)
    # The bread: the normal matrix sum M^T M with S = sum Q freed of the noise's second-order bias.
    A_p, A_c = noise_bias_matrices(W_p, W_c)
    S = Q[both].sum(axis=0)
    H = (np.swapaxes(M, -1, -2) @ M).sum(axis=0)
    H[:3, 3:] += 0.5 * (A_p @ S + S @ A_c)
    H[3:, :3] = H[:3, 3:].T
    np.testing.assert_allclose(full.cov, np.linalg.inv(H) @ B @ np.linalg.inv(H), rtol=1e-8, atol=1e-14)


def _skew(v: FloatArray) -> FloatArray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def test_sums_errors() -> None:
    W = np.eye(6)
    with pytest.raises(InputError, match="at least 3 frames"):
        centre_from_pose_sums(PoseSums.zeros(), W, W)
    with pytest.raises(InputError, match=r"\(6, 6\)"):
        centre_from_pose_sums(PoseSums.zeros(), np.eye(3), W)
    with pytest.raises(InputError, match=r"\(N, 3, 3\)"):
        pose_sums_from_relative(np.zeros((4, 3)), np.zeros((4, 3)))
    no_motion = pose_sums_from_relative(np.broadcast_to(np.eye(3), (10, 3, 3)), np.ones((10, 3)))
    with pytest.raises(NotIdentifiableError, match="no relative rotation"):
        centre_from_pose_sums(no_motion, 1e-4 * W, 1e-4 * W)


# --------------------------------------------------------------------------- properties


def test_rigid_transform_equivariance() -> None:
    rig = _rig(np.random.default_rng(5), 300)
    Rg = Rotation.from_rotvec([0.3, -1.2, 2.0]).as_matrix()
    dg = np.array([2000.0, -500.0, 150.0])
    moved = (rig.parent @ Rg.T + dg, rig.child @ Rg.T + dg)
    for weighted in (True, False):
        a = fit_centre_two_segments(rig.parent, rig.child, weighted=weighted)
        b = fit_centre_two_segments(*moved, weighted=weighted)
        # The local frames are aligned with the world at their reference frame, so they rotate with it.
        np.testing.assert_allclose(b.template_parent, a.template_parent @ Rg.T, atol=1e-8)
        np.testing.assert_allclose(b.centre_parent, Rg @ a.centre_parent, atol=1e-7)
        np.testing.assert_allclose(b.centre_child, Rg @ a.centre_child, atol=1e-7)
        np.testing.assert_allclose(b.cov_parent, Rg @ a.cov_parent @ Rg.T, rtol=1e-6, atol=1e-12)
        np.testing.assert_allclose(b.centre_world, a.centre_world @ Rg.T + dg, atol=1e-7)
        np.testing.assert_allclose(b.cov_world, Rg @ a.cov_world @ Rg.T, rtol=1e-6, atol=1e-10)
        np.testing.assert_allclose(b.residual, a.residual, atol=1e-7)
    hinge = _rig(np.random.default_rng(6), 300, motion="hinge")
    ref = np.array([1.0, 0.2, 0.0])
    a_ax = fit_axis_two_segments(hinge.parent, hinge.child, reference_direction=ref)
    b_ax = fit_axis_two_segments(
        hinge.parent @ Rg.T + dg, hinge.child @ Rg.T + dg, reference_direction=Rg @ ref
    )
    np.testing.assert_allclose(b_ax.direction_parent, Rg @ a_ax.direction_parent, atol=1e-9)
    np.testing.assert_allclose(b_ax.point_parent, Rg @ a_ax.point_parent, atol=1e-7)
    np.testing.assert_allclose(b_ax.point_world, a_ax.point_world @ Rg.T + dg, atol=1e-7)
    np.testing.assert_allclose(
        b_ax.cov_point_parent, Rg @ a_ax.cov_point_parent @ Rg.T, rtol=1e-5, atol=1e-10
    )


def test_unit_scaling() -> None:
    rig = _rig(np.random.default_rng(7), 300)
    mm = fit_centre_two_segments(rig.parent, rig.child)
    m = fit_centre_two_segments(rig.parent * 1e-3, rig.child * 1e-3)
    np.testing.assert_allclose(m.centre_parent, 1e-3 * mm.centre_parent, rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(m.centre_child, 1e-3 * mm.centre_child, rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(m.cov_parent, 1e-6 * mm.cov_parent, rtol=1e-6, atol=1e-18)
    np.testing.assert_allclose(m.cov_world, 1e-6 * mm.cov_world, rtol=1e-6, atol=1e-18)
    assert m.noise_std_parent == pytest.approx(1e-3 * mm.noise_std_parent)
    assert m.identifiable == mm.identifiable
    hinge = _rig(np.random.default_rng(8), 300, motion="hinge")
    ax_mm = fit_axis_two_segments(hinge.parent, hinge.child)
    ax_m = fit_axis_two_segments(hinge.parent * 1e-3, hinge.child * 1e-3)
    np.testing.assert_allclose(ax_m.direction_parent, ax_mm.direction_parent, atol=1e-9)
    np.testing.assert_allclose(ax_m.cov_direction_parent, ax_mm.cov_direction_parent, rtol=1e-5, atol=1e-16)
    np.testing.assert_allclose(ax_m.point_child, 1e-3 * ax_mm.point_child, rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(ax_m.cov_point_child, 1e-6 * ax_mm.cov_point_child, rtol=1e-5, atol=1e-18)


def test_marker_order_invariance() -> None:
    rig = _rig(np.random.default_rng(9), 300, n_markers=(4, 3))
    perm_p, perm_c = np.array([3, 1, 0, 2]), np.array([2, 0, 1])
    a = fit_centre_two_segments(rig.parent, rig.child)
    b = fit_centre_two_segments(rig.parent[:, perm_p], rig.child[:, perm_c])
    np.testing.assert_allclose(b.template_parent, a.template_parent[perm_p], atol=1e-8)
    np.testing.assert_allclose(b.template_child, a.template_child[perm_c], atol=1e-8)
    np.testing.assert_allclose(b.centre_parent, a.centre_parent, atol=1e-7)
    np.testing.assert_allclose(b.centre_child, a.centre_child, atol=1e-7)
    np.testing.assert_allclose(b.cov_parent, a.cov_parent, rtol=1e-6)


def test_nan_tolerance() -> None:
    rng = np.random.default_rng(10)
    rig = _rig(rng, 600, n_markers=(4, 4))
    parent, child = rig.parent.copy(), rig.child.copy()
    parent[rng.random(parent.shape[:2]) < 0.1] = np.nan
    child[rng.random(child.shape[:2]) < 0.1] = np.nan
    parent[50:60] = np.nan  # whole frames missing
    child[300:305] = np.nan
    fit = fit_centre_two_segments(parent, child)
    assert fit.identifiable, fit.reason
    err_p, err_c = _centre_errors(fit, rig)
    assert _mahalanobis(err_p, fit.cov_parent, 3) < 16.3
    assert _mahalanobis(err_c, fit.cov_child, 3) < 16.3
    assert np.isnan(fit.centre_world[50:60]).all() and np.isnan(fit.cov_world[50:60]).all()
    assert np.isfinite(fit.centre_world[300:305]).all()  # the parent still carries the centre
    assert np.isnan(fit.residual[300:305]).all() and np.isnan(fit.residual[50:60]).all()
    assert fit.n_frames == int(np.isfinite(fit.residual).sum()) <= 585
    closed = fit_centre_two_segments(parent, child, weighted=False)
    assert _mahalanobis(_centre_errors(closed, rig)[0], closed.cov_parent, 3) < 16.3
    hinge = _rig(rng, 600, motion="hinge", n_markers=(4, 4))
    hp, hc = hinge.parent.copy(), hinge.child.copy()
    hp[rng.random(hp.shape[:2]) < 0.1] = np.nan
    hc[100:120] = np.nan
    ax = fit_axis_two_segments(hp, hc)
    assert ax.identifiable, ax.reason
    err = _axis_errors(ax, hinge)
    assert _mahalanobis(err["direction_parent"], ax.cov_direction_parent, 2) < 13.8
    assert _mahalanobis(err["point_child"], ax.cov_point_child, 3) < 16.3


def test_hinge_sign_convention() -> None:
    rig = _rig(np.random.default_rng(11), 300, motion="hinge")
    default = fit_axis_two_segments(rig.parent, rig.child)
    k = int(np.argmax(np.abs(default.direction_parent)))
    assert default.direction_parent[k] > 0  # default: largest parent-frame component positive
    for ref in (default.direction_parent, -default.direction_parent, [0.0, 0.0, -1.0]):
        fit = fit_axis_two_segments(rig.parent, rig.child, reference_direction=ref)
        assert fit.direction_parent @ np.asarray(ref) >= 0
        np.testing.assert_allclose(abs(fit.direction_parent @ default.direction_parent), 1.0, atol=1e-12)
        # The child direction follows (Q n_c ~ n_p), so the pair flips together.
        assert np.sign(fit.direction_child @ default.direction_child) == np.sign(
            fit.direction_parent @ default.direction_parent
        )
        np.testing.assert_allclose(fit.point_parent, default.point_parent, atol=1e-9)
    with pytest.raises(InputError, match="reference_direction"):
        fit_axis_two_segments(rig.parent, rig.child, reference_direction=[0.0, 0.0, 0.0])
    with pytest.raises(InputError, match="reference_direction"):
        fit_axis_two_segments(rig.parent, rig.child, reference_direction=[1.0, 0.0])


def test_sphere_method_refuses_skin_markers() -> None:
    """method="sphere" has no soft-tissue term: on skin markers it would publish the white noise's sd."""
    rig = _rig(np.random.default_rng(14), 300)
    with pytest.raises(InputError, match="no soft-tissue term"):
        fit_centre_two_segments(rig.parent, rig.child, method="sphere", attachment="skin")  # the library's default
    with pytest.raises(InputError, match="no soft-tissue term"):
        fit_centre_two_segments(rig.parent, rig.child, method="sphere", attachment=("rigid", "skin"))
    assert fit_centre_two_segments(rig.parent, rig.child, method="sphere", attachment="rigid").method == "sphere"


# --------------------------------------------------------------------------- motion that cannot identify the joint


@pytest.mark.parametrize("method", ["poses", "sphere"])
def test_single_axis_relative_rotation_is_flagged(method: str) -> None:
    rig = _rig(np.random.default_rng(12), 300, motion="hinge")
    fit = fit_centre_two_segments(rig.parent, rig.child, method=method)
    assert not fit.identifiable
    assert "second axis" in fit.reason
    clean = _rig(np.random.default_rng(12), 300, motion="hinge", sigma=0.0)
    with pytest.raises(NotIdentifiableError, match="second axis"):
        fit_centre_two_segments(clean.parent, clean.child, method=method)


def test_no_relative_motion_is_flagged() -> None:
    rig = _rig(np.random.default_rng(13), 300, motion="none")
    fit = fit_centre_two_segments(rig.parent, rig.child)
    assert not fit.identifiable and "no relative rotation" in fit.reason
    axis = fit_axis_two_segments(rig.parent, rig.child)
    assert not axis.identifiable and "no relative rotation" in axis.reason
    clean = _rig(np.random.default_rng(13), 300, motion="none", sigma=0.0)
    with pytest.raises(NotIdentifiableError, match="no relative rotation"):
        fit_centre_two_segments(clean.parent, clean.child)
    with pytest.raises(NotIdentifiableError, match="no relative rotation"):
        fit_axis_two_segments(clean.parent, clean.child)


def test_hinge_fit_of_ball_motion_is_flagged() -> None:
    rig = _rig(np.random.default_rng(14), 300)
    fit = fit_axis_two_segments(rig.parent, rig.child)
    assert not fit.identifiable
    assert "not about a single fixed axis" in fit.reason and "fit_centre_two_segments" in fit.reason


def test_small_range_is_flagged() -> None:
    """A few frames of a slow motion (0.2 s) are flagged with a reason that says how to move."""
    rig = _rig(np.random.default_rng(15), 1200)
    fit = fit_centre_two_segments(rig.parent[:12], rig.child[:12])
    assert not fit.identifiable
    assert "rotat" in fit.reason


# --------------------------------------------------------------------------- input errors


def test_input_errors() -> None:
    rig = _rig(np.random.default_rng(16), 50)
    with pytest.raises(InputError, match=r"shape \(N, P, 3\)"):
        fit_centre_two_segments(rig.parent[:, :, :2], rig.child)
    with pytest.raises(InputError, match="use fit_centre_minimal"):
        fit_centre_two_segments(rig.parent[:, :2], rig.child)
    with pytest.raises(InputError, match="use fit_axis_minimal"):
        fit_axis_two_segments(rig.parent, rig.child[:, :2])
    with pytest.raises(InputError, match="same number of frames"):
        fit_centre_two_segments(rig.parent[:40], rig.child)
    with pytest.raises(InputError, match="every sample is NaN"):
        fit_centre_two_segments(np.full_like(rig.parent, np.nan), rig.child)
    with pytest.raises(InputError, match="method"):
        fit_centre_two_segments(rig.parent, rig.child, method="magic")
    child = rig.child.copy()
    child[:, 1] = np.nan
    with pytest.raises(InputError, match=r"child: .*marker\(s\) \[1\] are never visible"):
        fit_axis_two_segments(rig.parent, child)
    parent = rig.parent.copy()
    parent[2:, 0] = np.nan
    child = rig.child.copy()
    child[:2, 0] = np.nan  # the two segments are never posed in the same frame
    with pytest.raises(InputError, match="both segments"):
        fit_centre_two_segments(parent, child)
