"""Plausibility on real recordings (test/data, see its README and licences)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from jointfit_core.axis import fit_axis
from jointfit_core.frames import pelvis_frame, to_frame
from jointfit_core.io import read_c3d
from jointfit_core.pose import poses_from_markers
from jointfit_core.segments import fit_axis_two_segments, fit_centre_two_segments

DATA = Path(__file__).resolve().parent / "data"
#: Published methods on right_hip.c3d (data README), pelvis frame, mm.
HIP_BOX = np.array([[-63.0, -57.0], [-98.0, -72.0], [-95.0, -76.0]])
#: Those methods agree only to 15-25 mm; allow 5 mm beyond their spread.
HIP_MARGIN = 5.0


@pytest.fixture(scope="module")
def hip_fits() -> dict[str, tuple[np.ndarray, object]]:
    data = read_c3d(DATA / "biobuddy" / "right_hip.c3d")
    pelvis = data.select(["RASIS", "LASIS", "RPSIS", "LPSIS"])
    thigh = data.select(["RTHI1", "RTHI2", "RTHI3"])
    R_world_pelvis, origin = pelvis_frame(*(pelvis[:, i] for i in range(4)))
    out = {}
    for name, kwargs in {
        "weighted": {"method": "poses", "weighted": True},
        "unweighted": {"method": "poses", "weighted": False},
    }.items():
        fit = fit_centre_two_segments(pelvis, thigh, **kwargs)  # type: ignore[arg-type]
        out[name] = (np.nanmean(to_frame(fit.centre_world, R_world_pelvis, origin), axis=0), fit)
    return out


@pytest.mark.parametrize("name", ["weighted", "unweighted"])
def test_hip_centre_in_published_box(hip_fits: dict, name: str) -> None:
    centre, fit = hip_fits[name]
    assert fit.identifiable, fit.reason
    assert np.all(centre >= HIP_BOX[:, 0] - HIP_MARGIN) and np.all(centre <= HIP_BOX[:, 1] + HIP_MARGIN), centre


def test_hip_methods_agree_within_their_reported_uncertainty(hip_fits: dict) -> None:
    """The covariances must be honest about the spread between methods on real skin markers."""
    (c_w, f_w), (c_u, f_u) = hip_fits["weighted"], hip_fits["unweighted"]
    diff = f_w.centre_parent - f_u.centre_parent
    assert np.linalg.norm(c_w - c_u) < 25.0
    e = float(diff @ np.linalg.solve(f_w.cov_parent + f_u.cov_parent, diff))
    assert e / 3 < 9.0, f"methods differ by {np.linalg.norm(diff):.1f} mm, e/3 = {e / 3:.1f}"
    # the joint residual shows soft-tissue artefact far above marker noise: reported, not hidden
    assert f_w.rms > 3 * max(f_w.noise_std_parent, f_w.noise_std_child)


def test_hip_skin_sd_covers_the_published_methods() -> None:
    """Issue 17: the skin covariance is honest about the spread of published methods on this trial.

    The data README puts the centre by published methods anywhere in HIP_BOX (pelvis frame): each of
    its corners (the methods' extremes) must lie within the reported covariance (e/3 < 3, about 3 sd
    in 3-D), its centre well within (e/3 < 1); and the sd must not be so wide that it says nothing
    (below 25 mm: the methods span 26 mm at most; in vivo functional centres are ~11-13 mm off).
    """
    data = read_c3d(DATA / "biobuddy" / "right_hip.c3d")
    pelvis = data.select(["RASIS", "LASIS", "RPSIS", "LPSIS"])
    thigh = data.select(["RTHI1", "RTHI2", "RTHI3"])
    R_world_pelvis, origin = pelvis_frame(*(pelvis[:, i] for i in range(4)))
    covering = {}
    for attachment in ("skin", "rigid"):
        fit = fit_centre_two_segments(pelvis, thigh, attachment=attachment)
        centre = to_frame(fit.centre_world, R_world_pelvis, origin)
        ok = np.isfinite(centre).all(axis=1) & np.isfinite(fit.cov_world).all(axis=(1, 2))
        cov = np.median(np.einsum("nji,njk,nkl->nil", R_world_pelvis[ok], fit.cov_world[ok], R_world_pelvis[ok]), axis=0)
        c = centre[ok].mean(axis=0)
        corners = np.array(np.meshgrid(*HIP_BOX, indexing="ij")).reshape(3, -1).T
        e = [float((p - c) @ np.linalg.solve(cov, p - c)) / 3.0 for p in corners]
        covering[attachment] = max(e)
        if attachment == "skin":
            mid = HIP_BOX.mean(axis=1) - c
            assert max(e) < 3.0, (c, np.sqrt(np.diag(cov)), e)
            assert float(mid @ np.linalg.solve(cov, mid)) / 3.0 < 1.0
            assert np.sqrt(np.linalg.eigvalsh(cov).max()) < 25.0, np.sqrt(np.diag(cov))
    assert covering["skin"] < covering["rigid"]  # the artefact part is what covers them


def test_knee_skin_sd_covers_the_difference_between_methods() -> None:
    """Issue 17: the two-segment axis and the one-segment axis (shank markers in the thigh frame,
    Gamage-Lasenby) differ by ~2.1 deg on this trial (the closed form skin hinges report; 1.8 for the
    refinement they reported before); the skin direction covariance covers it (e/2 < 2 in the plane normal
    to the axis: 1.5, was 0.7 with the refinement's wider artefact part), without an sd so wide it says
    nothing (< 5 deg)."""
    data = read_c3d(DATA / "biobuddy" / "right_knee.c3d")
    thigh, shank = data.select(["RTHI1", "RTHI2", "RTHI3"]), data.select(["RLEG1", "RLEG2", "RLEG3"])
    fit = fit_axis_two_segments(thigh, shank)
    poses = poses_from_markers(thigh, fit.template_parent)
    local = np.einsum("nji,npj->npi", poses.R_world_local, shank - poses.d_world_local[:, None, :])
    local[~poses.valid] = np.nan
    one = fit_axis(local, reference_direction=fit.direction_parent)
    n = fit.direction_parent
    basis = np.linalg.svd(np.eye(3) - np.outer(n, n))[0][:, :2]
    diff = basis.T @ (one.direction - n)
    cov = basis.T @ (fit.cov_direction_parent + one.cov_direction) @ basis
    assert np.degrees(np.linalg.norm(diff)) > 0.5  # the methods do differ: the check has something to cover
    assert float(diff @ np.linalg.solve(cov, diff)) / 2.0 < 2.0, (np.degrees(np.linalg.norm(diff)), cov)
    assert np.degrees(np.sqrt(np.trace(fit.cov_direction_parent))) < 5.0


def test_knee_axis_near_epicondyle_line() -> None:
    data = read_c3d(DATA / "biobuddy" / "right_knee.c3d")
    fit = fit_axis_two_segments(data.select(["RTHI1", "RTHI2", "RTHI3"]), data.select(["RLEG1", "RLEG2", "RLEG3"]))
    assert fit.identifiable, fit.reason
    epi = data.select(["RLFE", "RMFE"])
    line = epi[:, 1] - epi[:, 0]
    line /= np.linalg.norm(line, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.abs(np.einsum("ni,ni->n", fit.direction_world, line))))
    assert np.nanmean(angle) < 15.0
    mid = epi.mean(axis=1) - fit.point_world
    off = mid - np.einsum("ni,ni->n", mid, fit.direction_world)[:, None] * fit.direction_world
    assert np.nanmean(np.linalg.norm(off, axis=1)) < 15.0


def test_elbow_is_flagged_as_a_poor_hinge() -> None:
    data = read_c3d(DATA / "kineticstoolkit" / "kinematics_racing_full.c3d")
    assert data.units == "m"
    elbow = fit_axis_two_segments(
        data.select(["ArmR1", "ArmR2", "ArmR3"]), data.select(["ForearmR1", "ForearmR2", "ForearmR3"])
    )
    knee_data = read_c3d(DATA / "biobuddy" / "right_knee.c3d")
    knee = fit_axis_two_segments(
        knee_data.select(["RTHI1", "RTHI2", "RTHI3"]), knee_data.select(["RLEG1", "RLEG2", "RLEG3"])
    )
    assert not elbow.identifiable
    assert "not a hinge" in elbow.reason or "not a clean hinge" in elbow.reason
    assert knee.identifiable
    assert elbow.rms * 1000.0 > 1.5 * knee.rms  # metres vs millimetres


def test_demo_runs(capsys: pytest.CaptureFixture[str]) -> None:
    from jointfit_core.demo import main

    assert main([str(DATA)]) == 0
    out = capsys.readouterr().out
    assert "Right hip" in out and "Right knee" in out and "NOT identifiable" in out
