"""The online soft-tissue prior's hinge reading from sums (:mod:`jointfit_core.artefact_sums`, issue 17).

The axis-alignment residual ``Q_t n_c - n_p`` of a hinge is read on the columns of a cluster turn that
follows the hinge angle (projected, as the batch fit reads its scale), from the features' second
moments in the sums. Checked against the explicit per-frame columns, and by Monte Carlo on hinges
whose clusters turn by a prior of known scale: with the hinge angle (the model) the reading is
unbiased; with another joint's angles (outside the model, as a thigh cluster moving with the hip
on a skeleton) it reads almost nothing (4 % of the scale here, where the energy ratio it replaces read 3.4
times the scale).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from jointfit_core import artefact_sums as sums_mod

FloatArray = NDArray[np.float64]
#: Rms radii of the two clusters (mm) and the hinge's axis points (mm) in the Monte Carlo.
RADII = (80.0, 60.0)
C_P, C_C = np.array([0.0, 0.0, -400.0]), np.array([0.0, 0.0, 20.0])


def _hinge(rng: np.random.Generator, n: int, rate: float) -> FloatArray:
    """Relative rotations (n, 3, 3) of a hinge flexing 0-90 deg in 2.5 s cycles about a random axis."""
    t = np.arange(n) / rate
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    theta = np.pi / 4.0 * (1.0 - np.cos(2.0 * np.pi * t / 2.5 + rng.uniform(0.0, 2.0 * np.pi)))
    out: FloatArray = Rotation.from_rotvec(theta[:, None] * axis).as_matrix()
    return out


def _reading(Q: FloatArray, white: float) -> tuple[float, float]:
    """The alignment reading's ``(s^2, nu)`` for measured relative rotations, as ``artefact_from_sums`` forms it."""
    n = Q.shape[0]
    t = C_P - Q @ C_C
    fs = sums_mod.feature_sums(Q, t, moments=True).sum(axis=0)
    S, st, sqt = Q.sum(axis=0), t.sum(axis=0), np.einsum("nji,nj->i", Q, t)
    ref = np.linalg.svd(S)[0][:, 0]

    def solver(X: FloatArray) -> FloatArray:
        return sums_mod.hinge_parameters(float(n), X[:, :9].reshape(-1, 3, 3), X[:, 9:12], X[:, 12:], ref)

    x0 = np.concatenate([S.ravel(), st, sqt])
    params = solver(x0[None])[0]
    n_p, n_c = params[:3], params[3:6]
    SQ, ST, SP, _ = sums_mod._centred(fs, float(n), S, st, sqt)
    delta = sums_mod._sum_perturbations(SQ, ST, SP).reshape(15, 108)
    length = max(float(np.linalg.norm(st)) / n, float(np.linalg.norm(sqt)) / n, max(RADII))
    steps = np.concatenate([np.full(9, float(n)), np.full(6, n * length)])
    dn = (sums_mod._jacobian(solver, x0, steps) @ delta)[:6, np.r_[0:27, 54:81]]
    ss = float(np.sum((Q @ n_c - n_p) ** 2))
    var = (1.0 / RADII[0] ** 2, 1.0 / RADII[1] ** 2)
    return sums_mod._rotation_moments(fs, float(n), S, SQ, (n_p, n_c), dn, var, ss, ss - white)


def test_second_moments_from_sums_equal_the_direct_ones() -> None:
    rng = np.random.default_rng(3)
    Q = Rotation.from_rotvec(rng.normal(0.0, 0.7, (60, 3))).as_matrix()
    t = rng.normal(0.0, 200.0, (60, 3))
    fs = sums_mod.feature_sums(Q, t, moments=True).sum(axis=0)
    F, M = sums_mod._centred_moments(fs, 60.0, Q.sum(axis=0))
    f = sums_mod.rotation_features(Q)
    fc = f - f.mean(axis=0)
    np.testing.assert_allclose(F, fc.T @ fc, atol=1e-10 * float(np.abs(F).max()))
    np.testing.assert_allclose(M, np.einsum("na,nb,nij->abij", fc, fc, Q), atol=1e-10 * float(np.abs(M).max()))


