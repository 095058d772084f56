"""Lag-1 correlation of the joint-constraint residual (jointfit_core.serial) and OnlineJoint's correction.

Checks: the sums formula equals the residuals' own autocorrelation; the hinge's
residual pair is the solved one; OnlineJoint's window sums equal the batch sums
after long random add/remove sequences (frame windows, time windows, forgetting,
chain breaks, freezing); the correction multiplies the estimate's covariances
and only their part of the world output; calibration under AR(1) marker noise
(without the correction the mean e/rank is tens, with it about 1) and on white
noise; saved calibrations with and without the new keys; the real hip fixture
against the batch fit's model-error inflation.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers import mahalanobis
from numpy.typing import NDArray
from scipy.signal import lfilter
from scipy.spatial.transform import Rotation

from jointfit_core.errors import InputError
from jointfit_core.estimator import OnlineJoint
from jointfit_core.hinge_from_sums import PoseSumsAxis, axis_from_pose_sums
from jointfit_core.pose import poses_from_markers
from jointfit_core.segments import PoseSums, PoseSumsCentre, pose_sums_from_relative, relative_poses
from jointfit_core.serial import (
    N_TIME_LAG_SUMS,
    RHO_MAX,
    LagHistory,
    LagSums,
    TimeLagSums,
    constraint_residual_autocorrelation,
    hinge_residual_pair,
    integrated_factor,
    lag1_autocorrelation_from_sums,
    lag_nodes,
    lag_sums_from_relative,
    residual_lag_sum_from_sums,
    residual_sum_squares_from_sums,
    serial_factor,
    time_lag_sums_from_relative,
)
from jointfit_core.synthetic import TwoSegmentMotion, two_segment_motion

FloatArray = NDArray[np.float64]
RATE = 100.0
DATA = Path(__file__).resolve().parent / "data"


def _ar1(rng: np.random.Generator, shape: tuple[int, ...], phi: float, sd: float) -> FloatArray:
    """Stationary AR(1) series along axis 0 (lag-1 correlation ``phi``, marginal sd ``sd``)."""
    e = rng.normal(0.0, 1.0, shape)
    e[0] /= np.sqrt(1.0 - phi**2)
    out: FloatArray = lfilter([sd * np.sqrt(1.0 - phi**2)], [1.0, -phi], e, axis=0)
    return out


def _rel(a: FloatArray, b: FloatArray) -> float:
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))) / max(float(np.max(np.abs(b))), 1e-300))


# --------------------------------------------------------------------------- batch formulas


def test_sums_formula_equals_the_residuals_autocorrelation() -> None:
    rng = np.random.default_rng(1)
    n, phi = 20_000, 0.8
    Q = Rotation.random(n, random_state=rng).as_matrix()
    c_p, c_c = rng.normal(0.0, 300.0, 3), rng.normal(0.0, 300.0, 3)
    r = _ar1(rng, (n, 3), phi, 2.0)
    t = c_p - np.einsum("nij,j->ni", Q, c_c) - r
    gaps = rng.random(n) < 0.05
    Q[gaps], t[gaps] = np.nan, np.nan
    x = np.concatenate([c_p, c_c])
    rho_direct = constraint_residual_autocorrelation(Q, t, x)
    sums, lag = pose_sums_from_relative(Q, t), lag_sums_from_relative(Q, t)
    assert lag.n_pairs == float(np.sum(~gaps[1:] & ~gaps[:-1]))
    assert lag1_autocorrelation_from_sums(sums, lag, c_p, c_c) == pytest.approx(rho_direct, abs=1e-8)  # |t| ~ 300 |r|
    assert rho_direct == pytest.approx(phi, abs=0.02)  # 19 000 pairs: sd of the estimate ~0.004
    ok = ~gaps
    assert residual_sum_squares_from_sums(sums, c_p, c_c) == pytest.approx(float(np.sum(r[ok] ** 2)), rel=1e-9)
    pairs = ok[1:] & ok[:-1]
    lag_direct = float(np.sum(r[1:][pairs] * r[:-1][pairs]))
    assert residual_lag_sum_from_sums(lag, c_p, c_c) == pytest.approx(lag_direct, rel=1e-8)
    # Sums of disjoint pair sets add: the flat layout round-trips.
    flat = np.concatenate([[lag.n_pairs], lag.sum_pair.ravel(), lag.cross.ravel()])
    back = LagSums.from_vector(flat)
    np.testing.assert_array_equal(back.cross, lag.cross)


def test_serial_factor_clips_and_rejects_bad_limits() -> None:
    assert serial_factor(-0.3) == (0.0, 1.0)
    assert serial_factor(float("nan")) == (0.0, 1.0)
    assert serial_factor(0.5) == (0.5, pytest.approx(3.0))
    assert serial_factor(1.2)[0] == RHO_MAX
    with pytest.raises(InputError, match="rho_max"):
        serial_factor(0.5, rho_max=1.0)
    with pytest.raises(InputError, match="29"):
        LagSums.from_vector(np.zeros(12))


def test_hinge_residual_pair_is_the_solved_pair() -> None:
    """The pair recovered from the reported points gives the solution's rms and minimises the residual."""
    rng = np.random.default_rng(3)
    motion = two_segment_motion(rng, kind="hinge")
    yp, yc = motion.markers_at(np.arange(1500) / RATE)
    yp = yp + rng.normal(0.0, 1.0, yp.shape)
    yc = yc + rng.normal(0.0, 1.0, yc.shape)
    Q, t, _ = relative_poses(
        poses_from_markers(yp, motion.template_parent), poses_from_markers(yc, motion.template_child)
    )
    sums = pose_sums_from_relative(Q, t)
    sol = axis_from_pose_sums(sums, 0.01 * np.eye(6), 0.01 * np.eye(6))
    c_p, c_c = hinge_residual_pair(sums, sol.direction_parent, sol.direction_child, sol.point_parent, sol.point_child)
    assert np.sqrt(residual_sum_squares_from_sums(sums, c_p, c_c) / sums.n) == pytest.approx(sol.rms, rel=1e-9)
    # Orthogonal to the gauge direction (n_p, n_c), and a minimum along (n_p, -n_c).
    assert abs(sol.direction_parent @ c_p + sol.direction_child @ c_c) < 1e-9 * np.linalg.norm(c_p)
    for step in (-1e-3, 1e-3):
        moved = residual_sum_squares_from_sums(
            sums, c_p + step * sol.direction_parent, c_c - step * sol.direction_child
        )
        assert moved > residual_sum_squares_from_sums(sums, c_p, c_c)


