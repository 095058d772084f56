"""Block updates: SlidingSums.push_many and OnlineJoint.update_many against one frame at a time.

The offline fit (``jointfit fit``) gives whole blocks of frames to the
estimators; the node gives them one by one. Both must end in the same state:
the same counters, stamps, templates and frames in the window, and sums
equal to rounding (SlidingSums.push_many alone is bit for bit for frame and
time windows; update_many poses its frames with a vectorised eigen-solve, to
~1e-13). Streams have occlusions, frames a segment cannot be posed in,
repeated and backward stamps, and block boundaries anywhere, including
inside template building.
"""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np
import pytest
from helpers import SUMS_RTOL, rel_diff
from numpy.typing import NDArray

from jointfit_core.errors import InputError
from jointfit_core.estimator import OnlineJoint
from jointfit_core.stats import SlidingSums, WindowSpec
from jointfit_core.synthetic import two_segment_motion

FloatArray = NDArray[np.float64]
RATE = 60.0

WINDOWS: list[dict[str, Any]] = [
    {"window": 100_000},  # covers the stream: the sums only grow (the offline fit's case)
    {"window": 250},
    {"window_s": 4.0},
    {"half_life": 150.0},
    {"half_life_s": 2.5},
]


# --------------------------------------------------------------------------- SlidingSums.push_many


def _ring_state(s: SlidingSums) -> dict[str, Any]:
    state: dict[str, Any] = {"sums": s.sums.copy(), "n_window": s.n_window, "n_pushed": s.n_pushed, "last": s.last_stamp}
    if not s.spec.exponential:
        state["records"] = s.window_records()
        state["stamps"] = s.window_stamps()
        state["shadow"] = s._shadow.copy()  # the drift control's rebuild, also replayed exactly
        state["shadow_at"] = (s._shadow_active, s._shadow_next, s._shadow_end)
    return state


@pytest.mark.parametrize("width", [1, 7, 262])
def test_push_many_equals_pushes(width: int) -> None:
    """Random specs, blocks, stamp gaps (several frames leaving at once), ring growth and its cap."""
    rng = np.random.default_rng(width)
    for trial in range(120):
        kind = trial % 4
        max_frames = 1_000_000
        if kind == 0:
            spec = WindowSpec(frames=int(rng.integers(3, 40)))
        elif kind == 1:
            spec = WindowSpec(seconds=float(rng.uniform(0.05, 1.0)))
            max_frames = int(rng.choice([1_000_000, 5, 17, 100]))
        elif kind == 2:
            spec = WindowSpec(half_life=float(rng.uniform(1.0, 50.0)))
        else:
            spec = WindowSpec(half_life_s=float(rng.uniform(0.05, 1.0)))
        one = SlidingSums(spec, width, width, None, max_frames=max_frames)
        many = SlidingSums(spec, width, width, None, max_frames=max_frames)
        t = 0.0
        stamped = kind in (1, 3) or bool(rng.integers(2))
        for _ in range(int(rng.integers(1, 8))):
            m = int(rng.integers(1, 200))
            records = rng.normal(size=(m, width)) * 10.0 ** rng.integers(-3, 3, size=(m, 1))
            stamps = t + np.cumsum(rng.choice([0.01, 0.01, 0.01, 0.03, 0.2, 0.0, 2.0], size=m))
            t = float(stamps[-1])
            for k in range(m):
                one.push(records[k], float(stamps[k]) if stamped else None)
            many.push_many(records, stamps if stamped else None)
            a, b = _ring_state(one), _ring_state(many)
            assert a.keys() == b.keys()
            for key in a:
                if key == "sums" and spec.exponential:
                    assert rel_diff(b[key], a[key]) < 1e-12
                elif isinstance(a[key], np.ndarray):
                    np.testing.assert_array_equal(b[key], a[key], err_msg=key)
                else:
                    assert b[key] == a[key], key


def test_push_many_unsorted_stamps_and_bad_input() -> None:
    """Stamps out of order in a time window are pushed one by one (the same result); bad blocks add nothing."""
    rng = np.random.default_rng(1)
    spec = WindowSpec(seconds=0.5)
    one, many = SlidingSums(spec, 5, 5, None), SlidingSums(spec, 5, 5, None)
    records = rng.normal(size=(60, 5))
    stamps = np.cumsum(rng.uniform(0.0, 0.05, 60))
    stamps[30] -= 0.2
    for k in range(60):
        one.push(records[k], float(stamps[k]))
    many.push_many(records[:20], stamps[:20])
    many.push_many(records[20:], stamps[20:])
    np.testing.assert_array_equal(many.sums, one.sums)
    np.testing.assert_array_equal(many.window_records(), one.window_records())
    before = many.sums.copy()
    with pytest.raises(InputError, match="needs a stamp"):
        many.push_many(records[:3])
    with pytest.raises(InputError, match=r"shape \(M, 5\)"):
        many.push_many(records[:3, :4], stamps[:3])
    with pytest.raises(InputError, match=r"stamps: expected shape \(3,\)"):
        many.push_many(records[:3], stamps[:4])
    np.testing.assert_array_equal(many.sums, before)
    assert many.n_pushed == 60


