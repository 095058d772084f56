"""The offline fit's block path against the node's message-by-message path.

``jointfit fit`` parses marker messages in blocks
(:meth:`MessageRouter.markers_many`), gives each joint its frames as a block
(:meth:`JointRunner.markers_block`, :meth:`OnlineJoint.update_many`) and
pose messages one by one. Everything the node would hold at the end must be
the same: the router's counters and recorded frames, every joint's counters,
dropped frames, sums and estimate (to rounding: the block path poses frames with a
vectorised eigen-solve), the hinge sign fixed toward
``axis_toward_marker``; bad messages of every kind counted the same way.
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers import SUMS_RTOL, assert_same_estimate, fake_rig_values, rel_diff
from numpy.typing import NDArray

from jointfit_core.estimator import OnlineJoint
from jointfit_ros.bag import iter_bag_messages
from jointfit_ros.fake_mocap import frame_at, make_rigs
from jointfit_ros.inputs import MessageRouter
from jointfit_ros.offline import run_fit
from jointfit_ros.params import node_config
from jointfit_ros.raw import pointcloud2_bytes, pose_array_bytes
from jointfit_ros.report import segment_geometry
from jointfit_ros.runner import JointRunner

FloatArray = NDArray[np.float64]
N = 700
RATE = 100.0
T0 = 1_700_000_000_000_000_000


def _values(**extra: Any) -> dict[str, Any]:
    return fake_rig_values(
        **{"hip.window": 400, "knee.window_s": 3.0, "knee.axis_toward_marker": "FEMUR2", "knee.axis_from_marker": "FEMUR4", **extra}
    )


def _frames(seed: int = 4) -> tuple[FloatArray, NDArray[np.int64]]:
    rigs = make_rigs(seed)
    rng = np.random.default_rng(seed)
    t = np.arange(N) / RATE
    frames = np.stack([frame_at(rigs, float(tk), rng, 0.5, 0.03) for tk in t]) / 1000.0
    return frames, T0 + np.rint(t * 1e9).astype(np.int64)


def _stream(marker_type: str, labelled: bool, rng: np.random.Generator) -> list[bytes]:
    """The recording with every kind of bad message mixed in (and, labelled, clouds with label problems)."""
    frames, stamps = _frames()
    p = frames.shape[1]

    def encode(stamp: int, frame: FloatArray, frame_id: str = "world", labels: Any = "rows") -> bytes:
        if marker_type == "pose_array":
            return pose_array_bytes(int(stamp), frame_id, frame)
        lab = np.arange(len(frame)) if isinstance(labels, str) else labels
        return pointcloud2_bytes(int(stamp), frame_id, frame, labels=lab if labelled else None, dtype=np.float64)

    out = []
    for k in range(N):
        frame = frames[k]
        if k % 50 == 7:
            frame = frame.copy()
            frame[3] = 0.0  # an occluded marker sent as zeros
        out.append(encode(stamps[k], frame))
        if k % 97 == 11:
            out.append(b"\x00\x01\x00\x00garbage")
        if k % 89 == 13:
            out.append(encode(stamps[k] + 1, frames[k], "camera"))
        if k % 83 == 17:
            out.append(encode(stamps[k] + 2, np.where(np.arange(p)[:, None] == 2, np.inf, frames[k])))
        if k % 79 == 19:
            out.append(encode(stamps[k], frames[k]))  # repeated stamp
        if k % 73 == 23:
            out.append(encode(stamps[k - 20], frames[k]))  # backward
        if k % 71 == 29 and not (labelled and marker_type == "pointcloud2"):
            out.append(encode(stamps[k] + 3, frames[k][:5]))  # too few points without labels
        if labelled and marker_type == "pointcloud2" and k % 67 == 31:
            lab = np.arange(p)
            lab[rng.integers(0, p)] = 0 if k % 2 else p + 5  # duplicated / out of range
            out.append(encode(stamps[k] + 4, frames[k], labels=lab))
            out.append(encode(stamps[k] + 5, frames[k][:10], labels=rng.permutation(p)[:10]))  # occluded left out
        if marker_type == "pointcloud2" and k % 61 == 37:
            out.append(encode(stamps[k] + 6, frames[k])[:-60])  # data cut short
    return out


def _snapshot(router: MessageRouter) -> dict[str, Any]:
    snap: dict[str, Any] = {
        "router": dict(router.counters),
        "last_problem": router.last_problem,
        "frame_id": router.frame_id,
    }
    assert router.recorded is not None
    snap["recorded_stamps"] = [s for s, _ in router.recorded]
    snap["recorded"] = np.stack([f for _, f in router.recorded])
    for r in router.runners:
        est = r.estimator
        name = r.cfg.name
        snap[f"{name}.counters"] = dict(r.counters)
        snap[f"{name}.rate_stamps"] = list(r._stamps)
        snap[f"{name}.dropped"] = dict(est.dropped)
        snap[f"{name}.seen"] = est.n_frames_seen
        snap[f"{name}.sums"] = None if est.statistics.window is None else est.statistics.window.sums.copy()
        snap[f"{name}.reference"] = est.reference_direction
        snap[f"{name}.last_error"] = r.last_error
        if est.solution is not None:
            snap[f"{name}.estimate"] = est.to_dict()["estimate"]
    return snap


def _assert_same(a: dict[str, Any], b: dict[str, Any]) -> None:
    """Equal snapshots; sums, estimates and hinge references to rounding (block poses: helpers.SUMS_RTOL)."""
    assert a.keys() == b.keys()
    for key in a:
        if key.endswith(".estimate"):
            assert_same_estimate(a[key], b[key], where=key)
        elif key.endswith((".sums", ".reference")) and a[key] is not None and b[key] is not None:
            assert rel_diff(a[key], b[key]) < SUMS_RTOL, key
        elif isinstance(a[key], np.ndarray) or isinstance(b[key], np.ndarray):
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)
        else:
            assert a[key] == b[key], key


@pytest.mark.parametrize(
    ("marker_type", "labelled", "extra"),
    [
        ("pose_array", False, {}),
        ("pointcloud2", True, {"label_field": "label"}),
        ("pointcloud2", False, {"zero_is_missing": False}),
        ("pointcloud2", False, {"unlabelled": True, "assignment_gate": 0.05}),
    ],
)
def test_markers_many_equals_markers(marker_type: str, labelled: bool, extra: dict[str, Any]) -> None:
    rng = np.random.default_rng(3)
    cfg = node_config(_values(marker_type=marker_type, **extra))
    stream = _stream(marker_type, labelled, rng)
    edges = np.unique(np.concatenate([[0, 5, 6, len(stream)], rng.integers(0, len(stream), 25)])).tolist()
    checkpoints = set(edges[3::4])

    one = MessageRouter(cfg, [JointRunner(j, cfg) for j in cfg.joints])
    one.recorded = []
    for k, raw in enumerate(stream):
        if k in checkpoints:
            for r in one.runners:
                r.estimate(force=True)
        one.markers(raw)
    many = MessageRouter(cfg, [JointRunner(j, cfg) for j in cfg.joints])
    many.recorded = []
    for lo, hi in itertools.pairwise(edges):
        if lo in checkpoints:
            for r in many.runners:
                r.estimate(force=True)
        assert many.markers_many(stream[lo:hi]) == []  # marker joints: no per-frame outputs
    for router in (one, many):
        for r in router.runners:
            assert r.estimate(force=True)
    a, b = _snapshot(many), _snapshot(one)
    _assert_same(a, b)
    c = b["router"]
    assert c["malformed"] > 0 and c["wrong_frame_id"] > 0 and c["messages"] == len(stream)
    assert b["knee.reference"] is not None  # the sign was fixed from FEMUR4 toward FEMUR2 on the way
    assert b["hip.dropped"].get("stamp_not_increasing", 0) > 0
    if labelled:
        assert c["label_problems"] > 0


def test_markers_block_gives_bad_frames_one_by_one() -> None:
    """Frames the estimator refuses (inf, from a marker file) are counted as malformed, as frame by frame."""
    frames, stamps = _frames(6)
    frames = frames.copy()
    frames[200, 1, 0] = np.inf
    frames[450, 9, 2] = -np.inf
    cfg = node_config(_values())
    one = [JointRunner(j, cfg) for j in cfg.joints]
    many = [JointRunner(j, cfg) for j in cfg.joints]
    for r in one:
        for k in range(N):
            r.markers_frame(int(stamps[k]), frames[k])
    for r in many:
        for lo in range(0, N, 128):
            r.markers_block(stamps[lo : lo + 128], frames[lo : lo + 128])
    for a, b in zip(many, one, strict=True):
        assert a.counters == b.counters and a.last_error == b.last_error
        assert a.counters["malformed"] == 1  # PELV2 in frame 200 (hip), FEMUR2 in frame 450 (knee)
        assert a.estimator.dropped == b.estimator.dropped
        assert rel_diff(a.estimator.statistics.window.sums, b.estimator.statistics.window.sums) < SUMS_RTOL  # type: ignore[union-attr]


@pytest.mark.parametrize("reader_process", [False, True])
def test_fit_with_pose_topics_equals_message_by_message(tmp_path: Path, reader_process: bool) -> None:
    """Marker joints in blocks; a joint pairing markers with a pose topic and a pose-only joint in bag order.

    ``reader_process``: the bag read and parsed in a second process (:mod:`jointfit_ros.bag_blocks`).
    """
    pytest.importorskip("rosbags")
    from bagtools import write_marker_bag

    frames, stamps = _frames(8)
    rigs = make_rigs(8)
    t = (stamps - stamps[0]) * 1e-9
    _, _, R_shank, d_shank = rigs["knee"].poses_at(t)
    R_pelvis, d_pelvis, R_thigh, d_thigh = rigs["hip"].poses_at(t)
    bag = write_marker_bag(
        tmp_path / "rec", frames, stamps, topic="/markers",
        pose_topics={
            "/shank": (R_shank, d_shank / 1000.0),
            "/pelvis": (R_pelvis, d_pelvis / 1000.0),
            "/thigh": (R_thigh, d_thigh / 1000.0),
        },
    )
    values = _values(
        joints=["hip", "knee", "pelvis"],
        marker_topic="/markers",
        **{
            "knee.child_markers": [],
            "knee.child_pose_topic": "/shank",
            "knee.pose_translation_sd": 0.0005,
            "knee.pose_rotation_sd_deg": 0.3,
            "pelvis.type": "ball",
            "pelvis.parent_pose_topic": "/pelvis",
            "pelvis.child_pose_topic": "/thigh",
            "pelvis.pose_translation_sd": 0.0005,
            "pelvis.pose_rotation_sd_deg": 0.3,
        },
    )
    cfg = node_config(values)
    run = run_fit(bag, cfg, whole_recording=False, n_checkpoints=13, reader_process=reader_process)

    # The node's way, with the offline fit's checkpoints: every message in bag order, one at a time.
    runners = [JointRunner(j, run.cfg) for j in run.cfg.joints]
    router = MessageRouter(run.cfg, runners)
    router.recorded = []
    step = N // 13
    outputs: dict[str, list[float]] = {"knee": [], "pelvis": []}
    checkpoints: dict[str, list[int]] = {r.cfg.name: [] for r in runners}
    for done, msg in enumerate(iter_bag_messages(bag, ["/markers", "/shank", "/pelvis", "/thigh"]), start=1):
        routed = router.markers(msg.raw) if msg.topic == "/markers" else router.pose(msg.topic, msg.raw)
        for r in routed:
            if r.runner.cfg.name in outputs:
                outputs[r.runner.cfg.name].append(r.output.residual)
        if done % step == 0:
            for r in runners:
                if r.estimate(force=True):
                    checkpoints[r.cfg.name].append(r.counters["frames"])
    for r in runners:
        assert r.estimate(force=True)

    assert run.router is not None and run.router.counters == router.counters
    assert run.n_inputs == 4 * N
    for trace, r in zip(run.traces, runners, strict=True):
        name = r.cfg.name
        assert trace.runner.counters == r.counters, name
        assert trace.runner.estimator.dropped == r.estimator.dropped, name
        assert trace.final is not None
        assert_same_estimate(trace.runner.estimator.to_dict()["estimate"], r.estimator.to_dict()["estimate"], where=name)
        assert [c.frames for c in trace.checkpoints][: len(checkpoints[name])] == checkpoints[name], name
        if name in outputs:
            np.testing.assert_array_equal(trace.residuals, outputs[name])
        else:
            assert trace.residuals == []  # marker joints: the report computes them from the final estimate
    assert run.frames is not None
    np.testing.assert_array_equal(run.frames, np.stack([f for _, f in router.recorded]))
    assert len(outputs["knee"]) > N // 2 and len(outputs["pelvis"]) > N // 2

    # The report's per-frame residual of the marker joint: the final estimate carried by both segments,
    # as the node's per-frame output with that estimate (a frozen copy) reports it.
    hip = run.traces[0]
    geo = segment_geometry(run, hip)
    assert geo is not None and geo.joint_residual is not None and geo.joint_residual.shape == (N,)
    frozen = OnlineJoint.from_dict(hip.runner.estimator.to_dict())
    node = np.full(N, np.nan)
    for k in range(N):
        out = frozen.update(run.frames[k, hip.runner.parent_rows], run.frames[k, hip.runner.child_rows])
        node[k] = np.nan if out is None else out.residual
    both = np.isfinite(node) & np.isfinite(geo.joint_residual)
    assert both.sum() > 0.9 * N
    np.testing.assert_allclose(geo.joint_residual[both], node[both], rtol=1e-6, atol=1e-9)