# --------------------------------------------------------------------------- online sums == batch sums


def _weighted_sums(Z: FloatArray, pushed: NDArray[np.bool_], w: FloatArray) -> tuple[PoseSums, LagSums]:
    """Batch sums over the rows that entered the statistics, weighted, with the pair to the previous row."""
    pair = np.zeros_like(pushed)
    pair[1:] = pushed[1:] & pushed[:-1]
    wf = np.where(pushed, w, 0.0)
    wp = np.where(pair, w, 0.0)
    Zs = np.where(pushed[:, None, None], Z, 0.0)
    prev = np.zeros_like(Zs)
    prev[1:] = Zs[:-1]
    Qs, ts = Zs[:, :, :3], Zs[:, :, 3]
    sums = PoseSums(
        n=float(wf.sum()),
        S=np.einsum("n,nij->ij", wf, Qs),
        sum_t=wf @ ts,
        sum_qt_t=np.einsum("n,nji,nj->i", wf, Qs, ts),
        sum_tt=float(np.einsum("n,ni,ni->", wf, ts, ts)),
        K=np.einsum("n,nij,nkl->ikjl", wf, Qs, Qs).reshape(9, 9),
    )
    lag = LagSums(
        n_pairs=float(wp.sum()),
        sum_pair=np.einsum("n,nij->ij", wp, Zs + prev),
        cross=np.einsum("n,nji,njk->ik", wp, Zs, prev),
    )
    return sums, lag


WINDOWS = {
    "window": {"window": 300},
    "window_s": {"window_s": 2.5},
    "half_life": {"half_life": 120.0},
    "half_life_s": {"half_life_s": 1.5},
}


