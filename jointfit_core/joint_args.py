"""The arguments of :class:`~jointfit_core.estimator.OnlineJoint`, checked; and the virtual markers of a pose stream.

:func:`check_settings` is the constructor's checking: it makes the ``check_*``
checks, one argument (or one pair of arguments) each, in turn, and returns
:class:`JointSettings`, the values as the joint keeps them, from which each
layer of the joint takes its own; a check raises
:class:`~jointfit_core.errors.InputError` saying what was expected and what
came. :func:`virtual_markers_template` turns a rigid-body pose stream's noise
into the fixed template and marker noise that the joint takes instead of
markers (its ``templates`` and ``noise_std`` arguments).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .artefact import check_attachment
from .checks import check_vector3
from .errors import InputError
from .pose import MIN_POSE_MARKERS
from .segment_tracker import shape_ok
from .stats import WindowSpec, window_spec
from .window_entries import check_window_max_frames

__all__ = [
    "KINDS",
    "JointSettings",
    "check_settings",
    "check_gate",
    "check_kind",
    "check_n_markers",
    "check_noise",
    "check_serial_correlation",
    "check_template_frames",
    "check_templates",
    "virtual_markers_template",
]

FloatArray = NDArray[np.float64]

#: The joint kinds: a ball joint (a centre) or a hinge (an axis).
KINDS = ("ball", "hinge")


@dataclass(frozen=True)
class JointSettings:
    """:class:`~jointfit_core.estimator.OnlineJoint`'s arguments, checked (their meaning there).

    Attributes
    ----------
    kind : {"ball", "hinge"}
    spec : WindowSpec
        The window (one of ``window``, ``window_s``, ``half_life``, ``half_life_s``).
    template_frames : int
        Fully visible frames per built template (>= 1).
    reference_direction : ndarray, shape (3,), or None
        Hinge sign convention, a unit vector in the parent local frame.
    templates : (ndarray or None, ndarray or None)
        Fixed templates, parent (Pa, 3) and child (Pc, 3), local frames, input units (None: to build).
    n_markers : (int, int) or None
        Marker counts of the parent and the child (None: from the first frame).
    noise_std : (float or None, float or None)
        Fixed marker noise of the parent and the child, input units (None: estimated).
    serial_correlation : bool
        Widen the covariances by the joint residual's serial correlation.
    gate : float
        Outlier gate (>= 0; 0: off).
    attachment : (str, str)
        ``"skin"`` or ``"rigid"``, the parent's and the child's markers.
    window_max_frames : int or None
        Most frames a time window holds (None: no bound; :mod:`jointfit_core.window_entries`).
    """

    kind: str
    spec: WindowSpec
    template_frames: int
    reference_direction: FloatArray | None
    templates: tuple[FloatArray | None, FloatArray | None]
    n_markers: tuple[int, int] | None
    noise_std: tuple[float | None, float | None]
    serial_correlation: bool
    gate: float
    attachment: tuple[str, str]
    window_max_frames: int | None = None


def check_settings(
    kind: str,
    window: int | None,
    *,
    window_s: float | None,
    half_life: float | None,
    half_life_s: float | None,
    template_frames: int,
    reference_direction: ArrayLike | None,
    n_markers: tuple[int, int] | None,
    templates: tuple[ArrayLike | None, ArrayLike | None] | None,
    noise_std: tuple[float | None, float | None] | None,
    serial_correlation: bool,
    gate: float,
    attachment: str | tuple[str, str],
    window_max_frames: int | None = None,
) -> JointSettings:
    """:class:`~jointfit_core.estimator.OnlineJoint`'s arguments (the same names) checked, in this order.

    Raises
    ------
    InputError
        The first argument that is not as the joint takes it.
    """
    kind = check_kind(kind)
    spec = window_spec(window, window_s=window_s, half_life=half_life, half_life_s=half_life_s)
    frames = check_template_frames(template_frames)
    direction = (
        None if reference_direction is None else check_vector3(reference_direction, name="reference_direction", unit=True)
    )
    fixed, counts = check_templates(templates, check_n_markers(n_markers))
    return JointSettings(
        kind=kind,
        spec=spec,
        template_frames=frames,
        reference_direction=direction,
        templates=fixed,
        n_markers=counts,
        noise_std=check_noise(noise_std),
        serial_correlation=check_serial_correlation(serial_correlation),
        gate=check_gate(gate),
        attachment=check_attachment(attachment),
        window_max_frames=check_window_max_frames(window_max_frames),
    )


def virtual_markers_template(translation_sd: float, rotation_sd: float) -> tuple[FloatArray, float]:
    """Virtual markers that stand for a rigid-body pose with the given noise.

    A pose stream (e.g. ``geometry_msgs/PoseStamped`` from a mocap rigid
    body) is turned into four virtual markers ``R x_i + d`` at the vertices
    of a regular tetrahedron ``x_i``. Fitting them with marker noise
    ``sigma`` per coordinate gives a pose whose translation has standard
    deviation ``sigma / 2`` per axis and whose rotation has ``sigma / (L
    sqrt(8/3))`` radians per axis (``L`` the vertex radius); choosing
    ``sigma = 2 translation_sd`` and ``L = sigma / (rotation_sd sqrt(8/3))``
    reproduces the pose noise the user states.

    Parameters
    ----------
    translation_sd : float
        Standard deviation of the pose's position per axis (input units).
    rotation_sd : float
        Standard deviation of its orientation per axis (radians).

    Returns
    -------
    template : ndarray, shape (4, 3)
        Vertex coordinates in the body frame (centroid at the origin).
    noise_std : float
        The marker noise ``sigma`` to give :class:`OnlineJoint`.
    """
    if not (np.isfinite(translation_sd) and translation_sd > 0 and np.isfinite(rotation_sd) and rotation_sd > 0):
        raise InputError(
            f"pose noise: expected positive translation and rotation sd, got {translation_sd!r}, {rotation_sd!r}"
        )
    sigma = 2.0 * float(translation_sd)
    radius = sigma / (float(rotation_sd) * np.sqrt(8.0 / 3.0))
    tetra = np.array([[1.0, 1.0, 1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]]) / np.sqrt(3.0)
    return radius * tetra, sigma


def check_kind(kind: str) -> str:
    """:class:`OnlineJoint`'s ``kind`` checked: one of :data:`KINDS`."""
    if kind not in KINDS:
        raise InputError(f"kind: expected one of {KINDS}, got {kind!r}")
    return kind


