"""A time window fed faster than it can hold: at most ``window_max_frames`` frames enter, evenly in time.

A ``window_s`` window keeps every frame's contribution (5-8.6 KB per frame and joint), so its memory
grew with the input rate: one skin hinge with a 30 s window at 1 kHz took 393 MB of resident memory
(35 s of frames, the ring doubling to 32768 slots), and a 12-joint body ~2.4 GB of rings: a node
that a lab following the short-window advice would see killed. Now at most one frame per
``window_s / window_max_frames`` seconds enters (:mod:`jointfit_core.window_entries`); every frame
still gets its output.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest
from helpers import SUMS_RTOL, rel_diff, rig_frames, rig_router
from numpy.typing import NDArray

from jointfit_core.errors import InputError
from jointfit_core.estimator import OnlineJoint
from jointfit_core.synthetic import two_segment_motion
from jointfit_core.window_entries import WINDOW_MAX_FRAMES, WindowEntries
from jointfit_ros.joint_diagnostics import joint_status
from jointfit_ros.raw import pose_array_bytes

FloatArray = NDArray[np.float64]
T0 = 1.7e9  # epoch-like stamps (s): the bins are cut in absolute stamp time


def _stream(kind: str, rate: float, seconds: float, seed: int = 0) -> tuple[FloatArray, FloatArray, FloatArray, Any]:
    m = two_segment_motion(np.random.default_rng(seed), kind=kind, offset=(2500.0, 3000.0, 900.0))
    t = np.arange(round(rate * seconds)) / rate
    rng = np.random.default_rng(100 + seed)
    yp, yc = m.markers_at(t)
    yp = (yp + rng.normal(0.0, 0.5, yp.shape)) * 1e-3
    yc = (yc + rng.normal(0.0, 0.5, yc.shape)) * 1e-3
    return yp, yc, t + T0, m


def _ring_capacity(est: OnlineJoint) -> int:
    window = est.statistics.window
    assert window is not None
    return int(window._ring_window("capacity").ring.capacity)


@pytest.mark.parametrize("attachment", ["skin", "rigid"])
def test_a_time_window_at_1khz_holds_at_most_its_max_frames_and_still_spans_its_seconds(attachment: str) -> None:
    yp, yc, t, _ = _stream("hinge", 1000.0, 12.0)
    capped = OnlineJoint("hinge", window_s=10.0, attachment=attachment, window_max_frames=2000)
    unbounded = OnlineJoint("hinge", window_s=10.0, attachment=attachment, window_max_frames=0)
    outputs = 0
    for k in range(t.size):
        outputs += capped.update(yp[k], yc[k], float(t[k])) is not None
        unbounded.update(yp[k], yc[k], float(t[k]))
        if k % 500 == 499:
            capped.estimate()
    assert unbounded.n_window == 10000 and unbounded.window_thinned == 0
    assert 1999 <= capped.n_window <= 2001
    assert capped.window_thinned == t.size - capped.statistics.window.n_pushed  # (the template frames too)
    stamps = capped.statistics.window.window_stamps()
    assert stamps[-1] - stamps[0] > 9.99  # the whole 10 s, at 200 Hz
    assert np.diff(stamps).min() > 0.004
    assert _ring_capacity(capped) <= 2002 < _ring_capacity(unbounded) == 16384
    assert outputs >= t.size - 600  # every frame after the first estimate still has its output
    capped.estimate()
    unbounded.estimate()
    a, b = capped.solution, unbounded.solution
    assert a is not None and b is not None and a.identifiable and b.identifiable
    # the same estimate to well within its sd; the window with a sixth of the frames is less certain
    diff = np.arccos(min(1.0, abs(float(a.direction_parent @ b.direction_parent))))
    assert diff < 3.0 * np.sqrt(np.trace(a.cov_direction_parent))
    assert np.trace(a.cov_direction_parent) > np.trace(b.cov_direction_parent)


@pytest.mark.parametrize("kind", ["ball", "hinge"])
def test_a_thinned_window_is_the_window_of_a_joint_fed_only_the_frames_that_enter(kind: str) -> None:
    """Bit for bit: the frames left out add nothing, and the lag pairs chain the frames that enter."""
    yp, yc, t, m = _stream(kind, 1000.0, 6.0, seed=1)
    kw: dict[str, Any] = {
        "window_s": 5.0,
        "attachment": "skin",
        "templates": (m.template_parent * 1e-3, m.template_child * 1e-3),
        "n_markers": (yp.shape[1], yc.shape[1]),
    }
    capped = OnlineJoint(kind, window_max_frames=1000, **kw)
    fed_few = OnlineJoint(kind, window_max_frames=None, **kw)
    bins = np.floor(t / 0.005)
    enters = np.r_[True, bins[1:] > bins[:-1]]
    for k in range(t.size):
        capped.update(yp[k], yc[k], float(t[k]))
        if enters[k]:
            fed_few.update(yp[k], yc[k], float(t[k]))
    a, b = capped.statistics.window, fed_few.statistics.window
    assert a is not None and b is not None
    assert capped.n_window == fed_few.n_window == 1000
    np.testing.assert_array_equal(a.sums, b.sums)
    capped.estimate()
    fed_few.estimate()
    sa, sb = capped.solution, fed_few.solution
    assert sa is not None and sb is not None
    for field in dataclasses.fields(sa):
        np.testing.assert_array_equal(getattr(sa, field.name), getattr(sb, field.name), err_msg=field.name)


def test_frame_by_frame_and_blocks_leave_out_the_same_frames_and_chain_the_same_pairs() -> None:
    """Frames a segment cannot be posed in break the chain of lag pairs the same way in both paths."""
    yp, yc, t, _ = _stream("hinge", 1000.0, 8.0, seed=2)
    yp[5200:5203, 1:] = np.nan  # the parent not posed: a break among frames left out
    yp[6000:6002, 1:] = np.nan  # ... and right before a frame that enters
    yc[7001, 2:] = np.nan
    one = OnlineJoint("hinge", window_s=4.0, attachment="skin", window_max_frames=700)
    blocks = OnlineJoint("hinge", window_s=4.0, attachment="skin", window_max_frames=700)
    for k in range(t.size):
        one.update(yp[k], yc[k], float(t[k]))
    for lo in range(0, t.size, 333):  # block edges anywhere, left-out frames across them
        blocks.update_many(yp[lo : lo + 333], yc[lo : lo + 333], t[lo : lo + 333])
    a, b = one.statistics.window, blocks.statistics.window
    assert a is not None and b is not None
    assert one.n_window == blocks.n_window and one.window_thinned == blocks.window_thinned > 0
    assert rel_diff(a.sums, b.sums) < SUMS_RTOL
    lag = one.statistics.lag_sums("")
    assert 0 < lag.n_pairs < one.n_window  # the breaks cost pairs, the thinning does not
    assert lag.n_pairs == blocks.statistics.lag_sums("").n_pairs


def test_an_input_the_window_holds_is_not_thinned() -> None:
    yp, yc, t, _ = _stream("ball", 100.0, 35.0)
    est = OnlineJoint("ball", window_s=30.0, attachment="skin")  # 100 Hz x 30 s = 3000 < WINDOW_MAX_FRAMES
    for k in range(t.size):
        est.update(yp[k], yc[k], float(t[k]))
    assert est.window_thinned == 0 and est.n_window == 3000
    frames = OnlineJoint("ball", window=8000, attachment="skin")  # a frame window keeps what it is given
    frames.update_many(yp, yc, t)
    assert frames.window_thinned == 0 and frames.n_window == t.size


def test_entries_admit_one_frame_per_bin_and_carry_breaks_to_the_next_entry() -> None:
    e = WindowEntries(1.0, 10)  # bins of 0.1 s
    assert e.rate_cap == pytest.approx(10.0)
    assert e.admit(0.00, True) is True
    assert e.admit(0.05, True) is None  # same bin
    assert e.admit(0.07, False) is None  # a break among the frames left out ...
    assert e.admit(0.12, True) is False  # ... and the next entry has no lag pair
    assert e.admit(0.25, True) is True
    assert e.thinned == 2
    assert WindowEntries(None, 10).admit(0.0, True) is True  # not a time window: every frame
    assert WindowEntries(1.0, None).bin_s is None
    block = WindowEntries(1.0, 10)
    rows, flags = block.admit_block(np.array([0.0, 0.05, 0.07, 0.12, 0.25]), np.array([True, True, False, True, True]))
    assert rows is not None
    assert rows.tolist() == [0, 3, 4] and flags.tolist() == [True, False, True]


def test_window_max_frames_is_checked() -> None:
    for bad in (-1, 2.5, True, "100"):
        with pytest.raises(InputError, match="window_max_frames"):
            OnlineJoint("ball", window_s=1.0, window_max_frames=bad)  # type: ignore[arg-type]
    assert OnlineJoint("ball", window_s=1.0).window_max_frames == WINDOW_MAX_FRAMES
    assert OnlineJoint("ball", window_s=1.0, window_max_frames=0).window_max_frames is None


def test_a_calibration_keeps_the_bound_and_an_older_file_gets_the_default() -> None:
    yp, yc, t, _ = _stream("ball", 100.0, 20.0)
    est = OnlineJoint("ball", window_s=10.0, attachment="rigid", window_max_frames=500)
    est.update_many(yp, yc, t)
    est.estimate()
    data = est.to_dict()
    assert data["window_max_frames"] == 500
    assert OnlineJoint.from_dict(data).window_max_frames == 500
    del data["window_max_frames"]
    assert OnlineJoint.from_dict(data).window_max_frames == WINDOW_MAX_FRAMES


def test_the_node_parameter_bounds_the_window_and_the_status_says_so() -> None:
    """The fake rigs at 250 Hz into a 4 s window of at most 500 frames: 125 Hz enter."""
    router, runners = rig_router(**{"hip.window_s": 4.0, "hip.window_max_frames": 500, "knee.window_s": 4.0})
    frames = rig_frames(1500)
    for k, f in enumerate(frames):
        router.markers(pose_array_bytes(100_000_000_000 + k * 4_000_000, "world", f))
        router.after_outputs()
    hip, knee = runners
    assert hip.estimator.window_max_frames == 500 and knee.estimator.window_max_frames == WINDOW_MAX_FRAMES
    assert 499 <= hip.estimator.n_window <= 501 and knee.estimator.n_window == 1000
    assert hip.estimate(force=True)
    values = joint_status(hip)[0].values
    assert values["frames entering the window (Hz, at most)"] == 125.0
    assert values["frames left out of the window (input faster than window_max_frames / window_s)"] > 700
    assert "frames entering the window (Hz, at most)" not in joint_status(knee)[0].values
