"""Every class of bad input is dropped, counted and reported, and leaves the estimate exactly as without it.

The node's per-message path (MessageRouter -> JointRunner -> OnlineJoint)
runs without ROS on the fake mocap stream (hip ball joint, knee hinge). A
clean run gives the reference estimates; the same stream with bad messages
interleaved (garbage bytes, wrong field layouts, wrong point counts, NaN and
inf, stamps repeated or going backwards, another frame_id) must give the
same estimates bit for bit, with each class in its counter. A stream in
millimetres sent to a node configured for metres is flagged in the joint's
diagnostics.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from helpers import fake_rig_values

from jointfit_ros.fake_mocap import frame_at, make_rigs
from jointfit_ros.inputs import MessageRouter
from jointfit_ros.params import node_config
from jointfit_ros.raw import pointcloud2_bytes, pose_array_bytes
from jointfit_ros.runner import OK, WARN, JointRunner, unit_problem

N = 600
RATE = 100.0
T0 = 1_000_000_000_000


def _config(**extra: Any) -> Any:
    return node_config(fake_rig_values(**extra))


def _frames(scale: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    rigs = make_rigs(5)
    rng = np.random.default_rng(5)
    t = np.arange(N) / RATE
    frames = np.stack([frame_at(rigs, float(tk), rng, 0.5, 0.02) for tk in t]) * scale
    return frames, T0 + np.rint(t * 1e9).astype(np.int64)


def _run(cfg: Any, messages: list[bytes]) -> tuple[MessageRouter, list[JointRunner]]:
    runners = [JointRunner(j, cfg) for j in cfg.joints]
    router = MessageRouter(cfg, runners)
    for raw in messages:
        router.markers(raw)
    for r in runners:
        assert r.estimate(force=True)
    return router, runners


def _estimates(runners: list[JointRunner]) -> list[dict[str, Any]]:
    return [r.estimator.to_dict()["estimate"] for r in runners]


@pytest.mark.parametrize("marker_type", ["pose_array", "pointcloud2"])
def test_bad_messages_leave_the_estimate_unchanged(marker_type: str) -> None:
    # Ordered points (no labels): the point count must match marker_names. (With labels a cloud may
    # leave occluded markers out; out-of-range labels are counted separately, see test_conversions.)
    extra = {"marker_type": marker_type}
    cfg = _config(**extra)
    frames, stamps = _frames()

    def encode(stamp: int, frame: np.ndarray, frame_id: str = "world") -> bytes:
        if marker_type == "pose_array":
            return pose_array_bytes(int(stamp), frame_id, frame)
        return pointcloud2_bytes(int(stamp), frame_id, frame, labels=np.arange(len(frame)))

    clean = [encode(s, f) for s, f in zip(stamps, frames, strict=True)]
    _, reference = _run(cfg, clean)

    bad: dict[str, list[bytes]] = {
        "garbage": [b"\x00\x01\x00\x00garbage", b"", b"\x00\x01\x00\x00" + bytes(7)],
        "point count": [encode(stamps[10] + 1, np.zeros((40, 3))), encode(stamps[10] + 2, frames[10][:5])],
        "frame_id": [encode(stamps[20] + 1, frames[20], "camera")],
        "inf": [encode(stamps[30] + 1, np.where(np.arange(16)[:, None] == 3, np.inf, frames[30]))],
        "repeated stamp": [encode(stamps[50], frames[51])],
        "backwards": [encode(stamps[5], frames[60])],
    }
    if marker_type == "pointcloud2":
        layout = pointcloud2_bytes(int(stamps[70]) + 1, "world", frames[70])
        bad["field layout"] = [layout[:-40]]  # truncated data: width * point_step no longer fits
    at = {"garbage": 3, "point count": 10, "frame_id": 20, "inf": 30, "all NaN": 40, "repeated stamp": 50,
          "backwards": 60, "field layout": 70}
    stream: list[bytes] = []
    for k, raw in enumerate(clean):
        stream.append(raw)
        for name, msgs in bad.items():
            if at[name] == k:
                stream.extend(msgs)
    router, runners = _run(cfg, stream)

    assert _estimates(runners) == _estimates(reference)  # bit for bit: nothing bad reached the sums
    c = router.counters
    n_layout = len(bad.get("field layout", []))
    assert c["messages"] == len(stream)
    assert c["malformed"] == len(bad["garbage"]) + len(bad["point count"]) + len(bad["inf"]) + n_layout
    assert c["wrong_frame_id"] == 1
    for r, ref in zip(runners, reference, strict=True):
        dropped = r.estimator.dropped
        assert dropped.get("stamp_not_increasing", 0) == 2  # repeated and backwards
        assert {k: v for k, v in dropped.items() if k != "stamp_not_increasing"} == ref.estimator.dropped
        assert r.status().level == OK


def test_fully_occluded_frames_are_dropped_and_counted() -> None:
    """All markers NaN (everything occluded) is valid input: the frame is dropped from the statistics and counted."""
    cfg = _config()
    frames, stamps = _frames()
    frames[100:103] = np.nan
    _, runners = _run(cfg, [pose_array_bytes(int(s), "world", f) for s, f in zip(stamps, frames, strict=True)])
    _, reference = _run(cfg, [pose_array_bytes(int(s), "world", f) for s, f in zip(stamps, _frames()[0], strict=True)])
    for r, ref in zip(runners, reference, strict=True):
        assert r.estimator.dropped.get("parent_not_posed", 0) == ref.estimator.dropped.get("parent_not_posed", 0) + 3
        assert r.estimator.n_window == ref.estimator.n_window - 3


def test_unit_mismatch_is_reported() -> None:
    frames, stamps = _frames(scale=1.0)  # millimetres
    cfg = _config()  # units: m (default)
    _, runners = _run(cfg, [pose_array_bytes(int(s), "world", f) for s, f in zip(stamps, frames, strict=True)])
    for r in runners:
        st = r.status()
        assert st.level == WARN and "looks like mm" in st.message, st.message
        assert "looks like mm" in st.values["unit check"]
    _, runners = _run(_config(units="mm"), [pose_array_bytes(int(s), "world", f) for s, f in zip(stamps, frames, strict=True)])
    assert all(r.status().level == OK for r in runners)
    assert unit_problem(0.08, "m") == "" and "looks like m" in unit_problem(0.08, "mm")
