"""Skeleton chains from minimal marker sets (jointfit_core.chain; Pham et al. section V-B).

The paper's leg: 3 trunk markers and one marker each on the thigh, shank and
foot identify the hip (spherical 3 + 1), the knee (revolute 2 + 1 on the hip
centre and the thigh marker) and the ankle (spherical 3 + 1 on the knee axis
and the shank marker).
"""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from jointfit_core import ChainJoint, MinimalAxisFit, MinimalCentreFit, fit_chain, leg_chain_spec
from jointfit_core.errors import InputError, NotIdentifiableError
from jointfit_core.synthetic import leg_chain_motion

FloatArray = NDArray[np.float64]


def _leg(seed: int, n_frames: int, sigma: float) -> tuple[dict[str, FloatArray], dict[str, FloatArray]]:
    rng = np.random.default_rng(seed)
    leg = leg_chain_motion(rng)
    times = np.linspace(0.0, 20.0, n_frames)
    mk = leg.markers_at(times)
    markers = {
        "trunk1": mk["trunk"][:, 0],
        "trunk2": mk["trunk"][:, 1],
        "trunk3": mk["trunk"][:, 2],
        "thigh": mk["thigh"][:, 0],
        "shank": mk["shank"][:, 0],
        "foot": mk["foot"][:, 0],
    }
    return {k: v + rng.normal(0.0, sigma, v.shape) for k, v in markers.items()}, leg.joints_at(times)


def _axis_errors(fit: MinimalAxisFit, truth: dict[str, FloatArray]) -> tuple[FloatArray, FloatArray]:
    n = truth["knee_axis"]
    angle = np.arccos(np.clip(np.abs(np.einsum("ni,ni->n", fit.direction_world, n)), 0.0, 1.0))
    w = fit.point_world - truth["knee"]
    return angle, np.linalg.norm(w - np.einsum("ni,ni->n", w, n)[:, None] * n, axis=1)


def test_leg_chain_noise_free_recovers_all_joints() -> None:
    """Structural identifiability: the minimal leg marker set determines hip, knee and ankle exactly."""
    markers, truth = _leg(1, 300, 0.0)
    results = fit_chain(markers, leg_chain_spec(knee_axis_hint=truth["knee_axis"]))
    assert list(results) == ["hip", "knee", "ankle"]
    hip, knee, ankle = results["hip"], results["knee"], results["ankle"]
    assert isinstance(hip, MinimalCentreFit) and isinstance(ankle, MinimalCentreFit)
    assert isinstance(knee, MinimalAxisFit)
    assert hip.method == "S31" and knee.method == "R21" and ankle.method == "S31"
    assert all(fit.identifiable for fit in results.values()), [fit.reason for fit in results.values()]
    np.testing.assert_allclose(hip.centre_world, truth["hip"], atol=1e-5)
    angle, off_axis = _axis_errors(knee, truth)
    assert angle.max() < 1e-6 and off_axis.max() < 1e-5
    assert knee.n_solutions == 4  # the 2 + 1 ambiguity, resolved by the hint
    np.testing.assert_allclose(ankle.centre_world, truth["ankle"], atol=1e-4)


def test_leg_chain_with_noise_flags_the_knee() -> None:
    """With 0.5 mm noise the hip is fine, but 2 + 1 markers cannot hold the knee: it and the ankle are flagged."""
    markers, truth = _leg(1, 300, 0.5)
    results = fit_chain(markers, leg_chain_spec(knee_axis_hint=truth["knee_axis"]))
    hip = results["hip"]
    assert isinstance(hip, MinimalCentreFit) and hip.identifiable, hip.reason
    err = hip.centre_world - truth["hip"]
    e = np.einsum("ni,ni->n", err, np.linalg.solve(hip.cov_world, err[..., None])[..., 0])
    assert np.mean(e) / 3 < 2.0
    assert np.median(np.linalg.norm(err, axis=1)) < 3.0
    assert not results["knee"].identifiable and results["knee"].reason
    assert not results["ankle"].identifiable
    assert "knee" in results["ankle"].reason


def test_custom_chain_with_s22() -> None:
    """A 2 + 2 ball joint (S22) in a chain, next to the 3 + 1 fit of the same hip."""
    rng = np.random.default_rng(2)
    leg = leg_chain_motion(rng)
    times = np.linspace(0.0, 20.0, 150)
    R_thigh, o_thigh = leg.frames_at(times)["thigh"]
    markers, truth = _leg(2, 150, 0.0)
    # A second thigh marker, rigid on the thigh (the seeded leg is the same as _leg's).
    markers["thigh2"] = np.einsum("nij,j->ni", R_thigh, np.array([-60.0, 40.0, -380.0])) + o_thigh
    joints = (
        ChainJoint("hip", "ball", ("trunk1", "trunk2"), ("thigh", "thigh2")),
        ChainJoint("hip3", "spherical", ("trunk1", "trunk2", "trunk3"), ("thigh",)),
    )
    results = fit_chain(markers, joints)
    hip, hip3 = results["hip"], results["hip3"]
    assert isinstance(hip, MinimalCentreFit) and isinstance(hip3, MinimalCentreFit)
    assert hip.identifiable and hip.method == "S22"
    np.testing.assert_allclose(hip.centre_world, truth["hip"], atol=1e-4)
    np.testing.assert_allclose(hip3.centre_world, truth["hip"], atol=1e-4)


def test_chain_errors() -> None:
    markers, _ = _leg(3, 40, 0.5)
    with pytest.raises(InputError, match="neither markers nor virtual markers"):
        fit_chain(markers, (ChainJoint("knee", "revolute", ("hip", "thigh"), ("shank",)),))
    with pytest.raises(NotIdentifiableError, match="IV-B"):
        fit_chain(markers, (ChainJoint("hip", "spherical", ("trunk1", "trunk2"), ("thigh",)),))
    with pytest.raises(NotIdentifiableError, match="III-B"):
        fit_chain(markers, (ChainJoint("knee", "hinge", ("thigh",), ("shank",)),))
    with pytest.raises(InputError, match="used twice"):
        fit_chain(markers, (leg_chain_spec()[0], leg_chain_spec()[0]))
    with pytest.raises(InputError, match="on both links"):
        fit_chain(markers, (ChainJoint("x", "spherical", ("trunk1", "trunk2", "thigh"), ("thigh",)),))
    with pytest.raises(InputError, match="kind"):
        fit_chain(markers, (ChainJoint("x", "prismatic", ("trunk1",), ("thigh",)),))
    with pytest.raises(InputError, match=r"shape \(N, 3\)"):
        fit_chain({**markers, "foot": markers["foot"][:, :2]}, leg_chain_spec())
    with pytest.raises(InputError, match="frames"):
        fit_chain({**markers, "foot": markers["foot"][:-1]}, leg_chain_spec())
    with pytest.raises(InputError, match="at least one"):
        fit_chain(markers, ())


def test_leg_chain_spec() -> None:
    hip, knee, ankle = leg_chain_spec(("a", "b", "c"), "t", "s", "f", knee_axis_hint=(1.0, 0.0, 0.0))
    assert (hip.kind, hip.parent, hip.child) == ("spherical", ("a", "b", "c"), ("t",))
    assert (knee.kind, knee.parent, knee.child, knee.axis_hint) == ("revolute", ("hip", "t"), ("s",), (1.0, 0.0, 0.0))
    assert (ankle.kind, ankle.parent, ankle.child) == ("spherical", ("knee", "knee:axis", "s"), ("f",))
