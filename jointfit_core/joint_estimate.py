"""The estimate side of an online joint: its window of relative-pose sums and the estimate solved from it.

:class:`JointEstimate` holds what :class:`~jointfit_core.estimator.OnlineJoint`
knows once frames have entered its window: the window's sums
(:class:`~jointfit_core.joint_sums.RelativePoseSums`) and their accessors, the
latest estimate with what came with it (noise, serial-correlation factor,
statistical part, artefact scale), the versions that tell a stale estimate and
a stale solve result (:meth:`~JointEstimate.solve_request`,
:meth:`~JointEstimate.install`, :func:`~jointfit_core.window_solve.solve_window`
in this or another process), and the frozen state. It is the root of
``OnlineJoint``'s layers: :class:`~jointfit_core.joint_segments.JointSegments`
supplies the templates' sizes (:meth:`~JointEstimate._radii`) and the status in
words (:meth:`~JointEstimate.status`), ``OnlineJoint``, which feeds the window
from markers frame after frame, what follows an install
(:meth:`~JointEstimate._installed`).
"""

from __future__ import annotations

import itertools

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .checks import check_vector3
from .hinge_from_sums import PoseSumsAxis
from .joint_args import JointSettings
from .joint_sums import RelativePoseSums
from .segments import PoseSums, PoseSumsCentre
from .serial import LagSums, SerialInflation, TimeLagSums
from .stats import WindowSpec
from .window_solve import SKIN_MIN_MOVEMENT_S, SolveRequest, SolveResult, solve_window, unpack_pose_sums

__all__ = ["JointEstimate", "SKIN_MIN_MOVEMENT_S"]

FloatArray = NDArray[np.float64]

#: Estimator states whose solve results may be installed, numbered across all estimators of the process
#: (a runner replaces its estimator on reset: an answer for the old one must not fit the new one).
_GENERATIONS = itertools.count(1)


