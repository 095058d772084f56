"""Joints from minimal marker sets (jointfit_core.minimal; Pham et al. sections III-A, IV-C, V-A).

Synthetic rigs from :func:`jointfit_core.synthetic.minimal_marker_motion`: two
links with 1-3 markers about 300 mm apart, the joint 300 mm from each link's
markers, the parent wandering while the child rotates about the joint.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import random_rigid, transform
from numpy.typing import NDArray

from jointfit_core import fit_axis_minimal, fit_centre_minimal, r21_closed_form, s22_closed_form
from jointfit_core.errors import InputError, NotIdentifiableError
from jointfit_core.results import MinimalAxisFit
from jointfit_core.synthetic import TwoSegmentMotion, minimal_marker_motion

FloatArray = NDArray[np.float64]
SIGMA = 1.7 / np.sqrt(3.0)  # per coordinate: sqrt(tr W_y) = 1.7 mm (Stoddart's rig)
CHI2_999 = {2: 13.8, 3: 16.3, 4: 18.5, 5: 20.5}  # 99.9 % quantiles


def _rig(
    seed: int, kind: str = "ball", n_markers: tuple[int, int] = (2, 2), n_frames: int = 200, sigma: float = SIGMA
) -> tuple[TwoSegmentMotion, FloatArray, FloatArray, FloatArray]:
    """A rig, its times and noisy parent and child markers."""
    rng = np.random.default_rng(seed)
    rig = minimal_marker_motion(rng, kind=kind, n_markers=n_markers)
    times = np.linspace(0.0, 20.0, n_frames)
    yp, yc = rig.markers_at(times)
    return rig, times, yp + rng.normal(0.0, sigma, yp.shape), yc + rng.normal(0.0, sigma, yc.shape)


def _true_distances(rig: TwoSegmentMotion) -> FloatArray:
    return np.concatenate(
        [
            np.linalg.norm(rig.template_parent - rig.centre_parent, axis=1),
            np.linalg.norm(rig.template_child - rig.centre_child, axis=1),
        ]
    )


def _true_axis(rig: TwoSegmentMotion, times: FloatArray) -> tuple[FloatArray, FloatArray]:
    """World (point, direction) of the true hinge per frame."""
    R_p, d_p, _, _ = rig.poses_at(times)
    return np.einsum("nij,j->ni", R_p, rig.centre_parent) + d_p, np.einsum("nij,j->ni", R_p, rig.axis)


def _true_hinge_constants(rig: TwoSegmentMotion, sign: float) -> FloatArray:
    """Marker radii from the axis and axial offsets vs marker 0 (along sign * axis), from the local frames."""
    local = np.concatenate([rig.template_parent - rig.centre_parent, rig.template_child - rig.centre_child])
    n = sign * rig.axis
    h = local @ n
    radii = np.linalg.norm(local - h[:, None] * n, axis=1)
    return np.concatenate([radii, h[1:] - h[0]])


def _hinge_errors(fit: MinimalAxisFit, rig: TwoSegmentMotion, times: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Errors of the constants, per-frame direction angles (rad) and point distances from the true axis."""
    point, direction = _true_axis(rig, times)
    sign = float(np.sign(np.nanmean(np.einsum("ni,ni->n", fit.direction_world, direction))))
    err = np.concatenate([fit.radii, fit.offsets]) - _true_hinge_constants(rig, sign)
    angle = np.arccos(np.clip(np.abs(np.einsum("ni,ni->n", fit.direction_world, direction)), 0.0, 1.0))
    w = fit.point_world - point
    off_axis = np.linalg.norm(w - np.einsum("ni,ni->n", w, direction)[:, None] * direction, axis=1)
    return err, angle, off_axis


def _e(err: FloatArray, cov: FloatArray) -> float:
    return float(err @ np.linalg.solve(cov, err))


# --------------------------------------------------------------------------- ball joint, S22 / S31


