"""Stamps without ROS: the Timeline's checks, the router and runners fed through it, and the activity status.

A stamp that is no time is dropped; one far ahead is dropped, not adopted; a
jump back that runs on (a looped recording) re-anchors the time line after
RESTART_FRAMES messages, so that the estimators' times keep increasing while
the outputs carry the real stamps; a single stamp back or a repeated stamp
is passed on for the estimators to drop, as before.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import rig_frames, rig_router

from jointfit_ros.activity import InputActivity
from jointfit_ros.inputs import MessageRouter
from jointfit_ros.params import node_config
from jointfit_ros.raw import ConversionError, parse_pose_array, parse_pose_arrays, pose_array_bytes
from jointfit_ros.runner import OK, STALE, WARN, JointRunner
from jointfit_ros.timeline import RESTART_FRAMES, Timeline

S = 1_000_000_000
STEP = 4_000_000  # 250 Hz


def _stamps(t0: int, n: int) -> list[int]:
    return [t0 + k * STEP for k in range(n)]


def test_steady_stream_passes_unchanged() -> None:
    tl = Timeline(S)
    stamps = _stamps(100 * S, 50)
    assert [tl.time_of(s, "m") for s in stamps] == stamps
    kept, times = tl.times_of(np.array(_stamps(stamps[-1] + STEP, 20)), "m")
    assert kept.all() and times.tolist() == _stamps(stamps[-1] + STEP, 20)
    assert tl.counters == {"invalid_stamps": 0, "stamps_ahead": 0, "timeline_restarts": 0}


def test_single_far_ahead_stamp_is_dropped_and_the_stream_goes_on() -> None:
    tl = Timeline(S)
    stamps = _stamps(100 * S, 20)
    for s in stamps[:10]:
        tl.time_of(s, "m")
    assert tl.time_of((2**31 - 1) * S, "m") is None
    assert tl.counters["stamps_ahead"] == 1 and tl.last_event is not None and "ahead" in tl.last_event[1]
    assert [tl.time_of(s, "m") for s in stamps[10:]] == stamps[10:]
    assert tl.counters["timeline_restarts"] == 0


def test_a_stamp_outside_int32_seconds_is_invalid() -> None:
    tl = Timeline(S)
    tl.time_of(100 * S, "m")
    assert tl.time_of(2**31 * S, "m") is None and tl.time_of(-(2**31) * S - 1, "m") is None
    assert tl.counters["invalid_stamps"] == 2
    assert tl.time_of(100 * S + STEP, "m") == 100 * S + STEP


def test_single_backward_and_repeated_stamps_are_passed_on_for_the_estimators_to_drop() -> None:
    tl = Timeline(S)
    stamps = _stamps(100 * S, 20)
    for s in stamps[:10]:
        tl.time_of(s, "m")
    assert tl.time_of(stamps[9], "m") == stamps[9]  # repeated: not after the latest
    assert tl.time_of(stamps[2], "m") == stamps[2]  # back once
    assert [tl.time_of(s, "m") for s in stamps[10:]] == stamps[10:]
    assert tl.offset_ns == 0 and tl.counters["timeline_restarts"] == 0


@pytest.mark.parametrize("block", [False, True])
def test_a_loop_back_to_the_start_reanchors_the_time_line(block: bool) -> None:
    tl = Timeline(S)
    first = _stamps(100 * S, 500)  # 2 s
    looped = first + first + first
    if block:
        kept, times = tl.times_of(np.array(looped), "m")
        out = [int(t) if k else None for k, t in zip(kept, times, strict=True)]
    else:
        out = [tl.time_of(s, "m") for s in looped]
    assert tl.counters["timeline_restarts"] == 2
    # the first RESTART_FRAMES - 1 messages of a loop go back (passed on, dropped by the estimators)
    for loop in (1, 2):
        at = loop * 500
        assert all(t is not None and t <= out[at - 1] for t in out[at : at + RESTART_FRAMES - 1])  # type: ignore[operator]
    # from the confirming message on, the times increase by the stream's step
    kept_times = [t for k, t in enumerate(out) if k % 500 >= RESTART_FRAMES - 1 or k < 500]
    assert all(t is not None for t in kept_times)
    steps = np.diff(np.array(kept_times, dtype=np.int64))
    assert (steps > 0).all() and steps.max() <= 3 * STEP
    assert tl.offset_ns > 0


def test_a_steady_run_far_ahead_is_adopted_without_an_offset() -> None:
    tl = Timeline(S)
    for s in _stamps(100 * S, 10):
        tl.time_of(s, "m")
    later = _stamps(200 * S, 10)
    out = [tl.time_of(s, "m") for s in later]
    assert out[: RESTART_FRAMES - 1] == [None] * (RESTART_FRAMES - 1)
    assert out[RESTART_FRAMES - 1 :] == later[RESTART_FRAMES - 1 :]
    assert tl.counters["timeline_restarts"] == 1 and tl.offset_ns == 0


@pytest.mark.parametrize("where", [-50 * S, 100 * S])
def test_a_run_with_repeated_stamps_still_restarts_the_time_line(where: int) -> None:
    """A stream stamping its frames in pairs, after a loop back or a jump ahead, is taken up again.

    Before, a repeated stamp started the run anew, so no run ever reached RESTART_FRAMES messages:
    every later message was dropped for good (stamps_ahead, or stamp_not_increasing in the estimators).
    """
    tl = Timeline(S)
    for s in _stamps(100 * S, 10):
        tl.time_of(s, "m")
    pairs = [s for s in _stamps(100 * S + where, 20) for _ in range(2)]
    out = [tl.time_of(s, "m") for s in pairs]
    assert tl.counters["timeline_restarts"] == 1, tl.counters
    taken = [t for t in out[2 * RESTART_FRAMES :] if t is not None]
    assert len(taken) == len(pairs) - 2 * RESTART_FRAMES
    assert (np.diff(np.array(taken)) >= 0).all()  # on one increasing time line again
    assert taken[-1] - taken[0] == (20 - 1 - RESTART_FRAMES) * STEP  # the stream's own steps


def test_with_a_clock_a_pause_is_no_jump() -> None:
    now = [0]
    tl = Timeline(S, clock=lambda: now[0])
    tl.time_of(100 * S, "m")
    now[0] = 10 * S  # 10 s later, the stream resumes 10 s later
    assert tl.time_of(110 * S, "m") == 110 * S
    assert tl.time_of((2**31 - 1) * S, "m") is None  # a bad stamp still is one
    assert tl.counters == {"invalid_stamps": 0, "stamps_ahead": 1, "timeline_restarts": 0}


def test_two_topics_of_one_recording_loop_together_and_still_pair() -> None:
    tl = Timeline(S)
    stamps = _stamps(100 * S, 100)
    out: dict[str, list[int | None]] = {"parent": [], "child": []}
    for s in stamps + stamps:
        for topic in out:  # the same stamp on both topics is no repeat
            out[topic].append(tl.time_of(s, topic))
    assert tl.counters["timeline_restarts"] == 1  # the parent confirms; the child continues on the new offset
    after = slice(100 + RESTART_FRAMES, None)
    assert out["parent"][after] == out["child"][after]
    assert np.all(np.diff(np.array(out["parent"][after], dtype=np.int64)) == STEP)


def test_bad_arguments() -> None:
    with pytest.raises(ValueError, match="max_jump_ns"):
        Timeline(0)
    with pytest.raises(ValueError, match="restart_frames"):
        Timeline(S, restart_frames=1)


# --------------------------------------------------------------------------- nanosec

def test_nanosec_of_1e9_or_more_is_malformed_per_message_and_in_blocks() -> None:
    good = pose_array_bytes(5 * S + 7, "world", np.zeros((2, 3)))
    bad = bytearray(good)
    bad[8:12] = (0xFFFFFFFF).to_bytes(4, "little")
    with pytest.raises(ConversionError, match="nanosec 4294967295"):
        parse_pose_array(bytes(bad))
    batch = parse_pose_arrays([good, bytes(bad), good])
    assert list(batch.errors) == [1] and "nanosec" in str(batch.errors[1])
    assert sum(g.index.size for g in batch.groups) == 2
    batch = parse_pose_arrays([bytes(bad), good])  # the invalid one first: the other still parses
    assert list(batch.errors) == [0] and batch.groups[0].index.tolist() == [1]


# --------------------------------------------------------------------------- through the router

@pytest.mark.parametrize("block", [False, True])
def test_router_loop_keeps_estimating_and_outputs_carry_the_real_stamps(block: bool) -> None:
    router, runners = rig_router(**{"hip.window_s": 1.0, "hip.template_frames": 20})
    frames = rig_frames(500)
    stamps = _stamps(100 * S, 500)
    msgs = [pose_array_bytes(s, "world", f) for s, f in zip(stamps + stamps, np.concatenate([frames, frames]), strict=True)]
    hip = runners[0]
    if block:
        router.markers_many(msgs[:500])
    else:
        for raw in msgs[:500]:
            router.markers(raw)
    assert hip.estimate(force=True)
    window = hip.estimator.n_window
    routed = []
    if block:
        router.markers_many(msgs[500:])
    else:
        for raw in msgs[500:]:
            routed.extend(router.markers(raw))
    assert router.counters["timeline_restarts"] == 1
    assert hip.estimator.dropped.get("stamp_not_increasing", 0) == RESTART_FRAMES - 1
    assert abs(hip.estimator.n_window - window) <= 2  # the 1 s window went on over the loop
    assert hip.estimate(force=True)
    if not block:
        hips = [r for r in routed if r.runner is hip]
        assert len(hips) >= 500 - RESTART_FRAMES
        assert hips[0].stamp_ns == stamps[RESTART_FRAMES - 1]  # the real stamp, not the timeline's


def test_router_single_bad_stamp_then_frozen_joint_goes_on() -> None:
    router, runners = rig_router()
    frames = rig_frames(400)
    stamps = _stamps(100 * S, 400)
    msgs = [pose_array_bytes(s, "world", f) for s, f in zip(stamps, frames, strict=True)]
    for raw in msgs[:300]:
        router.markers(raw)
    for r in runners:
        assert r.estimate(force=True)
        r.freeze(True)
    assert router.markers(pose_array_bytes((2**31 - 1) * S, "world", frames[300])) == []
    out = [o for raw in msgs[300:] for o in router.markers(raw)]
    assert len([o for o in out if o.runner is runners[0]]) == 100  # every frame after it
    assert router.counters["stamps_ahead"] == 1


# --------------------------------------------------------------------------- activity and status

def test_activity_rate_falls_to_zero_and_silence_is_measured() -> None:
    act = InputActivity(window_s=3.0)
    assert act.sample(0.0, 0, 0).rate_hz is None
    for k in range(1, 6):
        a = act.sample(float(k), 100 * k, 100 * k)
    assert a.rate_hz == pytest.approx(100.0) and a.silent_s == 0.0 and not a.all_dropped
    for k in range(6, 11):
        a = act.sample(float(k), 500, 500)
    assert a.rate_hz == 0.0 and a.silent_s == pytest.approx(5.0)
    a = act.sample(11.0, 600, 500, {"stamp_not_increasing": 100})
    assert a.all_dropped and "stamp_not_increasing 100" in a.dropped_text()
    assert act.sample(12.0, 0, 0).recent == 0  # totals went down (a reset): afresh


def test_joint_status_is_stale_after_silence_and_warns_when_all_is_dropped() -> None:
    router, runners = rig_router()
    frames = rig_frames(400)
    stamps = _stamps(100 * S, 400)
    for s, f in zip(stamps[:300], frames[:300], strict=True):
        router.markers(pose_array_bytes(s, "world", f))
    hip = runners[0]
    assert hip.estimate(force=True)
    assert hip.live_status(0.0).level == OK
    for s, f in zip(stamps[300:350], frames[300:350], strict=True):
        router.markers(pose_array_bytes(s, "world", f))
    st = hip.live_status(1.0)
    assert st.level == OK and st.values["input rate (Hz)"] == 50.0
    # every frame of the next second dropped by the estimator (stamps repeated)
    for f in frames[350:]:
        router.markers(pose_array_bytes(stamps[349], "world", f))
    st = hip.live_status(2.0)
    assert st.level == WARN and "all 50 inputs" in st.message and "stamp_not_increasing 50" in st.message
    # ... or by the router (stamps far ahead)
    for f in frames[350:]:
        router.markers(pose_array_bytes(stamps[349] + 100 * S, "world", f))
    st = hip.live_status(3.0)
    assert st.level == WARN and "dropped before this joint" in st.message, st.message
    # then nothing at all
    assert hip.live_status(4.0).level != STALE
    st = hip.live_status(6.5)
    assert st.level == STALE and "no input for 3.5 s" in st.message and st.values["input rate (Hz)"] == 0.0


def test_router_pose_topics_loop_together_and_keep_pairing() -> None:
    pytest.importorskip("rosbags")
    from bagtools import pose_stamped_bytes

    from jointfit_core.synthetic import two_segment_motion

    motion = two_segment_motion(np.random.default_rng(4), kind="ball")
    values = {
        "joints": ["hip"],
        "hip.parent_pose_topic": "/pelvis",
        "hip.child_pose_topic": "/thigh",
        "hip.pose_translation_sd": 0.3,
        "hip.pose_rotation_sd_deg": 0.2,
        "hip.window_s": 2.0,
        "sync_tolerance": 0.001,
    }
    cfg = node_config(values)
    hip = JointRunner(cfg.joints[0], cfg)
    router = MessageRouter(cfg, [hip])
    times = np.arange(300) / 100.0
    R_p, d_p, R_c, d_c = motion.poses_at(times)
    stamps = [100 * S + round(float(t) * 1e9) for t in times]
    routed = []
    for loop in range(2):
        for k, stamp in enumerate(stamps):
            routed.extend(router.pose("/pelvis", pose_stamped_bytes(stamp, "world", R_p[k], d_p[k])))
            routed.extend(router.pose("/thigh", pose_stamped_bytes(stamp, "world", R_c[k], d_c[k])))
            if loop == 0 and k == 200:
                assert hip.estimate(force=True)
    assert router.counters["timeline_restarts"] == 1  # one for both topics
    assert hip.counters["unmatched"] <= 2 * RESTART_FRAMES and hip.counters["frames"] >= 600 - RESTART_FRAMES
    second = routed[-(300 - RESTART_FRAMES) :]
    assert [r.stamp_ns for r in second] == stamps[RESTART_FRAMES:]  # the replay's own stamps
    assert hip.estimate(force=True)