@pytest.mark.parametrize("kind", ["ball", "hinge"])
def test_online_lag_sums_equal_the_batch_sums_of_the_window(kind: str) -> None:
    """2000 frames with occlusions, frames a segment cannot be posed in, repeated stamps, time jumps and a
    freeze: the window's sums (frames and lag pairs) and rho equal the batch formulas on its frames."""
    rng = np.random.default_rng(11 if kind == "ball" else 12)
    motion = two_segment_motion(rng, kind=kind, offset=(4000.0, -7000.0, 1500.0))
    n = 2000
    yp, yc = motion.markers_at(np.arange(n) / RATE)
    yp = yp + _ar1(rng, yp.shape, 0.9, 1.0)
    yc = yc + _ar1(rng, yc.shape, 0.9, 1.0)
    for y in (yp, yc):
        hide = rng.random(n) < 0.1
        y[hide, rng.integers(0, y.shape[1], int(hide.sum()))] = np.nan
    yc[rng.random(n) < 0.03] = np.nan  # child not posed: breaks the chain
    yp[rng.random(n) < 0.02] = np.nan  # parent not posed: breaks the chain
    dt = np.full(n, 1.0 / RATE)
    dt[rng.random(n) < 0.01] = 0.7  # time jumps: several frames leave a time window at once
    stamps = 50.0 + np.cumsum(dt)
    repeat = rng.random(n) < 0.02  # stamp not increasing: dropped before posing, does not break the chain
    repeat[0] = False
    stamps[repeat] = stamps[np.flatnonzero(repeat) - 1]
    frozen = np.zeros(n, dtype=bool)
    frozen[900:960] = True  # frames while frozen reach the estimator but not the statistics

    templates = (motion.template_parent, motion.template_child)
    ests = {name: OnlineJoint(kind, templates=templates, **kw) for name, kw in WINDOWS.items()}  # type: ignore[arg-type]
    reached: list[int] = []
    pushed: list[bool] = []
    last = -np.inf
    for k in range(n):
        if frozen[k] and not frozen[k - 1]:
            for est in ests.values():
                est.freeze()
        if not frozen[k] and k > 0 and frozen[k - 1]:
            for est in ests.values():
                est.thaw()
        before = [sum(est.dropped.get(r, 0) for r in ("parent_not_posed", "child_not_posed")) for est in ests.values()]
        for est in ests.values():
            est.update(yp[k], yc[k], float(stamps[k]))
        if stamps[k] <= last:
            continue
        last = stamps[k]
        after = [sum(est.dropped.get(r, 0) for r in ("parent_not_posed", "child_not_posed")) for est in ests.values()]
        assert len(set(after)) == 1
        reached.append(k)
        pushed.append(after[0] == before[0] and not frozen[k])
        if k == 400:
            for est in ests.values():
                est.estimate()
    idx = np.array(reached)
    ok = np.array(pushed)
    tp, tc = ests["window"].templates
    Q, t, both = relative_poses(poses_from_markers(yp[idx], tp), poses_from_markers(yc[idx], tc))
    assert np.array_equal(both & ~frozen[idx], ok)
    Z = np.concatenate([np.where(ok[:, None, None], Q, 0.0), np.where(ok[:, None], t, 0.0)[:, :, None]], axis=2)
    st = stamps[idx]
    rows = np.flatnonzero(ok)
    for name, est in ests.items():
        w = np.zeros(len(idx))
        if name == "window":
            w[rows[-300:]] = 1.0
        elif name == "window_s":
            w[rows[st[rows] > st[rows[-1]] - 2.5]] = 1.0
        elif name == "half_life":
            w[rows] = 0.5 ** ((len(rows) - 1 - np.arange(len(rows))) / 120.0)
        else:
            w[rows] = 0.5 ** ((st[rows[-1]] - st[rows]) / 1.5)
        sums, lag = _weighted_sums(Z, ok, w)
        online, *_ = est.pose_sums()
        online_lag = est.lag_sums()
        assert online.n == pytest.approx(sums.n, rel=1e-12), name
        assert online_lag.n_pairs == pytest.approx(lag.n_pairs, rel=1e-12), name
        assert _rel(online.sum_t, sums.sum_t) < 1e-9 and _rel(online.K, sums.K) < 1e-9, name
        assert _rel(online.sum_qt_t, sums.sum_qt_t) < 1e-9, name
        assert _rel(online_lag.sum_pair, lag.sum_pair) < 1e-9, name
        assert _rel(online_lag.cross, lag.cross) < 1e-9, name
        sol = est.estimate()
        if isinstance(sol, PoseSumsCentre):
            c_p, c_c = sol.centre_parent, sol.centre_child
        else:
            assert isinstance(sol, PoseSumsAxis)
            c_p, c_c = hinge_residual_pair(
                online, sol.direction_parent, sol.direction_child, sol.point_parent, sol.point_child
            )
        rho = lag1_autocorrelation_from_sums(sums, lag, c_p, c_c)
        serial = est.serial_inflation
        assert serial is not None and serial.rho_raw == pytest.approx(rho, abs=1e-7), name
        assert 0.5 < rho < 1.0, name  # AR(1) marker noise with phi = 0.9
        if name == "window":  # rectangular window: the pair of the oldest frame reaches the frame before it
            first = int(rows[-300])
            assert ok[first - 1]
            direct = lag_sums_from_relative(
                np.where(ok[:, None, None], Q, np.nan)[first - 1 :], np.where(ok[:, None], t, np.nan)[first - 1 :]
            )
            assert _rel(direct.cross, lag.cross) < 1e-12
            # the pairs at lags in seconds: those of the window's frames, found among all frames that entered
            contrib = np.zeros((rows.size, N_TIME_LAG_SUMS))
            LagHistory().contributions(st[rows], Z[rows], contrib)
            expected = TimeLagSums.from_vector(contrib[-300:].sum(axis=0))
            online_tl = est.time_lag_sums()
            assert online_tl.n_gaps == expected.n_gaps and online_tl.frame_interval == pytest.approx(
                expected.frame_interval, rel=1e-12
            )
            for got, want in zip(online_tl.nodes, expected.nodes, strict=True):
                assert got.n_pairs == want.n_pairs and want.n_pairs > 100
                assert _rel(got.sum_pair, want.sum_pair) < 1e-9 and _rel(got.cross, want.cross) < 1e-9
            np.testing.assert_allclose(online_tl.sum_lags, expected.sum_lags, rtol=1e-9)
            whole = time_lag_sums_from_relative(
                np.where(ok[:, None, None], Q, np.nan), np.where(ok[:, None], t, np.nan), st
            )
            np.testing.assert_allclose(whole.sum_lags, contrib.sum(axis=0)[2:].reshape(-1, 30)[:, 29], rtol=1e-12)


