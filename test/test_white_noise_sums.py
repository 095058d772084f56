"""Issue 17, item 1, online: skin markers' white noise read from the second differences, and the bias compensation that uses it.

On a thigh with 20 mm of soft-tissue artefact the pose fit's pooled residual reads ~10.5 mm for
0.7 mm of marker noise; an online ball joint that compensated its second-order bias with that
level moved its centre by ~20 mm (error 57-64 mm against the batch closed form's 45 mm,
``bench/results/sta_online.md``).
"""

from __future__ import annotations

import numpy as np
import pytest

from jointfit_core.artefact import white_noise_std
from jointfit_core.estimator import OnlineJoint
from jointfit_core.joint_sums import _WN
from jointfit_core.pose import poses_from_markers
from jointfit_core.segments import fit_centre_two_segments
from jointfit_core.soft_tissue import hip_motion, skin_markers_at
from jointfit_core.white_noise_sums import SecondDifferences, white_noise_from_sums

NOISE = 0.7  # mm, per coordinate


def _hip(seed: int, mm: float, seconds: float = 30.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    motion = hip_motion(rng)
    t = np.arange(round(seconds * 100.0)) / 100.0
    parent, child = skin_markers_at(rng, motion, t, child_mm=mm, noise_std=NOISE)
    return t, parent, child


@pytest.mark.parametrize("mm", [0.0, 20.0])
def test_the_white_noise_is_the_markers_noise_whatever_the_deformation(mm: float) -> None:
    """Both segments read 0.7 mm to sampling (5 %); the pooled residual reads the thigh's deformation."""
    t, parent, child = _hip(4, mm, seconds=15.0)
    est = OnlineJoint("ball", window=t.size + 10, attachment="skin")
    est.update_many(parent, child, t)
    est.estimate()
    white = est.white_noise_std
    assert white is not None
    np.testing.assert_allclose(white, NOISE, rtol=0.05)
    pooled = est.noise_std
    if mm > 0.0:
        assert pooled[1] > 8.0 * NOISE, pooled  # what the bias compensation used before
    else:
        np.testing.assert_allclose(pooled, NOISE, rtol=0.05)


def test_one_frame_at_a_time_and_blocks_give_the_same_sums_and_the_batch_reading() -> None:
    """Occlusions and a late stamp break the triples alike on both paths; the reading is the batch's to 1 %."""
    t, parent, child = _hip(5, 20.0, seconds=15.0)
    parent[100:103, 1] = np.nan
    child[400, 2] = np.nan
    child[900:905] = np.nan  # the child not posed: the joint's chain breaks
    stamps = t.copy()
    stamps[700] = stamps[650]  # dropped for its stamp: transparent, as for the lag pairs
    one = OnlineJoint("ball", window=t.size + 10, attachment="skin")
    many = OnlineJoint("ball", window=t.size + 10, attachment="skin")
    for k in range(t.size):
        one.update(parent[k], child[k], stamps[k])
    for s in range(0, t.size, 137):
        many.update_many(parent[s : s + 137], child[s : s + 137], stamps[s : s + 137])
    a, b = one.sums_vector(), many.sums_vector()
    assert a is not None and b is not None
    np.testing.assert_allclose(a[_WN], b[_WN], rtol=1e-10)
    assert a[_WN][1] > 0.9 * 6 * (3 * 4 - 6) * t.size  # nearly every frame made a triple
    tp, tc = one.templates
    assert tp is not None and tc is not None
    for markers, template, read in ((parent, tp, white_noise_from_sums(a[_WN])[0]), (child, tc, white_noise_from_sums(a[_WN])[1])):
        poses = poses_from_markers(markers, template)
        batch = white_noise_std(markers, template, poses.R_world_local, poses.d_world_local, poses.valid)
        np.testing.assert_allclose(read, batch, rtol=0.01)


def test_a_sliding_window_forgets_the_triples_of_the_frames_it_drops() -> None:
    """The sums are those of the window's frames: a window of the last 500 frames equals a joint fed those alone."""
    t, parent, child = _hip(6, 10.0, seconds=10.0)
    sliding = OnlineJoint("ball", window=500, attachment="skin")
    sliding.update_many(parent, child, t)
    tp, tc = sliding.templates
    fresh = OnlineJoint("ball", window=500, attachment="skin", templates=(tp, tc))
    fresh.update_many(parent[-502:], child[-502:], t[-502:])  # two frames before the window's first: its triple
    a, b = sliding.sums_vector(), fresh.sums_vector()
    assert a is not None and b is not None
    np.testing.assert_allclose(a[_WN], b[_WN], rtol=1e-9)


def test_the_skin_centre_is_the_batch_closed_form_with_its_templates() -> None:
    """Online (bias compensated with the white noise) equals the batch closed form to 1 % of its sd.

    With the pooled level, as before, the two were ~20 mm (a third of an sd) apart on these trials.
    """
    for seed in (1, 2):
        t, parent, child = _hip(seed, 20.0)
        batch = fit_centre_two_segments(parent, child, weighted=False)
        est = OnlineJoint(
            "ball", window=t.size + 10, attachment="skin", templates=(batch.template_parent, batch.template_child)
        )
        est.update_many(parent, child, t)
        sol = est.estimate()
        sd = float(np.sqrt(np.trace(batch.cov_parent)))
        assert np.linalg.norm(sol.centre_parent - batch.centre_parent) < 0.01 * sd


def test_rigid_markers_keep_no_white_noise_sums() -> None:
    t, parent, child = _hip(7, 0.0, seconds=5.0)
    est = OnlineJoint("ball", window=t.size + 10, attachment="rigid")
    est.update_many(parent, child, t)
    est.estimate()
    sums = est.sums_vector()
    assert sums is not None and not sums[_WN].any()
    assert est.white_noise_std is None


def test_second_differences_need_three_chained_frames_with_the_same_markers() -> None:
    """By hand: zeros until the third chained frame; a marker set change or a break restarts the count."""
    t, parent, child = _hip(8, 0.0, seconds=1.0)
    est = OnlineJoint("ball", window=t.size + 10, attachment="skin")
    est.update_many(parent, child, t)
    pair = est._pose
    assert pair is not None
    full = pair.pair(np.zeros((2, 4), dtype=bool))
    lost = np.zeros((2, 4), dtype=bool)
    lost[1, 0] = True  # the child without its first marker
    partial = pair.pair(lost)
    assert partial.child is not None
    rng = np.random.default_rng(0)
    R = rng.normal(size=(6, 2, 3, 3))
    d = rng.normal(size=(6, 2, 3))
    frames = rng.normal(size=(6, 2, 4, 3))
    paired = np.array([False, True, True, True, False, True])
    sets = [partial if k == 3 else full for k in range(6)]
    wn = np.stack([ps.wn for ps in sets])
    sd = SecondDifferences()  # one frame at a time: blocks of one
    got = [sd.add_many(frames[k : k + 1], wn[k : k + 1], R[k : k + 1], d[k : k + 1], paired[k : k + 1])[0] for k in range(6)]
    local = np.matmul(frames - d[:, :, None, :], R)  # R^T (y - d) as rows
    d2 = local[2] - 2 * local[1] + local[0]
    np.testing.assert_allclose(got[2], [np.sum(d2[0] ** 2), 36.0, np.sum(d2[1] ** 2), 36.0], rtol=1e-12)
    assert not got[0].any() and not got[1].any() and not got[4].any() and not got[5].any()
    assert got[3][1] == 36.0 and got[3][3] == 0.0  # the parent's triple stands, the child's markers changed
    many = SecondDifferences().add_many(frames, wn, R, d, paired)
    np.testing.assert_allclose(many, np.array(got), rtol=1e-12)
