"""The outlier gate drops swapped, ghost and jumping markers before they reach the statistics.

Acceptance (issue 7): on the real label swap of right_hip.c3d (RLFE/RMFE from
about frame 700) and on injected swaps, ghosts and jumps, the estimate with
the gate stays within its reported uncertainty of the clean estimate; without
the gate it does not. The block path (``update_many``) gates exactly as the
per-frame path.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers import mahalanobis
from numpy.typing import NDArray

from jointfit_core.estimator import OnlineJoint
from jointfit_core.synthetic import two_segment_motion

DATA = Path(__file__).parent / "data"
PELVIS = ["RASIS", "LASIS", "RPSIS", "LPSIS"]


def _stream(est: OnlineJoint, parent: NDArray[np.float64], child: NDArray[np.float64], every: int = 50) -> None:
    """Frames at 100 Hz, re-estimating every ``every`` frames as the node and jointfit fit do."""
    for k in range(parent.shape[0]):
        est.update(parent[k], child[k], k / 100.0)
        if k % every == every - 1 and est.templates_ready:
            est.estimate()


def test_real_label_swap_right_hip() -> None:
    pytest.importorskip("ezc3d")
    from jointfit_core.io import read_c3d

    data = read_c3d(DATA / "biobuddy" / "right_hip.c3d")
    pelvis = data.select(PELVIS)
    clean_est = OnlineJoint("ball", window=5000)
    _stream(clean_est, pelvis, data.select(["RTHI1", "RTHI2", "RTHI3"]))
    clean = clean_est.estimate()
    # The thigh with the two epicondyle markers whose labels swap from about frame 700.
    thigh = data.select(["RTHI1", "RTHI2", "RTHI3", "RLFE", "RMFE"])
    results = {}
    for gate in (5.0, 0.0):
        est = OnlineJoint("ball", window=5000, gate=gate)
        _stream(est, pelvis, thigh)
        results[gate] = (est.estimate(), est.dropped)
    gated, dropped = results[5.0]
    ungated, _ = results[0.0]
    # Same parent markers, so the same parent frame: compare the centres there.
    assert mahalanobis(gated.centre_parent - clean.centre_parent, gated.cov_parent) < 3.0**2 * 3
    assert np.linalg.norm(gated.centre_parent - clean.centre_parent) < 5.0  # mm; sd is ~8-12 mm here
    assert gated.identifiable
    # Without the gate the swap moves the centre by > 50 mm; the estimate only stays honest by
    # inflating its sd to 60-90 mm and calling itself not identifiable: useless either way.
    assert np.linalg.norm(ungated.centre_parent - clean.centre_parent) > 50.0
    assert not ungated.identifiable
    # About 950 swapped frames, both swapped markers removed in each; the clean thigh markers kept.
    assert 1500 < dropped["child_gated_markers"] < 2200
    assert "child_gated" not in dropped


def _rig(seed: int, n: int = 1500) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    rng = np.random.default_rng(seed)
    motion = two_segment_motion(rng, kind="ball", n_markers=(4, 5))
    parent, child = motion.markers_at(np.arange(n) / 100.0)
    return parent + rng.normal(0, 0.5, parent.shape), child + rng.normal(0, 0.5, child.shape)


def _corrupt(kind: str, parent: NDArray[np.float64], child: NDArray[np.float64], seed: int) -> None:
    """Corrupt about 30 % of the frames after the first 200, in place."""
    rng = np.random.default_rng([seed, 1])
    frames = 200 + np.flatnonzero(rng.random(parent.shape[0] - 200) < 0.3)
    for k in frames:
        seg = child if rng.random() < 0.5 else parent
        a, b = rng.choice(seg.shape[1], 2, replace=False)
        if kind == "swap":
            seg[k, [a, b]] = seg[k, [b, a]]
        elif kind == "ghost":  # a reflection taken for the marker: 20-80 mm away
            direction = rng.normal(size=3)
            seg[k, a] += rng.uniform(20, 80) * direction / np.linalg.norm(direction)
        else:  # jump: two markers of a segment off by a few cm (a bumped cluster, a mislabelled pair)
            seg[k, a] += rng.normal(0, 30, 3)
            seg[k, b] += rng.normal(0, 30, 3)


@pytest.mark.parametrize("kind", ["swap", "ghost", "jump"])
def test_injected_outliers(kind: str) -> None:
    """Gated: within the reported uncertainty of the clean estimate. Ungated: swaps move it far beyond
    its uncertainty while it still claims to be identifiable; ghosts and jumps inflate its residual, so it
    stays honest but is 3-30 times less accurate (median over 4 rigs > 3)."""
    beyond, ratios = 0, []
    for seed in range(4):
        parent, child = _rig(seed)
        clean = OnlineJoint("ball", window=5000)
        _stream(clean, parent, child)
        ref = clean.estimate()
        _corrupt(kind, parent, child, seed)
        est = OnlineJoint("ball", window=5000)
        _stream(est, parent, child)
        sol = est.estimate()
        err = np.concatenate([sol.centre_parent - ref.centre_parent, sol.centre_child - ref.centre_child])
        assert sol.identifiable and mahalanobis(err, sol.cov) < 3.0**2 * 6, (kind, seed, err)
        assert sum(v for k, v in est.dropped.items() if "gated" in k) > 200
        bad = OnlineJoint("ball", window=5000, gate=0.0)
        _stream(bad, parent, child)
        ub = bad.estimate()
        err_u = np.concatenate([ub.centre_parent - ref.centre_parent, ub.centre_child - ref.centre_child])
        beyond += ub.identifiable and mahalanobis(err_u, ub.cov) > 3.0**2 * 6
        ratios.append(float(np.linalg.norm(err_u) / np.linalg.norm(err)))
    if kind == "swap":
        assert beyond >= 3
    assert np.median(ratios) > 3.0 and min(ratios) > 2.0, ratios


def test_block_path_gates_exactly_as_the_frame_path() -> None:
    parent, child = _rig(7, 1200)
    _corrupt("swap", parent, child, 7)
    one = OnlineJoint("hinge", window=800)
    many = OnlineJoint("hinge", window=800)
    stamps = np.arange(parent.shape[0]) / 100.0
    for start in range(0, parent.shape[0], 150):
        stop = start + 150
        for k in range(start, min(stop, parent.shape[0])):
            one.update(parent[k], child[k], stamps[k])
        many.update_many(parent[start:stop], child[start:stop], stamps[start:stop])
        if one.templates_ready:
            one.estimate()
            many.estimate()
    assert one.dropped == many.dropped and any("gated" in k for k in one.dropped)
    assert one.to_dict()["estimate"] == many.to_dict()["estimate"]


def test_gate_is_saved_and_validated() -> None:
    parent, child = _rig(3, 400)
    est = OnlineJoint("ball", window=1000, gate=4.0)
    _stream(est, parent, child)
    assert OnlineJoint.from_dict(est.to_dict()).gate == 4.0
    from jointfit_core.errors import InputError

    with pytest.raises(InputError, match="gate"):
        OnlineJoint("ball", window=10, gate=-1.0)


def test_swap_while_the_templates_are_built() -> None:
    """A label swap in the first frames is left out of the template, and the gate works from the start."""
    parent, child = _rig(11, 1200)
    clean = OnlineJoint("ball", window=5000)
    _stream(clean, parent, child)
    ref = clean.estimate()
    child[10:25, [0, 2]] = child[10:25, [2, 0]]  # 15 of the 50 template frames
    parent[60:90, [1, 3]] = parent[60:90, [3, 1]]  # kept aside with the template frames, replayed after
    est = OnlineJoint("ball", window=5000)
    _stream(est, parent, child)
    sol = est.estimate()
    err = np.concatenate([sol.centre_parent - ref.centre_parent, sol.centre_child - ref.centre_child])
    assert sol.identifiable and mahalanobis(err, sol.cov) < 3.0**2 * 6, err
    assert est.dropped.get("parent_gated", 0) + est.dropped.get("parent_gated_markers", 0) >= 30
    # The template is the clean cluster: its inter-marker distances are the true ones.
    tc = est.templates[1]
    assert tc is not None
    true_d = np.linalg.norm(child[200, :, None] - child[200, None, :], axis=2)
    assert np.abs(np.linalg.norm(tc[:, None] - tc[None, :], axis=2) - true_d).max() < 3.0