def test_lag_pairs_follow_the_frames_that_enter_the_statistics() -> None:
    """The boundary convention, counted: a pair needs the previous frame to have entered the statistics."""
    rng = np.random.default_rng(5)
    motion = two_segment_motion(rng)
    yp, yc = motion.markers_at(np.arange(100) / RATE)
    yp = yp + rng.normal(0.0, 0.5, yp.shape)
    yc = yc + rng.normal(0.0, 0.5, yc.shape)
    est = OnlineJoint("ball", window=1000, templates=(motion.template_parent, motion.template_child))
    for k in range(40):
        est.update(yp[k], yc[k], k / RATE)
    assert est.lag_sums().n_pairs == 39  # the first frame has no predecessor
    est.update(yp[40], yc[40], 39 / RATE)  # stamp not increasing: dropped, the chain goes on
    est.update(yp[41], np.full_like(yc[41], np.nan), 41 / RATE)  # child not posed: the chain breaks
    est.update(yp[42], yc[42], 42 / RATE)
    est.update(yp[43], yc[43], 43 / RATE)
    assert (est.n_window, est.lag_sums().n_pairs) == (42, 40)
    est.freeze()
    est.update(yp[44], yc[44], 44 / RATE)  # frozen: not in the statistics, the chain breaks
    est.thaw()
    est.update(yp[45], yc[45], 45 / RATE)
    est.update(yp[46], yc[46], 46 / RATE)
    assert (est.n_window, est.lag_sums().n_pairs) == (44, 41)
    small = OnlineJoint("ball", window=3, templates=(motion.template_parent, motion.template_child))
    for k in range(10):
        small.update(yp[k], yc[k], k / RATE)
    assert (small.n_window, small.lag_sums().n_pairs) == (3, 3)  # the oldest frame keeps its pair


