"""Soft-tissue artefact (STA) on synthetic skin-marker clusters, with known bone truth.

Skin markers move over the bone smoothly and as functions of the joint
angles. This module displaces the markers of a :class:`~jointfit_core.synthetic.TwoSegmentMotion`
by a model of that artefact, for tests and benchmarks of the estimators on
the data labs have (not only on rigid clusters).

Model (after Dumas, Cheze & Frossard 2009; Camomilla et al. 2013, 2017;
Bonci et al. 2014): in the segment's bone frame, each marker's displacement
is a linear-plus-quadratic function of the joint angles,

    delta_i(t) = A_i f(q(t)),    f(q) = [q_1, q_2, q_3, q_1^2, q_2^2, q_3^2, q_1 q_2, q_1 q_3, q_2 q_3],

``q`` the rotation vector of the child relative to the parent (rad). The
field is split into a *rigid* part (the whole cluster turns and shifts on the
bone, ``omega(t) x x_i + tau(t)``, linear in ``f``) and a *deformation* part
(what no rigid motion of the cluster explains); Camomilla et al. (2013, 2017)
found the rigid part to dominate, about three quarters of the artefact on the
thigh. Both parts are scaled so that the rms over frames and markers of the
displacement from the reference posture (``q = 0``) is the requested
amplitude: thigh 10-30 mm, shank 5-15 mm in the review of Leardini et al.
(2005). ``mode="wobble"`` replaces ``f(q)`` by smooth random signals
(0.3-2 Hz) of the same size, an artefact not tied to the joint angles.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from .synthetic import TwoSegmentMotion, markers_from_poses

__all__ = ["SkinArtefact", "skin_artefact", "skin_markers_at", "STA_MODES"]

FloatArray = NDArray[np.float64]

#: The artefact's kinds: tied to the angles (rigid + deformation), deformation only, rigid only, or not tied.
STA_MODES = ("angle", "deformation", "rigid", "wobble")

_N_FEATURES = 9


def _features(q: FloatArray) -> FloatArray:
    """Linear and quadratic terms of the joint angles, (N, m) rad -> (N, m + m (m + 1) / 2).

    Order: ``q``, ``q**2``, then the products ``q_i q_j`` (i < j) row by row; for m = 3
    the 9 features of the module docstring.
    """
    m = q.shape[1]
    i, j = np.triu_indices(m, k=1)
    return np.concatenate([q, q**2, q[:, i] * q[:, j]], axis=1)


def _skew_rows(x: FloatArray) -> FloatArray:
    """(P, 3) points -> (3P, 6) map of [omega, tau] to the displacements omega x x_i + tau."""
    p = x.shape[0]
    G = np.zeros((p, 3, 6))
    G[:, 0, 1], G[:, 0, 2] = x[:, 2], -x[:, 1]
    G[:, 1, 0], G[:, 1, 2] = -x[:, 2], x[:, 0]
    G[:, 2, 0], G[:, 2, 1] = x[:, 1], -x[:, 0]
    G[:, :, 3:] = np.eye(3)
    return G.reshape(3 * p, 6)


@dataclass(frozen=True)
class SkinArtefact:
    """One segment's artefact field: displacements (P, 3) per feature, bone frame, mm.

    Attributes
    ----------
    rigid, deformation : ndarray, shape (F, P, 3)
        Displacement of each marker per unit of each feature, the rigid
        part (a small rotation about the cluster centroid plus a shift) and
        the deformation part (orthogonal to every rigid field).
    """

    rigid: FloatArray
    deformation: FloatArray


def skin_artefact(
    rng: np.random.Generator,
    template: ArrayLike,
    features: ArrayLike,
    *,
    amplitude: float,
    rigid_share: float = 0.75,
    mode: str = "angle",
) -> SkinArtefact:
    """A random artefact field for one cluster, scaled on the features it will see.

    Parameters
    ----------
    rng : numpy.random.Generator
    template : array_like, shape (P, 3)
        The cluster in its bone frame (mm).
    features : array_like, shape (N, F)
        The features the trial will feed it (:func:`_features` of the joint
        angles, F = 9 for one joint, or the wobble signals): the scaling makes the rms
        displacement over these frames and the markers ``amplitude``.
    amplitude : float
        Rms displacement magnitude over frames and markers (mm).
    rigid_share : float
        Share of the rms amplitude carried by the rigid part (0-1; the
        deformation part carries ``sqrt(1 - rigid_share**2)`` of it, so that
        the two, orthogonal, add up to ``amplitude``).
    mode : {"angle", "deformation", "rigid", "wobble"}
        "deformation" and "rigid" keep one part only (at the full amplitude).
    """
    if mode not in STA_MODES:
        raise ValueError(f"mode: expected one of {STA_MODES}, got {mode!r}")
    x = np.asarray(template, dtype=np.float64)
    x = x - x.mean(axis=0)
    f = np.asarray(features, dtype=np.float64)
    p, n_f = x.shape[0], f.shape[1]
    G = _skew_rows(x)
    # rigid: random (omega, tau) per feature, omega in rad per unit feature scaled like tau / radius
    radius = float(np.sqrt((x**2).sum(axis=1).mean()))
    coef = rng.normal(size=(n_f, 6))
    coef[:, :3] /= radius
    rigid = (coef @ G.T).reshape(n_f, p, 3)
    raw = rng.normal(size=(n_f, 3 * p))
    proj = G @ np.linalg.pinv(G)
    deformation = (raw - raw @ proj.T).reshape(n_f, p, 3)

    def rms(field: FloatArray) -> float:
        d = np.einsum("nf,fpi->npi", f, field)
        return float(np.sqrt((d**2).sum(axis=2).mean()))

    share = {"rigid": 1.0, "deformation": 0.0}.get(mode, float(rigid_share))
    a_r, a_d = amplitude * share, amplitude * np.sqrt(max(1.0 - share**2, 0.0))
    rigid = rigid * (a_r / rms(rigid)) if a_r > 0 else np.zeros_like(rigid)
    deformation = deformation * (a_d / rms(deformation)) if a_d > 0 else np.zeros_like(deformation)
    return SkinArtefact(rigid=rigid, deformation=deformation)


def _wobble(rng: np.random.Generator, t: FloatArray, n: int = _N_FEATURES) -> FloatArray:
    """``n`` smooth random signals (0.3-2 Hz sines, random phases) at ``t`` (s), shape (N, n)."""
    freq = rng.uniform(0.3, 2.0, n)
    phase = rng.uniform(0.0, 2.0 * np.pi, n)
    out: FloatArray = np.sin(2.0 * np.pi * freq * t[:, None] + phase)
    return out


def skin_markers_at(
    rng: np.random.Generator,
    motion: TwoSegmentMotion | JointMotion,
    times: ArrayLike,
    *,
    parent_mm: float = 0.0,
    child_mm: float = 0.0,
    rigid_share: float = 0.75,
    mode: str = "angle",
    noise_std: float = 0.0,
) -> tuple[FloatArray, FloatArray]:
    """World markers of ``motion`` at ``times`` with skin artefact and white noise.

    Parameters
    ----------
    rng : numpy.random.Generator
    motion : TwoSegmentMotion
        The bone motion; its joint (``centre_parent``, ``axis``) is the truth.
    times : array_like, shape (N,)
        Seconds.
    parent_mm, child_mm : float
        Rms artefact amplitude of each cluster (mm; 0: rigid cluster).
    rigid_share : float
        See :func:`skin_artefact`.
    mode : {"angle", "deformation", "rigid", "wobble"}
        See :func:`skin_artefact`.
    noise_std : float
        White marker noise per coordinate (mm).

    Returns
    -------
    parent, child : ndarray, shape (N, Pa, 3) and (N, Pc, 3)
        World marker positions (mm).
    """
    t = np.atleast_1d(np.asarray(times, dtype=np.float64))
    R_p, d_p, R_c, d_c = motion.poses_at(t)
    q = Rotation.from_matrix(np.einsum("nji,njk->nik", R_p, R_c)).as_rotvec()
    feats = _wobble(rng, t) if mode == "wobble" else _features(q)
    out = []
    for template, R, d, amp in (
        (motion.template_parent, R_p, d_p, parent_mm),
        (motion.template_child, R_c, d_c, child_mm),
    ):
        local = np.broadcast_to(template, (t.size, *template.shape)).copy()
        if amp > 0:
            field = skin_artefact(rng, template, feats, amplitude=amp, rigid_share=rigid_share, mode=mode)
            local += np.einsum("nf,fpi->npi", feats, field.rigid + field.deformation)
        world = np.einsum("nij,npj->npi", R, local) + d[:, None, :]
        if noise_std > 0:
            world += rng.normal(0.0, noise_std, world.shape)
        out.append(world)
    return out[0], out[1]


def skin_markers_by_block(
    rng: np.random.Generator,
    motion: TwoSegmentMotion | JointMotion,
    times: ArrayLike,
    blocks: int,
    **artefact: Any,
) -> tuple[FloatArray, FloatArray]:
    """:func:`skin_markers_at` with a new artefact field in each of ``blocks`` contiguous pieces of ``times``.

    An artefact that changes between movements (the cluster re-settles), for the consistency check
    across movement blocks (:mod:`jointfit_core.consistency`); ``blocks=1`` is one field for all.
    ``artefact``: the keyword arguments of :func:`skin_markers_at`.

    Returns
    -------
    parent, child : ndarray, shape (N, Pa, 3) and (N, Pc, 3)
        World marker positions (mm), the pieces in order.
    """
    parts = [skin_markers_at(rng, motion, tb, **artefact) for tb in np.array_split(np.asarray(times), blocks)]
    return np.concatenate([p for p, _ in parts]), np.concatenate([c for _, c in parts])


__all__ += ["skin_markers_by_block", "JointMotion", "hip_motion", "knee_motion"]


@dataclass(frozen=True)
class JointMotion:
    """A hip or knee movement with known bone truth, evaluable at any time (duck-types :class:`TwoSegmentMotion`).

    Attributes
    ----------
    template_parent, template_child : ndarray, shape (Pa, 3) and (Pc, 3)
        Marker coordinates in each bone frame (mm), centred at their centroids.
    centre_parent, centre_child : ndarray, shape (3,)
        Joint centre (hinge: a point of the axis) in the bone frames (mm).
    axis : ndarray, shape (3,)
        Hinge direction in both bone frames (unit; ``kind == "hinge"``).
    kind : {"ball", "hinge"}
    amplitude_deg : float
        Hip: arc and circumduction amplitude; knee: the largest flexion.
    period_s : float
        Duration of one arc (out and back) or one circumduction / flexion cycle.
    seed_phase : ndarray, shape (6,)
        Phases of the slow parent wander (rotation +-5 deg, translation +-40 mm).
    """

    template_parent: FloatArray
    template_child: FloatArray
    centre_parent: FloatArray
    centre_child: FloatArray
    axis: FloatArray
    kind: str
    amplitude_deg: float
    period_s: float
    seed_phase: FloatArray

    def joint_rotvec(self, times: ArrayLike) -> FloatArray:
        """Rotation vector of the child bone relative to the parent bone, shape (N, 3), rad.

        Ball (hip): eight star arcs (out along 0, 45, ..., 315 deg in the
        flexion-abduction plane and back, one per ``period_s``), then
        circumductions of the same amplitude (one per ``period_s``), repeated.
        Hinge (knee): flexion ``amplitude/2 (1 - cos)`` from 0 to
        ``amplitude_deg`` about ``axis``, one cycle per ``period_s``.
        """
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        amp = np.deg2rad(self.amplitude_deg)
        phase = 2.0 * np.pi * t / self.period_s
        if self.kind == "hinge":
            return np.outer(0.5 * amp * (1.0 - np.cos(phase)), self.axis)
        k = np.floor(t / self.period_s).astype(int) % 12  # 8 arcs then 4 circumductions
        bump = np.sin(0.5 * phase) ** 2  # 0 -> 1 -> 0 over one period
        star = np.deg2rad(45.0) * k
        q = np.zeros((t.size, 3))
        arc = k < 8
        q[arc, 0] = amp * bump[arc] * np.cos(star[arc])
        q[arc, 1] = amp * bump[arc] * np.sin(star[arc])
        q[~arc, 0] = amp * np.cos(phase[~arc])
        q[~arc, 1] = amp * np.sin(phase[~arc])
        q[:, 2] = 0.3 * amp * np.sin(0.5 * phase + 0.7)  # some internal-external rotation
        return q

    def poses_at(self, times: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """True world poses ``(R_parent, d_parent, R_child, d_child)`` at ``times`` (s), shapes (N, 3, 3), (N, 3)."""
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        wave = np.sin(2.0 * np.pi * t[:, None] / (3.7 * self.period_s) * np.array([1.0, 1.3, 0.7, 0.9, 1.1, 0.8])
                      + self.seed_phase)
        R_p = Rotation.from_rotvec(np.deg2rad(5.0) * wave[:, :3]).as_matrix()
        d_p = 40.0 * wave[:, 3:6] + np.array([100.0, 200.0, 900.0])
        R_c = R_p @ Rotation.from_rotvec(self.joint_rotvec(t)).as_matrix()
        joint = np.einsum("nij,j->ni", R_p, self.centre_parent) + d_p
        d_c = joint - np.einsum("nij,j->ni", R_c, self.centre_child)
        return R_p, d_p, R_c, d_c

    def markers_at(self, times: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Noise-free world markers ``(parent (N, Pa, 3), child (N, Pc, 3))`` at ``times`` (s)."""
        return markers_from_poses(self.poses_at(times), self.template_parent, self.template_child)


