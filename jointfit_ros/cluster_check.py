"""Which configured marker does not move with its segment, in words: the node's and the fit's label check.

ROS-free. :class:`ClusterCheck` holds one
:class:`~jointfit_core.cluster_rigidity.ClusterRigidity` for the segments of
the marker-topic joints (identical marker lists are one segment), fed by the
:class:`~jointfit_ros.inputs.MessageRouter` with every parsed marker frame,
and says, for a joint's two segments, which marker changes its distances to
the others (a label on the wrong segment): each joint's ``/diagnostics``
status then warns with the marker's name. :func:`recording_odd_markers` says
the same of a whole recording's frames (``jointfit fit``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from jointfit_core.cluster_rigidity import ClusterPairs, ClusterRigidity, OddMarker, odd_markers

from .anatomy_report import MM_PER_UNIT
from .params import JointConfig, NodeConfig

__all__ = ["ODD_FLOOR_MM", "ClusterCheck", "recording_odd_markers"]

FloatArray = NDArray[np.float64]

#: Smallest pair-distance sd (mm) that can name an odd marker, by attachment: skin clusters' own
#: deformation reaches ~20 mm at twice the literature's artefact (thigh 20 mm,
#: ``jointfit_core.skeleton_sta``) and never named a marker at 15 mm up to three times it; rigid clusters
#: read the marker noise (~0.7 mm at 0.5 mm noise). A marker on another segment read 17-43 mm.
ODD_FLOOR_MM = {"skin": 15.0, "rigid": 5.0}
#: At most this many frames of a recording are read for :func:`recording_odd_markers` (evenly spaced).
RECORDING_FRAMES = 20_000


class _Segments:
    """The marker-topic segments of some joints: their markers (names and rows), labels and floors."""

    def __init__(self, cfg: NodeConfig, joints: Sequence[JointConfig]) -> None:
        labels = cfg.segment_labels()
        per_mm = 1.0 / MM_PER_UNIT.get(cfg.units, 1000.0)
        self.names: list[tuple[str, ...]] = []
        self.floors: list[float] = []
        for j in joints:
            for markers in (j.parent_markers, j.child_markers):
                if not markers or not all(m in cfg.marker_names for m in markers):
                    continue
                floor = ODD_FLOOR_MM[j.attachment if j.attachment in ODD_FLOOR_MM else "skin"] * per_mm
                if markers in self.names:  # one segment: the loosest floor of its joints (skin, when any)
                    k = self.names.index(markers)
                    self.floors[k] = max(self.floors[k], floor)
                    continue
                self.names.append(tuple(markers))
                self.floors.append(floor)
        self.labels = [labels.get(n, "") for n in self.names]
        self.rows = [[cfg.marker_index(m) for m in n] for n in self.names]
        self.unit = cfg.units

    def words(self, odd: Sequence[OddMarker], markers: Sequence[str]) -> str:
        """What ``odd`` says of the segment with these ``markers`` (empty when nothing)."""
        scale = MM_PER_UNIT.get(self.unit, 1000.0)
        for o in odd:
            names = self.names[o.segment]
            if names != tuple(markers):
                continue
            marker = names[o.marker]
            others = ", ".join(m for m in names if m != marker)
            segment = f"segment {self.labels[o.segment]}" if self.labels[o.segment] else f"segment ({', '.join(names)})"
            return (
                f"marker {marker} does not move with the other markers of {segment}: its distances to {others} "
                f"vary by up to {o.spread * scale:.0f} mm (sd), theirs by {o.without * scale:.1f} mm; it is on "
                "another segment, its label is swapped with another marker's, or it sits on soft tissue that moves "
                "on its own: fix the labels or leave it out of the segment's markers"
            )
        return ""


class ClusterCheck:
    """The node's marker-topic segments' pair distances and the odd markers they name.

    Parameters
    ----------
    cfg : NodeConfig
    joints : sequence of JointConfig
        The joints fed by the marker topic.
    """

    def __init__(self, cfg: NodeConfig, joints: Sequence[JointConfig]) -> None:
        self.segments = _Segments(cfg, joints)
        self.rigidity = ClusterRigidity(self.segments.rows, self.segments.floors)

    def add(self, times_ns: NDArray[np.int64], frames: FloatArray) -> None:
        """Marker frames ``(K, P, 3)`` at increasing ``times_ns`` (K,): :meth:`ClusterRigidity.add`."""
        self.rigidity.add(times_ns, frames)

    def clear(self) -> None:
        """Forget the frames (a reset)."""
        self.rigidity.clear()

    def warning(self, joint: JointConfig) -> str:
        """The odd markers of the joint's two segments, in words (empty when none)."""
        odd = self.rigidity.odd_markers()
        if not odd:
            return ""
        texts = [self.segments.words(odd, m) for m in (joint.parent_markers, joint.child_markers)]
        return "; ".join(t for t in texts if t)


def recording_odd_markers(cfg: NodeConfig, joint: JointConfig, frames: FloatArray) -> str:
    """:meth:`ClusterCheck.warning` of a joint over a whole recording's marker frames ``(N, P, 3)``."""
    segments = _Segments(cfg, [joint])
    if not segments.rows or frames.shape[0] < 3:
        return ""
    step = max(1, -(-frames.shape[0] // RECORDING_FRAMES))
    pairs = ClusterPairs(segments.rows)
    odd = odd_markers(pairs, pairs.spread(pairs.distances(frames[::step])), segments.floors)
    texts = [segments.words(odd, m) for m in (joint.parent_markers, joint.child_markers)]
    return "; ".join(t for t in texts if t)
