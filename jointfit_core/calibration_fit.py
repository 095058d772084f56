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

A whole cluster taken off and put back elsewhere on its bone (a plate
re-strapped a few cm or degrees away, another subject or the other side with
plates of the same shape) keeps its shape, so its residual stays at the
noise, yet the saved joint, fixed in the old template frame, is no longer
where the bone's joint is: measured (hunt of the calibration reuse, hunt-calib
B1), a hip whose pelvis plate was put back 20 mm away was published 20 mm off
with an sd of 1.9 mm (mean e/3 41), a knee whose thigh plate turned 5 deg
4 mm and several degrees off (e/2 136), status OK "frozen". Such a move
breaks the joint itself: the centre (or axis) carried by the parent and the
one carried by the child no longer meet, by about the move, in every frame
(:func:`~jointfit_core.joint_gate.joint_residuals`; the joint test of
:mod:`jointfit_core.joint_gate` scores only sudden changes of it, and a move
made between two sessions is none). :class:`CalibrationFit` therefore also
keeps the recent mean of the joint residual while frozen and compares it with
what the calibration's covariance (and the residual's own scatter) allows:
beyond :data:`JOINT_MISFIT_RATIO` (a chi-square per degree of freedom) the
outputs are withheld in the same way.
"""

from __future__ import annotations

import math
from collections import deque
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from .hinge_from_sums import PoseSumsAxis
from .joint_gate import JointResidual
from .joint_misfit import misfit_statistic
from .segments import PoseSumsCentre

if TYPE_CHECKING:
    from .segment_pair import PairSet

__all__ = ["JOINT_MISFIT_FRAMES", "JOINT_MISFIT_RATIO", "MISFIT_FRAMES", "MISFIT_RMS_RATIO", "CalibrationFit"]

FloatArray = NDArray[np.float64]

#: Frames (posed, while frozen) the residual level averages over (exponentially), and needs before it is judged.
MISFIT_FRAMES = 50
#: The rms residual per degree of freedom beyond which a frozen segment no longer fits its template, as a
#: multiple of the calibration's noise: rigid markers 2 (white noise over 50 frames of 3-6 dof stays within
#: 1.2), skin 3 (the calibration's noise is the pooled residual, the cluster's deformation included, which
#: grows with the joint angles).
MISFIT_RMS_RATIO = {"rigid": 2.0, "skin": 3.0}
#: Frames (both segments posed, while frozen) the joint residual's mean is taken over (exponentially), and
#: needs before it is judged.
JOINT_MISFIT_FRAMES = 100
#: The recent mean joint residual's chi-square per degree of freedom, beyond which the frozen calibration no
#: longer fits the joint (cleared again below half of it): rigid 3, skin (either segment) 9. The mean is
#: judged against what the published outputs allow plus its own uncertainty
#: (:meth:`CalibrationFit._joint_statistic`), so on rigid markers it reads about the outputs' own e/k (0.5-0.9
#: of it). Measured on the rigid rigs (two_segment_motion, 10 seeds, a parent plate put back 2-3 mm away in a
#: random direction): honest reuses read 0.007-0.28; 3 mm moves published at mean e/k 6-31 read 3.1-14 and are
#: withheld, those at e/k 1.7-2.8 read 0.9-1.1 and go out. Until 2026-12-07 the residual's whole per-frame
#: scatter (~4 mm of pose noise at the joint) counted as the mean's uncertainty: the same 3 mm moves read
#: 0.5-2.0 and a 2-3 mm move was published at e/k up to 48, status OK. Skin (3-10 mm of artefact, markers
#: re-applied): honest reuses read 0.005-1.06 at the end of a session and up to 29 on the way (hips; the
#: artefact re-applied changes the thigh's calibration, the outputs' covariance still covers it), and a
#: cluster re-applied 20 mm away, whose outputs the skin covariance still covers (e/k 0.03-4.9), up to 7.6.
JOINT_MISFIT_RATIO = {"rigid": 3.0, "skin": 9.0}
#: The lag (frames) at which the joint residual's autocorrelation is read as its slow share: white pose noise
#: has none there, a drift (the skin's artefact, which follows the movement over seconds) keeps most of it.
SLOW_LAG_FRAMES = 10


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
        self._rigid = "skin" not in attachment
        self._joint_limit = JOINT_MISFIT_RATIO["rigid" if self._rigid else "skin"]
        self.restart()

    def restart(self) -> None:
        """Forget the levels (a freeze, a load, a thaw: the calibration the frames are judged against changed)."""
        self._level = [0.0, 0.0]
        self._count = [0, 0]
        self._misfit = ["", ""]
        self._joint_misfit = ""
        self._solution: PoseSumsCentre | PoseSumsAxis | None = None
        self._residual: JointResidual | None = None
        self._joint_count = 0
        self._e_mean = np.zeros(0)
        self._e_sq = np.zeros((0, 0))
        self._e_lag = np.zeros((0, 0))  # the recent mean of e_k e_{k-L}^T (L = SLOW_LAG_FRAMES): its slow part
        self._e_back: deque[FloatArray] = deque(maxlen=SLOW_LAG_FRAMES)  # the last residuals, oldest first
        self._q_mean = np.zeros((3, 3))
        self._noise_w = np.zeros((6, 6))  # the recent mean of the parent's pose covariance (sigma^2 W), local
        self._noise_count = 0
        #: The latest joint statistic (chi-square per degree of freedom; NaN: not judged yet).
        self.joint_ratio = float("nan")
        self._frames = 0
        self._hold = False
        self.problem = ""

    def hold_until_judged(self) -> None:
        """A calibration loaded from a file: its outputs are withheld until the checks have judged it.

        That is :data:`JOINT_MISFIT_FRAMES` frames with both segments posed (1 s at 100 Hz; the residual check
        needs :data:`MISFIT_FRAMES` of them; a calibration that is not identifiable, whose joint residual is not
        judged, :data:`JOINT_MISFIT_FRAMES` frames with a posed segment). A calibration frozen in this session was fitted to these
        markers; a loaded one may be another session's, whose clusters were put back elsewhere, or another
        subject's (the hunt of the calibration reuse: the first second after a load was published 20 to
        143 mm off at an sd of 1.9 mm before the checks could say so).
        """
        self._hold = True
        self._update_problem()

    @property
    def holding(self) -> bool:
        """A loaded calibration not judged yet, and nothing found wrong so far (:meth:`hold_until_judged`)."""
        return self._hold and not (self._misfit[0] or self._misfit[1] or self._joint_misfit)

    def _update_problem(self) -> None:
        held = ""
        if self._hold:
            held = (
                f"checking the loaded calibration against these markers ({self._joint_count} of "
                f"{JOINT_MISFIT_FRAMES} frames with both segments posed): outputs held until it is judged"
            )
        self.problem = self._misfit[0] or self._misfit[1] or self._joint_misfit or held

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
        self._update_problem()

    def add_joint(
        self,
        z: FloatArray,
        e: FloatArray,
        residual: JointResidual | None,
        solution: PoseSumsCentre | PoseSumsAxis | None,
    ) -> None:
        """One frame with both segments posed: its relative pose ``z`` (3, 4) = ``[Q | t]`` and joint residual ``e``.

        ``residual``: the calibration's joint residual (the joint test's,
        :attr:`JointTrack.residual <jointfit_core.joint_gate.JointTrack.residual>`, which has just
        computed ``e`` from ``z``); None when ``solution`` cannot be judged (not identifiable), and
        ``z``, ``e`` are then ignored. Keeps the recent mean of the joint residual
        (:func:`~jointfit_core.joint_gate.joint_residuals`) and of ``Q``, and every
        :data:`JOINT_MISFIT_FRAMES` // 10 frames judges the mean against its covariance under the
        calibration: the estimate's (``J cov J^T``, ``J`` the mean residual's derivative by the
        parent's and the child's estimate) plus the residual's recent per-frame covariance (the
        frames' pose noise at the joint; on skin markers the artefact's drift).
        """
        if solution is not self._solution:
            self._solution = solution
            self._joint_count = 0
            self._joint_misfit = ""
        self._residual = residual
        res = residual
        if res is None:
            return
        if not np.isfinite(e).all():
            return
        self._joint_count += 1
        n = self._joint_count
        w = 1.0 / min(n, JOINT_MISFIT_FRAMES)
        if n == 1:
            self._e_mean = e.copy()
            self._e_sq = np.outer(e, e)
            self._e_lag = np.outer(e, e)
            self._q_mean = z[:, :3].copy()
            self._e_back.clear()
        else:
            self._e_mean += w * (e - self._e_mean)
            self._e_sq += w * (np.outer(e, e) - self._e_sq)
            self._e_lag += w * (np.outer(e, self._e_back[0]) - self._e_lag)
            self._q_mean += w * (z[:, :3] - self._q_mean)
        self._e_back.append(e.copy())
        if n < JOINT_MISFIT_FRAMES or n % max(JOINT_MISFIT_FRAMES // 10, 1):
            return
        self.joint_ratio = self._joint_statistic(res)
        if self.joint_ratio > self._joint_limit:  # (cleared below half the limit: no flicker about it)
            what = "centre" if res.kind == "ball" else "axis"
            self._joint_misfit = (
                f"the frozen calibration no longer fits the joint: the {what} carried by the parent and by the "
                f"child disagree by {float(np.linalg.norm(self._e_mean)):.3g} (input units) over the last "
                f"{JOINT_MISFIT_FRAMES} frames, {math.sqrt(self.joint_ratio):.3g} sd of what the calibration "
                "allows: a cluster moved on its bone (taken off and put back), or another subject's or side's "
                "calibration; outputs withheld: put the cluster back, or reset the joint and calibrate again"
            )
        elif self.joint_ratio < 0.5 * self._joint_limit:
            self._joint_misfit = ""
        self._update_problem()

    def _joint_statistic(self, res: JointResidual) -> float:
        """The recent mean joint residual's chi-square per degree of freedom (the largest of its blocks).

        Notes
        -----
        The mean ``m`` of the last :data:`JOINT_MISFIT_FRAMES` frames' residuals (parent frame) is judged
        against ``C = J cov J^T + N + f S``: the calibration's covariance of it (``J`` its derivative by the
        parent's and the child's estimate), the parent's per-frame pose noise at the joint ``N`` (the part of
        a published output's covariance that is not the estimate's), and the residual's per-frame scatter
        ``S`` times the variance factor of a mean of :data:`JOINT_MISFIT_FRAMES` frames of a white part and
        a slow part, ``f = s + (1 - s) / JOINT_MISFIT_FRAMES``, ``s`` the residual's autocorrelation at
        :data:`SLOW_LAG_FRAMES` frames (the slow part's share; it does not average out). On rigid markers
        the scatter is the frames' white pose noise (``f`` ~ 1/100), so a plate put back a few mm away,
        which moves ``m`` and every output by as much, is judged at about the outputs' own scale (their
        e/k). Skin markers keep ``f = 1``: the artefact drifts over the movement's seconds, and the
        lag-10 share reads only part of that.
        """
        sol = self._solution
        assert sol is not None
        m = self._e_mean
        scatter = self._e_sq - np.outer(m, m)  # the residual's per-frame covariance
        var = float(np.trace(scatter))
        slow = min(max(float(np.trace(self._e_lag - np.outer(m, m))) / var, 0.0), 1.0) if var > 0.0 else 1.0
        f = slow + (1.0 - slow) / JOINT_MISFIT_FRAMES if self._rigid else 1.0
        return misfit_statistic(sol, res, m, f * scatter, self._q_mean, self._noise_w)

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
        if ps.parent is not None:  # the parent's pose noise, which every published output carries
            self._noise_count += 1
            w = 1.0 / min(self._noise_count, JOINT_MISFIT_FRAMES)
            self._noise_w += w * (sigma[0] ** 2 * ps.parent.W_unit - self._noise_w)
        if self._hold:
            self._frames += 1
            self._hold = self._frames < JOINT_MISFIT_FRAMES or self._joint_unjudged()
            self._update_problem()
        return bool(self.problem)

    def _joint_unjudged(self) -> bool:
        """The joint residual is still to be judged: no frame with both segments posed yet, or fewer than
        :data:`JOINT_MISFIT_FRAMES` of them under a calibration that can be judged (an identifiable one).

        A frame with the parent posed alone counts toward :data:`MISFIT_FRAMES` but cannot judge the joint;
        counting such frames toward the hold (hunt-calib2 A) let a hip whose pelvis plate was put back 20 mm
        away out 20 mm off at e/3 ~550, status OK, for as many frames as the thigh had been hidden.
        """
        if self._solution is None:
            return True
        return self._residual is not None and self._joint_count < JOINT_MISFIT_FRAMES
