"""Issue 17: the literature prior on the soft-tissue artefact's scale (artefact.py, eq. A6).

The scale of the prior on each skin cluster's rigid motion is read from the residuals along a few
effective directions (2-3.5). A draw whose rigid motion left almost no residual then read a scale
near zero, and the estimate came out many sd off while called identifiable: measured before this
prior, the batch hip centre of one seeded 25 deg trial of ``bench/sta.py``'s model at e/3 = 24.7
(20 mm off, sd 5.5 mm), at 8 deg of range e/3 = 72 (54 mm off, sd 10 mm); online, a hip at 8 deg
e/3 = 15.5 and a knee at 20 deg e/2 = 16.8 (21.7 deg off, sd 5.1 deg; ``bench/sta_rom.py``).
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import template_rotation, truth_in_template
from scipy.stats import chi2

from jointfit_core.artefact import PRIOR_NU, RIGID_SHARE, _prior_variances, posterior_scale2, prior_scale2
from jointfit_core.estimator import OnlineJoint
from jointfit_core.segments import fit_centre_two_segments
from jointfit_core.soft_tissue import hip_motion, knee_motion, skin_markers_at

RATE = 100.0
#: "Many sd off": the truth outside the published covariance's 99.9 % ellipsoid (e/k above this).
E3_OUT = float(chi2.ppf(0.999, 3)) / 3.0  # 5.4
E2_OUT = float(chi2.ppf(0.999, 2)) / 2.0  # 6.9


def test_posterior_is_the_conjugate_update() -> None:
    s2, nu = posterior_scale2(2.0, 3.0, 5.0)
    assert nu == pytest.approx(PRIOR_NU + 3.0)
    assert s2 == pytest.approx((PRIOR_NU * 5.0 + 3.0 * 2.0) / (PRIOR_NU + 3.0))
    assert posterior_scale2(2.0, 3.0, 0.0) == (2.0, 3.0)  # no prior (rigid, no deformation)
    assert posterior_scale2(2.0, float("inf"), 5.0) == (2.0, float("inf"))  # the data fix the scale
    # a reading far below the prior is pulled up to at least PRIOR_NU / (PRIOR_NU + nu) of it
    low, _ = posterior_scale2(1e-6, 3.0, 5.0)
    assert low >= PRIOR_NU / (PRIOR_NU + 3.0) * 5.0


@pytest.mark.parametrize("n_markers", [3, 4, 6])
def test_prior_expects_the_rigid_share_of_the_deformation_it_sees(n_markers: int) -> None:
    """A rigid motion at the prior's scale moves the markers rho^2 times as much as the deformation does.

    Deformation with no rigid part (mean square ``a^2`` per marker) leaves the pose-fit residual
    variance ``w`` per degree of freedom (the weight); the prior's rigid motion at ``s_0^2 w`` per unit
    feature, drawn as :func:`_prior_variances` says, over features of mean square ``F``.
    """
    rng = np.random.default_rng(n_markers)
    x = rng.normal(0.0, 60.0, (n_markers, 3))
    x -= x.mean(axis=0)
    r = float(np.sqrt(np.mean(np.sum(x**2, axis=1))))
    # a deformation without rigid part: remove the small rigid motions (omega x x + u) by least squares
    modes = np.concatenate([np.stack([np.cross(np.eye(3)[k], x) for k in range(3)], axis=-1),
                            np.broadcast_to(np.eye(3), (n_markers, 3, 3))], axis=-1).reshape(3 * n_markers, 6)
    delta = rng.normal(0.0, 4.0, 3 * n_markers)
    delta -= modes @ np.linalg.lstsq(modes, delta, rcond=None)[0]
    w = float(delta @ delta) / (3 * n_markers - 6)  # the residual variance per dof a rigid pose fit leaves
    feature_ms = 0.07
    s02 = prior_scale2(n_markers, feature_ms) * w
    var = _prior_variances(x) * s02 * feature_ms  # (omega, u) per frame
    draws = rng.normal(size=(20000, 6)) * np.sqrt(var)
    moved = np.cross(draws[:, None, :3], x[None]) + draws[:, None, 3:]
    rigid_ms = float(np.mean(np.sum(moved**2, axis=2)))
    rho2 = RIGID_SHARE**2 / (1.0 - RIGID_SHARE**2)
    assert r > 0.0
    assert rigid_ms == pytest.approx(rho2 * float(delta @ delta) / n_markers, rel=0.03)


def test_no_prior_without_movement_or_markers() -> None:
    assert prior_scale2(4, 0.0) == 0.0
    assert prior_scale2(2, 0.1) == 0.0


def _batch_hip(seed_index: int, n_trials: int, amplitude: float) -> tuple[float, bool]:
    rng = np.random.default_rng(np.random.SeedSequence(777).spawn(n_trials)[seed_index])
    noise = float(rng.uniform(0.5, 1.0))
    motion = hip_motion(rng, amplitude_deg=amplitude)
    t = np.arange(3000) / RATE
    p, c = skin_markers_at(rng, motion, t, child_mm=10.0, noise_std=noise)
    fit = fit_centre_two_segments(p, c, attachment="skin")
    delta = fit.centre_parent - truth_in_template(motion.template_parent, fit.template_parent, motion.centre_parent)
    return float(delta @ np.linalg.solve(fit.cov_parent, delta) / 3.0), bool(fit.identifiable)


def test_a_batch_hip_whose_artefact_left_little_residual_is_not_many_sd_off() -> None:
    """The seeded 25 deg trial that read its scale 40x below the prior: e/3 24.7 before."""
    e, identifiable = _batch_hip(16, 30, 25.0)
    assert identifiable
    assert e < E3_OUT, e


def test_small_range_batch_hips_stay_within_their_covariance() -> None:
    """Twenty seeded hips at 8 deg of range, 10 mm of thigh artefact: none called identifiable many sd off.

    Before the prior the worst was e/3 = 72 (54 mm off, sd 10 mm), the mean 4.6.
    """
    rows = [_batch_hip(k, 20, 8.0) for k in range(20)]
    worst = max(e for e, ok in rows if ok)
    assert worst < E3_OUT, rows
    assert 0.3 < float(np.mean([e for e, _ in rows])) < 2.0, rows


def test_online_knee_whose_scale_read_low_is_not_confidently_wrong() -> None:
    """The seeded 20 deg knee read its scale 80x below the others: 21.7 deg off with an sd of 5.1 deg before."""
    rng = np.random.default_rng(np.random.SeedSequence(777).spawn(40)[11])
    noise = float(rng.uniform(0.5, 1.0))
    motion = knee_motion(rng, amplitude_deg=20.0)
    t = np.arange(2000) / RATE
    p, c = skin_markers_at(rng, motion, t, child_mm=10.0, noise_std=noise)
    est = OnlineJoint("hinge", window=t.size + 10, attachment="skin")
    est.update_many(p, c, t)
    sol = est.estimate()
    tp = est.templates[0]
    assert tp is not None
    n_true = template_rotation(motion.template_parent, tp) @ motion.axis
    n_true = n_true if float(n_true @ sol.direction_parent) >= 0.0 else -n_true
    delta = sol.direction_parent - n_true
    e = float(delta @ np.linalg.pinv(sol.cov_direction_parent) @ delta) / 2.0
    error_deg = float(np.degrees(np.arccos(np.clip(abs(sol.direction_parent @ n_true), -1.0, 1.0))))
    assert error_deg > 10.0  # not vacuous: the artefact did move this knee's axis far
    assert not sol.identifiable or e < E2_OUT, (e, error_deg)


@pytest.mark.parametrize("rigid_share", [1.0, 0.75])
def test_the_prior_only_adds_caution(monkeypatch: pytest.MonkeyPatch, rigid_share: float) -> None:
    """A cluster moving rigidly on the bone without deforming (a plate) says nothing about the scale: unchanged.

    The prior is tied to the deformation the residuals show; where that is small (a strapped plate,
    ``rigid_share`` 1) a conjugate update would pull the reading towards zero. It is used only where
    it widens the covariance, so that no estimate is more confident with it than without it.
    """
    import jointfit_core.artefact as artefact

    rng = np.random.default_rng(7)
    motion = hip_motion(rng)
    t = np.arange(2000) / RATE
    p, c = skin_markers_at(rng, motion, t, child_mm=10.0, rigid_share=rigid_share, noise_std=0.7)
    with_prior = fit_centre_two_segments(p, c, attachment="skin")
    monkeypatch.setattr(artefact, "PRIOR_NU", 0.0)
    without = fit_centre_two_segments(p, c, attachment="skin")
    assert np.trace(with_prior.cov_parent) >= np.trace(without.cov_parent) * (1.0 - 1e-12)
    if rigid_share == 1.0:
        np.testing.assert_allclose(with_prior.cov_parent, without.cov_parent, rtol=1e-12)
