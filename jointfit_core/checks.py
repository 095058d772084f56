"""Input checks shared by the estimators.

Each helper converts to float64, checks the shape, then the numbers, and raises
:class:`~jointfit_core.errors.InputError` with a message that says what was
expected and what came.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import InputError

__all__ = [
    "as_real_array",
    "check_markers",
    "check_frame",
    "check_noise_std",
    "check_vector3",
    "small_all_finite",
    "valid_mask",
]


def as_real_array(value: ArrayLike, *, name: str, expected: str, copy: bool = False) -> NDArray[np.float64]:
    """Convert ``value`` to a float64 array, rejecting what is not real numbers.

    Parameters
    ----------
    value : array_like
        Anything :func:`numpy.asarray` converts to real numbers (numeric
        strings included).
    name : str
        Name used in error messages.
    expected : str
        What was expected, for the error message (e.g. ``"shape (N, P, 3)"``).
    copy : bool
        Always return a new array (default: only when the dtype changes).

    Returns
    -------
    ndarray, float64

    Raises
    ------
    InputError
        ``value`` is not numeric (ragged, strings, objects) or is complex: a
        cast would drop the imaginary part (numpy's ``ComplexWarning``), so
        complex input is refused even when the imaginary part is zero.
    """
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise InputError(
            f"{name}: expected a numeric array of {expected}, got {type(value).__name__}: {exc}"
        ) from None
    if arr.dtype.kind == "c":
        raise InputError(f"{name}: expected real numbers ({expected}), got complex values ({arr.dtype})")
    try:
        with np.errstate(invalid="ignore"):  # a float32 signalling NaN becomes a (quiet) NaN: missing
            return arr.astype(np.float64, copy=copy)
    except (TypeError, ValueError) as exc:
        raise InputError(
            f"{name}: expected a numeric array of {expected}, got {type(value).__name__}: {exc}"
        ) from None


def check_markers(
    markers: ArrayLike, *, name: str = "markers", min_markers: int = 1, min_frames: int = 1
) -> NDArray[np.float64]:
    """Return ``markers`` as a float64 array of shape (N, P, 3), NaN for missing.

    Parameters
    ----------
    markers : array_like, shape (N, P, 3)
        Marker positions, time first, then marker, then xyz. NaN (in any
        coordinate) marks a missing marker in that frame; the whole xyz triple
        is then treated as missing. ``inf`` is rejected.
    name : str
        Name used in error messages.
    min_markers, min_frames : int
        The least number of markers (P) and of frames (N) accepted.

    Returns
    -------
    ndarray, shape (N, P, 3), float64
        A copy in which a marker with any NaN coordinate has all three NaN.

    Raises
    ------
    InputError
        Not real numbers (complex included), wrong number of dimensions,
        last axis not 3, too few markers or frames, infinite values, or no
        valid sample at all.
    """
    arr = as_real_array(markers, name=name, expected="shape (N, P, 3)", copy=True)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise InputError(f"{name}: expected shape (N, P, 3) (frames, markers, xyz), got shape {arr.shape}")
    n_frames, n_markers, _ = arr.shape
    if n_markers < min_markers:
        raise InputError(f"{name}: expected at least {min_markers} marker(s) (axis 1), got {n_markers}")
    if n_frames < min_frames:
        raise InputError(f"{name}: expected at least {min_frames} frame(s) (axis 0), got {n_frames}")
    if np.isinf(arr).any():
        raise InputError(f"{name}: contains inf; use NaN for missing markers")
    missing = np.isnan(arr).any(axis=2)
    arr[missing] = np.nan
    if missing.all():
        raise InputError(f"{name}: every sample is NaN (no valid marker in any frame)")
    return arr


def check_frame(frame: ArrayLike, n_markers: int | None = None, *, name: str = "frame") -> NDArray[np.float64]:
    """Return one frame as float64 of shape (P, 3), NaN for missing.

    A float64 array input is returned as is (not copied) unless a partly
    NaN marker has to be made all-NaN; callers that keep the frame copy it.

    Parameters
    ----------
    frame : array_like, shape (P, 3)
        Marker positions of one frame; NaN marks a missing marker.
    n_markers : int, optional
        Expected P; checked when given.

    Raises
    ------
    InputError
        Not real numbers (complex included), wrong shape, wrong marker
        count or infinite values.
    """
    arr = as_real_array(frame, name=name, expected="shape (P, 3)")
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name}: expected shape (P, 3), got shape {arr.shape}")
    if n_markers is not None and arr.shape[0] != n_markers:
        raise InputError(f"{name}: expected {n_markers} markers, got {arr.shape[0]}")
    finite = np.isfinite(arr)
    if not finite.all():
        if np.isinf(arr).any():
            raise InputError(f"{name}: contains inf; use NaN for missing markers")
        arr = arr.copy()
        arr[~finite.all(axis=1)] = np.nan
    return arr


def check_noise_std(noise_std: float | None) -> float | None:
    """Return ``noise_std`` as a float (or None) after checking it is real, finite and >= 0."""
    if noise_std is None:
        return None
    dtype = getattr(noise_std, "dtype", None)
    if isinstance(noise_std, complex) or (isinstance(dtype, np.dtype) and dtype.kind == "c"):
        raise InputError(f"noise_std: expected None or a real number >= 0, got {noise_std!r}")
    try:
        value = float(noise_std)
    except (TypeError, ValueError):
        raise InputError(f"noise_std: expected None or a number >= 0, got {noise_std!r}") from None
    if not np.isfinite(value) or value < 0.0:
        raise InputError(f"noise_std: expected None or a finite number >= 0, got {value!r}")
    return value


def check_vector3(vector: ArrayLike, *, name: str, unit: bool = False) -> NDArray[np.float64]:
    """Return a finite, real float64 3-vector (normalised when ``unit``); InputError otherwise."""
    arr = as_real_array(vector, name=name, expected="a 3-vector", copy=True).reshape(-1)
    if arr.shape != (3,) or not np.isfinite(arr).all():
        raise InputError(f"{name}: expected a finite 3-vector, got {vector!r}")
    if unit:
        norm = float(np.linalg.norm(arr))
        if norm == 0.0:
            raise InputError(f"{name}: expected a non-zero direction, got {vector!r}")
        arr = arr / norm
    return arr


def valid_mask(markers: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Return the (N, P) mask of markers present (not NaN) in each frame."""
    return np.asarray(~np.isnan(markers).any(axis=-1), dtype=bool)


def small_all_finite(values: NDArray[np.float64]) -> bool:
    """Whether every entry of a small float array (a 3-vector, a 3 x 3 covariance) is finite.

    The per-frame output path's test: the sum of the entries as Python floats is finite only
    when every entry is (a NaN or an infinity makes it NaN or infinite); a sum that overflows
    from finite entries takes the exact test. The same verdict as ``np.isfinite(values).all()``,
    with fewer numpy calls on a few entries.
    """
    return math.isfinite(sum(values.ravel().tolist())) or bool(np.isfinite(values).all())
