"""Frozen result types returned by the jointfit estimators.

Every result carries, besides its estimate and covariance:

``rms``
    the rms residual of the fitted model, in the input units;
``n_frames``
    the number of frames that contributed;
``identifiable`` and ``reason``
    whether the data determine the estimate well enough to trust it, and if
    not, why and what movement is missing (empty string when fine).

Arrays are read-only views so that a result cannot be changed by accident.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from numpy.typing import NDArray

__all__ = ["CentreFit", "AxisFit", "SegmentsCentreFit", "SegmentsAxisFit"]

FloatArray = NDArray[np.float64]


class _Frozen:
    """Mixin: make every ndarray field read-only after construction."""

    def __post_init__(self) -> None:
        for f in fields(self):  # type: ignore[arg-type]
            value = getattr(self, f.name)
            if isinstance(value, np.ndarray):
                value = np.array(value, dtype=value.dtype, copy=True)
                value.setflags(write=False)
                object.__setattr__(self, f.name, value)


@dataclass(frozen=True, eq=False)
class CentreFit(_Frozen):
    """Centre of rotation of markers moving on concentric spheres.

    Attributes
    ----------
    centre : ndarray, shape (3,)
        Estimated centre, input units, in the frame of the input markers.
    cov : ndarray, shape (3, 3)
        Covariance of ``centre`` (input units squared).
    radii : ndarray, shape (P,)
        Sphere radius of each marker about ``centre`` (NaN for a marker with
        too few valid frames).
    rms : float
        Rms of the radial residuals |v - centre| - radius over all valid samples.
    n_frames : int
        Number of frames with at least one valid marker.
    identifiable : bool
        False when the motion does not determine the centre well.
    reason : str
        Why not, and which movement is missing; empty when identifiable.
    noise_std : float
        Marker noise standard deviation (per coordinate) used for the bias
        compensation and the covariance: estimated from the residuals unless
        given.
    bias_compensated : bool
        Whether the noise terms of A and b were removed.
    """

    centre: FloatArray
    cov: FloatArray
    radii: FloatArray
    rms: float
    n_frames: int
    identifiable: bool
    reason: str
    noise_std: float
    bias_compensated: bool


@dataclass(frozen=True, eq=False)
class AxisFit(_Frozen):
    """Axis of rotation of markers moving on coaxial circles.

    Attributes
    ----------
    point : ndarray, shape (3,)
        The point of the axis nearest the centroid of the marker means.
    direction : ndarray, shape (3,)
        Unit direction of the axis; its sign is fixed by the caller's
        reference direction (see :func:`jointfit_core.fit_axis`).
    cov_point : ndarray, shape (3, 3)
        Covariance of ``point`` (input units squared), including the
        along-axis shift caused by the direction's uncertainty.
    cov_direction : ndarray, shape (3, 3)
        Covariance of ``direction`` (rank 2, orthogonal to it; radians squared
        for small angles).
    circle_centres : ndarray, shape (P, 3)
        Centre of the circle traced by each marker (on the axis).
    radii : ndarray, shape (P,)
        Rms distance of each marker from the axis.
    rms : float
        Rms distance of the samples from their marker's plane (the residual
        of the Gamage-Lasenby axis cost), input units.
    n_frames, identifiable, reason, noise_std, bias_compensated
        As in :class:`CentreFit`.
    """

    point: FloatArray
    direction: FloatArray
    cov_point: FloatArray
    cov_direction: FloatArray
    circle_centres: FloatArray
    radii: FloatArray
    rms: float
    n_frames: int
    identifiable: bool
    reason: str
    noise_std: float
    bias_compensated: bool


@dataclass(frozen=True, eq=False)
class SegmentsCentreFit(_Frozen):
    """Ball joint between two moving segments.

    Attributes
    ----------
    centre_parent, centre_child : ndarray, shape (3,)
        Joint centre in each segment's local frame (the frame of its template).
    cov_parent, cov_child : ndarray, shape (3, 3)
        Their covariances (input units squared).
    template_parent : ndarray, shape (Pa, 3)
    template_child : ndarray, shape (Pc, 3)
        Body-fixed marker coordinates that define the local frames.
    centre_world : ndarray, shape (N, 3)
        Joint centre in world coordinates per frame, carried by the parent
        pose; NaN where the parent could not be posed.
    cov_world : ndarray, shape (N, 3, 3)
        Its covariance per frame (estimate uncertainty plus the parent pose
        uncertainty of that frame).
    residual : ndarray, shape (N,)
        Distance between the centre carried by the parent and by the child,
        per frame; NaN where either could not be posed.
    rms : float
        Rms of ``residual`` over the frames used.
    n_frames, identifiable, reason
        As in :class:`CentreFit`.
    noise_std_parent, noise_std_child : float
        Marker noise std of each segment estimated from its pose-fit residuals.
    method : str
        ``"poses"`` (Stoddart) or ``"sphere"`` (child markers in the parent
        frame, Gamage-Lasenby).
    cov_parent_statistical, cov_child_statistical : ndarray, shape (3, 3), or None
        Skin markers: the part of ``cov_parent`` / ``cov_child`` from white
        noise and the residuals (it shrinks with more data); the rest is the
        soft-tissue prior's (:mod:`jointfit_core.artefact`). None for rigid
        markers, where the whole covariance is statistical.
    attachment : (str, str)
        ``"skin"`` or ``"rigid"`` for the parent and the child markers.
    artefact_scale : (float, float)
        Estimated rms cluster shift on the bone per radian of joint rotation,
        parent and child (input units; 0 for rigid markers or none seen).
    """

    centre_parent: FloatArray
    centre_child: FloatArray
    cov_parent: FloatArray
    cov_child: FloatArray
    template_parent: FloatArray
    template_child: FloatArray
    centre_world: FloatArray
    cov_world: FloatArray
    residual: FloatArray
    rms: float
    n_frames: int
    identifiable: bool
    reason: str
    noise_std_parent: float
    noise_std_child: float
    method: str
    cov_parent_statistical: FloatArray | None = None
    cov_child_statistical: FloatArray | None = None
    attachment: tuple[str, str] = ("rigid", "rigid")
    artefact_scale: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True, eq=False)
class SegmentsAxisFit(_Frozen):
    """Hinge axis between two moving segments.

    Attributes
    ----------
    direction_parent, direction_child : ndarray, shape (3,)
        Unit axis direction in each segment's local frame; the sign is fixed
        by ``reference_direction`` (see :func:`fit_axis_two_segments`).
    point_parent, point_child : ndarray, shape (3,)
        The point of the axis nearest each template's centroid, local frame.
    cov_direction_parent, cov_direction_child : ndarray, shape (3, 3)
        Direction covariances (rank 2, radians squared for small angles).
    cov_point_parent, cov_point_child : ndarray, shape (3, 3)
        Point covariances (input units squared).
    template_parent, template_child : ndarray, shape (Pa, 3), (Pc, 3)
        Body-fixed marker coordinates that define the local frames.
    direction_world, point_world : ndarray, shape (N, 3)
        The axis in world coordinates per frame, carried by the parent pose;
        NaN where the parent could not be posed.
    residual : ndarray, shape (N,)
        Per-frame distance between the axis point carried by the parent and
        the child's axis line; NaN where either could not be posed.
    rms, n_frames, identifiable, reason, noise_std_parent, noise_std_child
        As in :class:`SegmentsCentreFit`.
    cov_direction_parent_statistical, cov_point_parent_statistical : ndarray, shape (3, 3), or None
        Skin markers: the statistical part of ``cov_direction_parent`` /
        ``cov_point_parent`` (as in :class:`SegmentsCentreFit`); None for rigid markers.
    attachment, artefact_scale
        As in :class:`SegmentsCentreFit`.
    """

    direction_parent: FloatArray
    point_parent: FloatArray
    direction_child: FloatArray
    point_child: FloatArray
    cov_direction_parent: FloatArray
    cov_point_parent: FloatArray
    cov_direction_child: FloatArray
    cov_point_child: FloatArray
    template_parent: FloatArray
    template_child: FloatArray
    direction_world: FloatArray
    point_world: FloatArray
    residual: FloatArray
    rms: float
    n_frames: int
    identifiable: bool
    reason: str
    noise_std_parent: float
    noise_std_child: float
    cov_direction_parent_statistical: FloatArray | None = None
    cov_point_parent_statistical: FloatArray | None = None
    attachment: tuple[str, str] = ("rigid", "rigid")
    artefact_scale: tuple[float, float] = (0.0, 0.0)


__all__ += ["MinimalCentreFit", "MinimalAxisFit"]


@dataclass(frozen=True, eq=False)
class MinimalCentreFit(_Frozen):
    """Ball joint from a minimal marker set (Pham et al.: S22, S31).

    No link needs a full frame, so the estimate is a set of constant
    distances plus the per-frame centre in the world.

    Attributes
    ----------
    distances : ndarray, shape (p + q,)
        Constant distance of the centre from each marker, parent markers
        first, then child markers (input units).
    cov : ndarray, shape (p + q, p + q)
        Covariance of ``distances`` (input units squared).
    centre_parent : ndarray, shape (2,)
        The centre in the parent *pair frame*: ``(axial, radial)``, the
        coordinate along the line from parent marker 0 towards parent marker
        1 (origin at marker 0) and the distance from that line -- the
        paper's ``(d, r)``. NaN when the parent has a single marker.
    cov_parent : ndarray, shape (2, 2)
        Its covariance.
    centre_child, cov_child : ndarray, shape (2,) and (2, 2)
        The same for the child's markers 0 and 1.
    centre_world : ndarray, shape (N, 3)
        The centre per frame, world frame of the input markers; NaN in frames
        that were not used (a marker missing).
    cov_world : ndarray, shape (N, 3, 3)
        Its covariance per frame (that frame's marker noise plus the
        constants' uncertainty).
    residual : ndarray, shape (N,)
        Per frame, the norm of the distance residuals ``|J_t - X_k| - a_k``
        at the fitted centre (input units); NaN where not used.
    rms : float
        Rms of ``residual`` over the frames used.
    n_frames : int
        Number of frames used.
    identifiable : bool
        False when the data do not determine the centre well.
    reason : str
        Why not and what to do; empty when identifiable.
    noise_std : float
        Marker noise standard deviation per coordinate used for the
        covariance (input units): the larger of the residual estimate and the
        estimate from the spread of the intra-link marker distances.
    method : str
        ``"S22"`` (2 + 2 markers) or ``"S31"`` (a link with 3 or more).
    """

    distances: FloatArray
    cov: FloatArray
    centre_parent: FloatArray
    cov_parent: FloatArray
    centre_child: FloatArray
    cov_child: FloatArray
    centre_world: FloatArray
    cov_world: FloatArray
    residual: FloatArray
    rms: float
    n_frames: int
    identifiable: bool
    reason: str
    noise_std: float
    method: str


@dataclass(frozen=True, eq=False)
class MinimalAxisFit(_Frozen):
    """Hinge from a minimal marker set (Pham et al.: R21).

    Attributes
    ----------
    radii : ndarray, shape (p + q,)
        Constant distance of each marker from the axis, parent markers first
        (input units).
    offsets : ndarray, shape (p + q - 1,)
        Constant axial position of markers 1, 2, ... relative to marker 0
        (parent marker 0), along ``direction_world`` (input units).
    cov : ndarray, shape (2 (p + q) - 1, 2 (p + q) - 1)
        Covariance of ``concatenate([radii, offsets])``.
    dh : ndarray, shape (5,)
        The paper's Denavit-Hartenberg constants ``(d, r, alpha, l, rho)``
        relative to the link with two markers (the *pair*; its marker 0 is
        the origin and the axial direction points to its marker 1) and the
        first marker of the other link: the common perpendicular from the
        pair line to the hinge starts at axial coordinate ``d`` and has
        length ``r``; ``alpha`` (rad) is the twist from the pair line to the
        hinge about that perpendicular (its sign is the handedness that the
        mirror-image solution flips); ``l`` is the axial position on the
        hinge of the centre of the single marker's circle, ``rho`` its
        radius. Lengths in input units.
    cov_dh : ndarray, shape (5, 5)
        Its covariance.
    point_world : ndarray, shape (N, 3)
        Per frame, the centre of the circle traced by the single marker (the
        point of the axis nearest it), world frame; NaN where not used.
    direction_world : ndarray, shape (N, 3)
        Per frame, the unit axis direction (world); the sign is consistent
        across frames (``offsets`` are measured along it).
    cov_point_world : ndarray, shape (N, 3, 3)
        Covariance of ``point_world`` per frame.
    cov_direction_world : ndarray, shape (N, 3, 3)
        Covariance of ``direction_world`` per frame (rank 2, radians squared
        for small angles).
    residual : ndarray, shape (N,)
        Per frame, the norm of the whitened constant-model residuals at the
        fitted axis (input units); NaN where not used.
    rms, n_frames, identifiable, reason, noise_std
        As in :class:`MinimalCentreFit`.
    n_solutions : int
        Number of geometrically distinct hinges that fit the data equally
        well (1 when unique; 4 is typical for 2 + 1 markers, see
        :func:`jointfit_core.fit_axis_minimal`).
    method : str
        ``"R21"``.
    """

    radii: FloatArray
    offsets: FloatArray
    cov: FloatArray
    dh: FloatArray
    cov_dh: FloatArray
    point_world: FloatArray
    direction_world: FloatArray
    cov_point_world: FloatArray
    cov_direction_world: FloatArray
    residual: FloatArray
    rms: float
    n_frames: int
    identifiable: bool
    reason: str
    noise_std: float
    n_solutions: int
    method: str
