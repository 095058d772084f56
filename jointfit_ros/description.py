"""``~/robot_description``: the URDF of the node's frozen joints, for robot_state_publisher and RViz.

The node publishes it latched (transient local) whenever the set of frozen, identified joints
or their estimates change (a calibration loaded at start, ``~/freeze``, ``~/reset``), built
by :func:`jointfit_core.urdf.urdf_from_calibrations` from what ``~/save`` would write. With
``~/joint_states`` (same joint names) ``robot_state_publisher`` shows the calibrated subject.
Joints still estimating are left out: a description must not move while it is used. When the
frozen joints do not form one tree, nothing is published and :attr:`RobotDescription.problem`
says why (in ``/diagnostics``).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

from jointfit_core.errors import JointfitError
from jointfit_core.io import METRES_PER_UNIT
from jointfit_core.urdf import urdf_from_calibrations

from .runner import JointRunner

__all__ = ["RobotDescription"]


class RobotDescription:
    """What the node's frozen joints describe, and whether it changed since the last look.

    Parameters
    ----------
    units : str
        The node's input length unit (``units``: m, cm or mm); the URDF is in metres.
    """

    def __init__(self, units: str, segment_labels: Mapping[tuple[str, ...], str] | None = None) -> None:
        self.metres_per_unit = METRES_PER_UNIT.get(units, 1.0)
        self.segment_labels = dict(segment_labels or {})
        self.problem = "no frozen joint yet"
        self.joints = 0
        self._key: list[tuple[str, object]] = []  # the frozen joints' names and estimates last described

    def update(self, runners: Iterable[JointRunner]) -> str | None:
        """The URDF text when the frozen joints changed since the last call and form a tree; else None."""
        frozen = [r for r in runners if r.estimator.frozen and r.estimator.solution is not None]
        frozen = [r for r in frozen if r.estimator.solution is not None and r.estimator.solution.identifiable]
        key: list[tuple[str, object]] = [(r.cfg.name, r.estimator.solution) for r in frozen]
        if len(key) == len(self._key) and all(a[0] == b[0] and a[1] is b[1] for a, b in zip(key, self._key, strict=True)):
            return None
        self._key = key
        if not frozen:
            self.problem = "no frozen joint yet"
            return None
        calibrations = []
        for r in frozen:
            data = r.estimator.to_dict()
            data.update(r.identity())
            calibrations.append(data)
        try:
            text = urdf_from_calibrations(
                calibrations, robot_name="subject", metres_per_unit=self.metres_per_unit,
                segment_labels=self.segment_labels,
            )
        except JointfitError as exc:
            self.problem = f"not published: {exc}"
            return None
        self.problem = ""
        self.joints = len(frozen)
        return text
