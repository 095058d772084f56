"""Skin markers on a whole skeleton: every segment's cluster moves on its bone with the adjacent joints.

Pure numpy/scipy (no ROS), for tests and ``bench/skeleton_sta.py``: the skin counterpart of
:func:`jointfit_core.skeleton_truth.skeleton_frames`. The bone motion and so the true joints
(:meth:`~jointfit_core.skeleton_truth.Skeleton.joints_local`) are those of the
:class:`~jointfit_core.skeleton_truth.Skeleton`; only the markers move on the bones.

Model: the soft-tissue artefact (STA) of :mod:`jointfit_core.soft_tissue` (after Dumas, Cheze &
Frossard 2009; Camomilla et al. 2013, 2017; Bonci et al. 2014), taken from two to many joints.
In its segment's own (bone) frame, each marker's displacement is linear plus quadratic in the
angles of the joints *adjacent* to the segment, its proximal joint and every distal one (the
thigh's skin follows the hip and the knee, the pelvis's both hips),

    delta_i(t) = A_i f(q(t)),    q = [q_j1, q_j2, ...],    f(q) = [q, q_k^2, q_k q_l (k < l)],

``q_j`` the rotation vector (rad) of joint ``j``'s child segment relative to its parent, so the
artefact is zero in the neutral standing posture (every ``q_j = 0``). A segment's field is
split as in :func:`~jointfit_core.soft_tissue.skin_artefact` into a rigid part (the whole
cluster turning about its centroid and shifting on the bone, ~75 % of the artefact, Camomilla
et al. 2013) and a deformation part, and scaled so that the rms over frames and markers of the
displacement is the segment's amplitude: thigh 10-30 mm, shank 5-15 mm in the review of
Leardini et al. (2005). For one joint and one segment this is exactly the two-segment model of
:func:`~jointfit_core.soft_tissue.skin_markers_at`.

For a joint estimator this is harder than the two-segment rigs: part of each segment's
artefact follows the *other* adjacent joint (the hip's thigh cluster moves with the knee), which
the estimator's prior, a function of its own joint's angles, does not model
(``bench/skeleton_sta.py`` measures what the node's covariances make of it).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from .skeleton_truth import Skeleton
from .soft_tissue import STA_MODES, _features, _wobble, skin_artefact

__all__ = ["TYPICAL_STA_M", "adjacent_joints", "joint_rotvecs", "skeleton_artefact", "skeleton_skin_frames",
           "sta_amplitudes"]

FloatArray = NDArray[np.float64]

#: Rms artefact per segment kind (m): thigh and shank at the low end of Leardini et al. (2005)
#: (10-30 mm and 5-15 mm); pelvis, foot, trunk and hand clusters over bony landmarks, smaller.
TYPICAL_STA_M: dict[str, float] = {
    "pelvis": 0.003, "thigh": 0.010, "shank": 0.005, "foot": 0.003,
    "trunk": 0.005, "upper_arm": 0.008, "forearm": 0.005, "hand": 0.002,
}  # fmt: skip


def sta_amplitudes(skeleton: Skeleton, scale: float = 1.0, **override: float) -> dict[str, float]:
    """Rms artefact amplitude (m) of every segment: :data:`TYPICAL_STA_M` by kind, times ``scale``.

    Parameters
    ----------
    skeleton : Skeleton
    scale : float
        Factor on every amplitude (>= 0).
    **override : float
        Amplitude (m, before ``scale``) of a segment kind (``thigh=0.02``) or a segment (``r_thigh=0.02``).

    Returns
    -------
    dict of str to float
        Segment name -> rms amplitude (m).
    """
    out = {}
    for s in skeleton.segments:
        kind = s.name[2:] if s.name[:2] in ("r_", "l_") else s.name
        out[s.name] = scale * override.get(s.name, override.get(kind, TYPICAL_STA_M[kind]))
    return out


def joint_rotvecs(skeleton: Skeleton, times: ArrayLike) -> dict[str, FloatArray]:
    """Every joint's rotation vector (child relative to parent, rad), shape (N, 3), by joint name.

    All joints of the motion, the estimated ones and the others (the lumbar joint of ``full``).
    """
    R, _ = skeleton.poses_at(times)
    index = {s.name: k for k, s in enumerate(skeleton.segments)}
    return {
        s.joint: Rotation.from_matrix(np.einsum("nji,njk->nik", R[:, index[s.parent]], R[:, index[s.name]])).as_rotvec()
        for s in skeleton.segments
        if s.parent is not None
    }


def adjacent_joints(skeleton: Skeleton) -> dict[str, tuple[str, ...]]:
    """Segment name -> the joints whose angles move its skin: its proximal joint, then its distal ones."""
    return {
        s.name: ((s.joint,) if s.parent is not None else ())
        + tuple(c.joint for c in skeleton.segments if c.parent == s.name)
        for s in skeleton.segments
    }


def skeleton_artefact(
    skeleton: Skeleton,
    times: ArrayLike,
    rng: np.random.Generator,
    amplitude: Mapping[str, float],
    *,
    rigid_share: float = 0.75,
    mode: str = "angle",
    drivers: Mapping[str, Sequence[str]] | None = None,
) -> FloatArray:
    """Every marker's skin displacement in its segment's own (bone) frame.

    Parameters
    ----------
    skeleton : Skeleton
    times : array_like, shape (N,)
        Motion time (s).
    rng : numpy.random.Generator
        Source of the random fields (drawn segment by segment, in ``skeleton.segments`` order).
    amplitude : mapping of str to float
        Segment name -> rms displacement over the frames and the markers (m, >= 0); a segment
        not named has none (a rigid cluster). See :func:`sta_amplitudes`.
    rigid_share : float
        Share of the amplitude in the rigid cluster motion (see
        :func:`~jointfit_core.soft_tissue.skin_artefact`).
    mode : {"angle", "deformation", "rigid", "wobble"}
        See :func:`~jointfit_core.soft_tissue.skin_artefact`; "wobble": smooth random signals,
        as many as the angle features, instead of the angles.
    drivers : mapping of str to sequence of str, optional
        Segment name -> the joints whose angles drive its artefact (default
        :func:`adjacent_joints`; e.g. only the proximal joint, to isolate one joint's share).

    Returns
    -------
    ndarray, shape (N, P, 3)
        Displacements (m) in :meth:`Skeleton.marker_names` order.

    Raises
    ------
    ValueError
        An unknown segment, joint or mode, a negative amplitude, or a segment with an
        amplitude and no driving joint.
    """
    if mode not in STA_MODES:
        raise ValueError(f"mode: expected one of {STA_MODES}, got {mode!r}")
    names = [s.name for s in skeleton.segments]
    unknown = sorted(set(amplitude) - set(names))
    if unknown:
        raise ValueError(f"amplitude: {unknown} are not segments of the {skeleton.name} skeleton; segments: {names}")
    bad = {k: v for k, v in amplitude.items() if not float(v) >= 0.0}
    if bad:
        raise ValueError(f"amplitude: expected rms displacements >= 0 m, got {bad}")
    t = np.atleast_1d(np.asarray(times, dtype=np.float64))
    q = joint_rotvecs(skeleton, t)
    drive = dict(adjacent_joints(skeleton)) | dict(drivers or {})
    out = np.zeros((t.size, len(skeleton.marker_names()), 3))
    start = 0
    for s in skeleton.segments:
        n, amp = len(s.markers), float(amplitude.get(s.name, 0.0))
        if amp > 0.0:
            joints = tuple(drive.get(s.name, ()))
            missing = [j for j in joints if j not in q]
            if not joints or missing:
                raise ValueError(f"drivers of {s.name}: expected joints of the skeleton {sorted(q)}, got {joints}")
            feats = _features(np.concatenate([q[j] for j in joints], axis=1))
            if mode == "wobble":
                feats = _wobble(rng, t, feats.shape[1])
            field = skin_artefact(rng, s.markers, feats, amplitude=amp, rigid_share=rigid_share, mode=mode)
            out[:, start : start + n] = np.einsum("nf,fpi->npi", feats, field.rigid + field.deformation)
        start += n
    return out


def skeleton_skin_frames(
    skeleton: Skeleton,
    times: ArrayLike,
    rng: np.random.Generator,
    amplitude: Mapping[str, float],
    *,
    noise: float = 0.0,
    occlusion: float = 0.0,
    rigid_share: float = 0.75,
    mode: str = "angle",
    drivers: Mapping[str, Sequence[str]] | None = None,
) -> FloatArray:
    """Skin-marker frames of the skeleton: :func:`skeleton_artefact` on the bones, then noise and occlusion.

    Parameters
    ----------
    skeleton : Skeleton
    times : array_like, shape (N,)
        Motion time (s).
    rng : numpy.random.Generator
        Source of the artefact fields, then the noise, then the occlusions.
    amplitude, rigid_share, mode, drivers
        See :func:`skeleton_artefact`.
    noise : float
        Standard deviation of the white noise per coordinate (m), >= 0.
    occlusion : float
        Probability that a marker is missing in a frame, in [0, 1].

    Returns
    -------
    ndarray, shape (N, P, 3)
        World marker positions (m) in :meth:`Skeleton.marker_names` order; occluded markers
        are NaN rows. The true joints are unchanged (:meth:`Skeleton.joints_local`).
    """
    if not noise >= 0.0 or not 0.0 <= occlusion <= 1.0:
        raise ValueError(f"noise: expected >= 0 m, got {noise}; occlusion: expected in [0, 1], got {occlusion}")
    t = np.atleast_1d(np.asarray(times, dtype=np.float64))
    delta = skeleton_artefact(skeleton, t, rng, amplitude, rigid_share=rigid_share, mode=mode, drivers=drivers)
    R, d = skeleton.poses_at(t)
    local = np.concatenate([s.markers for s in skeleton.segments])[None] + delta  # (N, P, 3)
    seg = np.repeat(np.arange(len(skeleton.segments)), [len(s.markers) for s in skeleton.segments])
    frames: FloatArray = np.einsum("npij,npj->npi", R[:, seg], local) + d[:, seg]
    if noise > 0.0:
        frames += rng.normal(0.0, noise, frames.shape)
    if occlusion > 0.0:
        frames[rng.random(frames.shape[:2]) < occlusion] = np.nan
    return frames
