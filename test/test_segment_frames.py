"""jointfit_core.segment_frames on the lower-body skeleton through the node's runners (no ROS): one frame per
segment, shared segments posed alike whichever joint posed them, a chain's joints in one thigh frame, and the
TF tree of these against the truth."""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest

from jointfit_core.segment_frames import SegmentFrames, SegmentJoint
from jointfit_core.skeleton_truth import make_skeleton, skeleton_frames
from jointfit_core.tf_tree import tf_tree
from jointfit_ros.inputs import MessageRouter
from jointfit_ros.params import node_config, params_from_file
from jointfit_ros.raw import pose_array_bytes
from jointfit_ros.runner import JointRunner

CONFIG = Path(__file__).resolve().parents[1] / "config" / "lower_body.yaml"
RATE, NOISE, T0 = 100.0, 0.0005, 1_000_000_000_000


@pytest.fixture(scope="module")
def skeleton_run() -> tuple[list[JointRunner], MessageRouter, np.ndarray, np.ndarray]:
    sk = make_skeleton("lower", seed=3)
    cfg = node_config(params_from_file(CONFIG))
    t = np.arange(int(8.0 * RATE)) / RATE
    frames = skeleton_frames(sk, t, np.random.default_rng(3), NOISE, 0.02)
    raws = [pose_array_bytes(T0 + round(tk * 1e9), "world", f) for tk, f in zip(t, frames, strict=True)]
    runners = [JointRunner(j, cfg) for j in cfg.joints]
    router = MessageRouter(cfg, runners)
    for start in range(0, len(raws) - 1, 100):
        router.markers_many(raws[start : min(start + 100, len(raws) - 1)])
    for r in runners:
        assert r.estimate(force=True), r.last_error
    last = router.markers(raws[-1])  # the last frame one by one, as the live node gets it
    assert len(last) == len(runners)
    router.last_outputs = {r.runner.cfg.name: r.output for r in last}  # type: ignore[attr-defined]
    return runners, router, t, frames


def _segments(runners: list[JointRunner]) -> SegmentFrames:
    return SegmentFrames([SegmentJoint(r.cfg.name, r.cfg.parent_markers, r.cfg.child_markers) for r in runners])


def test_segments_are_the_distinct_marker_lists_each_owned_by_the_joint_it_hangs_from(skeleton_run) -> None:
    runners = skeleton_run[0]
    seg = _segments(runners)
    sk = make_skeleton("lower")
    assert len(seg.names) == len(sk.segments) == 7  # pelvis, thighs, shanks, feet
    by = {r.cfg.name: k for k, r in enumerate(runners)}
    thigh = seg.segment_of(by["r_hip"], 1)
    assert seg.segment_of(by["r_knee"], 0) == thigh  # the hip's child is the knee's parent
    assert seg.owner[thigh] == (by["r_hip"], 1)
    pelvis = seg.segment_of(by["r_hip"], 0)
    assert seg.owner[pelvis] == (by["r_hip"], 0) and seg.segment_of(by["l_hip"], 0) == pelvis  # the root


def test_a_shared_segment_has_one_pose_whichever_joint_posed_it(skeleton_run) -> None:
    runners, _, _, frames = skeleton_run
    seg = _segments(runners)
    templates = [r.estimator.templates for r in runners]
    poses = [r.estimator.frame_poses for r in runners]
    assert all(p is not None for p in poses)
    R, t = seg.poses(poses, templates)
    assert np.isfinite(R).all() and np.isfinite(t).all()
    by = {r.cfg.name: k for k, r in enumerate(runners)}
    thigh = seg.segment_of(by["r_hip"], 1)
    without_owner = list(poses)
    without_owner[by["r_hip"]] = None  # the hip did not pose its thigh: the knee's pose, carried over
    R2, t2 = seg.poses(without_owner, templates)
    np.testing.assert_allclose(R2[thigh], R[thigh], atol=2e-3)  # two fits of the same noisy markers
    np.testing.assert_allclose(t2[thigh], t[thigh], atol=1e-3)
    # every segment's owner template, posed there, lands on this frame's markers (0.5 mm noise)
    names = list(runners[0].node.marker_names)
    for s, (i, side) in enumerate(seg.owner):
        markers = (runners[i].cfg.parent_markers, runners[i].cfg.child_markers)[side]
        y = frames[-1][[names.index(m) for m in markers]]
        fitted = templates[i][side] @ R2[s].T + t2[s]
        ok = np.isfinite(y).all(axis=1)
        assert np.sqrt(np.mean(np.sum((fitted[ok] - y[ok]) ** 2, axis=1))) < 3e-3, seg.names[s]
    nothing = seg.poses([None] * len(runners), templates)[0]
    assert np.isnan(nothing).all()


