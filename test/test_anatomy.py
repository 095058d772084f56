"""Anatomical frames, the hip-centre regressions, the knee axis against the epicondyles and the range of motion,
against synthetic segments with known truth and hand-computed values of the papers' formulas."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jointfit_core.anatomy import axis_against_epicondyles, hip_in_pelvis, hip_regression
from jointfit_core.errors import InputError
from jointfit_core.frames import isb_femur_frame, isb_pelvis_frame, isb_tibia_frame
from jointfit_core.rom import range_of_motion

RNG = np.random.default_rng(18)
R_TRUE = Rotation.random(random_state=5).as_matrix()  # columns: the anatomical axes in the world
ORIGIN = np.array([1200.0, -300.0, 950.0])
W, D = 230.0, 160.0  # inter-ASIS width, mid-ASIS to mid-PSIS depth (mm)


def _world(p_anat: np.ndarray) -> np.ndarray:
    return ORIGIN + R_TRUE @ np.asarray(p_anat, dtype=np.float64)


def _pelvis() -> tuple[np.ndarray, ...]:
    # In the ISB pelvis axes (x anterior, y superior, z right), origin mid-ASIS; mid-PSIS at (-D, 0, 0).
    return tuple(_world(p) for p in ([0, 0, W / 2], [0, 0, -W / 2], [-D, 0, 45.0], [-D, 0, -45.0]))


def test_isb_pelvis_frame_recovers_a_known_pelvis() -> None:
    R, origin = isb_pelvis_frame(*(p[None] for p in _pelvis()))
    np.testing.assert_allclose(R[0], R_TRUE, atol=1e-12)
    np.testing.assert_allclose(origin[0], ORIGIN, atol=1e-9)


@pytest.mark.parametrize("side", ["right", "left"])
def test_isb_femur_and_tibia_frames_recover_known_segments(side: str) -> None:
    s = 1.0 if side == "right" else -1.0  # the lateral side is +z (right) for a right leg
    lat_e, med_e = _world([0, -400, s * 45.0]), _world([0, -400, -s * 45.0])
    R, origin = isb_femur_frame(_world([0, 0, 0])[None], lat_e[None], med_e[None], side)
    np.testing.assert_allclose(R[0], R_TRUE, atol=1e-12)
    np.testing.assert_allclose(origin[0], ORIGIN, atol=1e-9)
    lat_c, med_c = _world([0, 380, s * 40.0]), _world([0, 380, -s * 40.0])
    lat_m, med_m = _world([0, 0, s * 35.0]), _world([0, 0, -s * 35.0])
    R, origin = isb_tibia_frame(lat_c[None], med_c[None], lat_m[None], med_m[None], side)
    np.testing.assert_allclose(R[0], R_TRUE, atol=1e-12)
    np.testing.assert_allclose(origin[0], ORIGIN, atol=1e-9)
    with pytest.raises(InputError, match="side"):
        isb_femur_frame(ORIGIN[None], lat_e[None], med_e[None], "up")


def test_regressions_equal_the_published_formulas_by_hand() -> None:
    # Bell et al. 1990: (-0.19 W, -0.30 W, 0.36 W); Harrington et al. 2007: (-0.24 D - 9.9, -0.30 W - 10.9,
    # 0.33 W + 7.3) mm.
    np.testing.assert_allclose(hip_regression("bell_1990", W, D, "right"), [-43.7, -69.0, 82.8], atol=1e-9)
    np.testing.assert_allclose(hip_regression("harrington_2007", W, D, "right"), [-48.3, -79.9, 83.2], atol=1e-9)
    np.testing.assert_allclose(hip_regression("harrington_2007", W, D, "left"), [-48.3, -79.9, -83.2], atol=1e-9)
    # metres: the same centre, the mm offsets converted
    np.testing.assert_allclose(
        hip_regression("harrington_2007", W / 1000, D / 1000, "right", mm_per_unit=1000.0),
        [-0.0483, -0.0799, 0.0832],
        atol=1e-12,
    )
    with pytest.raises(InputError, match="bell_1990"):
        hip_regression("davis", W, D, "right")


@pytest.mark.parametrize("side", ["right", "left"])
def test_hip_in_pelvis_gives_the_known_centre_percent_and_covariance(side: str) -> None:
    s = 1.0 if side == "right" else -1.0
    c_anat = np.array([-55.0, -80.0, s * 85.0])
    cov_anat = np.diag([4.0, 9.0, 16.0])
    thigh = _world([-20.0, -250.0, s * 120.0])
    hip = hip_in_pelvis(_world(c_anat), R_TRUE @ cov_anat @ R_TRUE.T, *_pelvis(), thigh_point=thigh)
    assert hip.side == side
    np.testing.assert_allclose(hip.centre, c_anat, atol=1e-9)
    np.testing.assert_allclose(hip.cov, cov_anat, atol=1e-9)
    assert hip.width == pytest.approx(W) and hip.depth == pytest.approx(D)
    np.testing.assert_allclose(hip.percent_width, 100.0 * np.array([-55.0, -80.0, 85.0]) / W, atol=1e-9)
    np.testing.assert_allclose(hip.regressions["bell_1990"], [-43.7, -69.0, s * 82.8], atol=1e-9)
    assert hip.distance_to("harrington_2007") == pytest.approx(np.linalg.norm(c_anat - [-48.3, -79.9, s * 83.2]))


def test_hip_in_pelvis_refuses_coincident_spines() -> None:
    p = _world([0, 0, 0])
    with pytest.raises(InputError, match="coincide"):
        hip_in_pelvis(p, np.eye(3), p, p, p, p, thigh_point=p)


def test_axis_against_epicondyles_known_angle_and_distance() -> None:
    lat, med = np.array([60.0, 0.0, 0.0]), np.array([-60.0, 0.0, 0.0])
    a = np.array([np.cos(np.radians(10.0)), np.sin(np.radians(10.0)), 0.0])
    point = np.array([0.0, 0.0, 7.0]) + 33.0 * a  # the axis passes 7 mm above the midpoint
    cov = np.diag([0.0, np.radians(1.0) ** 2, np.radians(0.5) ** 2])
    knee = axis_against_epicondyles(point, -a, cov, lat, med)  # the sign of the axis does not matter
    assert knee.angle_deg == pytest.approx(10.0)
    assert knee.distance == pytest.approx(7.0)
    assert knee.epicondyle_width == pytest.approx(120.0)
    assert knee.angle_sd_deg == pytest.approx(1.0)


def test_rom_of_a_known_hinge_motion() -> None:
    t = np.linspace(0.0, 20.0, 2001)
    axis = np.array([0.3, 0.9, 0.1]) / np.linalg.norm([0.3, 0.9, 0.1])
    flexion = np.radians(30.0 + 50.0 * np.sin(2 * np.pi * 0.5 * t))  # 100 deg range
    R = (Rotation.from_rotvec(flexion[:, None] * axis) * Rotation.from_rotvec([0.2, -0.4, 0.5])).as_matrix()
    R[7] = np.nan  # an unposed frame is left out
    rom = range_of_motion(R, axis)
    assert rom.n_frames == 2000
    assert rom.flexion_range_deg == pytest.approx(100.0, abs=0.1)
    assert rom.ranges_deg[0] == pytest.approx(100.0, abs=0.1) and rom.ranges_deg[1] < 1e-6
    assert abs(rom.axes[0] @ axis) > 1 - 1e-9
    assert np.isnan(rom.flexion_deg[7]) and np.nanmax(rom.flexion_deg) == pytest.approx(50.0, abs=0.05)


def test_rom_of_a_known_ball_motion() -> None:
    t = np.linspace(0.0, 40.0, 4001)
    e1, e2 = Rotation.random(random_state=2).as_matrix()[:, :2].T
    rv = np.radians(40.0) * np.sin(2 * np.pi * 0.25 * t)[:, None] * e1 + np.radians(20.0) * np.sin(
        2 * np.pi * 0.4 * t
    )[:, None] * e2
    R0 = Rotation.from_rotvec([0.1, 0.7, -0.3])
    rom = range_of_motion((Rotation.from_rotvec(rv) * R0).as_matrix())
    np.testing.assert_allclose(rom.ranges_deg, [80.0, 40.0, 0.0], atol=0.5)
    assert abs(rom.axes[0] @ e1) > 0.999 and abs(rom.axes[1] @ e2) > 0.999
    assert rom.flexion_range_deg is None


def test_rom_needs_two_rotations() -> None:
    with pytest.raises(InputError, match="at least 2"):
        range_of_motion(np.full((5, 3, 3), np.nan))
    with pytest.raises(InputError, match="shape"):
        range_of_motion(np.eye(3))
