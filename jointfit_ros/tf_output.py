"""The TF tree of :func:`jointfit_core.tf_tree.tf_tree` as ``geometry_msgs/TransformStamped``, broadcast through tf2_ros.

``tf2_ros`` comes with a full ROS install, not with the pip wheels of the
development environment: :class:`TfOutput` imports it inside a try and, when it is
missing, says so once (:attr:`TfOutput.problem`, for the log and ``/diagnostics``)
and broadcasts nothing. The conversion :func:`transform_stamped` needs only
``geometry_msgs``. The node broadcasts each marker frame's tree of
:class:`~jointfit_ros.segment_output.SegmentOutput` through it.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from geometry_msgs.msg import TransformStamped

from jointfit_core.tf_tree import TfTree, Transform

from .conversions import stamp_from_ns

__all__ = ["transform_stamped", "TfOutput"]


def transform_stamped(tf: Transform, stamp_ns: int) -> TransformStamped:
    """One transform as a ``geometry_msgs/TransformStamped`` stamped ``stamp_ns`` (ns).

    ``header.frame_id`` is ``tf.parent``, ``child_frame_id`` is ``tf.child``; translation in
    the input units (m for ROS), rotation the quaternion (x, y, z, w).
    """
    msg = TransformStamped()
    msg.header.stamp = stamp_from_ns(stamp_ns)
    msg.header.frame_id = tf.parent
    msg.child_frame_id = tf.child
    x, y, z = (float(v) for v in tf.translation)
    msg.transform.translation.x, msg.transform.translation.y, msg.transform.translation.z = x, y, z
    qx, qy, qz, qw = (float(v) for v in tf.rotation)
    r = msg.transform.rotation
    r.x, r.y, r.z, r.w = qx, qy, qz, qw
    return msg


def _messages(transforms: Iterable[Transform], stamp_ns: int) -> list[TransformStamped]:
    return [transform_stamped(tf, stamp_ns) for tf in transforms]


class TfOutput:
    """Broadcasts a :class:`~jointfit_core.tf_tree.TfTree` on ``/tf`` and ``/tf_static`` when tf2_ros imports.

    Parameters
    ----------
    node : rclpy.node.Node
        The node that owns the broadcasters.

    Attributes
    ----------
    available : bool
        Whether ``tf2_ros`` imported.
    problem : str
        Empty, or why nothing is broadcast (one line, for the log and ``/diagnostics``).
    """

    def __init__(self, node: Any) -> None:
        self.problem = ""
        self._dynamic: Any = None
        self._static: Any = None
        self._static_sent: dict[str, tuple[float, ...]] = {}
        try:
            from tf2_ros import StaticTransformBroadcaster, TransformBroadcaster
        except ImportError as exc:
            self.problem = f"tf2_ros is not installed ({exc}); the TF tree is not broadcast"
            return
        self._dynamic = TransformBroadcaster(node)
        self._static = StaticTransformBroadcaster(node)

    @property
    def available(self) -> bool:
        return self._dynamic is not None

    def send(self, tree: TfTree, stamp_ns: int) -> int:
        """Broadcast one frame's tree: the dynamic transforms always, a static one when new or changed.

        Returns
        -------
        int
            The number of transforms sent (0 when tf2_ros is missing).
        """
        if self._dynamic is None:
            return 0
        static = [tf for tf in tree.static if self._static_sent.get(tf.child) != _key(tf)]
        if static:
            self._static.sendTransform(_messages(static, stamp_ns))
            self._static_sent.update((tf.child, _key(tf)) for tf in static)
        if tree.dynamic:
            self._dynamic.sendTransform(_messages(tree.dynamic, stamp_ns))
        return len(static) + len(tree.dynamic)


def _key(tf: Transform) -> tuple[float, ...]:
    return (*(float(v) for v in tf.translation), *(float(v) for v in tf.rotation))