def check_template_frames(template_frames: int) -> int:
    """:class:`OnlineJoint`'s ``template_frames`` checked: a positive integer (not a bool)."""
    if isinstance(template_frames, bool) or int(template_frames) < 1:
        raise InputError(f"template_frames: expected a positive integer, got {template_frames!r}")
    return int(template_frames)


def check_serial_correlation(serial_correlation: bool) -> bool:
    """:class:`OnlineJoint`'s ``serial_correlation`` checked: True or False (numpy's too)."""
    if not isinstance(serial_correlation, (bool, np.bool_)):
        raise InputError(f"serial_correlation: expected True or False, got {serial_correlation!r}")
    return bool(serial_correlation)


def check_gate(gate: float) -> float:
    """:class:`OnlineJoint`'s outlier ``gate`` checked: a finite number >= 0 (0: off; not a bool)."""
    if isinstance(gate, bool) or not isinstance(gate, (int, float, np.floating)) or not (
        np.isfinite(gate) and gate >= 0.0
    ):
        raise InputError(f"gate: expected a number >= 0 (0: off), got {gate!r}")
    return float(gate)


def check_n_markers(n_markers: tuple[int, int] | None) -> tuple[int, int] | None:
    """:class:`OnlineJoint`'s ``n_markers`` checked: two counts of at least :data:`~jointfit_core.pose.MIN_POSE_MARKERS`, or None."""
    if n_markers is None:
        return None
    if len(n_markers) != 2 or min(int(n_markers[0]), int(n_markers[1])) < MIN_POSE_MARKERS:
        raise InputError(f"n_markers: expected two counts >= {MIN_POSE_MARKERS}, got {n_markers!r}")
    return (int(n_markers[0]), int(n_markers[1]))


def check_templates(
    templates: tuple[ArrayLike | None, ArrayLike | None] | None, n_markers: tuple[int, int] | None
) -> tuple[tuple[FloatArray | None, FloatArray | None], tuple[int, int] | None]:
    """:class:`OnlineJoint`'s fixed ``templates`` checked against ``n_markers`` (checked).

    Returns
    -------
    templates : (ndarray or None, ndarray or None)
        Parent (Pa, 3) and child (Pc, 3) float64 copies, input units (None: to build).
    n_markers : (int, int) or None
        ``n_markers``, or the fixed templates' counts when it is None.

    Raises
    ------
    InputError
        Not a pair, a template not (P >= 3, 3), non-finite or collinear, or
        its count not that of ``n_markers``; one template fixed without ``n_markers``.
    """
    fixed: list[FloatArray | None] = [None, None]
    if templates is not None:
        if len(templates) != 2:
            raise InputError("templates: expected a pair (parent, child); None for a template to build")
        for k, x in enumerate(templates):
            if x is None:
                continue
            arr = np.array(x, dtype=np.float64)
            if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] < MIN_POSE_MARKERS:
                raise InputError(f"templates: expected arrays of shape (P, 3) with P >= {MIN_POSE_MARKERS}")
            if not (np.isfinite(arr).all() and shape_ok(arr)):
                raise InputError("templates: expected finite, non-collinear template points")
            if n_markers is not None and n_markers[k] != arr.shape[0]:
                raise InputError(f"templates: {arr.shape[0]} points differ from n_markers {n_markers}")
            fixed[k] = arr
        if any(x is not None for x in fixed) and n_markers is None:
            if fixed[0] is None or fixed[1] is None:
                raise InputError("templates: with one template fixed, give n_markers for both segments")
            n_markers = (fixed[0].shape[0], fixed[1].shape[0])
    return (fixed[0], fixed[1]), n_markers


def check_noise(noise_std: tuple[float | None, float | None] | None) -> tuple[float | None, float | None]:
    """:class:`OnlineJoint`'s fixed ``noise_std`` checked: two finite numbers > 0 or None (input units)."""
    noise: list[float | None] = [None, None]
    if noise_std is not None:
        try:
            for k in range(2):
                if noise_std[k] is not None:
                    noise[k] = float(noise_std[k])  # type: ignore[arg-type]
        except (TypeError, ValueError, IndexError):
            raise InputError(f"noise_std: expected two numbers > 0 (or None), got {noise_std!r}") from None
        if any(v is not None and not (np.isfinite(v) and v > 0) for v in noise):
            raise InputError(f"noise_std: expected finite numbers > 0 (or None), got {noise_std!r}")
    return (noise[0], noise[1])
