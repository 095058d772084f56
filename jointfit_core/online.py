"""Online centre and axis of markers in a frame where the joint is fixed.

:class:`OnlineCentre` and :class:`OnlineAxis` keep the per-marker sufficient
statistics of :mod:`jointfit_core.moments` over a sliding window
(:mod:`jointfit_core.stats`), updated in O(1) per frame; :meth:`estimate`
solves the Gamage-Lasenby system from them and returns exactly what
:func:`~jointfit_core.sphere.fit_centre` / :func:`~jointfit_core.axis.fit_axis`
return for the frames of the window.
"""

from __future__ import annotations

from typing import Any, Self

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .axis import axis_from_moments
from .calibration import fit_from_dict, fit_to_dict
from .checks import check_frame, check_noise_std, check_vector3
from .errors import InputError
from .moments import MarkerMoments, shift_sums
from .results import AxisFit, CentreFit
from .sphere import centre_from_moments
from .stats import SlidingSums, WindowSpec, window_spec

__all__ = ["OnlineCentre", "OnlineAxis", "moment_contributions"]

FloatArray = NDArray[np.float64]

#: Sums layout per marker count P: w (P), s1 (3P), s2 (9P), s3 (3P), s4 (P), frames (1).
_PARTS = (("w", 1), ("s1", 3), ("s2", 9), ("s3", 3), ("s4", 1))


def _n_sums(n_markers: int) -> int:
    return 17 * n_markers + 1


def moment_contributions(records: FloatArray, refs: FloatArray) -> FloatArray:
    """Per-frame moment contributions, the sums layout of the online estimators.

    Parameters
    ----------
    records : ndarray, shape (m, 3 P)
        Frames, flattened, NaN for missing markers.
    refs : ndarray, shape (m, 3)
        Reference point of each row.

    Returns
    -------
    ndarray, shape (m, 17 P + 1)
        ``[w (P), s1 (3P), s2 (9P), s3 (3P), s4 (P), frame count (1)]`` of each
        row, as in :class:`~jointfit_core.moments.MarkerMoments` for unit weights.
    """
    m = records.shape[0]
    y = records.reshape(m, -1, 3) - refs[:, None, :]
    p = y.shape[1]
    valid = np.asarray(~np.isnan(y).any(axis=2), dtype=bool)
    y = np.where(valid[..., None], y, 0.0)
    yy = np.einsum("mpi,mpi->mp", y, y)
    out = np.empty((m, _n_sums(p)))
    out[:, :p] = valid
    out[:, p : 4 * p] = y.reshape(m, -1)
    out[:, 4 * p : 13 * p] = (y[..., :, None] * y[..., None, :]).reshape(m, -1)
    out[:, 13 * p : 16 * p] = (yy[..., None] * y).reshape(m, -1)
    out[:, 16 * p : 17 * p] = yy * yy
    out[:, -1] = valid.any(axis=1)
    return out


def _unpack(sums: FloatArray, p: int) -> list[FloatArray]:
    out = []
    start = 0
    for _, k in _PARTS:
        block = sums[start : start + k * p]
        out.append(block.reshape((p, 3, 3) if k == 9 else (p, 3) if k == 3 else (p,)))
        start += k * p
    return out


def _shift(sums: FloatArray, old: FloatArray, new: FloatArray) -> FloatArray:
    p = (sums.size - 1) // 17
    w, s1, s2, s3, s4 = _unpack(sums, p)
    n1, n2, n3, n4 = shift_sums(w, s1, s2, s3, s4, new - old)
    return np.concatenate([w, n1.ravel(), n2.ravel(), n3.ravel(), n4, sums[-1:]])


def _mean_ref(sums: FloatArray, ref: FloatArray) -> FloatArray | None:
    p = (sums.size - 1) // 17
    w = sums[:p].sum()
    if w <= 0.0:
        return None
    out: FloatArray = ref + sums[p : 4 * p].reshape(p, 3).sum(axis=0) / w
    return out