# --------------------------------------------------------------------------- the correction


def _integrated_from_sums(est: OnlineJoint, sol: PoseSumsCentre | PoseSumsAxis) -> float:
    """:func:`integrated_factor` of the estimator's window at ``sol`` (uninflated), from its public sums."""
    sums = est.pose_sums()[0]
    if isinstance(sol, PoseSumsCentre):
        c_p, c_c = sol.centre_parent, sol.centre_child
    else:
        c_p, c_c = hinge_residual_pair(sums, sol.direction_parent, sol.direction_child, sol.point_parent,
                                       sol.point_child)
    tl = est.time_lag_sums()
    nodes = lag_nodes(est.lag_sums(), tl)
    ss = residual_sum_squares_from_sums(sums, c_p, c_c) / sums.n
    lags = [x for x, _ in nodes]
    rhos = [residual_lag_sum_from_sums(node, c_p, c_c) / node.n_pairs / ss for _, node in nodes]
    return integrated_factor(lags, rhos, tl.frame_interval, sums.n, [node.n_pairs for _, node in nodes])



@pytest.mark.parametrize("kind", ["ball", "hinge"])
def test_correction_scales_the_estimate_and_the_estimate_part_of_the_world_output(kind: str) -> None:
    rng = np.random.default_rng(21 if kind == "ball" else 22)
    motion = two_segment_motion(rng, kind=kind)
    yp, yc = motion.markers_at(np.arange(1200) / RATE)
    yp = yp + _ar1(rng, yp.shape, 0.95, 1.0)
    yc = yc + _ar1(rng, yc.shape, 0.95, 1.0)
    on = OnlineJoint(kind, window=800, template_frames=40)
    off = OnlineJoint(kind, window=800, template_frames=40, serial_correlation=False)
    for k in range(1199):
        on.update(yp[k], yc[k])
        off.update(yp[k], yc[k])
    a, b = on.estimate(), off.estimate()
    s_on, s_off = on.serial_inflation, off.serial_inflation
    assert s_on is not None and s_off is not None
    assert s_on.rho_raw == s_off.rho_raw and 0.8 < s_on.rho < RHO_MAX
    # The factor is the residual's integrated autocorrelation over lags in seconds (no longer the AR(1)
    # (1 + rho) / (1 - rho) of the lag-1 correlation, which is not rate-invariant), from the window's sums.
    assert s_on.factor == pytest.approx(_integrated_from_sums(on, b), rel=1e-9) and s_off.factor == 1.0
    assert 10.0 < s_on.factor < 60.0  # AR(1) noise, phi = 0.95 per 10 ms: (1 + phi) / (1 - phi) = 39
    assert s_on.frame_interval_s == pytest.approx(1.0 / RATE)  # no stamps: frames at the nominal 100 Hz
    names = ["cov", "cov_parent", "cov_child"] if kind == "ball" else [
        "cov_direction_parent", "cov_direction_child", "cov_point_parent", "cov_point_child"
    ]
    for name in names:
        np.testing.assert_allclose(getattr(a, name), s_on.factor * getattr(b, name), rtol=1e-12, atol=0.0)
    out_a, out_b = on.update(yp[1199], yc[1199]), off.update(yp[1199], yc[1199])
    assert out_a is not None and out_b is not None
    np.testing.assert_array_equal(out_a.position, out_b.position)
    # The frame's own parent pose noise is not multiplied: only the estimate's covariance (rotated).
    local = a.cov_parent if isinstance(a, PoseSumsCentre) else a.cov_point_parent
    local_off = b.cov_parent if isinstance(b, PoseSumsCentre) else b.cov_point_parent
    diff = out_a.cov - out_b.cov
    # diff = R_p (local - local_off) R_p^T: same eigenvalues as the local difference
    np.testing.assert_allclose(
        np.linalg.eigvalsh(diff), np.linalg.eigvalsh(local - local_off), rtol=1e-9, atol=1e-12 * np.abs(local).max()
    )
    with pytest.raises(InputError, match="serial_correlation"):
        OnlineJoint(kind, window=10, serial_correlation="yes")  # type: ignore[arg-type]


