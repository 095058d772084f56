"""Rigid poses, templates and pose covariances (jointfit_core.pose; Stoddart et al. 1999 eq. 4-5)."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from jointfit_core.errors import InputError
from jointfit_core.pose import (
    COLLINEAR_RTOL,
    noise_std_from_fit,
    point_covariance_local,
    pose_covariance,
    pose_covariance_local,
    pose_noise_local,
    poses_from_markers,
    skew,
    template_from_markers,
)

FloatArray = NDArray[np.float64]


def _cluster(rng: np.random.Generator, n_markers: int, size: float = 80.0) -> FloatArray:
    x = rng.normal(0.0, size, (n_markers, 3))
    return x - x.mean(axis=0)


def _motion(
    rng: np.random.Generator, template: FloatArray, n_frames: int, sigma: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Random poses (R, d) and noisy markers of ``template``."""
    R = Rotation.random(n_frames, random_state=rng).as_matrix()
    d = rng.normal(0.0, 500.0, (n_frames, 3)) + np.array([0.0, 0.0, 1000.0])
    y = np.einsum("nij,pj->npi", R, template) + d[:, None, :]
    return y + rng.normal(0.0, sigma, y.shape), R, d


def _procrustes(a: FloatArray, b: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Rigid (R, d) minimising |a - (R b + d)|."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    U, _, Vt = np.linalg.svd((b - cb).T @ (a - ca))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, ca - R @ cb


def _rotvec_error(R_est: FloatArray, R_true: FloatArray) -> FloatArray:
    """World-frame rotation vector r with R_est = exp([r]x) R_true."""
    rel = R_est @ np.swapaxes(R_true, -1, -2)
    out: FloatArray = Rotation.from_matrix(rel).as_rotvec()
    return out


# --------------------------------------------------------------------------- poses


def test_poses_recover_known_poses_without_noise() -> None:
    rng = np.random.default_rng(1)
    x = _cluster(rng, 4)
    y, R, d = _motion(rng, x, 50, 0.0)
    poses = poses_from_markers(y, x)
    assert poses.valid.all()
    np.testing.assert_allclose(poses.R_world_local, R, atol=1e-12)
    np.testing.assert_allclose(poses.d_world_local, d, atol=1e-9)
    assert np.all(poses.rms < 1e-9)
    np.testing.assert_allclose(np.linalg.det(poses.R_world_local), 1.0, atol=1e-12)
    assert (poses.n_visible == 4).all()


def test_poses_equal_the_svd_procrustes_with_noise_occlusions_and_reflections() -> None:
    """Horn's batched rotation is Kabsch's optimum (reflection excluded), per frame, on the visible markers."""
    rng = np.random.default_rng(11)
    x = _cluster(rng, 5)
    y, _, _ = _motion(rng, x, 400, 2.0)
    y[150:200] *= np.array([1.0, 1.0, -1.0])  # mirrored frames: the best proper rotation, not a reflection
    y[rng.random(y.shape[:2]) < 0.15] = np.nan
    poses = poses_from_markers(y, x)
    for k in np.flatnonzero(poses.valid):
        seen = np.isfinite(y[k]).all(axis=1)
        R, d = _procrustes(y[k, seen], x[seen])
        np.testing.assert_allclose(poses.R_world_local[k], R, atol=1e-12)
        np.testing.assert_allclose(poses.d_world_local[k], d, atol=1e-9)
        rms = np.sqrt(np.mean(np.sum((y[k, seen] - x[seen] @ R.T - d) ** 2, axis=1)))
        assert poses.rms[k] == pytest.approx(rms, rel=1e-10)
    assert poses.valid.sum() > 300 and (~poses.valid).sum() > 0  # frames with < 3 markers seen
    np.testing.assert_allclose(np.linalg.det(poses.R_world_local[poses.valid]), 1.0, atol=1e-12)


def test_pose_covariance_calibrated() -> None:
    """Rotation + centroid translation errors against Pennec & Thirion's covariance: mean e/6 ~ 1."""
    rng = np.random.default_rng(2)
    sigma = 1.0
    x = _cluster(rng, 4, 60.0)
    y, R, d = _motion(rng, x, 3000, sigma)
    y[rng.random(y.shape[:2]) < 0.15] = np.nan  # occlusions: the covariance uses the visible markers
    poses = poses_from_markers(y, x)
    cov = pose_covariance(x, poses, sigma)
    v = poses.valid
    assert v.mean() > 0.5
    r = _rotvec_error(poses.R_world_local[v], R[v])
    vis = poses.visible[v]
    xbar = (vis[..., None] * x).sum(axis=1) / vis.sum(axis=1)[:, None]
    centroid_true = np.einsum("nij,nj->ni", R[v], xbar) + d[v]
    centroid_est = np.einsum("nij,nj->ni", poses.R_world_local[v], xbar) + poses.d_world_local[v]
    err = np.concatenate([r, centroid_est - centroid_true], axis=1)
    e = np.einsum("ni,nij,nj->n", err, np.linalg.inv(cov[v]), err)
    assert 0.93 < e.mean() / 6.0 < 1.07
    assert np.isnan(cov[~v]).all()


def test_poses_need_three_non_collinear_visible_markers() -> None:
    rng = np.random.default_rng(3)
    x = np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [200.0, 0.0, 0.0], [50.0, 80.0, 0.0]])
    x = x - x.mean(axis=0)
    y, _, _ = _motion(rng, x, 6, 0.1)
    y[0, 3] = np.nan  # three collinear markers left
    y[1, 2:] = np.nan  # two markers left
    y[2] = np.nan  # nothing
    poses = poses_from_markers(y, x)
    np.testing.assert_array_equal(poses.valid, [False, False, False, True, True, True])
    assert np.isnan(poses.R_world_local[:3]).all() and np.isnan(poses.d_world_local[:3]).all()
    assert np.isnan(poses.rms[:3]).all()
    np.testing.assert_array_equal(poses.n_visible, [3, 2, 0, 4, 4, 4])


