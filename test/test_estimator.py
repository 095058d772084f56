"""OnlineJoint: the two-segment online estimator (jointfit_core.estimator, jointfit_core.hinge_from_sums).

Ground truth from jointfit_core.synthetic.two_segment_motion (Stoddart-like
rigs, known joint). Checks: online equals the closed forms on the same window;
templates; covariance calibration (estimate and per-frame world output);
convergence of error and reported uncertainty together; rigid-transform,
unit and marker-order properties; freezing and saved calibrations; bad input.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import mahalanobis, mc_band, random_rigid
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from jointfit_core.calibration import load_calibration, save_calibration
from jointfit_core.errors import InputError
from jointfit_core.estimator import OnlineJoint, virtual_markers_template
from jointfit_core.hinge_from_sums import PoseSumsAxis, axis_from_pose_sums
from jointfit_core.pose import pose_covariance_local, poses_from_markers
from jointfit_core.segments import (
    PoseSumsCentre,
    centre_from_pose_sums,
    pose_sums_from_relative,
    relative_poses,
)
from jointfit_core.synthetic import TwoSegmentMotion, two_segment_motion

FloatArray = NDArray[np.float64]
RATE = 60.0


def _stream(
    rng: np.random.Generator, motion: TwoSegmentMotion, n: int, sigma: float = 1.0, occlusion: float = 0.0
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Noisy markers of n frames at RATE Hz; occlusion hides at most one marker per segment and frame."""
    times = np.arange(n) / RATE
    yp, yc = motion.markers_at(times)
    yp = yp + rng.normal(0.0, sigma, yp.shape)
    yc = yc + rng.normal(0.0, sigma, yc.shape)
    for y in (yp, yc):
        hide = rng.random(n) < occlusion
        y[hide, rng.integers(0, y.shape[1], int(hide.sum()))] = np.nan
    return yp, yc, times


