"""jointfit_core.tf_tree against the fake skeleton's truth (composed here, without tf2), and its conversion to TransformStamped."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jointfit_core.errors import InputError
from jointfit_core.skeleton_truth import make_skeleton
from jointfit_core.tf_tree import (
    JointFrame,
    TfTree,
    Transform,
    quaternion_z_to,
    quaternions_from_matrices,
    tf_tree,
)


def _matrix(tf: Transform) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(tf.rotation).as_matrix()
    T[:3, 3] = tf.translation
    return T


def _world_of(transforms: tuple[Transform, ...], frame: str, world: str = "world") -> np.ndarray:
    """Compose the chain of transforms from ``world`` down to ``frame`` (a tree walk, as tf2 would)."""
    by_child = {tf.child: tf for tf in transforms}
    T = np.eye(4)
    while frame != world:
        tf = by_child[frame]
        T = _matrix(tf) @ T
        frame = tf.parent
    return T


def _skeleton_tree(t: float, frozen: set[str]) -> tuple[TfTree, dict[str, tuple[np.ndarray, np.ndarray | None]]]:
    sk = make_skeleton("full", seed=2)
    R, origin = sk.template_poses_at([t], t_ref=1.5)
    local = sk.joints_local(1.5)
    joints = [JointFrame(j, tr.parent, tr.point, tr.direction, j in frozen) for j, tr in local.items()]
    tree = tf_tree("world", [s.name for s in sk.segments], R[0], origin[0], joints)
    world = {j: (p[0], None if d is None else d[0]) for j, (p, d) in sk.joints_world_at([t]).items()}
    return tree, world


@pytest.mark.parametrize("t", [0.0, 1.5, 7.3])
def test_joint_frames_land_on_the_true_joints(t: float) -> None:
    tree, world = _skeleton_tree(t, frozen={"r_hip", "r_elbow"})
    segments = [tf.child for tf in tree.dynamic if tf.parent == "world"]
    assert len(segments) == 14 and segments[0] == "pelvis"
    assert {tf.child for tf in tree.static} == {"r_hip", "r_elbow"}
    assert len(tree.all) == 14 + 12
    for j, (point, direction) in world.items():
        T = _world_of(tree.all, j)
        np.testing.assert_allclose(T[:3, 3], point, atol=1e-12)
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
        if direction is None:  # a ball joint's frame has its segment's axes
            parent = next(tf for tf in tree.all if tf.child == j).parent
            np.testing.assert_allclose(T[:3, :3], _world_of(tree.all, parent)[:3, :3], atol=1e-12)
        else:  # a hinge's z axis is the axis
            np.testing.assert_allclose(T[:3, 2], direction, atol=1e-12)
    for tf in tree.all:
        assert tf.rotation[3] >= 0.0 and abs(np.linalg.norm(tf.rotation) - 1.0) < 1e-12


def test_unposed_segments_have_no_world_transform_and_bad_input_is_refused() -> None:
    R = np.stack([np.eye(3), np.full((3, 3), np.nan)])
    t = np.array([[1.0, 2.0, 3.0], [np.nan] * 3])
    tree = tf_tree("world", ["a", "b"], R, t, [JointFrame("j", "b", [0.0, 0.0, 0.1])])
    assert [tf.child for tf in tree.dynamic] == ["a", "j"] and tree.static == ()
    with pytest.raises(InputError, match="S = 2 segments"):
        tf_tree("world", ["a", "b"], R[:1], t)
    with pytest.raises(InputError, match="proper rotation"):
        tf_tree("world", ["a"], -np.eye(3)[None], t[:1])
    with pytest.raises(InputError, match="not one of"):
        tf_tree("world", ["a"], R[:1], t[:1], [JointFrame("j", "z", [0.0, 0.0, 0.0])])
    with pytest.raises(InputError, match="finite point"):
        tf_tree("world", ["a"], R[:1], t[:1], [JointFrame("j", "a", [np.nan, 0.0, 0.0])])
    with pytest.raises(InputError, match="non-zero"):
        quaternion_z_to([0.0, 0.0, 0.0])


def test_quaternions() -> None:
    rng = np.random.default_rng(0)
    R = Rotation.random(50, random_state=rng).as_matrix()
    # half turns (w = 0: each of x, y, z the largest component in turn, and a tilted axis), near-identity
    half = Rotation.from_rotvec(np.pi * np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.6, 0.8, 0.0]])).as_matrix()
    R = np.concatenate([R, half, Rotation.from_rotvec([[1e-9, 0.0, 0.0]]).as_matrix(), np.eye(3)[None]])
    q = quaternions_from_matrices(R)
    ref = Rotation.from_matrix(R).as_quat()
    np.testing.assert_allclose(np.abs(np.sum(q * ref, axis=1)), 1.0, atol=1e-12)  # the same rotations, q or -q
    assert (q[:, 3] >= 0.0).all()
    np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), R, atol=1e-12)
    d = rng.normal(size=(50, 3))
    d[0] = [0.0, 0.0, -1.0]
    d[1] = [0.0, 0.0, 1.0]
    d[2] = [1e-9, 0.0, -1.0]
    z = Rotation.from_quat(quaternion_z_to(d)).apply([0.0, 0.0, 1.0])
    np.testing.assert_allclose(z, d / np.linalg.norm(d, axis=1, keepdims=True), atol=1e-12)
    from_ros = pytest.importorskip("jointfit_ros.raw").quaternion_z_to_direction
    for k in range(5):  # the node's axis pose orientation, vectorised
        np.testing.assert_allclose(quaternion_z_to(d[k]), from_ros(d[k]), atol=1e-15)


@pytest.mark.ros
def test_transform_stamped() -> None:
    from jointfit_ros.tf_output import transform_stamped

    tree, _ = _skeleton_tree(3.0, frozen={"l_knee"})
    tf = next(x for x in tree.all if x.child == "l_knee")
    msg = transform_stamped(tf, 1_700_000_000_123_456_789)
    assert (msg.header.frame_id, msg.child_frame_id) == ("l_thigh", "l_knee")
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    tr, rot = msg.transform.translation, msg.transform.rotation
    np.testing.assert_array_equal([tr.x, tr.y, tr.z], tf.translation)
    np.testing.assert_array_equal([rot.x, rot.y, rot.z, rot.w], tf.rotation)


def _tf2_ros_missing() -> bool:
    try:
        import tf2_ros  # noqa: F401
    except ImportError:
        return True
    return False


@pytest.mark.ros
@pytest.mark.skipif(not _tf2_ros_missing(), reason="tf2_ros is installed")
def test_without_tf2_ros_nothing_is_broadcast_and_it_says_why() -> None:
    from jointfit_ros.tf_output import TfOutput

    out = TfOutput(object())  # the node is only handed to tf2_ros's broadcasters
    assert not out.available and "tf2_ros is not installed" in out.problem
    tree, _ = _skeleton_tree(3.0, frozen={"l_knee"})
    assert out.send(tree, 0) == 0


@pytest.mark.ros
@pytest.mark.skipif(_tf2_ros_missing(), reason="tf2_ros not installed (a full ROS install has it)")
def test_broadcast_sends_static_transforms_once() -> None:
    import os

    import rclpy
    from rclpy.node import Node

    from jointfit_ros.tf_output import TfOutput

    tree, _ = _skeleton_tree(3.0, frozen={"l_knee"})
    domain_id = 230 + os.getpid() % 3
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain_id)
    try:
        node = Node("test_tf_output", context=context)
        out = TfOutput(node)
        assert out.available and out.problem == ""
        assert out.send(tree, 10**9) == len(tree.all)
        assert out.send(tree, 2 * 10**9) == len(tree.dynamic)  # unchanged static transforms are sent once
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
