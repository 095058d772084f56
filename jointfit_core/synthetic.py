"""Synthetic marker motions with known joints, for tests, benchmarks and demos.

Units are millimetres unless stated. Every generator takes a
``numpy.random.Generator`` so that runs are reproducible.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

__all__ = [
    "SyntheticCentre",
    "SyntheticAxis",
    "gl_axis_setup",
    "gl_random_walk_setup",
    "random_walk_rotations",
    "TwoSegmentMotion",
    "two_segment_motion",
    "random_cluster",
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


@dataclass(frozen=True)
class TwoSegmentMotion:
    """Two rigid marker clusters joined by a ball joint or a hinge, as a function of time.

    A Stoddart-like rig: the parent wanders (rotations of ~15 deg and
    translations of ~100 mm) while the child rotates relative to it about
    the joint (three axes for a ball, one for a hinge). The motion is a sum
    of sinusoids, so it can be evaluated at any time (streams, demos) and
    never ends.

    Attributes
    ----------
    template_parent, template_child : ndarray, shape (Pa, 3) and (Pc, 3)
        Marker coordinates in each segment's true local frame (mm).
    centre_parent, centre_child : ndarray, shape (3,)
        The joint centre (a point of the hinge axis) in the local frames (mm).
    axis : ndarray, shape (3,)
        Hinge direction in both local frames (unit; used when ``kind`` is "hinge").
    kind : str
        "ball", "hinge" or "none" (no relative rotation).
    phase, freq : ndarray, shape (9,)
        Phases (rad) and frequencies (Hz) of the sinusoids.
    offset : ndarray, shape (3,)
        Mean position of the parent origin in the world (mm).
    """

    template_parent: FloatArray
    template_child: FloatArray
    centre_parent: FloatArray
    centre_child: FloatArray
    axis: FloatArray
    kind: str
    phase: FloatArray
    freq: FloatArray
    offset: FloatArray

    def poses_at(self, times: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """True world poses ``(R_parent, d_parent, R_child, d_child)`` at ``times`` (s), shapes (N, 3, 3), (N, 3)."""
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        wave = np.sin(2.0 * np.pi * self.freq * t[:, None] + self.phase)
        R_p = Rotation.from_rotvec(np.deg2rad(15.0) * wave[:, :3]).as_matrix()
        d_p = 100.0 * wave[:, 3:6] + self.offset
        if self.kind == "ball":
            rotvec = np.deg2rad(np.array([40.0, 30.0, 20.0])) * wave[:, 6:9]
        elif self.kind == "hinge":
            rotvec = np.deg2rad(30.0 + 50.0 * wave[:, 6:7]) * self.axis
        else:
            rotvec = np.zeros((t.size, 3))
        R_c = R_p @ Rotation.from_rotvec(rotvec).as_matrix()
        joint = np.einsum("nij,j->ni", R_p, self.centre_parent) + d_p
        d_c = joint - np.einsum("nij,j->ni", R_c, self.centre_child)
        return R_p, d_p, R_c, d_c

    def markers_at(self, times: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Noise-free world markers ``(parent (N, Pa, 3), child (N, Pc, 3))`` at ``times`` (s)."""
        R_p, d_p, R_c, d_c = self.poses_at(times)
        yp = np.einsum("nij,pj->npi", R_p, self.template_parent) + d_p[:, None, :]
        yc = np.einsum("nij,pj->npi", R_c, self.template_child) + d_c[:, None, :]
        return yp, yc

    def centre_world_at(self, times: ArrayLike) -> FloatArray:
        """True joint centre (hinge: the axis point ``centre_parent``) in the world, shape (N, 3), mm."""
        R_p, d_p, _, _ = self.poses_at(times)
        out: FloatArray = np.einsum("nij,j->ni", R_p, self.centre_parent) + d_p
        return out


def random_cluster(rng: np.random.Generator, n_markers: int) -> FloatArray:
    """A marker cluster 100-200 mm wide, centred at its centroid, randomly oriented."""
    ang = np.linspace(0.0, 2.0 * np.pi, n_markers, endpoint=False) + rng.uniform(-0.3, 0.3, n_markers)
    r = rng.uniform(50.0, 100.0, n_markers)
    x = np.stack([r * np.cos(ang), r * np.sin(ang), rng.normal(0.0, 15.0, n_markers)], axis=1)
    x = x @ Rotation.random(random_state=rng).as_matrix().T
    out: FloatArray = x - x.mean(axis=0)
    return out


def two_segment_motion(
    rng: np.random.Generator,
    *,
    kind: str = "ball",
    n_markers: tuple[int, int] = (4, 4),
    cycle_s: float = 20.0,
    offset: ArrayLike = (100.0, 200.0, 900.0),
) -> TwoSegmentMotion:
    """A random Stoddart-like two-segment rig (see :class:`TwoSegmentMotion`).

    Parameters
    ----------
    rng : numpy.random.Generator
    kind : {"ball", "hinge", "none"}
    n_markers : (int, int)
        Markers on the parent and the child cluster.
    cycle_s : float
        Time scale of the motion (s): the sinusoids have periods between
        0.1 and 0.33 times ``cycle_s``, so that ``cycle_s`` seconds hold
        3-10 cycles of each. Default 20 s (periods 2-6.7 s, as the
        1200-frame, 60 Hz rig of the tests).
    offset : array_like, shape (3,)
        Mean world position of the parent origin (mm); lab coordinates can be
        far from the origin.
    """
    if kind not in ("ball", "hinge", "none"):
        raise ValueError(f"kind: expected 'ball', 'hinge' or 'none', got {kind!r}")
    xp = random_cluster(rng, n_markers[0])
    xc = random_cluster(rng, n_markers[1])
    c_p = np.array([0.0, 0.0, -500.0]) + rng.normal(0.0, 30.0, 3)
    c_c = np.array([0.0, 0.0, 500.0]) + rng.normal(0.0, 30.0, 3)
    phase = rng.uniform(0.0, 2.0 * np.pi, 9)
    freq = rng.uniform(0.15, 0.5, 9) * 20.0 / cycle_s
    return TwoSegmentMotion(
        template_parent=xp,
        template_child=xc,
        centre_parent=c_p,
        centre_child=c_c,
        axis=np.array([1.0, 0.0, 0.0]),
        kind=kind,
        phase=phase,
        freq=freq,
        offset=np.asarray(offset, dtype=np.float64),
    )
