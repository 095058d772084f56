"""Node parameters for the synthetic skeletons of :mod:`jointfit_core.skeleton_truth`.

No rclpy: the tests, ``bench/skeleton.py`` and ``config/lower_body.yaml`` /
``config/full_body.yaml`` (which must agree with :func:`skeleton_parameters`,
``test/test_skeleton_configs.py``) share one description of the skeleton's joints.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from jointfit_core.skeleton_truth import Skeleton

__all__ = ["skeleton_parameters"]


def skeleton_parameters(
    skeleton: Skeleton, joints: Sequence[str] | None = None, *, window: int = 3000
) -> dict[str, Any]:
    """Flat node parameters (``{"joints": [...], "r_hip.type": "ball", ...}``) for a skeleton stream.

    Parameters
    ----------
    skeleton : Skeleton
        From :func:`~jointfit_core.skeleton_truth.make_skeleton`; its markers are the
        ``marker_names`` (PoseArray on ``markers``, metres, as ``jointfit_fake_mocap --skeleton``).
    joints : sequence of str, optional
        The joints to estimate, a subset of ``skeleton.joints``; default all.
    window : int
        ``<joint>.window`` in frames.

    Returns
    -------
    dict of str to object
        For :func:`jointfit_ros.params.node_config`: the skeleton's ``segments`` used by the
        joints (``pelvis``, ``r_thigh``, ...; ``<segment>.markers``) and per joint its ``parent``
        and ``child`` segment. A segment shared by two joints (the thigh: the hip's child, the
        knee's parent) is named once.

    Raises
    ------
    ValueError
        A joint that is not one of the skeleton's.
    """
    chosen = list(skeleton.joints if joints is None else joints)
    unknown = [j for j in chosen if j not in skeleton.joints]
    if unknown:
        raise ValueError(f"joints: {unknown} are not joints of the {skeleton.name} skeleton {list(skeleton.joints)}")
    values: dict[str, Any] = {
        "joints": chosen,
        "marker_topic": "markers",
        "marker_type": "pose_array",
        "marker_names": skeleton.marker_names(),
    }
    used: set[str] = set()
    for j in chosen:
        child = skeleton.joint_segment(j)
        parent = skeleton.segment(child.parent or "")
        used |= {parent.name, child.name}
        values[f"{j}.type"] = child.kind
        values[f"{j}.parent"] = parent.name
        values[f"{j}.child"] = child.name
        values[f"{j}.window"] = window
    values["segments"] = [s.name for s in skeleton.segments if s.name in used]
    for s in skeleton.segments:
        if s.name in used:
            values[f"{s.name}.markers"] = s.marker_names
    return values
