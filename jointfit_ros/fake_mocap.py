"""A synthetic motion-capture stream with known joints, for demos, tests and benchmarks.

Two independent two-segment rigs (:func:`jointfit_core.synthetic.two_segment_motion`)
move in a lab whose origin is a few metres away:

* ``hip``: a ball joint, parent cluster PELV1..4, child cluster THIGH1..4;
* ``knee``: a hinge, parent FEMUR1..4, child SHANK1..4, 1.5 m further along x;

or, with ``--skeleton lower|full``, a human skeleton instead
(:mod:`jointfit_core.skeleton_truth`: ``lower`` = pelvis, thighs, shanks, feet with
ball hips and hinge knees and ankles, 6 joints; ``full`` adds trunk, upper arms,
forearms and hands with ball shoulders and wrists and hinge elbows, 12 joints;
clusters ``<PREFIX>1..4``, marker names as in ``config/lower_body.yaml`` and
``config/full_body.yaml``); plus, optionally, ``EXTRA1..K`` static markers (lab equipment, stray
reflections) that pad the frame to realistic marker counts. Every frame adds
Gaussian noise and drops each marker with a given probability.

The console script ``jointfit_fake_mocap`` publishes the frames as serialized
CDR bytes (the fast path of :mod:`jointfit_ros.conversions`) on ``markers``
and the truth on ``truth/<joint>/centre`` (``geometry_msgs/PointStamped``; for a
hinge the axis point nearest the parent's cluster) and ``truth/<joint>/axis``
(hinges, ``geometry_msgs/Vector3Stamped``, unit direction in the world frame), all
with the same stamp; the joints are ``hip`` and ``knee``, or the skeleton's. The pure functions (:func:`marker_names`,
:func:`make_rigs`, :func:`frame_at`, :func:`truth_at`) give tests and
benchmarks the same truth without ROS.

Example::

    jointfit_fake_mocap --rate 200 --format pointcloud2 --extra-markers 24 --ros-args -r markers:=/mocap/markers
    jointfit_fake_mocap --skeleton full --rate 100
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from geometry_msgs.msg import PointStamped, PoseArray, Vector3Stamped
from numpy.typing import NDArray
from rclpy.node import Node
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from rclpy.task import Future
from sensor_msgs.msg import PointCloud2

from jointfit_core.synthetic import TwoSegmentMotion, two_segment_motion

from .conversions import pointcloud2_bytes, pose_array_bytes, stamp_from_ns
from .fake_skeleton import SkeletonSource
from .stop_request import StopRequest

__all__ = [
    "RIGS",
    "FORMATS",
    "ORDERED_START_S",
    "marker_message",
    "Truth",
    "marker_names",
    "make_rigs",
    "extra_marker_positions",
    "frame_at",
    "truth_at",
    "truth_in_template_frame",
    "parse_args",
    "FakeMocapNode",
    "main",
]

FloatArray = NDArray[np.float64]

#: Rig name -> (joint kind, parent marker prefix, child marker prefix), in publishing order.
RIGS: dict[str, tuple[str, str, str]] = {
    "hip": ("ball", "PELV", "THIGH"),
    "knee": ("hinge", "FEMUR", "SHANK"),
}
#: Markers per cluster.
CLUSTER_SIZE = 4
#: Mean world position of each rig's parent origin (mm): lab coordinates far from the origin.
RIG_OFFSETS_MM: dict[str, tuple[float, float, float]] = {
    "hip": (2500.0, 3000.0, 900.0),
    "knee": (4000.0, 3000.0, 900.0),
}
#: Output formats of ``--format``.
FORMATS = ("pose_array", "pointcloud2", "pointcloud2_unlabelled")

#: ``pointcloud2_unlabelled``: for this many seconds from the start, every cloud holds every marker in
#: ``marker_names`` order (no occlusion, not shuffled): a node with ``unlabelled: true`` learns the
#: identities from its first complete cloud, and a best-effort subscriber may miss the first few.
ORDERED_START_S = 2.0


def marker_names(extra: int = 0) -> list[str]:
    """Marker names in publishing order.

    Parameters
    ----------
    extra : int
        Number of extra static markers ``EXTRA1..EXTRAk`` appended.

    Returns
    -------
    list of str
        ``PELV1..4, THIGH1..4, FEMUR1..4, SHANK1..4`` then the extras:
        row k of every frame (label k of a labelled cloud) is ``names[k]``.
    """
    if extra < 0:
        raise ValueError(f"extra: expected a non-negative number of markers, got {extra}")
    names = [
        f"{prefix}{i}"
        for _, parent, child in RIGS.values()
        for prefix in (parent, child)
        for i in range(1, CLUSTER_SIZE + 1)
    ]
    return names + [f"EXTRA{i}" for i in range(1, extra + 1)]


def make_rigs(seed: int | None = 0, *, cycle_s: float = 20.0) -> dict[str, TwoSegmentMotion]:
    """The two rigs of the fake stream, reproducibly from ``seed``.

    Parameters
    ----------
    seed : int or None
        Seed of ``numpy.random.default_rng``; the same seed gives the same
        templates, joints and motion.
    cycle_s : float
        Motion time scale (s), see :func:`jointfit_core.synthetic.two_segment_motion`.

    Returns
    -------
    dict of str to TwoSegmentMotion
        ``{"hip": ball joint, "knee": hinge}``, in mm, offsets :data:`RIG_OFFSETS_MM`.
    """
    if not cycle_s > 0.0:
        raise ValueError(f"cycle_s: expected a positive time scale in seconds, got {cycle_s}")
    rng = np.random.default_rng(seed)
    return {
        name: two_segment_motion(
            rng,
            kind=kind,
            n_markers=(CLUSTER_SIZE, CLUSTER_SIZE),
            cycle_s=cycle_s,
            offset=RIG_OFFSETS_MM[name],
        )
        for name, (kind, _, _) in RIGS.items()
    }


def extra_marker_positions(n: int, seed: int | None = 0) -> FloatArray:
    """Positions of ``n`` static extra markers (mm), around the rigs, 0-2 m high.

    Returns
    -------
    ndarray, shape (n, 3)
    """
    rng = np.random.default_rng(None if seed is None else [seed, 1])
    low, high = np.array([1500.0, 2000.0, 0.0]), np.array([5000.0, 4000.0, 2000.0])
    out: FloatArray = rng.uniform(low, high, (n, 3))
    return out


def marker_message(
    fmt: str, zeros: bool, stamp_ns: int, frame_id: str, frame: FloatArray, rng: np.random.Generator, ordered: bool
) -> bytes:
    """One frame's marker message (CDR bytes) in format ``fmt`` (:data:`FORMATS`).

    Parameters
    ----------
    fmt : str
        ``pose_array`` (occluded markers NaN, or zeros), ``pointcloud2`` (a ``label`` field, occluded
        markers left out, or zeros) or ``pointcloud2_unlabelled`` (x, y, z only, occluded markers
        left out, the points shuffled unless ``ordered``).
    zeros : bool
        Occluded markers as (0, 0, 0) (``pose_array``, ``pointcloud2``).
    stamp_ns : int
    frame_id : str
    frame : ndarray, shape (P, 3)
        Markers in ``marker_names`` order, NaN rows occluded (changed in place where zeroed).
    rng : numpy.random.Generator
        The shuffle's source.
    ordered : bool
        ``pointcloud2_unlabelled``: the points in ``marker_names`` order, not shuffled (the
        stream's start, from which a node learns the identities).
    """
    missing = np.isnan(frame[:, 0])
    if fmt == "pose_array":
        if zeros:
            frame[missing] = 0.0
        return pose_array_bytes(stamp_ns, frame_id, frame)
    if fmt == "pointcloud2":
        labels = np.arange(frame.shape[0])
        if zeros:
            frame[missing] = 0.0
        else:
            frame, labels = frame[~missing], labels[~missing]
        return pointcloud2_bytes(stamp_ns, frame_id, frame, labels=labels)
    visible = frame[~missing]
    return pointcloud2_bytes(stamp_ns, frame_id, visible if ordered else visible[rng.permutation(visible.shape[0])])


def frame_at(
    rigs: dict[str, TwoSegmentMotion],
    t: float,
    rng: np.random.Generator,
    noise: float,
    occlusion: float,
    *,
    extra: FloatArray | None = None,
) -> FloatArray:
    """One noisy frame of every marker at motion time ``t``.

    Parameters
    ----------
    rigs : dict of str to TwoSegmentMotion
        From :func:`make_rigs`; markers are taken in the dict's order,
        parent cluster then child cluster (the order of :func:`marker_names`).
    t : float
        Motion time (s).
    rng : numpy.random.Generator
        Source of the noise and the occlusions.
    noise : float
        Standard deviation of the Gaussian noise per coordinate (mm), >= 0.
    occlusion : float
        Probability that a marker is missing in this frame, in [0, 1].
    extra : ndarray, shape (K, 3), optional
        Static extra markers (mm), e.g. from :func:`extra_marker_positions`,
        appended after the rigs' markers (with noise and occlusion too).

    Returns
    -------
    ndarray, shape (P, 3)
        Marker positions (mm); occluded markers are NaN rows.
    """
    if noise < 0.0 or not 0.0 <= occlusion <= 1.0:
        raise ValueError(
            f"noise: expected >= 0 mm, got {noise}; occlusion: expected in [0, 1], got {occlusion}"
        )
    parts = []
    for rig in rigs.values():
        parent, child = rig.markers_at(t)
        parts += [parent[0], child[0]]
    if extra is not None:
        parts.append(np.asarray(extra, dtype=np.float64).reshape(-1, 3))
    frame = np.concatenate(parts, axis=0)
    if noise > 0.0:
        frame += rng.normal(0.0, noise, frame.shape)
    if occlusion > 0.0:
        frame[rng.random(frame.shape[0]) < occlusion] = np.nan
    return frame


@dataclass(frozen=True)
class Truth:
    """The true joints at one instant, in the world frame (mm).

    Attributes
    ----------
    centres : dict of str to ndarray, shape (3,)
        Joint centre of each rig (for the hinge: the axis point nearest the
        rig's ``centre_parent``).
    axes : dict of str to ndarray, shape (3,)
        Unit hinge direction of each hinge rig.
    """

    centres: dict[str, FloatArray]
    axes: dict[str, FloatArray]


def truth_at(rigs: dict[str, TwoSegmentMotion], t: float) -> Truth:
    """The true joint centres and hinge axes at motion time ``t`` (s), world frame, mm."""
    centres, axes = {}, {}
    for name, rig in rigs.items():
        R_p, d_p, _, _ = rig.poses_at(t)
        centres[name] = R_p[0] @ rig.centre_parent + d_p[0]
        if rig.kind == "hinge":
            axes[name] = R_p[0] @ rig.axis
    return Truth(centres=centres, axes=axes)


def truth_in_template_frame(
    rig: TwoSegmentMotion, template_parent: FloatArray | None = None, t0: float = 0.0
) -> tuple[FloatArray, FloatArray | None]:
    """The true joint in the node's parent template frame (what ``<joint>/centre_local`` and the calibration hold).

    Parameters
    ----------
    rig : TwoSegmentMotion
    template_parent : ndarray, shape (P, 3), optional
        The node's parent template (``OnlineJoint.templates[0]``, a calibration's ``template_parent``): the
        truth is carried into its frame by the rigid fit of the rig's template onto it (exact up to the
        template's own noise). Without it: the frame the node builds when its first template frame is the
        stream's frame at ``t0`` (origin at the parent markers' centroid, lab axes at ``t0``).
    t0 : float
        Motion time (s) of the node's first template frame, when ``template_parent`` is not given.

    Returns
    -------
    centre : ndarray, shape (3,)
        The joint centre (hinge: the axis point ``centre_parent``), mm.
    axis : ndarray, shape (3,) or None
        The hinge direction (unit), None for a ball joint.
    """
    x = rig.template_parent
    if template_parent is None:
        R_p, _, _, _ = rig.poses_at(t0)
        R = R_p[0]
        d = -R @ x.mean(axis=0)
    else:
        y = np.asarray(template_parent, dtype=np.float64)
        xc, yc = x - x.mean(axis=0), y - y.mean(axis=0)
        u, _, vt = np.linalg.svd(yc.T @ xc)
        R = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
        d = y.mean(axis=0) - R @ x.mean(axis=0)
    axis = R @ rig.axis if rig.kind == "hinge" else None
    return R @ rig.centre_parent + d, axis


# --------------------------------------------------------------------------- ROS


def _positive(text: str) -> float:
    value = float(text)
    if not value > 0.0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text}")
    return value


def _non_negative(text: str) -> float:
    value = float(text)
    if not value >= 0.0:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text}")
    return value


def _probability(text: str) -> float:
    value = float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a probability in [0, 1], got {text}")
    return value


def _count(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text}")
    return value


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """Options of ``jointfit_fake_mocap`` (ROS arguments already removed)."""
    p = argparse.ArgumentParser(
        prog="jointfit_fake_mocap",
        description="Publish a synthetic mocap stream (a ball-joint hip and a hinge knee rig, or a --skeleton) with its truth.",
        epilog="ROS arguments follow --ros-args, e.g. --ros-args -r markers:=/mocap/markers",
    )
    p.add_argument("--rate", type=_positive, default=100.0, help="frame rate (Hz), default 100")
    p.add_argument(
        "--duration",
        type=_non_negative,
        default=0.0,
        help="stop after this many seconds; 0 (default) runs forever",
    )
    p.add_argument(
        "--noise", type=_non_negative, default=0.5, help="marker noise sd per coordinate (mm), default 0.5"
    )
    p.add_argument(
        "--occlusion",
        type=_probability,
        default=0.02,
        help="probability a marker is missing in a frame, default 0.02",
    )
    p.add_argument(
        "--format",
        choices=FORMATS,
        default="pose_array",
        help="pose_array (default; NaN = occluded), pointcloud2 (uint32 'label' field = marker index, occluded "
        "markers left out), pointcloud2_unlabelled (x, y, z only, shuffled, occluded markers left out; the first "
        f"{ORDERED_START_S:g} s complete and in marker order, from which a node learns the identities)",
    )
    p.add_argument(
        "--zeros",
        action="store_true",
        help="send occluded markers as (0, 0, 0) like mocap4ros2's Vicon driver (pose_array, pointcloud2)",
    )
    p.add_argument(
        "--extra-markers", type=_count, default=0, help="add K static markers EXTRA1..K, default 0"
    )
    p.add_argument(
        "--units", choices=("m", "mm"), default="m", help="published length unit, default m (REP 103)"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the rigs and of the noise, default 0")
    p.add_argument("--topic", default="markers", help="marker topic, default 'markers'")
    p.add_argument("--frame-id", default="world", help="header.frame_id, default 'world'")
    p.add_argument(
        "--cycle",
        type=_positive,
        default=None,
        help="motion time scale (s), default 20 (the rigs: 3-10 cycles of each motion in it) or with --skeleton 10 "
        "(every joint through its range in it)",
    )
    p.add_argument(
        "--skeleton",
        choices=("lower", "full"),
        default=None,
        help="publish a skeleton instead of the two rigs: lower (pelvis, thighs, shanks, feet: 6 joints) or full "
        "(with trunk and arms: 12 joints); node parameters in config/lower_body.yaml, config/full_body.yaml",
    )
    opts = p.parse_args(argv)
    if opts.cycle is None:
        opts.cycle = 20.0 if opts.skeleton is None else 10.0
    return opts


class FakeMocapNode(Node):
    """Publishes one frame per timer tick, and the truth; ``done`` completes after ``--duration``.

    Parameters
    ----------
    opts : argparse.Namespace
        Options from :func:`parse_args`.
    """

    def __init__(self, opts: argparse.Namespace) -> None:
        super().__init__("jointfit_fake_mocap")
        self.opts = opts
        self.scale = 1e-3 if opts.units == "m" else 1.0
        self.extra = extra_marker_positions(opts.extra_markers, opts.seed)
        self.rigs = {} if opts.skeleton else make_rigs(opts.seed, cycle_s=opts.cycle)
        self.skeleton = SkeletonSource(opts.skeleton, opts.seed, opts.cycle, self.extra) if opts.skeleton else None
        self.rng = np.random.default_rng([opts.seed, 2])
        self.names = self.skeleton.marker_names() if self.skeleton else marker_names(opts.extra_markers)
        kinds = self.skeleton.kinds if self.skeleton else {name: rig.kind for name, rig in self.rigs.items()}
        self.done: Future = Future()
        self.frames = 0
        msg_type = PoseArray if opts.format == "pose_array" else PointCloud2
        # a mocap driver's QoS: best effort, keep last 5, volatile
        self.pub_markers = self.create_publisher(msg_type, opts.topic, qos_profile_sensor_data)
        truth_qos = QoSProfile(depth=10)  # reliable: any subscriber matches
        self.pub_centre = {
            name: self.create_publisher(PointStamped, f"truth/{name}/centre", truth_qos) for name in kinds
        }
        self.pub_axis = {
            name: self.create_publisher(Vector3Stamped, f"truth/{name}/axis", truth_qos)
            for name, kind in kinds.items()
            if kind == "hinge"
        }
        self.start_ns = int(self.get_clock().now().nanoseconds)
        self.timer = self.create_timer(1.0 / opts.rate, self._tick)
        self._log_setup()

    def _log_setup(self) -> None:
        unit = self.opts.units
        s = self.scale
        log = self.get_logger()
        log.info(
            f"publishing {len(self.names)} markers on '{self.pub_markers.topic_name}' as {self.opts.format} "
            f"at {self.opts.rate:g} Hz in {unit}, frame '{self.opts.frame_id}'"
        )
        log.info("marker order (row / label k): " + ", ".join(f"{k}:{n}" for k, n in enumerate(self.names)))
        if self.skeleton is not None:
            log.info(f"{self.opts.skeleton} skeleton, every joint through its range within {self.opts.cycle:g} s")
            for line in self.skeleton.truth_lines(s, unit):
                log.info(line)
        for name, rig in self.rigs.items():
            centre, axis = truth_in_template_frame(rig, t0=0.0)
            what = "centre" if rig.kind == "ball" else "axis point"
            text = (
                f"truth {name} ({rig.kind}) in the node's parent template frame (origin at the parent markers' "
                f"centroid, lab axes at this stream's first frame; compare <joint>/*_local and the calibration "
                f"when the node's templates start with that frame, else use "
                f"jointfit_ros.fake_mocap.truth_in_template_frame with the saved template): "
                f"{what} {np.round(centre * s, 6).tolist()} {unit}"
            )
            if axis is not None:
                text += f", axis {np.round(axis, 6).tolist()}"
            log.info(text + f"; in the world: truth/{name}/centre" + (f", truth/{name}/axis" if axis is not None else ""))

    def _tick(self) -> None:
        now_ns = int(self.get_clock().now().nanoseconds)
        t = (now_ns - self.start_ns) * 1e-9
        o = self.opts
        ordered = o.format == "pointcloud2_unlabelled" and t < ORDERED_START_S
        occlusion = 0.0 if ordered else o.occlusion
        if self.skeleton is not None:
            frame = self.skeleton.frame(t, self.rng, o.noise, occlusion) * self.scale
        else:
            frame = frame_at(self.rigs, t, self.rng, o.noise, occlusion, extra=self.extra) * self.scale
        self.pub_markers.publish(marker_message(o.format, o.zeros, now_ns, o.frame_id, frame, self.rng, ordered))
        self._publish_truth(now_ns, t)
        self.frames += 1
        if o.duration > 0.0 and t >= o.duration and not self.done.done():
            self.get_logger().info(f"published {self.frames} frames in {t:.2f} s; stopping")
            self.timer.cancel()
            self.done.set_result(self.frames)

    def _publish_truth(self, now_ns: int, t: float) -> None:
        if self.skeleton is not None:
            centres, axes = self.skeleton.truth(t)
        else:
            truth = truth_at(self.rigs, t)
            centres, axes = truth.centres, truth.axes
        stamp = stamp_from_ns(now_ns)
        for name, pub in self.pub_centre.items():
            msg = PointStamped()
            msg.header.stamp, msg.header.frame_id = stamp, self.opts.frame_id
            c = centres[name] * self.scale
            msg.point.x, msg.point.y, msg.point.z = float(c[0]), float(c[1]), float(c[2])
            pub.publish(msg)
        for name, pub in self.pub_axis.items():
            msg = Vector3Stamped()
            msg.header.stamp, msg.header.frame_id = stamp, self.opts.frame_id
            a = axes[name]
            msg.vector.x, msg.vector.y, msg.vector.z = float(a[0]), float(a[1]), float(a[2])
            pub.publish(msg)


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point of ``jointfit_fake_mocap``: parse options, publish until ``--duration`` or Ctrl-C.

    Parameters
    ----------
    argv : sequence of str, optional
        Arguments without the program name; default ``sys.argv[1:]``.
        Everything after ``--ros-args`` goes to rclpy.
    """
    import rclpy
    from rclpy.utilities import remove_ros_args

    args = [sys.argv[0], *(sys.argv[1:] if argv is None else argv)]
    opts = parse_args(remove_ros_args(args)[1:])
    with StopRequest() as stop:
        _publish(rclpy, args, opts, stop)


def _publish(rclpy: Any, args: list[str], opts: argparse.Namespace, stop: StopRequest) -> None:
    """Spin the fake mocap until ``--duration`` has passed, ``stop`` is requested (SIGINT, SIGTERM) or rclpy shuts down.

    As the node does (:mod:`jointfit_ros.stop_request`): rclpy's own SIGINT handler raised
    KeyboardInterrupt wherever the main thread was, once inside an executor Task's constructor,
    whose ``__del__`` then printed a traceback at exit (a CI run of test_two_subjects, 2026-12-06).
    """
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    node = None
    try:
        node = FakeMocapNode(opts)
        # SingleThreadedExecutor: the EventsExecutor of rclpy 7.1 (Jazzy) does not run
        # periodic timers when spun without a timeout.
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        while rclpy.ok() and not stop.requested and not (opts.duration > 0.0 and node.done.done()):
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
