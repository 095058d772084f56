"""Messages whose ``header.stamp`` is 0: a publisher that never sets it.

Before, every frame after the first was dropped as not increasing and no joint ever estimated;
the joint status said it was building templates (1/20). Live, the node now uses the message's
arrival time (its ROS clock) in place of the stamp and says so in ``jointfit: input`` (WARN);
a recording's zero stamps are counted and named (nothing to stand in for them).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from bagtools import write_raw_bag
from helpers import fake_rig_values, rig_frames, rig_router

from jointfit_ros.cli import fit_main
from jointfit_ros.input_status import InputStatus
from jointfit_ros.raw import pose_array_bytes

T0 = 1_700_000_000 * 10**9


def _clock(step_ns: int) -> Iterator[int]:
    return itertools.count(T0, step_ns)


def test_live_zero_stamps_take_the_arrival_time() -> None:
    ticks = _clock(4_000_000)  # 250 Hz
    router, runners = rig_router()
    router.stamp_clock = lambda: next(ticks)
    frames = rig_frames(1100, 1)
    for f in frames[:1000]:
        router.markers(pose_array_bytes(0, "world", f))
        router.after_outputs()
    assert router.counters["zero_stamps"] == 1000
    assert all(r.estimate(force=True) for r in runners)
    assert all(r.estimator.solution is not None and r.estimator.solution.identifiable for r in runners)
    hip_stamps = []
    for f in frames[1000:]:
        hip_stamps += [r.stamp_ns for r in router.markers(pose_array_bytes(0, "world", f)) if r.runner is runners[0]]
        router.after_outputs()
    # the outputs carry the arrival times
    assert len(hip_stamps) > 90 and hip_stamps[0] >= T0 and all(b > a for a, b in itertools.pairwise(hip_stamps))


def test_a_recording_with_zero_stamps_is_named() -> None:
    router, _ = rig_router()
    for f in rig_frames(300, 1):
        router.markers(pose_array_bytes(0, "world", f))
    assert router.counters["zero_stamps"] == 300
    many, _ = rig_router()
    many.markers_many([pose_array_bytes(0, "world", f) for f in rig_frames(300, 1)])
    assert many.counters["zero_stamps"] == 300
    values: dict[str, object] = {}
    level, message = InputStatus().status(0.0, router.counters, router.gaps, router.cfg, values)
    assert level >= 1 and "header.stamp 0" in message, message
    assert values["messages with header.stamp 0 (arrival time used)"] == 300


def test_stamps_that_are_set_are_kept() -> None:
    router, _ = rig_router()
    router.stamp_clock = lambda: 5
    out = []
    for k, f in enumerate(rig_frames(300, 1)):
        out += [r.stamp_ns for r in router.markers(pose_array_bytes(T0 + k * 4_000_000, "world", f))]
    assert router.counters["zero_stamps"] == 0
    assert 5 not in out


def test_a_bag_whose_stamps_are_all_zero_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Offline: one error line naming the cause, not "no estimate: building templates (1/20)" per joint."""
    frames = rig_frames(600, 1)
    bag = write_raw_bag(tmp_path / "bag", [
        ("/markers", "geometry_msgs/msg/PoseArray", 10**9 + k * 4_000_000, pose_array_bytes(0, "world", f))
        for k, f in enumerate(frames)
    ])
    config = tmp_path / "p.yaml"
    config.write_text(yaml.safe_dump({"jointfit": {"ros__parameters": fake_rig_values()}}))
    code = fit_main([str(bag), "--config", str(config), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 1 and len(lines) == 1 and "header.stamp 0" in lines[0], err
    assert not (tmp_path / "out").exists()