def test_s22_noise_free_is_exact() -> None:
    rig, times, yp, yc = _rig(1, n_frames=60, sigma=0.0)
    fit = fit_centre_minimal(yp, yc)
    assert fit.method == "S22" and fit.identifiable, fit.reason
    np.testing.assert_allclose(fit.distances, _true_distances(rig), atol=1e-6)
    np.testing.assert_allclose(fit.centre_world, rig.centre_world_at(times), atol=1e-6)
    # Pair frame: axial coordinate from parent marker 0 towards marker 1 and the distance from that line.
    a0, a1 = rig.template_parent - rig.centre_parent
    u = (a1 - a0) / np.linalg.norm(a1 - a0)
    axial = float((-a0) @ u)
    np.testing.assert_allclose(fit.centre_parent, [axial, np.sqrt(a0 @ a0 - axial**2)], atol=1e-6)
    assert fit.rms < 1e-6


def test_s22_closed_form_noise_free() -> None:
    """Section IV-C's linear system (re-derived, 9 unknowns after eliminating d^2) is exact without noise."""
    rig, _, yp, yc = _rig(2, n_frames=40, sigma=0.0)
    d, r, rho1, rho2 = s22_closed_form(yp, yc)
    a = _true_distances(rig)
    length = float(np.linalg.norm(rig.template_parent[1] - rig.template_parent[0]))
    np.testing.assert_allclose([np.hypot(d, r), np.hypot(length - d, r), rho1, rho2], a, rtol=1e-7)


def test_s22_recovers_the_centre_within_its_covariance() -> None:
    rig, times, yp, yc = _rig(3, n_frames=300)
    fit = fit_centre_minimal(yp, yc)  # global start search (closed form + grid)
    assert fit.identifiable, fit.reason
    assert _e(fit.distances - _true_distances(rig), fit.cov) < CHI2_999[4]
    assert fit.noise_std == pytest.approx(SIGMA, rel=0.15)
    err = fit.centre_world - rig.centre_world_at(times)
    e_world = np.einsum("ni,ni->n", err, np.linalg.solve(fit.cov_world, err[..., None])[..., 0])
    assert np.nanmean(e_world) / 3 == pytest.approx(1.0, abs=0.3)
    assert np.nanmedian(np.linalg.norm(err, axis=1)) < 10.0
    np.testing.assert_allclose(fit.cov, fit.cov.T)
    assert np.all(np.linalg.eigvalsh(fit.cov) > 0)
    assert fit.n_frames <= 300 and fit.rms == pytest.approx(float(np.sqrt(np.mean(fit.residual[np.isfinite(fit.residual)] ** 2))), rel=0.5)


def test_s22_covariance_calibration() -> None:
    """Mean of e/4 over 100 seeded random rigs (100 frames, 1 mm noise), started near the truth."""
    rng = np.random.default_rng(11)
    values = []
    for _ in range(100):
        rig = minimal_marker_motion(rng, kind="ball", n_markers=(2, 2))
        times = np.linspace(0.0, 20.0, 100)
        yp, yc = rig.markers_at(times)
        yp = yp + rng.normal(0.0, SIGMA, yp.shape)
        yc = yc + rng.normal(0.0, SIGMA, yc.shape)
        a_true = _true_distances(rig)
        fit = fit_centre_minimal(yp, yc, initial_distances=a_true + rng.normal(0.0, 1.0, 4))
        values.append(_e(fit.distances - a_true, fit.cov) / 4)
    mean = float(np.mean(values))
    assert 0.75 <= mean <= 1.3, f"mean e/4 = {mean:.3f}"


def test_s31_three_plus_one() -> None:
    rig, times, yp, yc = _rig(4, n_markers=(3, 1), n_frames=200)
    fit = fit_centre_minimal(yp, yc)
    assert fit.method == "S31" and fit.identifiable, fit.reason
    assert _e(fit.distances - _true_distances(rig), fit.cov) < CHI2_999[4]
    assert np.isnan(fit.centre_child).all()  # a single child marker has no pair frame
    assert np.isfinite(fit.centre_parent).all()
    assert np.nanmedian(np.linalg.norm(fit.centre_world - rig.centre_world_at(times), axis=1)) < 5.0


def test_s22_rigid_transform_equivariance() -> None:
    rng = np.random.default_rng(5)
    _, _, yp, yc = _rig(5, n_frames=150)
    R, t = random_rigid(rng)
    a = fit_centre_minimal(yp, yc)
    b = fit_centre_minimal(transform(yp, R, t), transform(yc, R, t))
    np.testing.assert_allclose(b.distances, a.distances, atol=1e-4)
    np.testing.assert_allclose(b.centre_parent, a.centre_parent, atol=1e-4)
    np.testing.assert_allclose(b.cov, a.cov, rtol=1e-3, atol=1e-9)
    np.testing.assert_allclose(b.centre_world, a.centre_world @ R.T + t, atol=1e-3)
    np.testing.assert_allclose(b.cov_world, R @ a.cov_world @ R.T, rtol=1e-3, atol=1e-6)