def _first_ref(record: FloatArray) -> FloatArray:
    pts = record.reshape(-1, 3)
    ok = ~np.isnan(pts).any(axis=1)
    return pts[ok].mean(axis=0) if ok.any() else np.zeros(3)


class _OnlineMoments:
    """Shared machinery of :class:`OnlineCentre` and :class:`OnlineAxis`."""

    kind = ""

    def __init__(
        self,
        window: int | None,
        window_s: float | None,
        half_life: float | None,
        half_life_s: float | None,
        noise_std: float | None,
        n_markers: int | None,
    ) -> None:
        self.spec: WindowSpec = window_spec(window, window_s=window_s, half_life=half_life, half_life_s=half_life_s)
        self.noise_std = check_noise_std(noise_std)
        if n_markers is not None and (isinstance(n_markers, bool) or int(n_markers) < 1):
            raise InputError(f"n_markers: expected a positive integer, got {n_markers!r}")
        self.n_markers: int | None = None if n_markers is None else int(n_markers)
        self.dropped: dict[str, int] = {}
        self._sums: SlidingSums | None = None
        self._frozen: Any = None
        self._last_stamp: float | None = None

    # ------------------------------------------------------------------ streaming

    def _drop(self, reason: str) -> bool:
        self.dropped[reason] = self.dropped.get(reason, 0) + 1
        return False

    def update(self, frame: ArrayLike, stamp: float | None = None) -> bool:
        """Add one frame.

        Parameters
        ----------
        frame : array_like, shape (P, 3)
            Marker positions (input units), NaN for a missing marker. P is
            fixed by the first frame (or ``n_markers``).
        stamp : float, optional
            Time of the frame in seconds; required by ``window_s`` and
            ``half_life_s``. Stamps must increase.

        Returns
        -------
        bool
            True when the frame was added. A frame is dropped (and counted
            in :attr:`dropped` under its reason) when its stamp does not
            increase (``"stamp_not_increasing"``), when no marker is present
            (``"empty"``) and while the estimate is frozen (``"frozen"``).

        Raises
        ------
        InputError
            Wrong shape, wrong marker count, infinite values, or a missing
            stamp that the window needs.
        """
        arr = check_frame(frame, self.n_markers)
        st = None if stamp is None else float(stamp)
        if st is not None and not np.isfinite(st):
            raise InputError(f"stamp: expected a finite number of seconds, got {stamp!r}")
        if self._frozen is not None:
            return self._drop("frozen")
        if st is not None and self._last_stamp is not None and st <= self._last_stamp:
            return self._drop("stamp_not_increasing")
        if st is not None:
            self._last_stamp = st  # an empty frame still marks the time: a repeat of it is a duplicate
        if np.isnan(arr).all():
            return self._drop("empty")
        if self._sums is None:
            self.n_markers = arr.shape[0]
            self._sums = SlidingSums(
                self.spec,
                3 * self.n_markers,
                _n_sums(self.n_markers),
                moment_contributions,
                ref_of=_mean_ref,
                first_ref=_first_ref,
                shift=_shift,
                count_index=np.arange(self.n_markers),
            )
        self._sums.push(arr.ravel(), st)
        return True

    @property
    def n_window(self) -> int:
        """Frames in the window (frames added, under exponential forgetting)."""
        return 0 if self._sums is None else self._sums.n_window

    def moments(self) -> MarkerMoments:
        """The window's sufficient statistics.

        Raises
        ------
        InputError
            No frame has been added yet.
        """
        if self._sums is None:
            raise InputError("no frame has been added yet")
        p = int(self.n_markers or 0)
        w, s1, s2, s3, s4 = _unpack(self._sums.sums, p)
        w2 = self._sums.counts_sq if self.spec.exponential else w
        return MarkerMoments(
            ref=self._sums.ref.copy(),
            w=w.copy(),
            w2=np.asarray(w2, dtype=np.float64).copy(),
            s1=s1.copy(),
            s2=s2.copy(),
            s3=s3.copy(),
            s4=s4.copy(),
            n_frames=float(self._sums.sums[-1]),
        )

    def window_markers(self) -> FloatArray:
        """The frames in the window, oldest first, shape (n, P, 3) (frame and time windows only)."""
        if self._sums is None:
            return np.zeros((0, int(self.n_markers or 0), 3))
        return self._sums.window_records().reshape(-1, int(self.n_markers or 0), 3)

    def reset(self) -> None:
        """Forget every frame and any frozen estimate; drop counters restart."""
        self._sums = None
        self._frozen = None
        self._last_stamp = None
        self.dropped = {}

    # ------------------------------------------------------------------ calibration

    @property
    def frozen(self) -> bool:
        """Whether the estimate is frozen (updates are ignored)."""
        return self._frozen is not None

    def _solve(self) -> Any:
        raise NotImplementedError

    def estimate(self) -> Any:
        """The fit of the current window (or the frozen one)."""
        return self._frozen if self._frozen is not None else self._solve()

    def freeze(self) -> Any:
        """Fix the current estimate; later frames are dropped until :meth:`thaw`.

        Returns
        -------
        The frozen fit.

        Raises
        ------
        InputError, NotIdentifiableError
            When there is no estimate to freeze.
        """
        if self._frozen is None:
            self._frozen = self._solve()
        return self._frozen

    def thaw(self) -> None:
        """Resume estimation from the window (which still holds the frames seen before freezing)."""
        self._frozen = None

    def _settings(self) -> dict[str, Any]:
        spec = self.spec
        return {
            "kind": self.kind,
            "window": spec.frames,
            "window_s": spec.seconds,
            "half_life": spec.half_life,
            "half_life_s": spec.half_life_s,
            "noise_std": self.noise_std,
            "n_markers": self.n_markers,
        }

    #: The fit dataclass a calibration holds, and the constructor keywords saved by :meth:`_settings`.
    _fit_type: Any = None
    _keywords: tuple[str, ...] = ("window_s", "half_life", "half_life_s", "noise_std", "n_markers")

    def to_dict(self) -> dict[str, Any]:
        """The settings and the frozen (else current) fit as plain YAML-able types."""
        return {**self._settings(), "fit": fit_to_dict(self.estimate())}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Self:
        """A frozen estimator holding a saved fit (see :meth:`to_dict`).

        Raises
        ------
        InputError
            Another kind of calibration, or missing or malformed fields.
        """
        _check_kind(data, cls.kind)
        est = cls(data.get("window"), **{k: data.get(k) for k in cls._keywords})
        est._frozen = fit_from_dict(cls._fit_type, data["fit"])
        est._check_fit(est._frozen)
        return est

    def _check_fit(self, fit: Any) -> None:
        """Shape checks of a loaded fit beyond its fields (none by default)."""