class JointEstimate:
    """A joint's window of relative-pose sums and its estimate: solve requests, installs, freeze and thaw.

    The root of :class:`~jointfit_core.estimator.OnlineJoint`, whose frames
    feed the window (its layers: :class:`~jointfit_core.joint_segments.JointSegments`
    adds the segments and their templates, ``OnlineJoint`` the frame path).

    Parameters
    ----------
    settings : JointSettings
        The joint's checked arguments; this class keeps ``kind``, ``spec``,
        ``reference_direction``, ``noise_std`` (fixed), ``serial_correlation``
        and ``attachment``.

    Notes
    -----
    **Estimate.** :meth:`estimate` is
    :func:`~jointfit_core.segments.centre_from_pose_sums` (ball; Stoddart eq.
    9 with bias compensation and sandwich covariance) or
    :func:`~jointfit_core.hinge_from_sums.axis_from_pose_sums` (hinge) on the
    window's sums, with the mean local pose covariances times the current
    noise variances: identical to those functions on the window's frames.
    On rigid markers the weighted (Gauss-Markov) batch fit is about 25 % more
    precise but needs every frame; on skin markers a batch hinge reports the
    same closed form as this (the refinement is less accurate under soft-tissue
    artefact, :func:`~jointfit_core.segments.fit_axis_two_segments`).

    **Serial correlation** (``serial_correlation=True``). Those covariances
    treat the frames as independent. Soft-tissue artefact moves markers
    smoothly, so the constraint residual ``r_k = c_p - Q_k c_c - t_k`` is
    correlated in time (lag-1 autocorrelation 0.95-0.998 on skin markers at
    100 Hz; the real hip's falls to 0.45 at 0.32 s and to 0 at 0.64 s) and
    N frames carry the information of about ``N / F`` independent ones, ``F =
    1 + 2 sum_l (1 - l dt / T) rho(l dt)`` the integrated autocorrelation
    (Bartlett, ``T`` = :data:`~jointfit_core.serial.SERIAL_WINDOW_S`). The
    window therefore also keeps, per frame k, the products of its relative
    pose with that of frame k-1 and with those of the frames
    :data:`~jointfit_core.serial.SERIAL_LAGS_S` seconds earlier
    (:mod:`jointfit_core.serial`, :class:`~jointfit_core.serial.LagHistory`:
    pairs found from the stamps, frames without stamps counted at
    :data:`~jointfit_core.serial.NOMINAL_RATE_HZ`), from which
    ``rho(lag) = (sum_pairs r_k . r_j / n_pairs) / (sum_frames |r_k|^2 / n)``
    at the estimate (ball: the centres; hinge: the solved axis-point pair,
    :func:`~jointfit_core.serial.hinge_residual_pair`), and every covariance
    of the estimate (ball: ``cov``, ``cov_parent``, ``cov_child``; hinge:
    directions and points) is multiplied by
    :func:`~jointfit_core.serial.integrated_factor` of them (summed until the
    correlation is noise). Reading the correlation in seconds makes ``N dt /
    F``, the seconds per independent sample, the same at any frame rate; the
    lag-1 AR(1) factor ``(1 + rho) / (1 - rho)`` that
    :func:`~jointfit_core.model_error.residual_inflation` applies to the batch
    fits is not (real hip: 2 effective frames at 100 Hz, 8 at 12.5 Hz; now
    30 and 29). The batch fits' ``chi2`` factor is not applied: the sandwich's middle is the
    residual covariance predicted from the pooled pose-fit noise, which on
    skin markers already grows with the cluster deformation (right hip
    fixture: ``sum |r|^2 / ((N - 2) tr W) = 1.09``); artefact that moves a
    cluster rigidly would not show there. When the factor makes an
    identifiable estimate's standard deviation exceed the verdict's limits
    (:data:`~jointfit_core.segments.SD_REL_MAX` of the lever arm,
    :data:`~jointfit_core.segments.AXIS_SD_MAX_DEG`), it is flagged as the
    batch fits flag it. *Lag pairs*: the pair ``(k-1, k)`` is stored with
    frame k, and only when frame k-1 is the frame that entered the
    statistics just before it, with no frame in between that reached the
    estimator but could not enter them (a segment not posed, or frozen);
    frames dropped for a non-increasing stamp do not break the chain. A
    pair leaves the window (or decays) with frame k, so the oldest frame of
    a window still carries its pair with the frame before it: the window's
    sums are the batch sums of its frames
    (:func:`~jointfit_core.segments.pose_sums_from_relative`) and of the
    pairs ending in them (:func:`~jointfit_core.serial.lag_sums_from_relative`
    over the window and the frame before it). The pairs at lags in seconds are
    stored with their later frame in the same way.
    """

    def __init__(self, settings: JointSettings) -> None:
        self.kind = settings.kind
        self.spec: WindowSpec = settings.spec
        self.reference_direction = settings.reference_direction
        self._noise_arg = settings.noise_std
        self.serial_correlation = settings.serial_correlation
        #: ``("skin" | "rigid", "skin" | "rigid")``: how the parent's and the child's markers are attached.
        self.attachment = settings.attachment
        #: Most frames a time window holds (None: no bound; :mod:`jointfit_core.window_entries`).
        self.window_max_frames = settings.window_max_frames
        self._skin = "skin" in self.attachment
        self._moments = self._skin and self.kind == "hinge"
        self.reset()

    def reset(self) -> None:
        """Forget the window's frames, the estimate and the frozen state."""
        self._stats = RelativePoseSums(self.spec, self._skin, self._moments, self.window_max_frames)
        self._solution: PoseSumsCentre | PoseSumsAxis | None = None
        self._sigma = (0.0, 0.0)
        # Data changes since the start (frames entered; hinge sign convention) and the change the
        # solution was solved at: the solution is stale while they differ. A reset (and a new sign
        # convention) starts a new generation, whose solve results alone may be installed.
        self._version = 0
        self._solved_version = 0
        self._generation = next(_GENERATIONS)
        self._frozen = False
        self._serial: SerialInflation | None = None
        self._statistical: PoseSumsCentre | PoseSumsAxis | None = None
        self._artefact_scale = 0.0
        self._cluster_motion: FloatArray | None = None
        self._white_sigma: tuple[float, float] | None = None
        self._matched: FloatArray | None = None  # hinge: point_child_matched (joint_file.matched_child_point)

    # ------------------------------------------------------------------ what the layers above supply

    def status(self) -> str:
        """What the estimator is waiting for, in words (empty when estimating; here always empty)."""
        return ""

    def _radii(self) -> tuple[float, float]:
        """The rms radii of the parent's and the child's templates (input units; here (0, 0): none)."""
        return (0.0, 0.0)

    def _marker_counts(self) -> tuple[int, int]:
        """The parent's and the child's marker counts (here (4, 4), the usual cluster: not known)."""
        return (4, 4)

    @property
    def length_scale(self) -> float:
        """The larger rms radius of the two templates (input units; 0 until they exist)."""
        return max(self._radii())

    def _installed(self) -> None:
        """Called when a solve result has become the estimate (here: nothing)."""

    # ------------------------------------------------------------------ the window

    @property
    def statistics(self) -> RelativePoseSums:
        """The joint's window of relative-pose sums (:class:`~jointfit_core.joint_sums.RelativePoseSums`)."""
        return self._stats

    @property
    def n_window(self) -> int:
        """Frames in the window (frames added, under forgetting)."""
        return 0 if self._stats.window is None else self._stats.window.n_window

    @property
    def window_thinned(self) -> int:
        """Frames left out of a time window fed faster than ``window_max_frames`` allows, since the window started.

        :mod:`jointfit_core.window_entries`; 0 for other windows.
        """
        return self._stats.entries.thinned

    @property
    def movement_seconds(self) -> float:
        """Seconds of movement in the window (weighted, with forgetting): frames whose relative rotation turned by more than :data:`~jointfit_core.joint_sums.MOVING_DEG` in 0.32 s.

        Skin estimates are identifiable from :data:`SKIN_MIN_MOVEMENT_S` on (see
        :func:`~jointfit_core.joint_sums.moving_seconds`).
        """
        return self._stats.movement_seconds

    def pose_sums(self) -> tuple[PoseSums, FloatArray, FloatArray, float, float]:
        """The window's sums: ``(PoseSums, mean unit W_p (6, 6), mean unit W_c (6, 6), sigma_p, sigma_c)``.

        Raises
        ------
        InputError
            No frame has entered the statistics yet.
        """
        return unpack_pose_sums(self._entered_sums())

    def lag_sums(self) -> LagSums:
        """The window's lag-pair sums (:class:`~jointfit_core.serial.LagSums`; see the class Notes).

        Raises
        ------
        InputError
            No frame has entered the statistics yet.
        """
        return self._stats.lag_sums(self.status())

    def time_lag_sums(self) -> TimeLagSums:
        """The window's lag-pair sums at lags in seconds (:class:`~jointfit_core.serial.TimeLagSums`).

        Raises
        ------
        InputError
            No frame has entered the statistics yet.
        """
        return self._stats.time_lag_sums(self.status())

    def sums_vector(self) -> FloatArray | None:
        """A copy of the window's sums vector (the layout :meth:`request_for` takes); None before any frame entered."""
        window = self._stats.window
        if window is None or window.sums[0] <= 0.0:
            return None
        return window.sums.copy()

    def window_contributions(self) -> tuple[FloatArray, FloatArray] | None:
        """Each frame's contribution to the window's sums, oldest first, and its stamp.

        Returns
        -------
        (ndarray, shape (n, n_sums), ndarray, shape (n,)) or None
            The rows sum to :meth:`sums_vector`; stamps in seconds (NaN when
            not stamped). None for exponential forgetting (which keeps no
            frames) and before any frame entered.
        """
        window = self._stats.window
        if window is None or window.spec.exponential or window.n_window == 0:
            return None
        return window.window_records(), window.window_stamps()

    def _entered_sums(self) -> FloatArray:
        """The window's sums vector; InputError when no frame has entered the statistics yet."""
        return self._stats.entered(self.status())

    # ------------------------------------------------------------------ the estimate

    @property
    def solution(self) -> PoseSumsCentre | PoseSumsAxis | None:
        """The latest estimate, without solving again (None before the first)."""
        return self._solution

    @property
    def frozen(self) -> bool:
        """Whether the estimate is frozen (per-frame outputs continue, statistics do not)."""
        return self._frozen

    @property
    def noise_std(self) -> tuple[float, float]:
        """Marker noise estimates (parent, child) used by the latest estimate, input units.

        The pooled pose-fit residual: on skin markers it holds the clusters' deformation too
        (the covariance's pose-noise part and the outlier gate use it as such); their white
        noise alone is :attr:`white_noise_std`.
        """
        return self._sigma

    @property
    def white_noise_std(self) -> tuple[float, float] | None:
        """Skin markers: the white marker noise (parent, child) of the latest estimate, input units.

        Read from the second differences of the pose-fit residuals
        (:mod:`~jointfit_core.white_noise_sums`); what a ball joint's bias compensation used.
        None for rigid markers and before an estimate.
        """
        return self._white_sigma

    @property
    def serial_inflation(self) -> SerialInflation | None:
        """The lag-1 correlation of the latest estimate's residual and the factor applied to its covariances.

        None before the first estimate and after
        :meth:`OnlineJoint.from_dict <jointfit_core.estimator.OnlineJoint.from_dict>` of a
        calibration saved without it.
        """
        return self._serial

    @property
    def statistical_solution(self) -> PoseSumsCentre | PoseSumsAxis | None:
        """Skin markers: the latest estimate with its statistical covariances only (without the soft-tissue part).

        None for rigid markers (:meth:`estimate`'s covariances are then the
        statistical ones), before the first estimate and after
        :meth:`OnlineJoint.from_dict <jointfit_core.estimator.OnlineJoint.from_dict>`.
        """
        return self._statistical

    @property
    def artefact_scale(self) -> float:
        """The soft-tissue prior's scale at the latest estimate (input units per radian; 0 for rigid markers)."""
        return self._artefact_scale

    @property
    def cluster_motion(self) -> FloatArray | None:
        """Skin markers: per frame, the variance of each cluster's motion on its bone at the latest estimate.

        Shape (2, 6): ``(omega, u)`` per component (rad^2, input units squared), parent then child
        (:attr:`~jointfit_core.artefact_sums.SumsArtefact.cluster_motion`); None for rigid markers
        and calibrations saved before it existed.
        """
        return self._cluster_motion

    @property
    def solved_version(self) -> tuple[int, int]:
        """``(generation, version)`` of the window the current estimate was solved from (changes with every solve)."""
        return self._generation, self._solved_version

    # ------------------------------------------------------------------ solving, installing, freezing

    def estimate(self) -> PoseSumsCentre | PoseSumsAxis:
        """Solve the window's sums (or return the frozen or still current estimate).

        Returns
        -------
        PoseSumsCentre or PoseSumsAxis
            For ``kind`` "ball" and "hinge"; local frames are the templates'.
            Covariances include the serial-correlation factor
            (:attr:`serial_inflation`; see the class Notes).

        Raises
        ------
        InputError
            Fewer than 3 frames in the statistics.
        NotIdentifiableError
            The window's motion cannot determine the joint at all.

        Notes
        -----
        ``install(solve_window(solve_request()))``: the same steps as a solve in
        another process (:meth:`solve_request`, :func:`solve_window`, :meth:`install`).
        """
        request = self.solve_request()
        if request is not None:
            self._install(solve_window(request))
        assert self._solution is not None
        return self._solution

    def solve_request(self) -> SolveRequest | None:
        """A snapshot of the window for :func:`solve_window`; None when the estimate is current.

        The estimate is current when frozen, or when no frame has entered the
        statistics since it was solved. The request holds copies, so the
        estimator takes further frames while it is solved elsewhere.

        Raises
        ------
        InputError
            No frame has entered the statistics yet.
        """
        if self._solution is not None and (self._frozen or self._version == self._solved_version):
            return None
        return self.request_for(self._entered_sums().copy())

    def request_for(self, sums: FloatArray) -> SolveRequest:
        """A :class:`SolveRequest` of this estimator's settings for other sums (e.g. one block of the window).

        Parameters
        ----------
        sums : ndarray, shape (n_sums,)
            A sums vector in the estimator's layout: a sum of rows of
            :meth:`window_contributions`, or a difference of :meth:`sums_vector`
            snapshots of a window that forgets nothing.
        """
        return SolveRequest(
            kind=self.kind,
            sums=np.asarray(sums, dtype=np.float64),
            noise_std=self._noise_arg,
            length_scale=self.length_scale,
            reference_direction=self._sign_reference(),
            serial_correlation=self.serial_correlation,
            generation=self._generation,
            version=self._version,
            attachment=self.attachment,
            radii=self._radii(),
            n_markers=self._marker_counts(),
        )

    def _sign_reference(self) -> FloatArray | None:
        """Hinge: the direction the next estimate's sign follows (parent frame), or None for the default rule.

        The configured convention (:meth:`set_reference_direction`); without one, the latest
        identifiable estimate's direction, so that the sign, once an estimate is identifiable,
        is kept from solve to solve. The default rule alone (the parent-frame component of
        largest magnitude positive) flipped the axis between solves whenever two components
        were about as large (``test/test_hinge_sign_continuity.py``).
        """
        if self.reference_direction is not None:
            return self.reference_direction
        sol = self._solution
        if isinstance(sol, PoseSumsAxis) and sol.identifiable:
            return sol.direction_parent
        return None

    def is_current(self, request: SolveRequest) -> bool:
        """Whether a :meth:`solve_request` was made in the state the estimator is in now.

        False after a reset, a freeze or a new hinge sign convention: the answer
        to it, a result or an error, is about a window that is gone.
        """
        return request.generation == self._generation and not self._frozen

    def install(self, result: SolveResult) -> bool:
        """Make a :func:`solve_window` result of an earlier :meth:`solve_request` the estimate.

        Returns False (and changes nothing) when the result is stale: the
        estimator was reset or frozen since the request, its hinge sign
        convention changed, or the estimate is already as recent.
        """
        if result.generation != self._generation or self._frozen:
            return False
        if self._solution is not None and result.version <= self._solved_version:
            return False
        self._install(result)
        return True

    def _install(self, result: SolveResult) -> None:
        """Make ``result`` the estimate, whatever its age, and tell the subclass (:meth:`_installed`)."""
        self._solution = result.solution
        self._sigma = result.noise_std
        self._serial = result.serial
        self._statistical = result.statistical
        self._artefact_scale = result.artefact_scale
        self._cluster_motion = result.cluster_motion
        self._white_sigma = result.white_noise_std
        self._solved_version = result.version
        self._installed()

    def set_reference_direction(self, direction: ArrayLike) -> None:
        """Set the hinge sign convention (a direction in the parent local frame); the next estimate follows it."""
        self.reference_direction = check_vector3(direction, name="reference_direction", unit=True)
        self._version += 1
        self._generation = next(_GENERATIONS)  # a solve under way has the old convention

    def freeze(self) -> PoseSumsCentre | PoseSumsAxis:
        """Fix the current estimate; per-frame outputs continue, the statistics stop.

        Raises
        ------
        InputError, NotIdentifiableError
            No estimate can be made yet.
        """
        sol = self.estimate()
        self._frozen = True
        return sol

    def thaw(self) -> None:
        """Resume updating the statistics (the window holds the frames from before freezing)."""
        self._frozen = False

    def _forget_estimate(self) -> None:
        """Drop the estimate (not the window): none until the window is solved again."""
        self._solution = None
        self._statistical = None
        self._solved_version = 0
        self._installed()