def test_s22_units_scale() -> None:
    _, _, yp, yc = _rig(6, n_frames=150)
    mm = fit_centre_minimal(yp, yc)
    m = fit_centre_minimal(yp / 1000.0, yc / 1000.0)
    np.testing.assert_allclose(m.distances, mm.distances / 1000.0, rtol=1e-6)
    np.testing.assert_allclose(m.cov, mm.cov / 1e6, rtol=1e-4)
    np.testing.assert_allclose(m.centre_world, mm.centre_world / 1000.0, rtol=1e-6, atol=1e-9)
    assert m.noise_std == pytest.approx(mm.noise_std / 1000.0, rel=1e-6)


def test_s22_nan_frames_are_ignored() -> None:
    _, _, yp, yc = _rig(7, n_frames=150)
    gaps = np.zeros(150, dtype=bool)
    gaps[[3, 40, 41, 99]] = True
    yp_nan = yp.copy()
    yp_nan[gaps, 1, 0] = np.nan  # one coordinate of one marker
    yc_nan = yc.copy()
    yc_nan[5, 0] = np.nan
    gaps[5] = True
    fit = fit_centre_minimal(yp_nan, yc_nan)
    ref = fit_centre_minimal(yp[~gaps], yc[~gaps])
    np.testing.assert_allclose(fit.distances, ref.distances, rtol=1e-9)
    assert np.isnan(fit.centre_world[gaps]).all() and np.isfinite(fit.centre_world[~gaps]).all()
    np.testing.assert_allclose(fit.centre_world[~gaps], ref.centre_world, atol=1e-9)


def test_s22_without_relative_rotation_raises() -> None:
    _, _, yp, yc = _rig(8, kind="none", n_frames=60, sigma=0.0)
    with pytest.raises(NotIdentifiableError, match="rotate the child"):
        fit_centre_minimal(yp, yc)


def test_ball_joint_bad_input() -> None:
    _, _, yp, yc = _rig(9, n_frames=40)
    with pytest.raises(NotIdentifiableError, match="IV-B"):
        fit_centre_minimal(yp, yc[:, :1])  # (2, 1)
    with pytest.raises(InputError, match=r"shape \(N, P, 3\)"):
        fit_centre_minimal(yp[..., :2], yc)
    with pytest.raises(InputError, match="same number of frames"):
        fit_centre_minimal(yp, yc[:-1])
    with pytest.raises(InputError, match="inf"):
        bad = yp.copy()
        bad[0, 0, 0] = np.inf
        fit_centre_minimal(bad, yc)
    with pytest.raises(InputError, match="at least 10 frames"):
        fit_centre_minimal(yp[:9], yc[:9])
    with pytest.raises(InputError, match="initial_distances"):
        fit_centre_minimal(yp, yc, initial_distances=[1.0, 2.0, 3.0])
    with pytest.raises(InputError, match="shapes"):
        s22_closed_form(yp, yc[:, :1])


# --------------------------------------------------------------------------- hinge, R21