def _check_kind(data: dict[str, Any], kind: str) -> None:
    if not isinstance(data, dict) or data.get("kind") != kind or not isinstance(data.get("fit"), dict):
        got = data.get("kind") if isinstance(data, dict) else type(data).__name__
        raise InputError(f"calibration: expected a dict with kind {kind!r} and a 'fit', got kind {got!r}")


class OnlineCentre(_OnlineMoments):
    """Centre of rotation over a sliding window of frames, O(1) per frame.

    Parameters
    ----------
    window : int, optional
        Window length in frames (>= 3).
    window_s : float, optional
        Window length in seconds of stamp time (``update(frame, stamp)``).
    half_life : float, optional
        Exponential forgetting: a frame's weight halves every ``half_life`` frames.
    half_life_s : float, optional
        Exponential forgetting in stamp time (seconds).
    noise_std : float, optional
        As in :func:`jointfit_core.sphere.fit_centre` (None: estimated).
    n_markers : int, optional
        Expected P (default: taken from the first frame).

    Exactly one of ``window``, ``window_s``, ``half_life``, ``half_life_s``.

    Notes
    -----
    :meth:`estimate` is :func:`jointfit_core.sphere.centre_from_moments` on
    the window's sums: for a frame or time window identical (to rounding) to
    :func:`~jointfit_core.sphere.fit_centre` on the window's frames
    (Gamage & Lasenby 2002, eq. 5, with bias compensation); under
    forgetting, the same with each frame weighted by its decay factor and
    the effective degrees of freedom ``w - w2 / w`` in place of ``n - 1``.
    Per frame, :meth:`update` costs O(P) whatever the window length.

    Examples
    --------
    >>> from jointfit_core.online import OnlineCentre
    >>> est = OnlineCentre(window=500)
    >>> # for frame in stream: est.update(frame); fit = est.estimate()
    """

    kind = "centre"
    _fit_type = CentreFit

    def __init__(
        self,
        window: int | None = None,
        *,
        window_s: float | None = None,
        half_life: float | None = None,
        half_life_s: float | None = None,
        noise_std: float | None = None,
        n_markers: int | None = None,
    ) -> None:
        super().__init__(window, window_s, half_life, half_life_s, noise_std, n_markers)

    def _solve(self) -> CentreFit:
        return centre_from_moments(self.moments(), noise_std=self.noise_std)

    def estimate(self) -> CentreFit:
        """The centre of the window (or the frozen one); see :func:`~jointfit_core.sphere.fit_centre`.

        Raises
        ------
        InputError, NotIdentifiableError
            As :func:`~jointfit_core.sphere.centre_from_moments` (too few
            frames, no motion, a singular system).
        """
        out: CentreFit = super().estimate()
        return out

    def _check_fit(self, fit: Any) -> None:
        if fit.centre.shape != (3,) or fit.cov.shape != (3, 3):
            raise InputError("calibration: expected centre of shape (3,) and cov of shape (3, 3)")


