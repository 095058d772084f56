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
    "markers_from_poses",
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
        return markers_from_poses(self.poses_at(times), self.template_parent, self.template_child)

    def centre_world_at(self, times: ArrayLike) -> FloatArray:
        """True joint centre (hinge: the axis point ``centre_parent``) in the world, shape (N, 3), mm."""
        R_p, d_p, _, _ = self.poses_at(times)
        out: FloatArray = np.einsum("nij,j->ni", R_p, self.centre_parent) + d_p
        return out


def markers_from_poses(
    poses: tuple[FloatArray, FloatArray, FloatArray, FloatArray], template_parent: FloatArray, template_child: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """World markers of two segments from their poses ``(R_p (N, 3, 3), d_p (N, 3), R_c, d_c)`` and templates (P, 3)."""
    R_p, d_p, R_c, d_c = poses
    yp: FloatArray = np.einsum("nij,pj->npi", R_p, template_parent) + d_p[:, None, :]
    yc: FloatArray = np.einsum("nij,pj->npi", R_c, template_child) + d_c[:, None, :]
    return yp, yc


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


__all__ += ["minimal_marker_motion", "LegChainMotion", "leg_chain_motion"]


def minimal_marker_motion(
    rng: np.random.Generator,
    *,
    kind: str = "ball",
    n_markers: tuple[int, int] = (2, 2),
    spread: tuple[float, float] = (300.0, 300.0),
    lever: tuple[float, float] = (300.0, 300.0),
    cycle_s: float = 20.0,
    offset: ArrayLike = (100.0, 200.0, 900.0),
) -> TwoSegmentMotion:
    """A two-segment rig with few, widely spread markers per link (minimal marker sets).

    Like :func:`two_segment_motion` (same motion model: the parent wanders,
    the child rotates about the joint), but each link's markers are a
    :func:`random_cluster` scaled to ``spread`` mm between its farthest
    markers (a single marker sits at the link origin), and the joint is
    ``lever`` mm from each link's marker centroid in a random direction.

    Parameters
    ----------
    rng : numpy.random.Generator
    kind : {"ball", "hinge", "none"}
    n_markers : (int, int)
        Markers on the parent and the child (1 or more each).
    spread : (float, float)
        Largest marker separation on each link (mm).
    lever : (float, float)
        Distance of the joint from each link's marker centroid (mm).
    cycle_s, offset
        As in :func:`two_segment_motion`.
    """
    if kind not in ("ball", "hinge", "none"):
        raise ValueError(f"kind: expected 'ball', 'hinge' or 'none', got {kind!r}")
    templates = []
    for count, size in zip(n_markers, spread, strict=True):
        x = random_cluster(rng, count)
        sep = float(np.max(np.linalg.norm(x[:, None] - x[None], axis=2))) if count > 1 else 1.0
        templates.append(x * (size / sep))
    centres = []
    for dist in lever:
        v = rng.normal(size=3)
        centres.append(dist * v / np.linalg.norm(v))
    base = two_segment_motion(rng, kind=kind, n_markers=(3, 3), cycle_s=cycle_s, offset=offset)
    return TwoSegmentMotion(
        template_parent=templates[0],
        template_child=templates[1],
        centre_parent=centres[0],
        centre_child=centres[1],
        axis=base.axis,
        kind=kind,
        phase=base.phase,
        freq=base.freq,
        offset=base.offset,
    )


@dataclass(frozen=True)
class LegChainMotion:
    """A trunk -> thigh -> shank -> foot chain with the paper's minimal marker set (section V-B).

    Segment frames (mm): the trunk carries 3 markers and the hip centre; the
    thigh rotates about the hip (ball) and carries one marker; the shank
    rotates about the knee hinge (fixed in the thigh and shank frames) and
    carries one marker; the foot rotates about the ankle (ball) and carries
    one marker. Angles are sums of sinusoids, so the motion can be evaluated
    at any time.

    Attributes
    ----------
    trunk_markers : ndarray, shape (3, 3)
        Trunk marker coordinates in the trunk frame.
    hip_trunk : ndarray, shape (3,)
        Hip centre in the trunk frame (also the thigh frame origin).
    thigh_marker : ndarray, shape (3,)
        Thigh marker in the thigh frame.
    knee_thigh, knee_axis : ndarray, shape (3,)
        A point of the knee axis (the shank frame origin) and its unit
        direction, in the thigh frame (the shank frame is the thigh frame
        turned about this axis).
    shank_marker : ndarray, shape (3,)
        Shank marker in the shank frame.
    ankle_shank : ndarray, shape (3,)
        Ankle centre in the shank frame (the foot frame origin).
    foot_marker : ndarray, shape (3,)
        Foot marker in the foot frame.
    phase, freq : ndarray, shape (13,)
        Phases (rad) and frequencies (Hz) of the sinusoids.
    offset : ndarray, shape (3,)
        Mean world position of the trunk origin (mm).
    """

    trunk_markers: FloatArray
    hip_trunk: FloatArray
    thigh_marker: FloatArray
    knee_thigh: FloatArray
    knee_axis: FloatArray
    shank_marker: FloatArray
    ankle_shank: FloatArray
    foot_marker: FloatArray
    phase: FloatArray
    freq: FloatArray
    offset: FloatArray

    def frames_at(self, times: ArrayLike) -> dict[str, tuple[FloatArray, FloatArray]]:
        """World poses ``(R (N, 3, 3), origin (N, 3))`` of "trunk", "thigh", "shank" and "foot"."""
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        w = np.sin(2.0 * np.pi * self.freq * t[:, None] + self.phase)
        R_trunk = Rotation.from_rotvec(np.deg2rad(15.0) * w[:, :3]).as_matrix()
        o_trunk = 100.0 * w[:, 3:6] + self.offset
        hip = Rotation.from_euler("xyz", np.deg2rad(np.stack([30.0 + 40.0 * w[:, 6], 20.0 * w[:, 7], 15.0 * w[:, 8]], 1)))
        R_thigh = R_trunk @ hip.as_matrix()
        o_thigh = np.einsum("nij,j->ni", R_trunk, self.hip_trunk) + o_trunk
        knee = Rotation.from_rotvec(np.deg2rad(-45.0 - 40.0 * w[:, 9])[:, None] * self.knee_axis).as_matrix()
        R_shank = R_thigh @ knee
        o_shank = np.einsum("nij,j->ni", R_thigh, self.knee_thigh) + o_thigh
        ankle = Rotation.from_euler("xyz", np.deg2rad(np.stack([25.0 * w[:, 10], 15.0 * w[:, 11], 10.0 * w[:, 12]], 1)))
        R_foot = R_shank @ ankle.as_matrix()
        o_foot = np.einsum("nij,j->ni", R_shank, self.ankle_shank) + o_shank
        return {"trunk": (R_trunk, o_trunk), "thigh": (R_thigh, o_thigh), "shank": (R_shank, o_shank), "foot": (R_foot, o_foot)}

    def markers_at(self, times: ArrayLike) -> dict[str, FloatArray]:
        """Noise-free world markers: "trunk" (N, 3, 3), "thigh", "shank", "foot" (N, 1, 3)."""
        f = self.frames_at(times)

        def carry(name: str, local: FloatArray) -> FloatArray:
            R, o = f[name]
            out: FloatArray = np.einsum("nij,pj->npi", R, np.atleast_2d(local)) + o[:, None, :]
            return out

        return {
            "trunk": carry("trunk", self.trunk_markers),
            "thigh": carry("thigh", self.thigh_marker),
            "shank": carry("shank", self.shank_marker),
            "foot": carry("foot", self.foot_marker),
        }

    def joints_at(self, times: ArrayLike) -> dict[str, FloatArray]:
        """True joints in the world: "hip", "knee" (axis point), "knee_axis" (unit), "ankle", each (N, 3)."""
        f = self.frames_at(times)
        R_thigh, o_thigh = f["thigh"]
        return {
            "hip": o_thigh,
            "knee": f["shank"][1],
            "knee_axis": np.einsum("nij,j->ni", R_thigh, self.knee_axis),
            "ankle": f["foot"][1],
        }


def leg_chain_motion(rng: np.random.Generator, *, cycle_s: float = 20.0, offset: ArrayLike = (0.0, 0.0, 1000.0)) -> LegChainMotion:
    """A random leg with the minimal marker set of the paper's section V-B (see :class:`LegChainMotion`).

    Trunk markers about 200 mm apart, the hip ~100 mm below them, a thigh
    marker on the lateral thigh (off the knee axis), the knee axis roughly
    medio-lateral ~420 mm below the hip, a shank marker on the lateral shank
    and a foot marker ~120 mm in front of the ankle. Dimensions get a few
    per cent of random variation.
    """
    j = lambda scale, size=3: rng.normal(0.0, scale, size)  # noqa: E731
    trunk = np.array([[-80.0, -60.0, 60.0], [90.0, -50.0, 40.0], [0.0, 90.0, 80.0]]) + j(10.0, (3, 3))
    axis = np.array([1.0, 0.0, 0.0]) + j(0.05)
    freq = rng.uniform(0.15, 0.5, 13) * 20.0 / cycle_s
    return LegChainMotion(
        trunk_markers=trunk,
        hip_trunk=np.array([80.0, 0.0, -100.0]) + j(10.0),
        thigh_marker=np.array([80.0, 30.0, -230.0]) + j(10.0),
        knee_thigh=np.array([0.0, 0.0, -420.0]) + j(15.0),
        knee_axis=axis / np.linalg.norm(axis),
        shank_marker=np.array([60.0, 40.0, -200.0]) + j(10.0),
        ankle_shank=np.array([0.0, 0.0, -400.0]) + j(15.0),
        foot_marker=np.array([20.0, 130.0, -40.0]) + j(10.0),
        phase=rng.uniform(0.0, 2.0 * np.pi, 13),
        freq=freq,
        offset=np.asarray(offset, dtype=np.float64),
    )