def test_r21_closed_form_has_two_exact_roots() -> None:
    """Eq. (7)-(13): without noise one root is the true hinge, and the other admissible root fits eq. (7) exactly too."""
    rig, _, yp, yc = _rig(1, kind="hinge", n_markers=(2, 1), n_frames=50, sigma=0.0)
    rows = r21_closed_form(yp, yc)
    assert rows.shape == (2, 5)
    # True DH constants from the local frames, with the axis oriented along the pair (cos alpha >= 0).
    a0, a1 = rig.template_parent
    u = (a1 - a0) / np.linalg.norm(a1 - a0)
    n = rig.axis if u @ rig.axis >= 0 else -rig.axis
    w0 = a0 - rig.centre_parent
    b, du, dn = u @ n, u @ w0, n @ w0
    s = (b * dn - du) / (1 - b * b)  # the common perpendicular: a0 + s u and centre + t n
    t = (dn - b * du) / (1 - b * b)
    r = np.linalg.norm(rig.centre_parent + t * n - (a0 + s * u))
    x_b = rig.template_child[0] - rig.centre_child
    rho = np.linalg.norm(x_b - (x_b @ n) * n)
    truth = np.array([s, r, np.arccos(b), x_b @ n - t, rho])
    assert np.min(np.max(np.abs(rows - truth), axis=1)) < 1e-6
    # Both roots satisfy eq. (7) at every sample.
    v = yc[:, 0] - yp[:, 0]
    z = np.einsum("ni,ni->n", v, (yp[:, 1] - yp[:, 0]) / np.linalg.norm(yp[:, 1] - yp[:, 0], axis=1)[:, None])
    R2 = np.einsum("ni,ni->n", v, v)
    M = np.stack([-4 * R2 * z, 2 * R2, -4 * z, np.ones_like(z), 4 * z * z], axis=1)
    for d, rr, alpha, l, rh in rows:
        sa, ca = np.sin(alpha), np.cos(alpha)
        Q = rr * rr + d * d - l * l - rh * rh
        Y = [d, Q - 2 * rr * rr, Q * d + 2 * rr * rr * ca * (l + d * ca) / sa**2, Q * Q + 4 * rr * rr * (l + d * ca) ** 2 / sa**2, d * d + rr * rr / sa**2]
        np.testing.assert_allclose(M @ Y, -R2 * R2, rtol=1e-8)


def test_r21_noise_free_four_solutions_and_the_hint_picks_the_truth() -> None:
    rig, times, yp, yc = _rig(1, kind="hinge", n_markers=(2, 1), n_frames=60, sigma=0.0)
    _, direction = _true_axis(rig, times)
    fit = fit_axis_minimal(yp, yc, axis_hint=direction)
    assert fit.method == "R21" and fit.n_solutions == 4
    assert fit.identifiable, fit.reason
    err, angle, off_axis = _hinge_errors(fit, rig, times)
    assert np.max(np.abs(err)) < 1e-6 and angle.max() < 1e-6 and off_axis.max() < 1e-6
    np.testing.assert_allclose(np.linalg.norm(fit.direction_world, axis=1), 1.0)
    # point_world is the centre of the single marker's circle: on the axis, in the marker's plane.
    w = yc[:, 0] - fit.point_world
    np.testing.assert_allclose(np.einsum("ni,ni->n", w, fit.direction_world), 0.0, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(w, axis=1), fit.radii[2], rtol=1e-8)
    # Without a hint the ambiguity is reported.
    plain = fit_axis_minimal(yp, yc)
    assert not plain.identifiable and "axis_hint" in plain.reason and plain.n_solutions == 4


def test_r21_low_noise_within_covariance() -> None:
    rig, times, yp, yc = _rig(1, kind="hinge", n_markers=(2, 1), n_frames=200, sigma=0.3)
    fit = fit_axis_minimal(yp, yc, axis_hint=_true_axis(rig, times)[1])
    assert fit.identifiable, fit.reason
    err, angle, _ = _hinge_errors(fit, rig, times)
    assert _e(err, fit.cov) < CHI2_999[5]
    assert fit.noise_std == pytest.approx(0.3, rel=0.2)
    sd_dir = np.sqrt(np.linalg.eigvalsh(fit.cov_direction_world)[:, -1])
    assert np.median(angle / sd_dir) < 3.0
    assert np.abs(fit.cov_direction_world @ fit.direction_world[..., None]).max() < 1e-12  # rank 2, orthogonal
    np.testing.assert_allclose(fit.cov_dh, fit.cov_dh.T, atol=1e-12)


def test_r21_covariance_calibration() -> None:
    """Mean of e/5 over 100 noise draws on a well-conditioned rig (100 frames, 0.3 mm noise)."""
    rig, times, _, _ = _rig(1, kind="hinge", n_markers=(2, 1), n_frames=100, sigma=0.0)
    yp0, yc0 = rig.markers_at(times)
    hint = _true_axis(rig, times)[1]
    rng = np.random.default_rng(2024)
    values = []
    for _ in range(100):
        fit = fit_axis_minimal(yp0 + rng.normal(0.0, 0.3, yp0.shape), yc0 + rng.normal(0.0, 0.3, yc0.shape), axis_hint=hint)
        err, _, _ = _hinge_errors(fit, rig, times)
        values.append(_e(err, fit.cov) / 5)
    mean = float(np.mean(values))
    assert 0.75 <= mean <= 1.3, f"mean e/5 = {mean:.3f}"