def _local_truth(motion: TwoSegmentMotion) -> dict[str, FloatArray]:
    """True joint in the (fixed, true) template frames."""
    out = {"centre_parent": motion.centre_parent, "centre_child": motion.centre_child}
    for side in ("parent", "child"):
        n, c = motion.axis, out[f"centre_{side}"]
        out[f"direction_{side}"] = n
        out[f"point_{side}"] = c - n * (n @ c)
    return out


@pytest.mark.parametrize(("kind", "seed"), [("ball", 31), ("hinge", 32)])
def test_calibrated_under_ar1_marker_noise(kind: str, seed: int) -> None:
    """40 seeded streams of 2000 frames at 100 Hz with AR(1) marker noise (phi = 0.95, 1 mm, independent per
    marker coordinate; fixed true templates, so that the noise level is estimated from the poses alone).

    Without the correction the mean e/rank is ~(1 + phi) / (1 - phi) = 39 (measured 27-40); with it
    ~0.7-1.1 (conservative when the motion changes within a correlation time)."""
    rng = np.random.default_rng(seed)
    keys = ["centre_parent", "centre_child"] if kind == "ball" else [
        "direction_parent", "direction_child", "point_parent", "point_child"
    ]
    e_on: dict[str, list[float]] = {k: [] for k in keys}
    e_world: list[float] = []
    rhos: list[float] = []
    factors: list[float] = []
    n = 2000
    for _ in range(40):
        motion = two_segment_motion(rng, kind=kind)
        times = np.arange(n) / RATE
        yp, yc = motion.markers_at(times)
        yp = yp + _ar1(rng, yp.shape, 0.95, 1.0)
        yc = yc + _ar1(rng, yc.shape, 0.95, 1.0)
        est = OnlineJoint(kind, window=10 * n, templates=(motion.template_parent, motion.template_child))
        for k in range(n - 1):
            est.update(yp[k], yc[k])
        sol = est.estimate()
        serial = est.serial_inflation
        assert serial is not None
        rhos.append(serial.rho_raw)
        factors.append(serial.factor)
        truth = _local_truth(motion)
        for key in keys:
            value, true = getattr(sol, key), truth[key]
            if key.startswith("direction") and value @ true < 0:
                true = -true
            cov = getattr(sol, "cov_" + key.split("_")[1]) if kind == "ball" else getattr(sol, "cov_" + key)
            e_on[key].append(mahalanobis(value - true, cov))
        out = est.update(yp[n - 1], yc[n - 1])
        if kind == "ball" and out is not None:
            e_world.append(mahalanobis(out.position - motion.centre_world_at(times[n - 1 :])[0], out.cov))
    assert np.mean(rhos) == pytest.approx(0.95, abs=0.01)
    factor = np.array(factors)  # what was applied (the integrated autocorrelation)
    for key, values in e_on.items():
        with_corr = float(np.mean(values))
        without = float(np.mean(np.array(values) * factor))  # the covariance without the factor
        print(f"{kind} {key}: mean e/rank with {with_corr:.2f}, without {without:.1f}")
        assert without > 10.0, key
        assert 0.6 <= with_corr <= 1.6, key
    if e_world:
        print(f"{kind} world centre: mean e/3 {np.mean(e_world):.2f}")
        assert 0.6 <= np.mean(e_world) <= 1.6


# --------------------------------------------------------------------------- calibration files


