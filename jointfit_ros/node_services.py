"""What the node's ``~/freeze`` and ``~/save`` services do to its joints, and what they answer.

Pure Python (no rclpy), so that it is tested without ROS: each function acts on
the node's :class:`~jointfit_ros.runner.JointRunner` objects (and its node
calibration file, when it has one) and returns ``(success, message)``, the two
fields of the service's response; the node logs the message.
"""

from __future__ import annotations

from collections.abc import Iterable

from jointfit_core.errors import JointfitError

from .calibration_store import NodeCalibrationFile
from .runner import JointRunner

__all__ = ["freeze_joints", "save_joints"]


def freeze_joints(runners: Iterable[JointRunner], on: bool) -> tuple[bool, str]:
    """Freeze (``on``) or thaw every joint; a joint that cannot freeze is named, the others still are."""
    results = []
    ok = True
    for runner in runners:
        try:
            results.append(runner.freeze(on))
        except JointfitError as exc:
            ok = False
            results.append(f"{runner.cfg.name}: cannot freeze: {exc}")
    return ok, "; ".join(results)


def save_joints(runners: Iterable[JointRunner], calibration_file: NodeCalibrationFile | None) -> tuple[bool, str]:
    """Save the calibrations: the node's one file when configured, else each joint's own ``calibration_file``.

    Success needs every joint that could be saved saved and at least one saved; a joint without a
    file is named, a write that fails is reported (the previous file and its ``.bak`` stay).
    """
    if calibration_file is not None:
        try:
            results = calibration_file.save()
            ok = not calibration_file.unsaved
        except (JointfitError, OSError) as exc:
            results, ok = [f"not saved: {exc}"], False
        return ok, "; ".join(results)
    results = []
    ok = True
    for runner in runners:
        if not runner.cfg.calibration_file:
            results.append(f"{runner.cfg.name}: no calibration_file configured")
            continue
        try:
            results.append(f"{runner.cfg.name}: saved {runner.save()}")
        except (JointfitError, OSError) as exc:
            ok = False
            results.append(f"{runner.cfg.name}: not saved: {exc}")
    return ok and any("saved" in r for r in results), "; ".join(results)