def test_r21_rigid_transform_equivariance_and_units() -> None:
    rng = np.random.default_rng(12)
    rig, times, yp, yc = _rig(1, kind="hinge", n_markers=(2, 1), n_frames=120, sigma=0.3)
    hint = _true_axis(rig, times)[1]
    R, t = random_rigid(rng)
    a = fit_axis_minimal(yp, yc, axis_hint=hint)
    b = fit_axis_minimal(transform(yp, R, t), transform(yc, R, t), axis_hint=hint @ R.T)
    np.testing.assert_allclose(b.radii, a.radii, atol=1e-5)
    np.testing.assert_allclose(b.offsets, a.offsets, atol=1e-5)
    np.testing.assert_allclose(b.cov, a.cov, rtol=1e-4, atol=1e-10)
    np.testing.assert_allclose(b.point_world, a.point_world @ R.T + t, atol=1e-5)
    np.testing.assert_allclose(b.direction_world, a.direction_world @ R.T, atol=1e-8)
    np.testing.assert_allclose(b.cov_direction_world, R @ a.cov_direction_world @ R.T, atol=1e-12)
    m = fit_axis_minimal(yp / 1000.0, yc / 1000.0, axis_hint=hint)
    np.testing.assert_allclose(m.radii, a.radii / 1000.0, rtol=1e-6)
    np.testing.assert_allclose(m.cov, a.cov / 1e6, rtol=1e-4)
    np.testing.assert_allclose(m.dh[[0, 1, 3, 4]], a.dh[[0, 1, 3, 4]] / 1000.0, rtol=1e-6)
    assert m.dh[2] == pytest.approx(a.dh[2], abs=1e-8)


def test_r21_swapped_links_and_nan_frames() -> None:
    rig, times, yp, yc = _rig(1, kind="hinge", n_markers=(2, 1), n_frames=120, sigma=0.3)
    hint = _true_axis(rig, times)[1]
    fit = fit_axis_minimal(yp, yc, axis_hint=hint)
    swapped = fit_axis_minimal(yc, yp, axis_hint=hint)  # (1, 2): the single marker is now the parent
    np.testing.assert_allclose(swapped.radii, fit.radii[[2, 0, 1]], atol=1e-4)
    np.testing.assert_allclose(swapped.point_world, fit.point_world, atol=1e-4)
    np.testing.assert_allclose(np.abs(np.einsum("ni,ni->n", swapped.direction_world, fit.direction_world)), 1.0, atol=1e-9)
    gaps = np.zeros(120, dtype=bool)
    gaps[[0, 7, 60]] = True
    yc_nan = yc.copy()
    yc_nan[gaps, 0, 2] = np.nan
    holed = fit_axis_minimal(yp, yc_nan, axis_hint=hint)
    ref = fit_axis_minimal(yp[~gaps], yc[~gaps], axis_hint=hint[~gaps])
    assert holed.n_frames == 117
    np.testing.assert_allclose(holed.radii, ref.radii, rtol=1e-9)
    assert np.isnan(holed.point_world[gaps]).all() and np.isnan(holed.residual[gaps]).all()


def test_hinge_bad_input() -> None:
    _, _, yp, yc = _rig(9, kind="hinge", n_markers=(2, 1), n_frames=40)
    with pytest.raises(NotIdentifiableError, match="III-B"):
        fit_axis_minimal(yp[:, :1], yc)  # (1, 1)
    with pytest.raises(InputError, match="fit_axis"):
        fit_axis_minimal(np.concatenate([yp, yp[:, :1] + 50.0], axis=1), yc)  # (3, 1)
    with pytest.raises(InputError, match="axis_hint"):
        fit_axis_minimal(yp, yc, axis_hint=[1.0, 0.0])
    with pytest.raises(InputError, match="axis_hint"):
        fit_axis_minimal(yp, yc, axis_hint=[0.0, 0.0, 0.0])
    with pytest.raises(InputError, match="at least 6 frames"):
        fit_axis_minimal(yp[:5], yc[:5])
    with pytest.raises(InputError, match="shapes"):
        r21_closed_form(yp, yp)
