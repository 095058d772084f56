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
from bagtools import pose_stamped_bytes
from helpers import rig_frames, rig_router

from jointfit_core.synthetic import two_segment_motion
from jointfit_ros.inputs import MessageRouter
from jointfit_ros.params import node_config
from jointfit_ros.raw import pose_array_bytes
from jointfit_ros.repeated_frames import RepeatedFrames, window_horizon
from jointfit_ros.runner import JointRunner
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
    memory = RepeatedFrames(1, capacity=3)
    frame = np.zeros((2, 3))
    inf = np.array([np.inf])
    for k in range(4):
        assert memory.fresh(k, frame + k, 100 + k, inf).all()
    assert memory.fresh(0, frame, 200, inf).all()  # forgotten: taken as new
    assert not memory.fresh(3, frame + 3, 201, inf).any() and memory.count == 1
    assert memory.fresh(3, frame + 4, 202, inf).all()  # the same stamp, other markers: new
    stamps = np.array([10, 3, 10])
    times = np.array([300, 301, 302])
    got = memory.fresh_many(stamps, np.stack([frame, frame + 4, frame]), times, inf)
    assert got[:, 0].tolist() == [True, False, False]


def test_each_joint_takes_a_frame_again_once_its_copy_has_left_its_window() -> None:
    """Two joints, windows of 1000 and 3000 ns: a frame taken at 0 is new to the first at 1000, to the second at 3000."""
    memory = RepeatedFrames(2)
    frame = np.ones((2, 3))
    horizons = np.array([1000.0, 3000.0])
    assert memory.fresh(7, frame, 0, horizons).tolist() == [True, True]
    assert memory.fresh(7, frame, 999, horizons).tolist() == [False, False]
    assert memory.fresh(7, frame, 1000, horizons).tolist() == [True, False]  # left the first's window
    assert memory.fresh(7, frame, 1999, horizons).tolist() == [False, False]  # its new copy is there now
    assert memory.fresh(7, frame, 3000, horizons).tolist() == [True, True]
    np.testing.assert_allclose(window_horizon([(300, 0.0, 0.0), (0, 2.0, 0.0), (0, 0.0, 1.0)], 1e7), [3e9, 2e9, 5e9])
    assert window_horizon([(3000, 0.0, 0.0)], 0.0)[0] == np.inf  # the frame period not known yet


def test_a_window_shorter_than_the_loop_keeps_one_copy_of_every_frame() -> None:
    """A 1 s window over a looped 2 s bag: the window stays full (each frame once), and the joint estimates.

    The other joint's window is 10 s: its horizon does not hold the first joint's frames back.
    """
    router, runners = rig_router(**{"hip.window_s": 1.0, "knee.window_s": 10.0})
    msgs = _messages(rig_frames(N, 1))
    for _ in range(3):
        _feed(router, msgs, False)
    hip, knee = runners
    assert 0.9 * 250 <= hip.estimator.n_window <= 250 + 1, hip.estimator.n_window
    assert hip.estimator.replayed_frames == 0  # every looped frame had left its 1 s window
    assert knee.estimator.n_window == N  # each frame once in its 10 s window
    assert all(r.estimate(force=True) for r in runners)


def test_looped_rigid_body_poses_leave_the_window_and_the_covariance_as_after_one_pass() -> None:
    """Pose topics (rigid-body input) too: a looped bag's poses are published but not added again.

    Before, every loop of a 2 s bag of two PoseStamped topics entered the hip's window again: after
    3 loops it held the bag 4 times and the centre's covariance was ~1/4 of one pass's.
    """
    cfg = node_config({
        "joints": ["hip"], "hip.type": "ball", "hip.parent_pose_topic": "/p", "hip.child_pose_topic": "/c",
        "hip.pose_translation_sd": 0.0003, "hip.pose_rotation_sd_deg": 0.1, "hip.attachment": "rigid",
        "hip.window_s": 10.0,
    })
    rig = two_segment_motion(np.random.default_rng(1), kind="ball")
    rng = np.random.default_rng(2)
    bag = []
    for k in range(N):
        R_p, d_p, R_c, d_c = rig.poses_at(k * STEP / S)
        stamp = 100 * S + k * STEP
        bag.append(("/p", pose_stamped_bytes(stamp, "world", R_p[0], d_p[0] / 1000.0 + rng.normal(0.0, 3e-4, 3))))
        bag.append(("/c", pose_stamped_bytes(stamp, "world", R_c[0], d_c[0] / 1000.0 + rng.normal(0.0, 3e-4, 3))))
    runner = JointRunner(cfg.joints[0], cfg)
    router = MessageRouter(cfg, [runner])
    for topic, raw in bag:
        router.pose(topic, raw)
    assert runner.estimate(force=True)
    n_before, sol_before = runner.estimator.n_window, runner.estimator.solution
    assert sol_before is not None and sol_before.identifiable
    published = 0
    for _ in range(3):
        for topic, raw in bag:
            published += len(router.pose(topic, raw))
    assert router.counters["timeline_restarts"] == 3
    assert router.counters["repeated_frames"] >= 3 * 2 * (N - RESTART_FRAMES)
    assert published >= 3 * (N - RESTART_FRAMES)  # the looped poses were published
    assert runner.estimator.n_window == n_before
    assert runner.estimate(force=True)
    sol = runner.estimator.solution
    assert sol is not None
    np.testing.assert_allclose(sol.cov_parent, sol_before.cov_parent, rtol=1e-9, atol=0.0)  # type: ignore[union-attr]
