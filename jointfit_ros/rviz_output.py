"""``~/markers`` for RViz: one joint's covariance ellipsoid and, for a hinge, its axis arrow.

The node publishes one joint's markers per ``rviz`` timer tick, in turn, from the joint's
latest output (:meth:`~jointfit_ros.node.JointfitNode._on_rviz_timer`); this module makes them
(:func:`~jointfit_ros.conversions.covariance_ellipsoid_marker`,
:func:`~jointfit_ros.conversions.axis_arrow_marker`).
"""

from __future__ import annotations

from visualization_msgs.msg import Marker

from jointfit_core.estimator import JointOutput

from .conversions import axis_arrow_marker, covariance_ellipsoid_marker

__all__ = ["joint_markers"]


def joint_markers(
    name: str, marker_id: int, stamp_ns: int, frame_id: str, out: JointOutput, k_sigma: float, rate_hz: float, length: float
) -> list[Marker]:
    """The markers of joint ``name``'s output ``out`` (world frame ``frame_id``, input units).

    Parameters
    ----------
    name : str
        The joint (the markers' namespaces are ``<name>/covariance`` and ``<name>/axis``).
    marker_id : int
        The joint's marker id.
    stamp_ns, frame_id
        The output's stamp (ns) and frame.
    out : JointOutput
        The joint's latest world output.
    k_sigma : float
        The ellipsoid's size in standard deviations (``ellipsoid_sigma``).
    rate_hz : float
        The markers' rate per joint (``rviz_rate``): they live two periods.
    length : float
        The hinge arrow's length (input units; the segments' size).
    """
    lifetime_ns = int(2e9 / max(rate_hz, 1e-3))
    markers = [
        covariance_ellipsoid_marker(
            stamp_ns, frame_id, out.position, out.cov, k_sigma=k_sigma, ns=f"{name}/covariance",
            marker_id=marker_id, lifetime_ns=lifetime_ns,
        )
    ]  # fmt: skip
    if out.direction is not None:
        markers.append(
            axis_arrow_marker(
                stamp_ns, frame_id, out.position, out.direction, length=length,
                shaft_diameter=max(length / 40.0, 1e-6), ns=f"{name}/axis", marker_id=marker_id, lifetime_ns=lifetime_ns,
            )
        )  # fmt: skip
    return markers