def test_collinearity_threshold_is_relative() -> None:
    base = np.array([[-100.0, 0.0, 0.0], [0.0, 0.0, 0.0], [100.0, 0.0, 0.0]])
    # Shifting the middle point by ``off`` gives singular values ~100 sqrt(2) and off sqrt(2/3):
    # this ``off`` is twice the threshold, a tenth of it is well below.
    off = 2.0 * COLLINEAR_RTOL * 100.0 * np.sqrt(2.0) / np.sqrt(2.0 / 3.0)
    for scale in (1.0, 1e-3):
        good = (base + np.array([[0.0, 0.0, 0.0], [0.0, off, 0.0], [0.0, 0.0, 0.0]])) * scale
        bad = (base + np.array([[0.0, 0.0, 0.0], [0.0, off / 10.0, 0.0], [0.0, 0.0, 0.0]])) * scale
        assert poses_from_markers(good[None], good).valid[0]
        assert not poses_from_markers(bad[None], bad).valid[0]


def test_poses_errors() -> None:
    x = np.eye(3) * 100.0
    with pytest.raises(InputError, match=r"\(N, P, 3\)"):
        poses_from_markers(np.zeros((5, 3)), x)
    with pytest.raises(InputError, match="at least 3 marker"):
        poses_from_markers(np.zeros((5, 2, 3)), x[:2])
    with pytest.raises(InputError, match="expected 3 points"):
        poses_from_markers(np.zeros((5, 3, 3)), np.zeros((4, 3)))
    with pytest.raises(InputError, match="finite"):
        poses_from_markers(np.ones((5, 3, 3)), np.full((3, 3), np.nan))
    with pytest.raises(InputError, match="every sample is NaN"):
        poses_from_markers(np.full((5, 3, 3), np.nan), x)
    with pytest.raises(InputError, match="inf"):
        poses_from_markers(np.full((5, 3, 3), np.inf), x)


# --------------------------------------------------------------------------- templates


def test_template_recovery_and_frame_convention() -> None:
    rng = np.random.default_rng(4)
    x = _cluster(rng, 4)
    y, R, _ = _motion(rng, x, 400, 0.5)
    template = template_from_markers(y)
    # Centroid at the origin, reference frame (frame 0: all visible) posed with R = I.
    np.testing.assert_allclose(template.mean(axis=0), 0.0, atol=1e-9)
    poses = poses_from_markers(y, template)
    np.testing.assert_allclose(poses.R_world_local[0], np.eye(3), atol=1e-12)
    # The shape is the true one (up to the frame) to ~ sigma / sqrt(N).
    Ra, da = _procrustes(template, x)
    assert np.abs(template - (x @ Ra.T + da)).max() < 0.2
    # The axes are those of the world at frame 0: template ~ R_0 x.
    np.testing.assert_allclose(Ra, R[0], atol=5e-3)


def test_template_without_noise_is_exact() -> None:
    rng = np.random.default_rng(5)
    x = _cluster(rng, 3)
    y, R, _ = _motion(rng, x, 30, 0.0)
    template = template_from_markers(y)
    np.testing.assert_allclose(template, x @ R[0].T, atol=1e-9)
    assert np.all(poses_from_markers(y, template).rms < 1e-9)