def _cluster(rng: np.random.Generator, n: int, radius: tuple[float, float]) -> FloatArray:
    """``n`` markers around a ring of ``radius`` mm (range), +-15 mm out of its plane, randomly oriented, centred."""
    ang = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False) + rng.uniform(-0.3, 0.3, n)
    r = rng.uniform(radius[0], radius[1], n)
    x = np.stack([r * np.cos(ang), r * np.sin(ang), rng.normal(0.0, 15.0, n)], axis=1)
    x = x @ Rotation.random(random_state=rng).as_matrix().T
    out: FloatArray = x - x.mean(axis=0)
    return out


def hip_motion(
    rng: np.random.Generator, *, n_markers: tuple[int, int] = (4, 4), amplitude_deg: float = 25.0,
    period_s: float = 2.5,
) -> JointMotion:
    """A hip: pelvis cluster (ASIS/PSIS-like, radius 100-140 mm), thigh cluster (radius 80-120 mm) 200-300 mm below the centre.

    The hip centre is ~80 mm below and ~90 mm lateral of the pelvis marker
    centroid; the thigh cluster's centroid is 200-300 mm distal of it (the
    lever arm that turns a thigh-cluster rotation into a centre shift).
    Star arcs and circumductions of ``amplitude_deg`` (20-30 deg in
    functional-calibration protocols, e.g. Camomilla et al. 2006).
    """
    xp = _cluster(rng, n_markers[0], (100.0, 140.0))
    xc = _cluster(rng, n_markers[1], (80.0, 120.0))
    c_p = np.array([90.0, 0.0, -80.0]) + rng.normal(0.0, 10.0, 3)
    c_c = np.array([0.0, 60.0, rng.uniform(200.0, 300.0)])
    return JointMotion(xp, xc, c_p, c_c, np.array([0.0, 1.0, 0.0]), "ball", float(amplitude_deg), float(period_s),
                       rng.uniform(0.0, 2.0 * np.pi, 6))


def knee_motion(
    rng: np.random.Generator, *, n_markers: tuple[int, int] = (4, 4), amplitude_deg: float = 90.0,
    period_s: float = 2.5,
) -> JointMotion:
    """A knee: thigh cluster 150-250 mm above the axis, shank cluster 100-200 mm below, flexion 0-``amplitude_deg``."""
    xp = _cluster(rng, n_markers[0], (50.0, 80.0))
    xc = _cluster(rng, n_markers[1], (50.0, 80.0))
    c_p = np.array([0.0, 50.0, -rng.uniform(150.0, 250.0)])
    c_c = np.array([0.0, 50.0, rng.uniform(100.0, 200.0)])
    axis = np.array([1.0, 0.0, 0.0]) + rng.normal(0.0, 0.05, 3)
    return JointMotion(xp, xc, c_p, c_c, axis / np.linalg.norm(axis), "hinge", float(amplitude_deg),
                       float(period_s), rng.uniform(0.0, 2.0 * np.pi, 6))
