"""What a joint of the node takes for a broken value: absurd markers and outputs, clusters in the wrong unit.

On a frame's path through a :class:`~jointfit_ros.runner.JointRunner`,
:class:`MarkerScreen` comes first: before the estimator sees a frame (or a
block of frames), a marker beyond the ``workspace`` (when set, in input units
:func:`workspace_limit`) or farther from its segment's visible markers' mean
than :data:`ABSURD_RADII` times the larger template's rms radius is set
missing: no swap, ghost or skin motion puts a marker there, only a broken
value (a finite 1e299 from a driver). :func:`output_sane` comes last: a world
output that is non-finite, beyond the workspace (without one:
:data:`ABSURD_OUTPUT`) or with a larger sd is withheld. :func:`unit_problem`
is read with the diagnostics: a marker cluster whose size is implausible for
the configured ``units``. The runner counts what these refuse and says why.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from jointfit_core.checks import small_all_finite
from jointfit_core.estimator import JointOutput

from .params import NodeConfig

__all__ = [
    "ABSURD_OUTPUT",
    "ABSURD_RADII",
    "CLUSTER_RADIUS_M",
    "MarkerScreen",
    "output_sane",
    "unit_problem",
    "workspace_limit",
]

FloatArray = NDArray[np.float64]

#: Metres per unit of the ``units`` parameter.
_METRES = {"m": 1.0, "cm": 0.01, "mm": 0.001}
#: Plausible rms radius of a segment's marker cluster (or virtual markers), metres.
CLUSTER_RADIUS_M = (0.003, 1.0)

#: A marker farther than this many template rms radii from its segment's mean is absurd (a broken value).
ABSURD_RADII = 20.0

#: Without a workspace, no output beyond this (input units: 1e9 mm or m) or with a larger sd is published.
ABSURD_OUTPUT = 1e9


def unit_problem(rms_radius: float, units: str) -> str:
    """Why a cluster's rms radius (input units) is implausible for ``units``; empty when plausible.

    A mocap stream in millimetres sent to a node configured for metres (or the
    reverse) gives clusters 1000 times too large (small): the estimates are then
    in the wrong unit for every consumer, and the noise settings are off.
    """
    if not rms_radius > 0.0 or units not in _METRES:
        return ""
    metres = rms_radius * _METRES[units]
    low, high = CLUSTER_RADIUS_M
    if low <= metres <= high:
        return ""
    guess = min(_METRES, key=lambda u: abs(np.log10(rms_radius * _METRES[u] / 0.05)))
    return (
        f"marker clusters are {rms_radius:.3g} {units} in rms radius, implausible for units '{units}' "
        f"(expected {low:g}-{high:g} m): the stream looks like {guess}; check the driver's units or set units"
    )



def workspace_limit(node: NodeConfig) -> float:
    """The ``workspace`` half-width in input units (inf when off or the units are unknown)."""
    metres = _METRES.get(node.units, 0.0)
    return node.workspace / metres if node.workspace > 0.0 and metres > 0.0 else math.inf


def output_sane(out: JointOutput, limit: float) -> bool:
    """Whether an output may be published: finite, within ``limit`` (input units; inf: :data:`ABSURD_OUTPUT`), its sd below it."""
    if not (small_all_finite(out.position) and small_all_finite(out.cov)):
        return False
    if out.direction is not None and not (
        out.cov_direction is not None and small_all_finite(out.direction) and small_all_finite(out.cov_direction)
    ):
        return False
    if not math.isfinite(limit):
        limit = ABSURD_OUTPUT
    x, y, z = out.position.tolist()
    c = out.cov.ravel().tolist()
    return max(abs(x), abs(y), abs(z)) <= limit and max(c[0], c[4], c[8]) <= limit**2



class MarkerScreen:
    """The absurd-marker test of one joint's two marker clusters in the node's frames.

    Parameters
    ----------
    parent_rows, child_rows : ndarray of intp, shape (Pa,) and (Pc,)
        The segments' markers' rows in the node's frames (empty for a
        segment of a pose topic).

    Attributes
    ----------
    cluster_rows : ndarray of intp, shape (Pa + Pc,)
        Both segments' rows, parent first.
    compact_starts : ndarray of intp, shape (2,), or None
        Where each segment starts in ``cluster_rows`` when both have markers:
        the usual frame's shortcut (:meth:`compact`; None: off).
    """

    def __init__(self, parent_rows: NDArray[np.intp], child_rows: NDArray[np.intp]) -> None:
        self.parent_rows = parent_rows
        self.child_rows = child_rows
        self.cluster_rows = np.concatenate([parent_rows, child_rows])
        self.compact_starts = (
            np.array([0, len(parent_rows)], dtype=np.intp) if len(parent_rows) and len(child_rows) else None
        )

    def screened(self, frames: FloatArray, limit: float, scale: float) -> tuple[FloatArray, int]:
        """``frames`` (..., P, 3) with absurd markers set missing (a copy when any is), and how many were.

        Absurd: a coordinate beyond ``limit`` (input units; inf: no workspace),
        or a marker farther from its segment's visible markers' mean than
        ``scale`` (input units; 0: no templates yet, no such test). One such
        marker drags the mean of its segment, so its neighbours may go with it
        in that frame: the segment is then not posed there. Without templates
        and without a workspace, a coordinate beyond :data:`ABSURD_OUTPUT` is
        absurd: the template frames' shape test squares it (a finite 1e160 or
        1e299 from a driver overflowed it, raised from the frame callback and
        left the joint without an estimate for the rest of the session).
        """
        if not math.isfinite(limit):
            if self.compact(frames, scale):
                return frames, 0
            if not scale > 0.0:
                limit = ABSURD_OUTPUT
        out = self._absurd(frames, limit, scale)
        if out is None or not out.any():
            return frames, 0
        frames = frames.copy()
        where = np.zeros(frames.shape[:-1], dtype=bool)
        where[..., self.cluster_rows] = out
        frames[where] = np.nan
        return frames, int(out.sum())

    def _absurd(self, frames: FloatArray, limit: float, scale: float) -> NDArray[np.bool_] | None:
        """The absurd markers of :meth:`screened`, (..., Pa + Pc) over :attr:`cluster_rows` (None: no test applies)."""
        out: NDArray[np.bool_] | None = None
        with np.errstate(invalid="ignore", over="ignore"):
            if math.isfinite(limit):
                out = np.asarray((np.abs(frames[..., self.cluster_rows, :]) > limit).any(axis=-1))
            if scale > 0.0:
                for rows in (self.parent_rows, self.child_rows):
                    y = frames[..., rows, :]
                    # no marker is far from the mean when the segment's extent is within the limit (the usual
                    # frame: two reductions instead of the test below)
                    if y.shape[-2] == 0 or not y.size:  # a segment of pose topics (no markers), or no frames
                        continue
                    if bool((np.fmax.reduce(y, axis=-2) - np.fmin.reduce(y, axis=-2) <= scale).all()):
                        continue
                    seen = ~np.isnan(y[..., :1])
                    centre = np.where(seen, y, 0.0).sum(axis=-2, keepdims=True) / np.maximum(
                        seen.sum(axis=-2, keepdims=True), 1
                    )
                    # (an infinite value is left to the estimator, which refuses the frame as malformed)
                    far = np.asarray((np.abs(y - centre) > scale).any(axis=-1) & np.isfinite(centre).all(axis=-1))
                    far &= ~np.isinf(y).any(axis=-1)
                    if far.any():
                        part = np.zeros(frames.shape[:-1], dtype=bool)
                        part[..., rows] = far
                        part = part[..., self.cluster_rows]
                        out = part if out is None else out | part
        return out

    def compact(self, frames: FloatArray, scale: float) -> bool:
        """Whether every segment of ``frames`` (..., P, 3) spans at most ``scale`` per coordinate (no absurd marker).

        The usual frame's test of :meth:`screened` (no marker far from its segment's mean
        when the segment's extent is within the limit), for both segments of markers at once:
        one gather and one ``reduceat`` per bound instead of two per segment. False when it does
        not settle it (a segment without markers, no templates yet, no frames, a wide segment
        or an all-missing coordinate): the segment-by-segment test then decides.
        """
        if not (scale > 0.0 and self.compact_starts is not None and frames.size):
            return False
        y = frames[..., self.cluster_rows, :]
        with np.errstate(invalid="ignore", over="ignore"):
            spread = np.fmax.reduceat(y, self.compact_starts, axis=-2) - np.fmin.reduceat(y, self.compact_starts, axis=-2)
            return bool((spread <= scale).all())