# --------------------------------------------------------------------------- OnlineJoint.update_many


def _stream(
    rng: np.random.Generator, kind: str, n: int, n_markers: tuple[int, int] = (4, 5)
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Noisy markers with occlusions, frames a segment cannot be posed in, bad stamps."""
    motion = two_segment_motion(rng, kind=kind, n_markers=n_markers)
    times = np.arange(n) / RATE
    yp, yc = motion.markers_at(times)
    yp = yp + rng.normal(0.0, 0.5, yp.shape)
    yc = yc + rng.normal(0.0, 0.5, yc.shape)
    for y in (yp, yc):
        y[rng.random(y.shape[:2]) < 0.04] = np.nan  # occlusions, some leaving fewer than 3 markers
    yp[rng.random(n) < 0.01, :2] = np.nan  # parent not posed
    yc[rng.random(n) < 0.01, :3] = np.nan  # child not posed
    yp[7, 1, 2] = np.nan  # one NaN coordinate: the marker is missing as a whole
    stamps = times.copy()
    a, b, c = n // 10, n // 5, n // 3
    stamps[a] = stamps[a - 1]  # repeated
    stamps[b : b + 4] = stamps[b - 40]  # backward
    stamps[c] = stamps[c - 1] + 0.5  # a jump: the next 30 frames are behind it
    return yp, yc, stamps


def _state(est: OnlineJoint) -> dict[str, Any]:
    s = est.statistics.window
    assert s is not None
    out: dict[str, Any] = {
        "sums": s.sums.copy(),
        "dropped": dict(est.dropped),
        "n_frames_seen": est.n_frames_seen,
        "n_window": est.n_window,
        "templates": est.templates,
    }
    if not s.spec.exponential:
        out["stamps"] = s.window_stamps()
        out["shadow"] = s._shadow.copy()
    return out


def _assert_same(many: OnlineJoint, one: OnlineJoint, exact: bool) -> None:
    """Counters, stamps and templates equal; sums equal to rounding (see helpers.SUMS_RTOL).

    ``exact``: frame and time windows, whose window holds the same frames; else exponential
    forgetting, whose block form also adds in another order (still well inside SUMS_RTOL).
    """
    a, b = _state(many), _state(one)
    for key in b:
        if key == "templates":
            for ta, tb in zip(a[key], b[key], strict=True):
                np.testing.assert_array_equal(ta, tb)
        elif key in ("sums", "shadow"):
            assert rel_diff(a[key], b[key]) < SUMS_RTOL, key
        elif isinstance(b[key], np.ndarray):
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)
        else:
            assert a[key] == b[key], key


@pytest.mark.parametrize("kind", ["ball", "hinge"])
@pytest.mark.parametrize("window", WINDOWS, ids=lambda w: "-".join(f"{k}={v}" for k, v in w.items()))
def test_update_many_equals_updates(kind: str, window: dict[str, Any]) -> None:
    rng = np.random.default_rng(len(kind) * 100 + len(str(window)))
    yp, yc, stamps = _stream(rng, kind, 1600)
    exact = not ("half_life" in window or "half_life_s" in window)
    one = OnlineJoint(kind, template_frames=40, **window)
    many = OnlineJoint(kind, template_frames=40, **window)
    for k in range(len(stamps)):
        one.update(yp[k], yc[k], stamps[k])
    # block edges anywhere, the first inside template building; a single frame too
    edges = np.unique(np.concatenate([[0, 17, 18, len(stamps)], rng.integers(18, len(stamps), 9)]))
    for lo, hi in itertools.pairwise(edges.tolist()):
        many.update_many(yp[lo:hi], yc[lo:hi], stamps[lo:hi])
    assert one.dropped.keys() >= {"parent_not_posed", "child_not_posed", "stamp_not_increasing"}
    _assert_same(many, one, exact)
    assert many.lag_sums().n_pairs == pytest.approx(one.lag_sums().n_pairs, rel=0.0 if exact else 1e-12)
    sol_a, sol_b = many.estimate(), one.estimate()
    assert sol_a.n_frames == sol_b.n_frames and sol_a.identifiable == sol_b.identifiable
    assert sol_a.rms == pytest.approx(sol_b.rms, rel=1e-9)
    # the lag-pair and stamp state carry on: more frames one at a time keep both equal
    more_p, more_c, more_t = _stream(rng, kind, 200)
    for est in (one, many):
        for k in range(200):
            est.update(more_p[k], more_c[k], stamps[-1] + 1.0 + more_t[k])
    _assert_same(many, one, exact)
    assert many.lag_sums().n_pairs == pytest.approx(one.lag_sums().n_pairs, rel=0.0 if exact else 1e-12)


def test_update_many_without_stamps_fixed_templates_and_frozen() -> None:
    """Frame windows need no stamps; fixed templates skip the sequential start; frozen adds nothing but counts."""
    rng = np.random.default_rng(11)
    motion = two_segment_motion(rng, kind="ball")
    yp, yc, _ = _stream(rng, "ball", 900, (4, 4))
    templates = (motion.template_parent, motion.template_child)
    one = OnlineJoint("ball", window=300, templates=templates)
    many = OnlineJoint("ball", window=300, templates=templates)
    for k in range(600):
        one.update(yp[k], yc[k])
    many.update_many(yp[:250], yc[:250])
    many.update_many(yp[250:600], yc[250:600])
    _assert_same(many, one, exact=True)
    one.freeze()
    many.freeze()
    sums = many.statistics.window.sums.copy()  # type: ignore[union-attr]
    for k in range(600, 750):
        one.update(yp[k], yc[k])
    many.update_many(yp[600:750], yc[600:750])
    np.testing.assert_array_equal(many.statistics.window.sums, sums)  # type: ignore[union-attr]
    _assert_same(many, one, exact=True)
    one.thaw()
    many.thaw()
    for k in range(750, 900):
        one.update(yp[k], yc[k])
    many.update_many(yp[750:], yc[750:])
    _assert_same(many, one, exact=True)


def test_update_many_checks_the_whole_block_first() -> None:
    rng = np.random.default_rng(12)
    yp, yc, stamps = _stream(rng, "hinge", 300)
    est = OnlineJoint("hinge", window_s=2.0, template_frames=30)
    est.update_many(yp[:200], yc[:200], stamps[:200])
    before = _state(est)
    bad_p = yp[200:260].copy()
    bad_p[40, 2] = np.inf
    bad_stamps = stamps[200:260].copy()
    bad_stamps[30] = np.nan
    cases = [
        ((bad_p, yc[200:260], stamps[200:260]), "parent: contains inf"),
        ((yp[200:260], yc[200:260], bad_stamps), "finite"),
        ((yp[200:260], yc[200:260], None), "needs a stamp"),
        ((yp[200:260, :3], yc[200:260], stamps[200:260]), "expected 4 markers"),
        ((yp[200:260], yc[200:250], stamps[200:260]), "same number of frames"),
        ((yp[200:260, 0], yc[200:260], stamps[200:260]), r"shape \(N, P, 3\)"),
        ((yp[200:260], yc[200:260], stamps[200:250]), r"stamps: expected shape \(60,\)"),
        ((yp[200:260] + 0j, yc[200:260], stamps[200:260]), "complex"),
    ]
    for args, match in cases:
        with pytest.raises(InputError, match=match):
            est.update_many(*args)
        after = _state(est)
        np.testing.assert_array_equal(after["sums"], before["sums"])
        assert after["dropped"] == before["dropped"] and after["n_frames_seen"] == before["n_frames_seen"]
    est.update_many(yp[200:200], yc[200:200], stamps[200:200])  # an empty block is fine
    fresh = OnlineJoint("ball", window=10)
    with pytest.raises(InputError, match="at least 3 markers"):
        fresh.update_many(np.zeros((5, 2, 3)), np.zeros((5, 4, 3)))


def test_push_weighted_sum_equals_push_many() -> None:
    """Exponential forgetting: a block given as its weighted sum ends where push_many of its rows does."""
    rng = np.random.default_rng(21)
    b, t0 = SlidingSums(WindowSpec(half_life=40.0), 5, 5, None), 0.0
    for spec in (WindowSpec(half_life=40.0), WindowSpec(half_life_s=0.7)):
        a = SlidingSums(spec, 5, 5, None)
        b = SlidingSums(spec, 5, 5, None)
        t0 = 0.0
        for m in (1, 17, 60):
            c = rng.normal(size=(m, 5))
            st = t0 + np.cumsum(rng.uniform(0.005, 0.02, m))
            t0 = float(st[-1])
            a.push_many(c, st)
            w, w_old = b.block_weights(m, st)
            b.push_weighted_sum(w @ c, w_old, m, st)
            assert rel_diff(b.sums, a.sums) < 1e-14 and b.n_pushed == a.n_pushed and b.last_stamp == a.last_stamp
    ring = SlidingSums(WindowSpec(frames=10), 5, 5, None)
    with pytest.raises(InputError, match="exponential"):
        ring.push_weighted_sum(np.zeros(5), 1.0, 1, None)
    with pytest.raises(InputError, match="shape"):
        b.push_weighted_sum(np.zeros(4), 1.0, 1, np.array([t0 + 1.0]))