def test_a_chains_joints_share_the_thigh_frame_and_the_tf_tree_lands_on_the_truth(skeleton_run) -> None:
    runners, _, t, _ = skeleton_run
    seg = _segments(runners)
    templates = [r.estimator.templates for r in runners]
    R, origin = seg.poses([r.estimator.frame_poses for r in runners], templates)
    joints = seg.joint_frames([r.estimator.solution for r in runners], templates, [False] * len(runners))
    assert [j.name for j in joints] == [r.cfg.name for r in runners]
    by = {j.name: j for j in joints}
    sk = make_skeleton("lower", seed=3)
    truth = sk.joints_world_at([t[-1]])
    # hip centre and knee axis in one thigh frame: the femur's length is read off the frame (to ~1 mm)
    knee = by["r_knee"]
    thigh = seg.names[seg.segment_of([r.cfg.name for r in runners].index("r_knee"), 0)]
    assert knee.parent == thigh and by["r_hip"].parent != thigh
    # the hip centre carried by the thigh (its child) is in the thigh frame through the child estimate
    i_hip = [r.cfg.name for r in runners].index("r_hip")
    sol = runners[i_hip].estimator.solution
    hip_in_thigh = sol.centre_child  # the thigh is the hip's child and owned by it: its template frame
    direction = np.asarray(knee.direction) / np.linalg.norm(knee.direction)
    lever = np.asarray(knee.point) - hip_in_thigh
    femur = np.linalg.norm(lever - direction * (lever @ direction))
    p_hip, _ = truth["r_hip"]
    p_knee, d_knee = truth["r_knee"]
    assert d_knee is not None
    true_lever = p_knee[0] - p_hip[0]
    true_femur = np.linalg.norm(true_lever - d_knee[0] * (true_lever @ d_knee[0]))
    assert 0.3 < true_femur and abs(femur - true_femur) < 2e-3, (femur, true_femur)
    # world -> segment -> joint, composed as tf2 would: every joint on its true world position
    tree = tf_tree("world", seg.names, R, origin, joints)
    world = {tf.child: tf for tf in tree.dynamic if tf.parent == "world"}
    for j in joints:
        s = seg.names.index(j.parent)
        at = R[s] @ np.asarray(j.point) + origin[s]
        p_true, d_true = truth[j.name]
        if d_true is None:
            assert np.linalg.norm(at - p_true[0]) < 2e-3, j.name
        else:
            gap = at - p_true[0]
            assert np.linalg.norm(gap - d_true[0] * (gap @ d_true[0])) < 2e-3, j.name  # on the true axis
        assert j.parent in world


class _Broadcaster:
    """Stands in for tf2_ros's broadcasters (not installed here): records what is sent."""

    sent: ClassVar[list[tuple[str, list]]] = []

    def __init__(self, node: object) -> None:
        self.kind = type(self).__name__

    def sendTransform(self, transforms: list) -> None:  # noqa: N802 (tf2_ros's name)
        _Broadcaster.sent.append((self.kind, list(transforms)))


class TransformBroadcaster(_Broadcaster):
    pass


class StaticTransformBroadcaster(_Broadcaster):
    pass