def test_template_reference_frame_and_fill_with_occlusions() -> None:
    """No frame shows every marker: the frame with the most markers is the reference, the rest is filled."""
    rng = np.random.default_rng(6)
    x = _cluster(rng, 5)
    y, _, _ = _motion(rng, x, 300, 0.3)
    hide = rng.integers(0, 5, 300)
    y[np.arange(300), hide] = np.nan  # exactly one marker missing per frame
    y[:2, 0] = np.nan  # frames 0 and 1 show only 3 markers: frame 2 is the reference
    template = template_from_markers(y)
    assert np.isfinite(template).all()
    Ra, da = _procrustes(template, x)
    assert np.abs(template - (x @ Ra.T + da)).max() < 0.3
    poses = poses_from_markers(y, template)
    np.testing.assert_allclose(poses.R_world_local[2], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(template.mean(axis=0), 0.0, atol=1e-9)


def test_template_marker_order_and_rigid_transform() -> None:
    rng = np.random.default_rng(7)
    x = _cluster(rng, 4)
    y, _, _ = _motion(rng, x, 200, 0.5)
    y[rng.random(y.shape[:2]) < 0.1] = np.nan
    template = template_from_markers(y)
    perm = np.array([2, 0, 3, 1])
    np.testing.assert_allclose(template_from_markers(y[:, perm]), template[perm], atol=1e-8)
    Rg = Rotation.random(random_state=rng).as_matrix()
    dg = np.array([1000.0, -2000.0, 300.0])
    moved = y @ Rg.T + dg
    np.testing.assert_allclose(template_from_markers(moved), template @ Rg.T, atol=1e-8)
    np.testing.assert_allclose(template_from_markers(y * 1e-3), template * 1e-3, atol=1e-11)


def test_template_errors() -> None:
    rng = np.random.default_rng(8)
    x = _cluster(rng, 4)
    y, _, _ = _motion(rng, x, 20, 0.1)
    with pytest.raises(InputError, match="at least 3 marker"):
        template_from_markers(y[:, :2])
    y_never = y.copy()
    y_never[:, 3] = np.nan
    with pytest.raises(InputError, match=r"marker\(s\) \[3\] are never visible"):
        template_from_markers(y_never)
    y_lonely = y.copy()
    y_lonely[:, 3] = np.nan
    y_lonely[5, :3] = np.nan
    y_lonely[5, 3] = 1.0  # marker 3 only seen alone
    with pytest.raises(InputError, match="cannot be estimated"):
        template_from_markers(y_lonely)
    line = np.zeros((10, 3, 3))
    line[:, :, 0] = [0.0, 1.0, 2.0]
    with pytest.raises(InputError, match="non-collinear"):
        template_from_markers(line)
    with pytest.raises(InputError, match="max_iter"):
        template_from_markers(y, max_iter=0)
    with pytest.raises(InputError, match="tol"):
        template_from_markers(y, tol=-1.0)


# --------------------------------------------------------------------------- noise and covariances


def test_noise_std_from_fit_unbiased() -> None:
    rng = np.random.default_rng(9)
    x = _cluster(rng, 3, 60.0)
    s2 = []
    for _ in range(30):
        y, _, _ = _motion(rng, x, 300, 0.7)
        template = template_from_markers(y)
        s2.append(noise_std_from_fit(y, template) ** 2)
    # dof = 30 * (300 * 3 - 3): the mean of s2 / 0.49 has sd ~ sqrt(2 / dof) ~ 0.0086; 4 sd
    assert abs(np.mean(s2) / 0.49 - 1.0) < 0.035
    with pytest.raises(InputError, match="too few posed frames"):
        noise_std_from_fit(y[:1], template)


def test_noise_std_scales_with_units() -> None:
    rng = np.random.default_rng(10)
    x = _cluster(rng, 4)
    y, _, _ = _motion(rng, x, 50, 0.5)
    t_mm = template_from_markers(y)
    t_m = template_from_markers(y * 1e-3)
    assert noise_std_from_fit(y * 1e-3, t_m) == pytest.approx(1e-3 * noise_std_from_fit(y, t_mm), rel=1e-8)


def test_local_covariances_are_consistent() -> None:
    rng = np.random.default_rng(11)
    x = _cluster(rng, 4)
    vis = np.array([[True, True, True, True], [True, False, True, True], [True, True, False, False]])
    cov6 = pose_covariance_local(x, 0.8, vis)
    xbar, cov_rot, var_u = pose_noise_local(x, 0.8, vis)
    assert np.isnan(cov6[2]).all() and np.isnan(cov_rot[2]).all()  # two markers cannot be posed
    p = np.array([10.0, -400.0, 30.0])
    W = point_covariance_local(x, p, 0.8, vis)
    for k in range(2):
        a = p - xbar[k]
        expected = skew(a) @ cov_rot[k] @ skew(a).T + var_u[k] * np.eye(3)
        np.testing.assert_allclose(W[k], expected, rtol=1e-10)
        # Inertia form of the rotation covariance.
        xc = x[vis[k]] - x[vis[k]].mean(axis=0)
        inertia = (xc**2).sum() * np.eye(3) - xc.T @ xc
        np.testing.assert_allclose(cov_rot[k], 0.64 * np.linalg.inv(inertia), rtol=1e-10)
    full = pose_covariance_local(x, 0.8)
    assert full.shape == (6, 6)
    np.testing.assert_allclose(full[:3, 3:], 0.0, atol=1e-12)  # origin = centroid: independent
    with pytest.raises(InputError, match="noise_std"):
        pose_covariance_local(x, -1.0)
    with pytest.raises(InputError, match="point_local"):
        point_covariance_local(x, [1.0, 2.0], 1.0)
