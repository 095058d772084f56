"""Synthetic marker motions with known joints, for tests, benchmarks and demos.

Units are millimetres unless stated. Every generator takes a
``numpy.random.Generator`` so that runs are reproducible.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

__all__ = [
    "SyntheticCentre",
    "SyntheticAxis",
    "gl_axis_setup",
    "gl_random_walk_setup",
    "random_walk_rotations",
]

FloatArray = NDArray[np.float64]

#: Gamage & Lasenby section 4, axis simulation: femur markers (cm in the paper), mm here.
GL_AXIS_MARKERS = np.array([[0.0, 0.0, -50.0], [0.0, 0.0, -300.0], [0.0, -50.0, -150.0], [0.0, 50.0, -150.0]])
#: Gamage & Lasenby section 4, centre simulation: marker positions relative to the CoR, mm.
GL_CENTRE_MARKERS = np.array([[70.0, -10.0, 50.0], [50.0, -160.0, 120.0], [30.0, -260.0, -10.0], [20.0, -340.0, 50.0]])


@dataclass(frozen=True)
class SyntheticCentre:
    """Markers rotating about a fixed centre.

    Attributes
    ----------
    markers : ndarray, shape (N, P, 3)
        Noisy marker positions.
    clean : ndarray, shape (N, P, 3)
        The same without noise.
    centre : ndarray, shape (3,)
        True centre.
    """

    markers: FloatArray
    clean: FloatArray
    centre: FloatArray


@dataclass(frozen=True)
class SyntheticAxis:
    """Markers rotating about a fixed axis.

    Attributes
    ----------
    markers, clean : ndarray, shape (N, P, 3)
        Noisy and noise-free marker positions.
    point : ndarray, shape (3,)
        A point of the true axis.
    direction : ndarray, shape (3,)
        Unit direction of the true axis.
    """

    markers: FloatArray
    clean: FloatArray
    point: FloatArray
    direction: FloatArray


def random_walk_rotations(
    rng: np.random.Generator, n_frames: int, *, step_deg: float = 1.0, axis_step: float = 0.1
) -> Rotation:
    """Cumulative rotations whose axis wanders as a random walk.

    Each frame rotates by ``step_deg`` about the current axis; the axis gets
    a Gaussian increment of std ``axis_step`` per component and is
    renormalised (Gamage & Lasenby section 4). Frame 0 is the identity and
    the initial axis is z.

    Returns
    -------
    scipy.spatial.transform.Rotation
        ``n_frames`` rotations.
    """
    axis = np.array([0.0, 0.0, 1.0])
    quats = np.empty((n_frames, 4))
    current = Rotation.identity()
    quats[0] = current.as_quat()
    for k in range(1, n_frames):
        axis = axis + rng.normal(0.0, axis_step, 3)
        axis /= np.linalg.norm(axis)
        current = Rotation.from_rotvec(np.deg2rad(step_deg) * axis) * current
        quats[k] = current.as_quat()
    return Rotation.from_quat(quats)


def gl_random_walk_setup(
    rng: np.random.Generator,
    noise_std: float,
    *,
    n_frames: int = 100,
    step_deg: float = 1.0,
    centre: FloatArray | None = None,
) -> SyntheticCentre:
    """Gamage & Lasenby's centre-of-rotation simulation (section 4).

    Four markers at :data:`GL_CENTRE_MARKERS` about the centre rotate by
    ``step_deg`` per frame about an axis that starts along z and wanders
    (std 0.1 per component per frame). Isotropic Gaussian noise of
    ``noise_std`` (mm, per coordinate) is added.
    """
    c = np.zeros(3) if centre is None else np.asarray(centre, dtype=np.float64)
    rots = random_walk_rotations(rng, n_frames, step_deg=step_deg)
    clean = np.einsum("nij,pj->npi", rots.as_matrix(), GL_CENTRE_MARKERS) + c
    noisy = clean + rng.normal(0.0, noise_std, clean.shape)
    return SyntheticCentre(markers=noisy, clean=clean, centre=c)


def gl_axis_setup(
    rng: np.random.Generator, noise_std: float, *, n_frames: int = 60, step_deg: float = 1.0
) -> SyntheticAxis:
    """Gamage & Lasenby's axis-of-rotation simulation (section 4).

    Femur markers :data:`GL_AXIS_MARKERS` rotate ``step_deg`` per frame for
    ``n_frames`` frames about an axis parallel to y through (0, 0, 50) mm.
    """
    point = np.array([0.0, 0.0, 50.0])
    direction = np.array([0.0, 1.0, 0.0])
    angles = np.deg2rad(step_deg) * np.arange(n_frames)
    rots = Rotation.from_rotvec(angles[:, None] * direction[None, :]).as_matrix()
    clean = np.einsum("nij,pj->npi", rots, GL_AXIS_MARKERS - point) + point
    noisy = clean + rng.normal(0.0, noise_std, clean.shape)
    return SyntheticAxis(markers=noisy, clean=clean, point=point, direction=direction)