def test_calibration_round_trip_with_and_without_the_serial_keys() -> None:
    rng = np.random.default_rng(41)
    motion = two_segment_motion(rng)
    yp, yc = motion.markers_at(np.arange(600) / RATE)
    yp = yp + _ar1(rng, yp.shape, 0.9, 1.0)
    yc = yc + _ar1(rng, yc.shape, 0.9, 1.0)
    est = OnlineJoint("ball", window=1000, template_frames=30, serial_correlation=False)
    for k in range(500):
        est.update(yp[k], yc[k])
    data = est.to_dict()
    assert data["serial_correlation"] is False and data["serial_inflation"]["factor"] == 1.0
    back = OnlineJoint.from_dict(data)
    assert back.serial_correlation is False and back.serial_inflation == est.serial_inflation
    old = {k: v for k, v in data.items() if k not in ("serial_correlation", "serial_inflation")}
    legacy = OnlineJoint.from_dict(old)  # a calibration written before these keys existed
    assert legacy.serial_correlation is True and legacy.serial_inflation is None
    for restored in (back, legacy):
        a, b = restored.update(yp[550], yc[550]), est.update(yp[550], yc[550])
        assert a is not None and b is not None
        np.testing.assert_allclose(a.cov, b.cov, rtol=1e-12)
    bad = dict(data, serial_inflation=[1.0])
    with pytest.raises(InputError, match="serial_inflation"):
        OnlineJoint.from_dict(bad)


# --------------------------------------------------------------------------- real skin markers


def test_real_hip_reports_an_honest_spread() -> None:
    """Skin markers on a hip: the residual is smooth (rho ~ 0.99); the factor is its integrated autocorrelation
    over 3 s, ~28 effective frames at 100 Hz and at 12.5 Hz (bench/results/serial_lags.md, from the batch fit's
    residual), and the online sd stays below 3x the batch fit's model-error-inflated sd.

    (Until the factor was rate-invariant this test asked for the sd within 3x of the batch's either way; the
    lag-1 AR(1) factor, 182 here, over-states the correlation at 100 Hz: with the integrated factor, 56, the
    sd is 3.4x below the batch's, which also carries a model-error inflation the online estimate has not.)"""
    pytest.importorskip("ezc3d")
    from jointfit_core.io import read_c3d
    from jointfit_core.segments import fit_centre_two_segments

    data = read_c3d(DATA / "biobuddy" / "right_hip.c3d")
    pelvis = data.select(["RASIS", "LASIS", "RPSIS", "LPSIS"])
    thigh = data.select(["RTHI1", "RTHI2", "RTHI3"])
    on = OnlineJoint("ball", window=3000)
    off = OnlineJoint("ball", window=3000, serial_correlation=False)
    for k in range(pelvis.shape[0]):
        on.update(pelvis[k], thigh[k])
        off.update(pelvis[k], thigh[k])
    sol, raw = on.estimate(), off.estimate()
    assert isinstance(sol, PoseSumsCentre) and isinstance(raw, PoseSumsCentre)
    # Like with like: the batch fit's residual inflation (attachment="rigid"). The skin default adds a
    # soft-tissue prior that the online estimator does not have yet: larger still, and checked below.
    batch = fit_centre_two_segments(pelvis, thigh, attachment="rigid")
    skin = fit_centre_two_segments(pelvis, thigh)
    assert np.trace(skin.cov_parent) > np.trace(batch.cov_parent)
    sd_on = np.sqrt(np.diag(sol.cov_parent))
    sd_off = np.sqrt(np.diag(raw.cov_parent))
    sd_batch = np.sqrt(np.diag(batch.cov_parent))
    serial = on.serial_inflation
    assert serial is not None
    print(f"hip: rho {serial.rho:.4f}, factor {serial.factor:.0f}; sd (mm) online before {np.round(sd_off, 2)}, "
          f"after {np.round(sd_on, 2)}, batch {np.round(sd_batch, 2)}")
    assert serial.rho > 0.95
    assert np.all(sd_off < sd_batch / 10)  # what the online estimator used to report
    assert np.all(sd_on > 5 * sd_off) and np.all(sd_on < 3 * sd_batch)
    assert sol.identifiable, sol.reason
    effective = on.n_window / serial.factor
    sub = OnlineJoint("ball", window=3000)
    sub.update_many(pelvis[::8], thigh[::8], np.arange(0, pelvis.shape[0], 8) / 100.0)  # 12.5 Hz
    sub.estimate()
    assert sub.serial_inflation is not None
    effective_sub = sub.n_window / sub.serial_inflation.factor
    print(f"effective frames {effective:.1f} at 100 Hz, {effective_sub:.1f} at 12.5 Hz")
    assert 20.0 < effective < 40.0
    assert effective_sub == pytest.approx(effective, rel=0.15)  # the same seconds hold the same information