class OnlineAxis(_OnlineMoments):
    """Axis of rotation over a sliding window of frames, O(1) per frame.

    Parameters
    ----------
    window, window_s, half_life, half_life_s, noise_std, n_markers
        As in :class:`OnlineCentre`.
    reference_direction : array_like, shape (3,), optional
        Sign convention of the direction, as in
        :func:`jointfit_core.axis.fit_axis`; keeps the sign stable over time.

    Notes
    -----
    :meth:`estimate` is :func:`jointfit_core.axis.axis_from_moments` on the
    window's sums (Gamage & Lasenby 2002, eq. 6-10).
    """

    kind = "axis"
    _fit_type = AxisFit
    _keywords = (*_OnlineMoments._keywords, "reference_direction")

    def __init__(
        self,
        window: int | None = None,
        *,
        window_s: float | None = None,
        half_life: float | None = None,
        half_life_s: float | None = None,
        noise_std: float | None = None,
        n_markers: int | None = None,
        reference_direction: ArrayLike | None = None,
    ) -> None:
        super().__init__(window, window_s, half_life, half_life_s, noise_std, n_markers)
        self.reference_direction = (
            None
            if reference_direction is None
            else check_vector3(reference_direction, name="reference_direction", unit=True)
        )

    def _solve(self) -> AxisFit:
        return axis_from_moments(
            self.moments(), noise_std=self.noise_std, reference_direction=self.reference_direction
        )

    def estimate(self) -> AxisFit:
        """The axis of the window (or the frozen one); see :func:`~jointfit_core.axis.fit_axis`."""
        out: AxisFit = super().estimate()
        return out

    def _settings(self) -> dict[str, Any]:
        ref = None if self.reference_direction is None else self.reference_direction.tolist()
        return {**super()._settings(), "reference_direction": ref}
