"""Whether a joint's recent frames still agree with its estimate: the joint residual's recent mean, judged.

Pure numpy. Two users:

* :class:`~jointfit_core.calibration_fit.CalibrationFit`, while a joint is frozen: a calibration reused
  after a cluster was put back elsewhere on its bone (:func:`misfit_statistic`);
* :class:`JointDrift`, while a joint on rigid markers estimates: a cluster bumped on its bone in the
  session. The window then holds frames of two placements. Its estimate stays with the older ones
  for seconds, and every output is off by the move at the covariance of the old estimate. Measured
  on the rigid rigs (``two_segment_motion``, window 3000 frames at 100 Hz, 3 seeds, the parent plate
  moved at 30 s): over the next 10 s, a 10 mm move gave outputs at mean e/3 12-25 (hinge point e/2
  24-41), a 3 mm move 3.4-6.4. The joint test scores only sudden changes against the frames' noise
  at the joint (~4 mm there), so it let both through, and nothing was said.

The recent mean ``m`` of the joint residual (:func:`~jointfit_core.joint_gate.joint_residuals`: the
joint carried by the parent against the one carried by the child, parent frame) is zero under the
joint's estimate, to within what the estimate's covariance and the frames' noise allow. A cluster
moved on its bone moves ``m`` by about the move, and every output by as much: judged against the
estimate's covariance of ``m`` and the parent's pose noise at the joint (the outputs' own), its
chi-square per degree of freedom reads about the outputs' e/k. With the check (:class:`JointDrift`:
outputs held from the first mean beyond the limits, the window restarted when a second, disjoint one
is too), the same moves are held 20-75 frames after them and restarted 100 frames later; the outputs
since read mean e/k 0.9-1.0 (``test/test_joint_drift.py``).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .hinge_from_sums import PoseSumsAxis
from .joint_gate import JointResidual
from .pose import lever_jacobian, skew
from .segments import PoseSumsCentre, _perp_basis

__all__ = ["DRIFT_FRAMES", "DRIFT_LIMIT", "DRIFT_RATE_HZ", "JointDrift", "misfit_statistic"]

FloatArray = NDArray[np.float64]

#: Frames the recent mean of :class:`JointDrift` is taken over (1 s at 100 Hz), and how often it is judged.
DRIFT_FRAMES, DRIFT_EVERY = 100, 25
#: Most frames per second :class:`JointDrift` takes (one per 1 / DRIFT_RATE_HZ s of stamp time), so that its
#: frame counts are the same seconds at any faster rate: at 1 kHz with every frame, its 30 past blocks were 3 s
#: and the screw-home knee above restarted its window 21-25 times a minute (2325-2500 of 60000 outputs held;
#: none at 100 Hz).
DRIFT_RATE_HZ = 100.0
#: :class:`JointDrift`'s limit on the recent mean's chi-square per degree of freedom (rigid markers): as the
#: frozen calibration's (:data:`~jointfit_core.calibration_fit.JOINT_MISFIT_RATIO`), about the outputs' e/k.
DRIFT_LIMIT = 3.0
#: Past blocks of :data:`DRIFT_FRAMES` frames kept, and the fewest needed before judging: a recent mean must
#: also read :data:`DRIFT_OVER_PAST` times any of theirs. A joint that is not quite the model (a knee with
#: 10 deg of screw-home rotation near extension, rigid markers) has a residual that follows the angle, so its
#: recent mean reads up to 70 against the estimate whenever the limb dwells where the model errs; a cluster
#: moved on its bone shifts it beyond what the past blocks read.
DRIFT_BLOCKS, DRIFT_MIN_BLOCKS, DRIFT_OVER_PAST = 30, 5, 2.0


def misfit_statistic(
    sol: PoseSumsCentre | PoseSumsAxis,
    res: JointResidual,
    mean: FloatArray,
    mean_cov: FloatArray,
    q_mean: FloatArray,
    noise_w: FloatArray,
) -> Any:
    """The joint residual's recent mean against what the estimate allows: chi-square per degree of freedom.

    Parameters
    ----------
    sol : PoseSumsCentre or PoseSumsAxis
        The estimate the residuals were taken under.
    res : JointResidual
        Its joint residual (:attr:`JointTrack.residual <jointfit_core.joint_gate.JointTrack.residual>`).
    mean : ndarray, shape (..., 3) (ball) or (..., 6) (hinge: turn, then point)
        The recent mean residual (input units; a ball joint's may have three more entries, unused), or
        several.
    mean_cov : ndarray, shape (k, k), k as ``mean``
        The mean's own noise covariance (the frames' scatter over their effective count).
    q_mean : ndarray, shape (3, 3)
        The recent mean relative rotation ``Q`` (child template frame to parent template frame).
    noise_w : ndarray, shape (6, 6)
        The parent's recent per-frame pose covariance ``sigma^2 W`` (local frame).

    Returns
    -------
    float, or ndarray of shape (...)
        Per mean, the largest over the residual's blocks (ball: the centre, 3 dof; hinge: the turn across the
        axis and the point across it, 2 dof each) of ``m^T C^+ m / dof``.

    Notes
    -----
    ``C = J cov J^T + N + mean_cov``: the estimate's covariance of ``m`` (``J`` its derivative by the
    parent's and the child's estimate), the parent's per-frame pose noise at the joint ``N`` (the part
    of a published output's covariance that is not the estimate's), and the mean's own noise. Stoddart
    et al. (1999), eq. 14, is the joint residual's linearisation this carries.
    """
    Qm, W = q_mean, noise_w
    if isinstance(sol, PoseSumsAxis):
        u = res.u
        B = _perp_basis(u).T  # (2, 3): the plane across the axis, where both blocks are judged
        Nx = skew(u)
        # the turn across the axis only: along it, ``Q a_c - a_p`` is of second order (the pose noise's
        # shrinking of ``Q a_c``, a bias with next to no scatter, that no direction error causes)
        turn = res.length**2 * (Qm @ sol.cov_direction_child @ Qm.T + sol.cov_direction_parent + Nx @ W[:3, :3] @ Nx.T)
        Jp = lever_jacobian(sol.point_parent)
        across = Qm @ sol.cov_point_child @ Qm.T + sol.cov_point_parent + Jp @ W @ Jp.T
        worst = np.maximum(
            _per_dof(mean[..., :3] @ B.T, B @ (turn + mean_cov[:3, :3]) @ B.T),
            _per_dof(mean[..., 3:6] @ B.T, B @ (across + mean_cov[3:6, 3:6]) @ B.T),
        )
    else:
        J = np.concatenate([-np.eye(3), Qm], axis=1)
        Jp = lever_jacobian(sol.centre_parent)
        worst = _per_dof(mean[..., :3], J @ sol.cov @ J.T + Jp @ W @ Jp.T + mean_cov[:3, :3])
    return worst if np.ndim(worst) else float(worst)


def _per_dof(v: FloatArray, C: FloatArray) -> Any:
    """``v^T C^-1 v / d`` of vectors ``v`` (..., d) against one covariance ``C`` (d, d) (degenerate: its pseudo-inverse)."""
    try:
        inv = np.linalg.inv(C)
    except np.linalg.LinAlgError:
        inv = np.linalg.pinv(C, rcond=1e-10, hermitian=True)
    return np.einsum("...i,ij,...j->...", v, inv, v) / C.shape[0]


class JointDrift:
    """While a joint on rigid markers estimates: do its last :data:`DRIFT_FRAMES` frames agree with the estimate?

    A recent mean beyond the limits makes the joint *hold* its outputs; one that stays beyond them for
    :data:`DRIFT_FRAMES` more frames (two disjoint means: a cluster moved stays moved) is a *drift*. One
    mean alone is not enough: where the parent's pose noise at the joint is small (across a lever, the
    hinge point's other direction), the mean is judged against little more than its own noise, and
    over a session some mean reads beyond 3 by chance (the fake mocap's knee, 5 min at 250 Hz: 2.75).

    Attributes
    ----------
    ratio : float
        The latest :func:`misfit_statistic` (NaN: not judged since the last :meth:`restart`).
    holding : bool
        The recent frames disagree with the estimate; not (yet) for :data:`DRIFT_FRAMES` frames.
    """

    def __init__(self) -> None:
        self._e = np.zeros((DRIFT_FRAMES, 6))
        self._z = np.zeros((DRIFT_FRAMES, 3, 4))
        self._noise: tuple[FloatArray, float] = (np.zeros((6, 6)), 0.0)  # the latest parent unit W and sigma^2
        self._generation = -1  # the estimator's window the frames are of (:meth:`step`)
        self._slot: float = -math.inf  # the 1 / DRIFT_RATE_HZ s slot of stamp time of the last frame taken
        self.restart()

    def step(
        self, generation: int, time: float, z: FloatArray, e: FloatArray, w_unit: FloatArray, sigma2: float,
        sol: PoseSumsCentre | PoseSumsAxis | None, res: JointResidual | None,
    ) -> bool:
        """:meth:`add` then :meth:`judge` of a frame of the window ``generation`` at ``time`` (s); a new window restarts first.

        A frame within ``1 / DRIFT_RATE_HZ`` of stamp time of the previous one taken is skipped
        (:data:`DRIFT_RATE_HZ`). Returns whether the joint drifted (the caller restarts its window;
        this restarts too).
        """
        if generation != self._generation:  # a new window: its residuals only
            self.restart()
            self._generation = generation
        slot = float(math.floor(time * DRIFT_RATE_HZ))
        if slot <= self._slot:
            return False
        self._slot = slot
        self.add(z, e, w_unit, sigma2)
        if not self.judge(sol, res):
            return False
        self.restart()
        return True

    def holds(self, generation: int) -> bool:
        """Whether a frame of the window ``generation`` is held (:attr:`holding`, for this window)."""
        return self.holding and generation == self._generation

    def restart(self) -> None:
        """Forget the frames (a new window of the estimator, or after a drift: :meth:`step`)."""
        self._n = 0
        self.ratio = math.nan
        self._pending: FloatArray | None = None  # the last block's mean, until it is older than the recent frames
        self._past = np.zeros((DRIFT_BLOCKS, 6))  # the means of the blocks before (a ring)
        self._blocks = 0
        self._since: int | None = None  # the frame count at which the recent mean first went beyond the limits
        self._slot = -math.inf
        self.holding = False

    def add(self, z: FloatArray, e: FloatArray, w_unit: FloatArray, sigma2: float) -> None:
        """One frame that passed the joint test: its ``[Q | t]`` (3, 4), joint residual ``e`` (3 or 6,) and the parent's pose covariance ``sigma2 * w_unit`` (6, 6)."""
        k = self._n % DRIFT_FRAMES
        self._e[k, : e.size] = e  # (a ball joint's residual has 3 entries)
        self._z[k] = z
        self._noise = (w_unit, sigma2)  # (the latest: it changes with the visible markers and the solves only)
        self._n += 1
        if self._n % DRIFT_FRAMES == 0:  # a block is complete: the one before it is now older than the recent frames
            if self._pending is not None:
                self._past[self._blocks % DRIFT_BLOCKS] = self._pending
                self._blocks += 1
            self._pending = self._e.mean(axis=0)

    def judge(self, sol: PoseSumsCentre | PoseSumsAxis | None, res: JointResidual | None) -> bool:
        """Every :data:`DRIFT_EVERY` frames once :data:`DRIFT_MIN_BLOCKS` blocks are past: whether the joint drifted (see the class).

        The recent mean is beyond the limits when it reads over :data:`DRIFT_LIMIT` and over
        :data:`DRIFT_OVER_PAST` times every past block's mean. Its own noise is the frames' white part
        only, read from their first differences (``cov(e_k - e_{k-1}) / 2``, over
        :data:`DRIFT_FRAMES`): a cluster that moved within these frames is a step, which would swell
        their scatter about the mean and hide itself. Sets :attr:`holding`.
        """
        n = self._n
        if sol is None or res is None or self._blocks < DRIFT_MIN_BLOCKS:
            self._since, self.holding = None, False
            return False
        if n % DRIFT_EVERY:
            return False
        k = n % DRIFT_FRAMES
        e = np.roll(self._e, -k, axis=0)  # oldest first
        d = np.diff(e, axis=0)
        white = 0.5 * (d.T @ d) / d.shape[0]
        means = np.concatenate([e.mean(axis=0)[None], self._past[: min(self._blocks, DRIFT_BLOCKS)]])
        w_unit, sigma2 = self._noise
        stats = misfit_statistic(sol, res, means, white / DRIFT_FRAMES, self._z[:, :, :3].mean(axis=0), sigma2 * w_unit)
        self.ratio = float(stats[0])
        if not (self.ratio > DRIFT_LIMIT and self.ratio > DRIFT_OVER_PAST * float(stats[1:].max())):
            self._since, self.holding = None, False
            return False
        if self._since is None:
            self._since = n
        self.holding = n - self._since < DRIFT_FRAMES
        return not self.holding