def _to_template_frame(template_est: FloatArray, template_true: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Rigid (R, d) mapping true local coordinates into the estimated template's frame."""
    ca, cb = template_est.mean(axis=0), template_true.mean(axis=0)
    U, _, Vt = np.linalg.svd((template_true - cb).T @ (template_est - ca))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, ca - R @ cb


def _run(est: OnlineJoint, yp: FloatArray, yc: FloatArray, times: FloatArray, solve_every: int = 0) -> list[object]:
    outs = []
    for k in range(yp.shape[0]):
        outs.append(est.update(yp[k], yc[k], times[k]))
        if solve_every and k % solve_every == solve_every - 1 and est.templates_ready:
            est.estimate()
    return outs


def _rel(a: FloatArray, b: FloatArray) -> float:
    return float(np.max(np.abs(a - b)) / max(float(np.max(np.abs(b))), 1e-300))


# --------------------------------------------------------------------------- online == closed form on the window


@pytest.mark.parametrize("kind", ["ball", "hinge"])
def test_online_joint_equals_the_closed_form_on_its_window(kind: str) -> None:
    rng = np.random.default_rng(31 if kind == "ball" else 32)
    motion = two_segment_motion(rng, kind=kind, offset=(4000.0, -7000.0, 1500.0))
    yp, yc, times = _stream(rng, motion, 2500, occlusion=0.2)
    window = 700
    # The closed forms themselves: without the serial-correlation factor (test_serial checks the factor).
    est = OnlineJoint(kind, window=window, template_frames=40, serial_correlation=False)
    _run(est, yp, yc, times)
    assert est.n_window == window and not est.dropped  # one marker hidden at most: every frame posed
    tp, tc = est.templates
    assert tp is not None and tc is not None
    sl = slice(yp.shape[0] - window, None)
    pp, pc = poses_from_markers(yp[sl], tp), poses_from_markers(yc[sl], tc)
    Q, t, both = relative_poses(pp, pc)
    assert both.all()
    sums = pose_sums_from_relative(Q, t)

    def sigma(y: FloatArray, tpl: FloatArray, poses: object) -> float:
        R, d, vis = poses.R_world_local, poses.d_world_local, poses.visible  # type: ignore[attr-defined]
        res = np.where(vis[..., None], y - (np.einsum("nij,pj->npi", R, tpl) + d[:, None]), 0.0)
        return float(np.sqrt(np.sum(res**2) / np.sum(3 * vis.sum(axis=1) - 6)))

    sp, sc = sigma(yp[sl], tp, pp), sigma(yc[sl], tc, pc)
    Wp = sp**2 * pose_covariance_local(tp, 1.0, pp.visible).mean(axis=0)
    Wc = sc**2 * pose_covariance_local(tc, 1.0, pc.visible).mean(axis=0)
    scale = max(float(np.sqrt(np.mean(np.sum(x**2, axis=1)))) for x in (tp, tc))
    online = est.estimate()
    assert est.noise_std == pytest.approx((sp, sc), rel=1e-9)
    if kind == "ball":
        batch_c = centre_from_pose_sums(sums, Wp, Wc, length_scale=scale)
        assert isinstance(online, PoseSumsCentre)
        assert _rel(online.centre_parent, batch_c.centre_parent) < 1e-9
        assert _rel(online.cov, batch_c.cov) < 1e-8
        assert online.identifiable and batch_c.identifiable
    else:
        batch_a = axis_from_pose_sums(sums, Wp, Wc, length_scale=scale)
        assert isinstance(online, PoseSumsAxis)
        assert _rel(online.direction_parent, batch_a.direction_parent) < 1e-9
        assert _rel(online.point_parent, batch_a.point_parent) < 1e-9
        assert _rel(online.cov_point_parent, batch_a.cov_point_parent) < 1e-8
        assert _rel(online.cov_direction_child, batch_a.cov_direction_child) < 1e-8


def test_templates_match_the_rig() -> None:
    rng = np.random.default_rng(4)
    motion = two_segment_motion(rng)
    yp, yc, times = _stream(rng, motion, 400, sigma=0.5, occlusion=0.3)
    est = OnlineJoint("ball", window=300, template_frames=50)
    _run(est, yp, yc, times)
    for est_tpl, true_tpl in zip(est.templates, (motion.template_parent, motion.template_child), strict=True):
        assert est_tpl is not None
        R, d = _to_template_frame(est_tpl, true_tpl)
        # 50 frames of 0.5 mm noise: the template points are known to ~0.1 mm
        assert np.abs(est_tpl - (true_tpl @ R.T + d)).max() < 0.3
        np.testing.assert_allclose(est_tpl.mean(axis=0), 0.0, atol=1e-9)


# --------------------------------------------------------------------------- calibration and convergence


def _local_truth(est: OnlineJoint, motion: TwoSegmentMotion) -> dict[str, FloatArray]:
    tp, tc = est.templates
    assert tp is not None and tc is not None
    R, d = _to_template_frame(tp, motion.template_parent)
    Rc, dc = _to_template_frame(tc, motion.template_child)
    out = {"centre_parent": R @ motion.centre_parent + d, "centre_child": Rc @ motion.centre_child + dc}
    for side, rot, c in (("parent", R, out["centre_parent"]), ("child", Rc, out["centre_child"])):
        n = rot @ motion.axis
        out[f"direction_{side}"] = n
        out[f"point_{side}"] = c - n * (n @ c)
    return out


def test_ball_estimate_and_world_output_are_calibrated() -> None:
    """Mean e/3 of the local centres and of the per-frame world centre over 150 seeded streams."""
    rng = np.random.default_rng(77)
    e_p: list[float] = []
    e_c: list[float] = []
    e_world: list[float] = []
    for _ in range(150):
        motion = two_segment_motion(rng, kind="ball")
        yp, yc, times = _stream(rng, motion, 330, occlusion=0.1)
        est = OnlineJoint("ball", window=1000, template_frames=30)
        outs = _run(est, yp, yc, times, solve_every=300)
        sol = est.estimate()
        assert isinstance(sol, PoseSumsCentre)
        truth = _local_truth(est, motion)
        e_p.append(mahalanobis(sol.centre_parent - truth["centre_parent"], sol.cov_parent))
        e_c.append(mahalanobis(sol.centre_child - truth["centre_child"], sol.cov_child))
        world_truth = motion.centre_world_at(times[300:])
        for k, out in enumerate(outs[300:]):
            if out is not None:
                e_world.append(mahalanobis(out.position - world_truth[k], out.cov))  # type: ignore[attr-defined]
    mc_band(e_p)
    mc_band(e_c)
    mc_band(e_world)


def test_hinge_estimate_is_calibrated() -> None:
    rng = np.random.default_rng(78)
    e: dict[str, list[float]] = {k: [] for k in ("direction_parent", "direction_child", "point_parent", "point_child")}
    for _ in range(150):
        motion = two_segment_motion(rng, kind="hinge")
        yp, yc, times = _stream(rng, motion, 330, occlusion=0.1)
        est = OnlineJoint("hinge", window=1000, template_frames=30)
        _run(est, yp, yc, times)
        sol = est.estimate()
        assert isinstance(sol, PoseSumsAxis)
        truth = _local_truth(est, motion)
        for key in e:
            true = truth[key]
            if key.startswith("direction") and true @ getattr(sol, key) < 0:
                true = -true
            cov = getattr(sol, "cov_" + key)
            e[key].append(mahalanobis(getattr(sol, key) - true, cov))
    for values in e.values():
        mc_band(values)


def test_error_and_uncertainty_shrink_together_while_streaming() -> None:
    """A calibration movement streamed frame by frame: at every checkpoint the rms error tracks the
    reported sqrt(tr cov), both shrink, and the mean validation index squared stays near 1."""
    checkpoints = [120, 240, 480, 960, 1920]
    n_trials = 40
    err = np.zeros((n_trials, len(checkpoints)))
    sd = np.zeros_like(err)
    e3 = np.zeros_like(err)
    rng = np.random.default_rng(99)
    for trial in range(n_trials):
        motion = two_segment_motion(rng, kind="ball", cycle_s=40.0)
        yp, yc, times = _stream(rng, motion, checkpoints[-1], occlusion=0.05)
        est = OnlineJoint("ball", window=10_000, template_frames=30)
        for k in range(yp.shape[0]):
            est.update(yp[k], yc[k], times[k])
            if k + 1 in checkpoints:
                sol = est.estimate()
                assert isinstance(sol, PoseSumsCentre)
                diff = sol.centre_parent - _local_truth(est, motion)["centre_parent"]
                j = checkpoints.index(k + 1)
                err[trial, j] = float(np.sqrt(diff @ diff))
                sd[trial, j] = float(np.sqrt(np.trace(sol.cov_parent)))
                e3[trial, j] = mahalanobis(diff, sol.cov_parent)
    rms_err = np.sqrt(np.mean(err**2, axis=0))
    rms_sd = np.sqrt(np.mean(sd**2, axis=0))
    assert np.all(np.diff(rms_err) < 0) and np.all(np.diff(rms_sd) < 0), (rms_err, rms_sd)
    assert rms_err[-1] < 0.4 * rms_err[0]
    # error / sd per trial, then rms over the trials (a pooled rms of the sds is one trial's: at 240 frames
    # the least excited trial's sd is 3x the next one's)
    np.testing.assert_allclose(np.sqrt(np.mean((err / sd) ** 2, axis=0)), 1.0, atol=0.25)
    for j in range(len(checkpoints)):
        mc_band(list(e3[:, j]), 0.7, 1.4)  # 40 trials: the mean of e/3 has sd ~0.13


# --------------------------------------------------------------------------- properties


def _world_outputs(est: OnlineJoint, yp: FloatArray, yc: FloatArray, times: FloatArray) -> tuple[FloatArray, FloatArray]:
    outs = _run(est, yp, yc, times, solve_every=100)
    pos = np.array([o.position for o in outs if o is not None])  # type: ignore[attr-defined]
    cov = np.array([o.cov for o in outs if o is not None])  # type: ignore[attr-defined]
    return pos, cov


def test_rigid_transform_units_and_marker_order() -> None:
    rng = np.random.default_rng(12)
    motion = two_segment_motion(rng, kind="hinge")
    yp, yc, times = _stream(rng, motion, 600, occlusion=0.1)
    pos, cov = _world_outputs(OnlineJoint("hinge", window=400, template_frames=20), yp, yc, times)
    assert pos.shape[0] > 400

    R, t = random_rigid(rng, 3000.0)
    pos_t, cov_t = _world_outputs(
        OnlineJoint("hinge", window=400, template_frames=20), yp @ R.T + t, yc @ R.T + t, times
    )
    np.testing.assert_allclose(pos_t, pos @ R.T + t, atol=1e-6)
    np.testing.assert_allclose(cov_t, R @ cov @ R.T, rtol=1e-6, atol=1e-9)

    pos_m, cov_m = _world_outputs(OnlineJoint("hinge", window=400, template_frames=20), yp / 1000.0, yc / 1000.0, times)
    np.testing.assert_allclose(pos_m, pos / 1000.0, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(cov_m, cov / 1e6, rtol=1e-6, atol=1e-15)

    perm_p, perm_c = rng.permutation(yp.shape[1]), rng.permutation(yc.shape[1])
    pos_o, cov_o = _world_outputs(
        OnlineJoint("hinge", window=400, template_frames=20), yp[:, perm_p], yc[:, perm_c], times
    )
    np.testing.assert_allclose(pos_o, pos, atol=1e-6)
    np.testing.assert_allclose(cov_o, cov, rtol=1e-6, atol=1e-9)


def test_hinge_sign_is_stable_and_follows_the_reference() -> None:
    rng = np.random.default_rng(8)
    motion = two_segment_motion(rng, kind="hinge")
    yp, yc, times = _stream(rng, motion, 900)
    for ref in (np.array([1.0, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0])):
        est = OnlineJoint("hinge", window=200, template_frames=20, reference_direction=ref)
        signs = []
        for k in range(yp.shape[0]):
            est.update(yp[k], yc[k], times[k])
            if k >= 60 and k % 20 == 0:
                sol = est.estimate()
                assert isinstance(sol, PoseSumsAxis)
                signs.append(float(sol.direction_parent @ ref))
        assert min(signs) > 0.0


# --------------------------------------------------------------------------- freezing, saving, bad input


def test_freeze_thaw_and_reload_give_the_same_outputs(tmp_path: object) -> None:
    rng = np.random.default_rng(15)
    motion = two_segment_motion(rng, kind="ball")
    yp, yc, times = _stream(rng, motion, 900, occlusion=0.1)
    est = OnlineJoint("ball", window=500, template_frames=30)
    _run(est, yp[:600], yc[:600], times[:600])
    frozen = est.freeze()
    n_window = est.n_window
    outs = _run(est, yp[600:], yc[600:], times[600:])
    assert est.n_window == n_window and est.estimate() is frozen

    path = save_calibration(tmp_path / "knee.yaml", est.to_dict())  # type: ignore[operator]
    loaded = OnlineJoint.from_dict(load_calibration(path))
    assert loaded.frozen and loaded.templates_ready
    outs_loaded = _run(loaded, yp[600:], yc[600:], times[600:])
    for a, b in zip(outs, outs_loaded, strict=True):
        assert (a is None) == (b is None)
        if a is not None and b is not None:
            np.testing.assert_allclose(b.position, a.position, rtol=1e-12)
            np.testing.assert_allclose(b.cov, a.cov, rtol=1e-9)

    est.thaw()
    _run(est, yp[600:700], yc[600:700], times[600:700] + 100.0)
    assert est.n_window == 500 and est.estimate() is not frozen

    data = est.to_dict()
    for change, match in (
        ({"format": "something"}, "format"),
        ({"version": 99}, "version"),
        ({"template_parent": [[0.0, 0.0, 0.0]]}, "templates"),
        ({"estimate": {"centre_parent": [0.0, 0.0, 0.0]}}, "fields"),
    ):
        with pytest.raises(InputError, match=match):
            OnlineJoint.from_dict({**data, **change})


def test_bad_input_is_dropped_and_counted() -> None:
    rng = np.random.default_rng(2)
    motion = two_segment_motion(rng, kind="ball")
    yp, yc, times = _stream(rng, motion, 200)
    est = OnlineJoint("ball", window=100, template_frames=20)
    _run(est, yp[:150], yc[:150], times[:150])
    est.estimate()
    assert est.update(yp[150], yc[150], times[149]) is None  # stamp repeated
    bad_parent = yp[151].copy()
    bad_parent[:2] = np.nan  # two of four parent markers: cannot pose
    assert est.update(bad_parent, yc[151], times[151]) is None
    bad_child = yc[152].copy()
    bad_child[1:] = np.nan
    out = est.update(yp[152], bad_child, times[152])
    assert out is not None and np.isnan(out.residual)  # parent posed: output, but no residual
    assert est.dropped == {"stamp_not_increasing": 1, "parent_not_posed": 1, "child_not_posed": 1}
    with pytest.raises(InputError, match="expected 4 markers"):
        est.update(yp[153, :3], yc[153], times[153])
    with pytest.raises(InputError, match="inf"):
        est.update(np.full((4, 3), np.inf), yc[153], times[153])
    with pytest.raises(InputError, match="kind"):
        OnlineJoint("saddle", window=10)
    with pytest.raises(InputError, match="at least 3 markers"):
        OnlineJoint("ball", window=10).update(np.zeros((2, 3)), np.zeros((3, 3)))
    fresh = OnlineJoint("ball", window=10)
    with pytest.raises(InputError, match="no frame"):
        fresh.estimate()
    assert "waiting" in fresh.status()


def test_rigid_body_poses_through_virtual_markers() -> None:
    """Pose streams (translation sd 0.5 mm, rotation sd 0.3 deg) as virtual markers: calibrated estimate."""
    t_sd, r_sd = 0.5, np.deg2rad(0.3)
    template, sigma = virtual_markers_template(t_sd, r_sd)
    rng = np.random.default_rng(41)
    e3: list[float] = []
    for _ in range(100):
        motion = two_segment_motion(rng, kind="ball")
        times = np.arange(300) / RATE
        R_p, d_p, R_c, d_c = motion.poses_at(times)

        def noisy(R: FloatArray, d: FloatArray) -> FloatArray:
            dR = Rotation.from_rotvec(rng.normal(0.0, r_sd, (len(d), 3))).as_matrix()
            Rn = R @ dR
            dn = d + rng.normal(0.0, t_sd, d.shape)
            return np.einsum("nij,pj->npi", Rn, template) + dn[:, None, :]

        yp, yc = noisy(R_p, d_p), noisy(R_c, d_c)
        est = OnlineJoint("ball", window=1000, templates=(template, template), noise_std=(sigma, sigma))
        assert est.templates_ready
        _run(est, yp, yc, times)
        sol = est.estimate()
        assert isinstance(sol, PoseSumsCentre)
        # The virtual template's frame is the body frame itself.
        e3.append(mahalanobis(sol.centre_parent - motion.centre_parent, sol.cov_parent))
    mc_band(e3)
    with pytest.raises(InputError, match="pose noise"):
        virtual_markers_template(0.0, 0.1)
    with pytest.raises(InputError, match="noise_std"):
        OnlineJoint("ball", window=10, noise_std=(1.0, -1.0))


def test_a_marker_with_one_nan_coordinate_is_missing_as_a_whole() -> None:
    rng = np.random.default_rng(6)
    motion = two_segment_motion(rng, kind="ball")
    yp, yc, times = _stream(rng, motion, 300)
    a = OnlineJoint("ball", window=200, template_frames=20)
    b = OnlineJoint("ball", window=200, template_frames=20)
    partial, whole = yp.copy(), yp.copy()
    partial[150:, 1, 2] = np.nan  # one coordinate, after the templates are built (fast path)
    whole[150:, 1, :] = np.nan
    outs_a = _run(a, partial, yc, times, solve_every=50)
    outs_b = _run(b, whole, yc, times, solve_every=50)
    for oa, ob in zip(outs_a, outs_b, strict=True):
        assert (oa is None) == (ob is None)
        if oa is not None and ob is not None:
            np.testing.assert_array_equal(oa.position, ob.position)
    assert a.estimate().centre_parent.tolist() == b.estimate().centre_parent.tolist()  # type: ignore[union-attr]
