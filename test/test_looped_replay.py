"""A looped replay sends the same frames again: they are published but are no new data for the windows.

Before, a frame that came round again entered the window a second time, and every loop made
the covariance smaller while the error stayed: on the live node a hip calibration saved after
a minute of ``jointfit_replay --loop --rate max`` of a 20 s bag was 5.9-8.2 sd off, with the
status OK (the hunt of 2026-12-03, D2). A recording that restarts its stamps with new markers
is new data and goes on into the windows as before (``test/test_timeline.py``).
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import rig_frames, rig_router

from jointfit_ros.inputs import MessageRouter
from jointfit_ros.raw import pose_array_bytes
from jointfit_ros.repeated_frames import RepeatedFrames, window_horizon
from jointfit_ros.timeline import RESTART_FRAMES

S = 1_000_000_000
STEP = 4_000_000  # 250 Hz
N = 500  # a 2 s bag


def _messages(frames: np.ndarray) -> list[bytes]:
    return [pose_array_bytes(100 * S + k * STEP, "world", f) for k, f in enumerate(frames)]


def _feed(router: MessageRouter, msgs: list[bytes], block: bool) -> int:
    if block:
        router.markers_many(msgs)
        return 0
    outputs = 0
    for raw in msgs:
        outputs += len(router.markers(raw))
        router.after_outputs()
    return outputs


@pytest.mark.parametrize("block", [False, True])
def test_loops_of_the_same_frames_leave_the_window_and_the_covariance_as_after_one_pass(block: bool) -> None:
    router, runners = rig_router(**{"hip.window_s": 10.0, "knee.window_s": 10.0})
    msgs = _messages(rig_frames(N, 1))
    _feed(router, msgs, block)
    first = {}
    for r in runners:
        assert r.estimate(force=True)
        sol = r.estimator.solution
        assert sol is not None
        first[r.cfg.name] = (r.estimator.n_window, sol)
    published = sum(_feed(router, msgs, block) for _ in range(3))  # the bag three more times, from its start
    assert router.counters["timeline_restarts"] == 3
    # every frame of the loops was recognised (the 2 before each restart reach the joints, which drop
    # them for their stamps)
    assert router.counters["repeated_frames"] == 3 * N
    if not block:
        assert published >= 2 * 3 * (N - RESTART_FRAMES)  # both joints published for the looped frames
    for r in runners:
        n_before, sol_before = first[r.cfg.name]
        assert r.estimator.n_window == n_before, r.cfg.name  # 4 passes, the window holds one
        assert r.estimate(force=True)
        sol = r.estimator.solution
        assert sol is not None
        cov_before = sol_before.cov_parent if hasattr(sol_before, "cov_parent") else sol_before.cov_direction_parent
        cov = sol.cov_parent if hasattr(sol, "cov_parent") else sol.cov_direction_parent
        # before: each loop added the bag again and the covariance shrank ~1 / (loops + 1)
        np.testing.assert_allclose(cov, cov_before, rtol=1e-9, atol=0.0)
    if not block:
        assert runners[0].estimator.replayed_frames == 3 * (N - (RESTART_FRAMES - 1))


def test_a_recording_restarted_with_new_markers_is_new_data() -> None:
    router, runners = rig_router(**{"hip.window_s": 10.0, "knee.window_s": 10.0})
    _feed(router, _messages(rig_frames(N, 1)), False)
    hip = runners[0]
    n_first = hip.estimator.n_window
    _feed(router, _messages(rig_frames(N, 2)), False)  # the same stamps again, other noise: a new take
    assert router.counters["timeline_restarts"] == 1 and router.counters["repeated_frames"] == 0
    assert hip.estimator.n_window == n_first + N - (RESTART_FRAMES - 1)


def test_after_a_reset_the_looped_frames_are_new_to_the_emptied_windows() -> None:
    router, runners = rig_router()
    msgs = _messages(rig_frames(N, 1))
    _feed(router, msgs, False)
    for r in runners:
        r.reset()
    router.reset()
    _feed(router, msgs, False)
    assert router.counters["repeated_frames"] == 0
    assert all(r.estimate(force=True) for r in runners)


def test_memory_forgets_the_oldest_frames() -> None:
    memory = RepeatedFrames(capacity=3)
    frame = np.zeros((2, 3))
    inf = float("inf")
    for k in range(4):
        assert not memory.repeated(k, frame + k, 100 + k, inf)
    assert not memory.repeated(0, frame, 200, inf)  # forgotten: taken as new
    assert memory.repeated(3, frame + 3, 201, inf) and memory.count == 1
    assert not memory.repeated(3, frame + 4, 202, inf)  # the same stamp, other markers: new
    stamps = np.array([10, 3, 10])
    times = np.array([300, 301, 302])
    assert memory.repeated_many(stamps, np.stack([frame, frame + 4, frame]), times, inf).tolist() == [False, True, True]


def test_a_frame_enters_again_once_its_first_copy_has_left_the_longest_window() -> None:
    memory = RepeatedFrames()
    frame = np.ones((2, 3))
    assert not memory.repeated(7, frame, 0, 1000.0)
    assert memory.repeated(7, frame, 999, 1000.0)  # still in the window: a repeat
    assert not memory.repeated(7, frame, 1000, 1000.0)  # left it: enters again, from now
    assert memory.repeated(7, frame, 1999, 1000.0)
    assert window_horizon([(300, 0.0, 0.0), (0, 2.0, 0.0), (0, 0.0, 1.0)], 1e7) == pytest.approx(5e9)
    assert window_horizon([(3000, 0.0, 0.0)], 1e7) == pytest.approx(3e10)
    assert window_horizon([(3000, 0.0, 0.0)], 0.0) == float("inf")  # the frame period not known yet


def test_a_window_shorter_than_the_loop_keeps_one_copy_of_every_frame() -> None:
    """A 1 s window over a looped 2 s bag: the window stays full (each frame once), and the joint estimates."""
    router, runners = rig_router(**{"hip.window_s": 1.0, "knee.window_s": 1.0})
    msgs = _messages(rig_frames(N, 1))
    for _ in range(3):
        _feed(router, msgs, False)
    for r in runners:
        assert 0.9 * 250 <= r.estimator.n_window <= 250 + 1, (r.cfg.name, r.estimator.n_window)
        assert r.estimate(force=True)
    # every looped frame the joints took had left the 1 s window (the router recognises only the few before
    # each restart, whose stamps go back and which the joints drop anyway)
    assert all(r.estimator.replayed_frames == 0 for r in runners)
    assert router.counters["repeated_frames"] <= 2 * (RESTART_FRAMES - 1)
