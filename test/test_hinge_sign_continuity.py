"""A hinge's axis keeps its sign from solve to solve without a configured convention.

Without ``axis_toward_marker`` the sign rule is "the parent-frame component of largest magnitude
is positive". Template frames are arbitrary, so an axis with two components about as large is
ordinary; each solve's noise then decided which was larger, and the published axis (and the
joint angle's sign) flipped between solves. The first identifiable estimate now sets the sign
and later solves follow it.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from jointfit_core.estimator import OnlineJoint
from jointfit_core.hinge_from_sums import PoseSumsAxis

RATE = 100.0


def _hinge(seed: int, seconds: float = 12.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A still parent and a child swinging 0-60 deg about an axis whose x and -y components are equal (mm)."""
    rng = np.random.default_rng(seed)
    axis = np.array([1.0, -1.0, 0.05]) / np.linalg.norm([1.0, -1.0, 0.05])
    point = np.array([0.0, 0.0, -250.0])
    parent_tpl = rng.normal(0.0, 60.0, (4, 3))
    child_tpl = rng.normal(0.0, 60.0, (4, 3)) + np.array([0.0, 0.0, -450.0])
    t = np.arange(round(seconds * RATE)) / RATE
    angle = np.radians(30.0) * (1.0 - np.cos(2.0 * np.pi * t / 2.5))
    R = Rotation.from_rotvec(angle[:, None] * axis).as_matrix()
    child = np.einsum("nij,pj->npi", R, child_tpl - point) + point
    parent = np.broadcast_to(parent_tpl, (t.size, 4, 3)).copy()
    return t, parent + rng.normal(0.0, 0.8, parent.shape), child + rng.normal(0.0, 0.8, child.shape)


def _directions(seed: int) -> list[np.ndarray]:
    """The identifiable estimates' parent-frame directions, solved every 0.1 s over a 2 s window."""
    t, parent, child = _hinge(seed)
    est = OnlineJoint("hinge", window_s=2.0, attachment="rigid")
    out = []
    for lo in range(0, t.size, 10):
        est.update_many(parent[lo : lo + 10], child[lo : lo + 10], t[lo : lo + 10])
        if est.templates_ready and est.n_window >= 10:
            sol = est.estimate()
            if sol.identifiable:
                assert isinstance(sol, PoseSumsAxis)
                out.append(sol.direction_parent.copy())
    return out


def test_the_axis_sign_does_not_flip_between_solves() -> None:
    """Over 4 streams, ~100 solves each: no consecutive pair of estimates points apart.

    With the per-solve rule these streams flipped 10, 3, 5 and 22 times in 115 solves (the two
    largest components of the estimated axis differ by less than its noise).
    """
    for seed in range(4):
        dirs = np.array(_directions(seed))
        assert len(dirs) > 50, len(dirs)
        dots = np.einsum("ni,ni->n", dirs[1:], dirs[:-1])
        assert (dots > 0.0).all(), (seed, int(np.sum(dots < 0.0)))


def test_the_first_identifiable_estimate_follows_the_default_rule() -> None:
    """The sign the stream keeps is the default rule's at the first identifiable estimate."""
    first = _directions(0)[0]
    assert first[int(np.argmax(np.abs(first)))] > 0.0