def test_alignment_reading_is_the_projection_on_the_per_frame_columns() -> None:
    """The sums give the moment estimate of the explicit columns (hinge-angle plane, refit included)."""
    rng = np.random.default_rng(11)
    n = 300
    Q = Rotation.from_rotvec(rng.normal(0.0, 0.02, (n, 3))).as_matrix() @ _hinge(rng, n, 25.0)
    n_p = np.linalg.svd(Q.sum(axis=0))[0][:, 0]
    n_c = np.linalg.svd(Q.sum(axis=0))[2][0]
    fs = sums_mod.feature_sums(Q, np.zeros((n, 3)), moments=True).sum(axis=0)
    S = Q.sum(axis=0)
    SQ = sums_mod._centred(fs, float(n), S, np.zeros(3), np.zeros(3))[0]
    dn = rng.normal(0.0, 1e-3, (6, 54))
    var = (0.7, 1.3)
    got, nu = sums_mod._rotation_moments(fs, float(n), S, SQ, (n_p, n_c), dn, var, 0.0, 0.0)
    # explicit columns over the frames: features in the plane of the two leading directions
    f = sums_mod.rotation_features(Q)
    fc = f - f.mean(axis=0)
    V = np.linalg.eigh(fc.T @ fc)[1][:, ::-1][:, :2]
    h = fc @ V
    Qn = Q @ n_c
    cols = []
    for side in range(2):
        for j in range(3):
            e = np.eye(3)[j]
            d = np.cross(Qn, e) if side == 0 else -(Q @ np.cross(n_c, e))
            for k in range(2):
                dn_jk = dn[:, side * 27 + j * 9 : side * 27 + j * 9 + 9] @ V[:, k]
                refit = Q @ dn_jk[3:] - dn_jk[:3]
                cols.append((h[:, [k]] * d + refit).ravel() * np.sqrt(var[side]))
    C = np.stack(cols, axis=1)
    rho = (Qn - n_p).ravel()
    lam = np.linalg.eigvalsh(C.T @ C)
    want = float((C.T @ rho) @ (C.T @ rho)) / float(lam @ lam)
    assert got > 0.0
    # [Q n_c]x is taken as [n_p]x in the Gram: equal up to the 1-deg wobble off the axis
    assert abs(got - want) < 1e-3 * want, (got, want)
    assert abs(nu - float(lam @ lam) ** 2 / float(np.sum(lam**4))) < 1e-3 * nu


def _turned(rng: np.random.Generator, Q: FloatArray, f: FloatArray, s: float, sigma: float) -> FloatArray:
    """``Q`` with each cluster turned by ``G f_t`` (entries ``N(0, (s / r)^2)``) and white turns of ``sigma`` rad."""
    fc = f - f.mean(axis=0)
    w = [fc @ rng.normal(0.0, s / r, (3, 9)).T + rng.normal(0.0, sigma, (Q.shape[0], 3)) for r in RADII]
    out: FloatArray = Rotation.from_rotvec(-w[0]).as_matrix() @ Q @ Rotation.from_rotvec(w[1]).as_matrix()
    return out


def test_alignment_reading_is_unbiased_in_the_model_and_blind_outside_it() -> None:
    """Monte Carlo, known scale: turns following the hinge angle are read at their size (mean s^2 within
    3 sd of the truth), turns following another joint's angles (three components at other periods, as
    large) are not (under 15 %); the white part (known here) is subtracted."""
    rng = np.random.default_rng(5)
    n, rate, s, sigma = 500, 25.0, 3.0, 0.003
    white = 4.0 * n * sigma**2  # two in-plane components, each from both clusters' white turns
    inside, outside = [], []
    for _ in range(60):
        Q = _hinge(rng, n, rate)
        inside.append(_reading(_turned(rng, Q, sums_mod.rotation_features(Q), s, sigma), white)[0] / s**2)
        t = np.arange(n) / rate
        other = np.stack([0.4 * np.sin(2.0 * np.pi * t / p + rng.uniform(0.0, 6.3)) for p in (3.3, 4.1, 5.7)], axis=1)
        f_other = sums_mod.rotation_features(Rotation.from_rotvec(other).as_matrix())
        outside.append(_reading(_turned(rng, Q, f_other, s, sigma), white)[0] / s**2)
    mean, sd_mean = float(np.mean(inside)), float(np.std(inside, ddof=1)) / np.sqrt(len(inside))
    assert abs(mean - 1.0) < 3.0 * sd_mean, (mean, sd_mean)
    assert float(np.mean(outside)) < 0.15, float(np.mean(outside))


def test_ball_parameters_jacobian_is_the_derivative_of_the_ball_solution() -> None:
    """The analytic Jacobian of eq. 9's centre pair equals central differences (it replaced them in every skin solve)."""
    rng = np.random.default_rng(4)
    Q = Rotation.from_rotvec(rng.normal(scale=0.4, size=(300, 3))).as_matrix()
    t = C_P - Q @ C_C + rng.normal(scale=2.0, size=(300, 3))
    n = float(Q.shape[0])
    S, st, sqt = Q.sum(axis=0), t.sum(axis=0), np.einsum("nji,nj->i", Q, t)
    x0 = np.concatenate([S.ravel(), st, sqt])

    def solver(X: FloatArray) -> FloatArray:
        return np.stack([sums_mod.ball_parameters(n, x[:9].reshape(3, 3), x[9:12], x[12:]) for x in X])

    steps = np.concatenate([np.full(9, n), np.full(6, n * 400.0)])
    numeric = sums_mod._jacobian(solver, x0, steps)
    analytic = sums_mod.ball_parameters_jacobian(n, S, st, sqt)
    assert analytic.shape == (6, 15)
    np.testing.assert_allclose(analytic, numeric, rtol=1e-6, atol=1e-9 * float(np.abs(numeric).max()))
    # and the solution it differentiates is eq. 9's, about the true centre pair
    np.testing.assert_allclose(solver(x0[None])[0], np.concatenate([C_P, C_C]), atol=1.0)