def test_segments_message_and_tf_broadcast_through_a_stand_in_tf2(skeleton_run, monkeypatch) -> None:
    pytest.importorskip("rclpy")
    import types

    from geometry_msgs.msg import PoseArray
    from rclpy.serialization import deserialize_message
    from scipy.spatial.transform import Rotation

    from jointfit_ros.segment_output import SegmentOutput
    from jointfit_ros.tf_output import TfOutput

    runners, router, t, _ = skeleton_run
    out = SegmentOutput(runners, prefix="subject_a/")
    R, origin = out.poses()
    msg = deserialize_message(out.pose_array(T0, "world", R, origin), PoseArray)
    assert len(msg.poses) == len(out.names) == 7 and msg.header.frame_id == "world"
    for k, pose in enumerate(msg.poses):
        q = [pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w]
        np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), R[k], atol=1e-12)
        np.testing.assert_allclose([pose.position.x, pose.position.y, pose.position.z], origin[k], atol=1e-15)

    assert not TfOutput(None).available  # no tf2_ros here: said, nothing sent
    fake = types.ModuleType("tf2_ros")
    fake.TransformBroadcaster, fake.StaticTransformBroadcaster = TransformBroadcaster, StaticTransformBroadcaster
    monkeypatch.setitem(__import__("sys").modules, "tf2_ros", fake)
    _Broadcaster.sent.clear()
    runners[0].estimator.freeze()  # r_hip frozen: its transform goes to /tf_static, once
    try:
        tf = TfOutput(None)
        assert tf.available and tf.problem == ""
        n = tf.send(out.tree(R, origin, "world"), T0)
        n2 = tf.send(out.tree(R, origin, "world"), T0 + 10_000_000)
    finally:
        runners[0].estimator.thaw()  # the module's runners as they were
    # segments 7, joints 6 (1 frozen: static), each joint's own parent template frame 6 (static): the statics
    # are not sent again
    assert n == 7 + 6 + 6 and n2 == 7 + 5
    assert [k for k, _ in _Broadcaster.sent] == [
        "StaticTransformBroadcaster", "TransformBroadcaster", "TransformBroadcaster"
    ]
    sent = {m.child_frame_id: m for _, msgs in _Broadcaster.sent for m in msgs}
    assert all(child.startswith("subject_a/") for child in sent)  # two subjects' trees stay apart
    assert {m.header.frame_id for m in sent.values()} - {f"subject_a/{n}" for n in out.names} == {"world"}
    hip = "subject_a/" + runners[0].cfg.name
    assert sent[hip].header.frame_id == "subject_a/" + out.names[out.frames.segment_of(0, 0)]
    sent = {k.removeprefix("subject_a/"): m for k, m in sent.items()}
    for m in sent.values():
        m.header.frame_id = m.header.frame_id.removeprefix("subject_a/")

    def world_of(frame: str) -> np.ndarray:
        T = np.eye(4)
        while frame != "world":
            m = sent[frame]
            A = np.eye(4)
            r = m.transform.rotation
            A[:3, :3] = Rotation.from_quat([r.x, r.y, r.z, r.w]).as_matrix()
            A[:3, 3] = [m.transform.translation.x, m.transform.translation.y, m.transform.translation.z]
            T = A @ T
            frame = m.header.frame_id
        return T

    # composed as tf2 would, each joint's frame is the node's per-frame output of this frame (the same poses
    # and estimates), and near the truth: within this frame's pose noise (0.5 mm markers on 5-10 cm clusters:
    # up to ~1 deg and ~1 mm)
    truth = make_skeleton("lower", seed=3).joints_world_at([t[-1]])
    for r in runners:
        T = world_of(r.cfg.name)
        published = router.last_outputs[r.cfg.name]
        sol, fp = r.estimator.solution, r.estimator.frame_poses  # (r_hip was frozen since: its final estimate)
        assert fp is not None
        local = sol.centre_parent if d_is_none(sol) else sol.point_parent
        np.testing.assert_allclose(T[:3, 3], fp[0][0] @ local + fp[1][0], atol=1e-9)
        if r is not runners[0]:
            np.testing.assert_allclose(T[:3, 3], published.position, atol=1e-9)
        p_true, d_true = truth[r.cfg.name]
        gap = T[:3, 3] - p_true[0]
        if d_true is not None:
            assert published.direction is not None
            assert abs(T[:3, 2] @ published.direction) > 1.0 - 1e-12, r.cfg.name  # the frame's z along the axis
            assert np.degrees(np.arccos(min(1.0, abs(T[:3, 2] @ d_true[0])))) < 2.0, r.cfg.name
            gap = gap - d_true[0] * (gap @ d_true[0])
        assert np.linalg.norm(gap) < 3e-3, r.cfg.name
        # <joint>/centre_local is in <joint>.local_frame_id: through TF it lands on the same point
        L = world_of(r.cfg.local_frame_id)
        np.testing.assert_allclose(L[:3, :3] @ local + L[:3, 3], T[:3, 3], atol=1e-9)


def d_is_none(sol: object) -> bool:
    """Whether an estimate is a ball joint's (a centre, no direction)."""
    return not hasattr(sol, "direction_parent")


def test_pose_array_orientations_must_match_the_points() -> None:
    from jointfit_ros.raw import ConversionError, pose_array_bytes

    with pytest.raises(ConversionError, match=r"orientations: expected shape \(2, 4\)"):
        pose_array_bytes(T0, "world", np.zeros((2, 3)), orientations=np.zeros((3, 4)))
