"""Whether a frozen joint's markers still fit its calibration: a marker knocked on its cluster after freezing.

A frozen joint (``~/freeze``, or a calibration loaded) poses each frame's
markers on its fixed templates and carries its fixed estimate with the pose.
A marker that moved on its cluster since (knocked, re-stuck) is a step that
stays, which the outlier gate lets through by design (skin that slipped),
and every output is then off by the marker's move times the lever arm, with
the frozen covariance: measured on the live node (hunt D1), a 5 mm move on
the fake mocap's pelvis and thigh put the hip 38 mm off with an sd of
2.3 mm (9.5 sd), status OK "frozen". The pose fits show it: their residual,
per degree of freedom, rises from the calibration's noise to about the move
(5 mm on one of 4 markers: ~1.6 mm rms against 0.5 mm).
:class:`CalibrationFit` keeps each segment's recent residual level while
frozen and says when it is beyond :data:`MISFIT_RMS_RATIO` times the
calibration's noise: the joint then withholds its outputs and says why.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from .segment_pair import PairSet

__all__ = ["MISFIT_FRAMES", "MISFIT_RMS_RATIO", "CalibrationFit"]

FloatArray = NDArray[np.float64]

#: Frames (posed, while frozen) the residual level averages over (exponentially), and needs before it is judged.
MISFIT_FRAMES = 50
#: The rms residual per degree of freedom beyond which a frozen segment no longer fits its template, as a
#: multiple of the calibration's noise: rigid markers 2 (white noise over 50 frames of 3-6 dof stays within
#: 1.2), skin 3 (the calibration's noise is the pooled residual, the cluster's deformation included, which
#: grows with the joint angles).
MISFIT_RMS_RATIO = {"rigid": 2.0, "skin": 3.0}


class CalibrationFit:
    """Each segment's recent pose-fit residual level while frozen, against the calibration's noise.

    Parameters
    ----------
    attachment : (str, str)
        ``"skin"`` or ``"rigid"`` per segment (parent, child): sets :data:`MISFIT_RMS_RATIO`.

    Attributes
    ----------
    problem : str
        Empty while the markers fit; else which segment does not, in words.
    """

    def __init__(self, attachment: tuple[str, str]) -> None:
        self._ratio = tuple(MISFIT_RMS_RATIO[a] for a in attachment)
        self.restart()

    def restart(self) -> None:
        """Forget the levels (a freeze, a load, a thaw: the calibration the frames are judged against changed)."""
        self._level = [0.0, 0.0]
        self._count = [0, 0]
        self._misfit = ["", ""]
        self.problem = ""

    def add(self, segment: int, ss: float, dof: float, sigma: float) -> None:
        """One posed frame of ``segment`` (0 parent, 1 child): its residual sum of squares over ``dof`` degrees of freedom.

        ``sigma``: the calibration's noise of that segment (input units).
        """
        if not dof > 0.0 or not math.isfinite(ss) or not sigma > 0.0:  # (virtual markers: no residual to judge)
            return
        k = segment
        self._count[k] += 1
        weight = 1.0 / min(self._count[k], MISFIT_FRAMES)
        self._level[k] += weight * (ss / dof - self._level[k])
        if self._count[k] >= MISFIT_FRAMES and self._level[k] > (self._ratio[k] * sigma) ** 2:
            side = ("parent", "child")[k]
            self._misfit[k] = (
                f"the {side}'s markers no longer fit the frozen calibration's template: rms pose-fit residual "
                f"{math.sqrt(self._level[k]):.3g} against its noise {sigma:.3g} (input units) over the last "
                f"{MISFIT_FRAMES} frames: a marker moved on its cluster (knocked, re-stuck) or another subject; "
                "outputs withheld: put the marker back, or reset the joint and calibrate again"
            )
        elif self._count[k] >= MISFIT_FRAMES:
            self._misfit[k] = ""
        self.problem = self._misfit[0] or self._misfit[1]

    def add_frame(self, ss: FloatArray, ps: PairSet, sigma: tuple[float, float]) -> bool:
        """One frame's posed segments (:meth:`add` of each); whether the markers no longer fit (:attr:`problem`).

        Parameters
        ----------
        ss : ndarray, shape (2,)
            The parent's and the child's residual sums of squares (input units squared).
        ps : PairSet
            Their visible sets (None: not posed); their degrees of freedom.
        sigma : (float, float)
            The calibration's noise of the parent and the child (input units).
        """
        for k, vs in enumerate((ps.parent, ps.child)):
            if vs is not None:
                self.add(k, float(ss[k]), float(vs.dof), sigma[k])
        return bool(self.problem)
