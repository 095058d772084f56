"""A synthetic human skeleton with known joints: segment geometry, motion and the true joints.

Pure numpy/scipy (no ROS), for the fake mocap's ``--skeleton`` stream, the tests and
``bench/skeleton.py``. Units are **metres** and seconds; the world is z up, x forward,
y to the subject's left (REP 103). Every segment carries a rigid cluster of 4 markers
``<PREFIX>1..4``; the noise is added by :func:`skeleton_frames` (white, per coordinate).

Skeletons (:func:`make_skeleton`):

* ``lower`` (7 segments, 6 joints): pelvis; right and left thigh, shank, foot.
  Hips are ball joints, knees hinges (flexion, axis tilted 3 deg), ankles hinges
  (the talocrural axis, oblique: ~7 deg down and ~9 deg back toward the lateral side).
* ``full`` (14 segments, 12 joints): ``lower`` plus trunk, right and left upper arm,
  forearm and hand. Shoulders and wrists are ball joints (the wrist moves in flexion
  and deviation, with a little rotation), elbows hinges (flexion; no pronation). The
  trunk moves on the pelvis through a lumbar ball joint that is part of the motion
  but not one of the 12 estimated joints.

Each segment's own frame has its origin at its proximal joint (the pelvis's at the
pelvis centre) and is parallel to the world in the neutral standing pose. Joint
motions are sums of sinusoids whose periods are 0.2-1 times ``cycle_s`` (default
10 s), so that every joint moves through its range (a ball about 2-3 axes, a hinge
about its axis) within ``cycle_s``; the pelvis wanders through the lab (+-0.15 m,
+-15 deg). The left side mirrors the right with phases shifted by half a cycle.

The true joints in the frame the node estimates them in, its *template frame*
(origin at the centroid of the parent's markers, axes parallel to the world at the
first template frame), are :meth:`Skeleton.joints_local`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

__all__ = ["SKELETONS", "SegmentSpec", "JointTruth", "Skeleton", "make_skeleton", "skeleton_frames"]

FloatArray = NDArray[np.float64]

#: Skeleton name -> estimated joints, in order.
SKELETONS: dict[str, tuple[str, ...]] = {
    "lower": ("r_hip", "r_knee", "r_ankle", "l_hip", "l_knee", "l_ankle"),
    "full": (
        "r_hip", "r_knee", "r_ankle", "l_hip", "l_knee", "l_ankle",
        "r_shoulder", "r_elbow", "r_wrist", "l_shoulder", "l_elbow", "l_wrist",
    ),
}  # fmt: skip
#: Mean world position of the pelvis origin (m): lab coordinates away from the origin.
PELVIS_OFFSET = (2.5, 3.0, 1.0)
_MIRROR = np.array([1.0, -1.0, 1.0])


@dataclass(frozen=True)
class SegmentSpec:
    """One rigid segment and the joint that attaches it to its parent.

    Attributes
    ----------
    name : str
        Segment name (``r_thigh``); also its TF frame id.
    prefix : str
        Marker prefix; the markers are ``<prefix>1..4``.
    parent : str or None
        Parent segment (None: the root, the pelvis).
    joint : str
        Name of the joint to the parent (``r_hip``; ``pelvis`` for the root's free motion).
    kind : str
        ``ball`` or ``hinge`` (``free`` for the root).
    joint_parent : ndarray, shape (3,)
        Joint position in the parent's own frame (m); for the root its mean world position.
    axis : ndarray, shape (3,)
        Unit hinge axis in the parent's own frame (and the child's: the child's frame is
        the parent's turned about it); unused for a ball.
    markers : ndarray, shape (4, 3)
        The cluster in the segment's own frame (m).
    mean_deg, amp_deg, freq, phase : ndarray, shape (3,)
        Relative rotation vector (deg, about the parent's x, y, z; a hinge uses component
        0 as its angle about ``axis``) = ``mean + amp * sin(2 pi freq t / cycle_s + phase)``.
    """

    name: str
    prefix: str
    parent: str | None
    joint: str
    kind: str
    joint_parent: FloatArray
    axis: FloatArray
    markers: FloatArray
    mean_deg: FloatArray
    amp_deg: FloatArray
    freq: FloatArray
    phase: FloatArray

    @property
    def marker_names(self) -> list[str]:
        """``<prefix>1..4``."""
        return [f"{self.prefix}{i}" for i in range(1, len(self.markers) + 1)]


def _a(*v: float) -> FloatArray:
    return np.array(v, dtype=np.float64)


def _unit(*v: float) -> FloatArray:
    x = _a(*v)
    out: FloatArray = x / np.linalg.norm(x)
    return out


# Right side and midline. Columns: name, prefix, parent, joint, kind, joint position in the parent (m),
# hinge axis (parent frame), markers (segment frame, m), mean / amplitude (deg), frequency (per cycle_s),
# phase (rad).
_Row = tuple[str, str, str | None, str, str, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]
_RIGHT: tuple[_Row, ...] = (
    ("pelvis", "PELV", None, "pelvis", "free", _a(*PELVIS_OFFSET), _a(0, 0, 1),
     np.array([[0.07, -0.12, 0.0], [0.07, 0.12, 0.0], [-0.10, -0.045, 0.03], [-0.10, 0.045, 0.03]]),
     _a(0, 0, 0), _a(8, 6, 15), _a(0.7, 1.1, 0.5)),
    ("r_thigh", "RTHI", "pelvis", "r_hip", "ball", _a(-0.01, -0.085, -0.08), _a(0, 0, 1),
     np.array([[0.05, -0.07, -0.12], [0.0, -0.085, -0.18], [0.05, -0.075, -0.26], [-0.03, -0.07, -0.30]]),
     _a(-5, -10, 0), _a(15, 30, 12), _a(1.7, 1.0, 2.3)),
    ("r_shank", "RSHK", "r_thigh", "r_knee", "hinge", _a(0, 0, -0.42), _unit(0, 1, 0.05),
     np.array([[0.04, -0.05, -0.10], [-0.01, -0.06, -0.15], [0.045, -0.05, -0.23], [-0.02, -0.055, -0.28]]),
     _a(35, 0, 0), _a(30, 0, 0), _a(1.3, 0, 0)),
    ("r_foot", "RFOO", "r_shank", "r_ankle", "hinge", _a(0, 0, -0.40), _unit(0.15, 1, 0.12),
     np.array([[-0.06, 0.0, -0.05], [0.16, 0.0, -0.06], [0.12, 0.035, -0.06], [0.11, -0.04, -0.03]]),
     _a(0, 0, 0), _a(20, 0, 0), _a(2.1, 0, 0)),
    ("trunk", "TRNK", "pelvis", "lumbar", "ball", _a(-0.04, 0, 0.04), _a(0, 0, 1),
     np.array([[-0.08, 0.0, 0.50], [0.06, 0.0, 0.45], [0.09, 0.0, 0.28], [-0.09, -0.07, 0.38]]),
     _a(0, 5, 0), _a(6, 8, 10), _a(0.9, 1.4, 0.6)),
    ("r_upper_arm", "RUPA", "trunk", "r_shoulder", "ball", _a(-0.01, -0.18, 0.45), _a(0, 0, 1),
     np.array([[0.03, -0.05, -0.10], [-0.03, -0.055, -0.14], [0.025, -0.05, -0.20], [-0.02, -0.045, -0.24]]),
     _a(-25, -20, 0), _a(20, 40, 25), _a(1.9, 1.0, 1.4)),
    ("r_forearm", "RFRA", "r_upper_arm", "r_elbow", "hinge", _a(0, 0, -0.30), _unit(0.05, -1, 0),
     np.array([[0.02, -0.035, -0.06], [-0.02, -0.03, -0.10], [0.02, -0.03, -0.16], [-0.015, -0.025, -0.20]]),
     _a(50, 0, 0), _a(40, 0, 0), _a(1.6, 0, 0)),
    ("r_hand", "RHND", "r_forearm", "r_wrist", "ball", _a(0, 0, -0.26), _a(0, 0, 1),
     np.array([[0.03, -0.02, -0.04], [-0.02, -0.03, -0.05], [0.03, -0.01, -0.09], [-0.02, -0.02, -0.10]]),
     _a(0, 0, 0), _a(15, 35, 5), _a(2.2, 1.2, 3.1)),
)  # fmt: skip
_LOWER = ("pelvis", "r_thigh", "r_shank", "r_foot", "l_thigh", "l_shank", "l_foot")
_UPPER = ("trunk", "r_upper_arm", "r_forearm", "r_hand", "l_upper_arm", "l_forearm", "l_hand")


def _specs(phase_seed: int) -> dict[str, SegmentSpec]:
    """Right-side and midline segments and their mirrored left twins (phases from ``phase_seed``)."""
    rng = np.random.default_rng(phase_seed)
    out: dict[str, SegmentSpec] = {}
    for name, prefix, parent, joint, kind, jp, axis, markers, mean, amp, freq in _RIGHT:
        phase = rng.uniform(0.0, 2.0 * np.pi, 3)
        out[name] = SegmentSpec(name, prefix, parent, joint, kind, jp, axis, markers, mean, amp, freq, phase)
        if name.startswith("r_"):
            # Mirror in the sagittal plane: positions M p; a rotation vector r becomes -M r (for a hinge the
            # angle stays and the axis becomes -M a), half a cycle later.
            flip = -_MIRROR
            out["l" + name[1:]] = SegmentSpec(
                "l" + name[1:], "L" + prefix[1:], parent if parent is None or not parent.startswith("r_") else "l" + parent[1:],
                "l" + joint[1:], kind, jp * _MIRROR, axis * flip, markers * _MIRROR,
                mean if kind == "hinge" else mean * flip, amp if kind == "hinge" else amp * flip, freq, phase + np.pi,
            )  # fmt: skip
    return out


@dataclass(frozen=True)
class JointTruth:
    """A true joint in its parent's template frame (see :meth:`Skeleton.joints_local`).

    Attributes
    ----------
    name, kind, parent, child : str
        Joint name, ``ball`` or ``hinge``, parent and child segment names.
    point : ndarray, shape (3,)
        Ball: the centre; hinge: the axis point nearest the parent markers' centroid (m),
        as the node reports it.
    direction : ndarray, shape (3,) or None
        Unit hinge direction (sign arbitrary: compare ``|cos|``); None for a ball.
    """

    name: str
    kind: str
    parent: str
    child: str
    point: FloatArray
    direction: FloatArray | None


@dataclass(frozen=True)
class Skeleton:
    """A skeleton's segments (parents first), its estimated joints and its motion time scale."""

    name: str
    segments: tuple[SegmentSpec, ...]
    joints: tuple[str, ...]
    cycle_s: float

    def segment(self, name: str) -> SegmentSpec:
        """The segment called ``name``."""
        for s in self.segments:
            if s.name == name:
                return s
        raise KeyError(f"{name!r}: no such segment; segments: {[s.name for s in self.segments]}")

    def joint_segment(self, joint: str) -> SegmentSpec:
        """The child segment of ``joint`` (the segment the joint attaches to its parent)."""
        for s in self.segments:
            if s.joint == joint:
                return s
        raise KeyError(f"{joint!r}: no such joint; joints: {list(self.joints)}")

    def marker_names(self) -> list[str]:
        """All marker names, segment by segment (row k of :meth:`markers_at` is name k)."""
        return [n for s in self.segments for n in s.marker_names]

    def poses_at(self, times: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """True world poses of every segment's own frame.

        Parameters
        ----------
        times : array_like, shape (N,)
            Motion time (s).

        Returns
        -------
        R : ndarray, shape (N, S, 3, 3)
            Rotation from segment frame to world (``R_world_segment``), segments in :attr:`segments` order.
        d : ndarray, shape (N, S, 3)
            Segment origin in the world (m).
        """
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        index = {s.name: k for k, s in enumerate(self.segments)}
        R = np.empty((t.size, len(self.segments), 3, 3))
        d = np.empty((t.size, len(self.segments), 3))
        for k, s in enumerate(self.segments):
            wave = np.sin(2.0 * np.pi * s.freq * t[:, None] / self.cycle_s + s.phase)
            rotvec = np.deg2rad(s.mean_deg + s.amp_deg * wave)
            if s.kind == "hinge":
                rotvec = rotvec[:, :1] * s.axis
            rel = Rotation.from_rotvec(rotvec).as_matrix()
            if s.parent is None:
                R[:, k] = rel
                d[:, k] = s.joint_parent + np.array([0.15, 0.08, 0.03]) * wave[:, [1, 0, 2]]
                continue
            p = index[s.parent]
            R[:, k] = R[:, p] @ rel
            d[:, k] = np.einsum("nij,j->ni", R[:, p], s.joint_parent) + d[:, p]
        return R, d

    def markers_at(self, times: ArrayLike) -> FloatArray:
        """Noise-free world markers, shape (N, P, 3) (m), in :meth:`marker_names` order."""
        R, d = self.poses_at(times)
        local = np.stack([s.markers for s in self.segments])  # (S, 4, 3)
        out: FloatArray = (np.einsum("nsij,smj->nsmi", R, local) + d[:, :, None, :]).reshape(R.shape[0], -1, 3)
        return out

    def template_poses_at(self, times: ArrayLike, t_ref: float = 0.0) -> tuple[FloatArray, FloatArray]:
        """True world poses of every segment's template frame (the node's segment frame, see :meth:`joints_local`).

        Parameters
        ----------
        times : array_like, shape (N,)
            Motion time (s).
        t_ref : float
            Motion time (s) of the first template frame.

        Returns
        -------
        R : ndarray, shape (N, S, 3, 3)
            ``R_world_template``: the segment's rotation since ``t_ref`` (identity at ``t_ref``).
        origin : ndarray, shape (N, S, 3)
            The centroid of the segment's markers in the world (m).
        """
        R, d = self.poses_at(times)
        R_ref, _ = self.poses_at([t_ref])
        centroids = np.stack([s.markers.mean(axis=0) for s in self.segments])  # (S, 3)
        origin: FloatArray = np.einsum("nsij,sj->nsi", R, centroids) + d
        R_template: FloatArray = np.einsum("nsij,skj->nsik", R, R_ref[0])
        return R_template, origin

    def _local_point(self, s: SegmentSpec) -> FloatArray:
        """The joint's point in the parent's own frame: the centre, or the axis point nearest the parent centroid."""
        if s.kind != "hinge":
            return s.joint_parent
        m = self.segment(s.parent or "").markers.mean(axis=0)
        out: FloatArray = s.joint_parent + s.axis * float((m - s.joint_parent) @ s.axis)
        return out

    def joints_world_at(self, times: ArrayLike) -> dict[str, tuple[FloatArray, FloatArray | None]]:
        """Every estimated joint's world point (N, 3) (m) and hinge direction (N, 3) (None for a ball)."""
        R, d = self.poses_at(times)
        index = {s.name: k for k, s in enumerate(self.segments)}
        out: dict[str, tuple[FloatArray, FloatArray | None]] = {}
        for j in self.joints:
            s = self.joint_segment(j)
            p = index[s.parent or ""]
            point = np.einsum("nij,j->ni", R[:, p], self._local_point(s)) + d[:, p]
            out[j] = (point, None if s.kind != "hinge" else np.einsum("nij,j->ni", R[:, p], s.axis))
        return out

    def joints_local(self, t_ref: float = 0.0) -> dict[str, JointTruth]:
        """The true joints in each parent's template frame, as the node defines it.

        Parameters
        ----------
        t_ref : float
            Motion time (s) of the parent's first template frame: the template frame's
            origin is the centroid of the parent's markers, its axes are the world's at
            that frame. The node's template frame is the one of its first fully visible
            frame (a node running before the stream starts: ``t_ref`` = 0).

        Returns
        -------
        dict of str to JointTruth
        """
        R, _ = self.poses_at([t_ref])
        index = {s.name: k for k, s in enumerate(self.segments)}
        out = {}
        for j in self.joints:
            s = self.joint_segment(j)
            parent = self.segment(s.parent or "")
            Rp = R[0, index[parent.name]]
            point = Rp @ (self._local_point(s) - parent.markers.mean(axis=0))
            direction = None if s.kind != "hinge" else Rp @ s.axis
            out[j] = JointTruth(j, s.kind, parent.name, s.name, point, direction)
        return out

    def joint_in_template(self, joint: str, template: ArrayLike, t_ref: float = 0.0) -> tuple[FloatArray, FloatArray | None]:
        """The true joint in a frame defined by an estimated template of its parent's markers.

        The true template frame (:meth:`joints_local` at ``t_ref``) is mapped onto ``template``
        by the rigid fit (Kabsch) of the parent's true cluster to it, so the truth lands in
        the node's own parent frame whatever noise or skin motion its template holds.

        Parameters
        ----------
        joint : str
            An estimated joint.
        template : array_like, shape (P, 3)
            The node's template of the parent's markers (m), in :attr:`SegmentSpec.markers` order.
        t_ref : float
            Motion time (s) of the template's frame.

        Returns
        -------
        point : ndarray, shape (3,)
            Ball: the centre; hinge: the axis point nearest the template frame's origin (m).
        direction : ndarray, shape (3,) or None
            Unit hinge direction (sign arbitrary); None for a ball.
        """
        truth = self.joints_local(t_ref)[joint]
        parent = self.segment(truth.parent)
        R0 = self.poses_at([t_ref])[0][0, [s.name for s in self.segments].index(parent.name)]
        true_template = (parent.markers - parent.markers.mean(axis=0)) @ R0.T
        x = np.asarray(template, dtype=np.float64)
        U, _, Vt = np.linalg.svd(true_template.T @ x)
        Q = Vt.T @ np.diag([1.0, 1.0, np.linalg.det(Vt.T @ U.T)]) @ U.T
        point: FloatArray = Q @ truth.point + x.mean(axis=0) - Q @ true_template.mean(axis=0)
        if truth.direction is None:
            return point, None
        direction: FloatArray = Q @ truth.direction
        return point - direction * (point @ direction), direction


def make_skeleton(name: str = "lower", *, cycle_s: float = 10.0, seed: int = 0) -> Skeleton:
    """The ``lower`` or ``full`` skeleton (see the module docstring).

    Parameters
    ----------
    name : {"lower", "full"}
    cycle_s : float
        Motion time scale (s): every joint goes through its range within it. Default 10.
    seed : int
        Seed of the motion phases (the geometry is fixed).

    Raises
    ------
    ValueError
        An unknown name or a non-positive ``cycle_s``.
    """
    if name not in SKELETONS:
        raise ValueError(f"skeleton: expected one of {sorted(SKELETONS)}, got {name!r}")
    if not cycle_s > 0.0:
        raise ValueError(f"cycle_s: expected a positive time scale in seconds, got {cycle_s}")
    specs = _specs(seed)
    names = _LOWER + (_UPPER if name == "full" else ())
    return Skeleton(name, tuple(specs[n] for n in names), SKELETONS[name], float(cycle_s))


def skeleton_frames(
    skeleton: Skeleton, times: ArrayLike, rng: np.random.Generator, noise: float, occlusion: float = 0.0
) -> FloatArray:
    """Noisy marker frames of the skeleton.

    Parameters
    ----------
    skeleton : Skeleton
    times : array_like, shape (N,)
        Motion time (s).
    rng : numpy.random.Generator
        Source of the noise and the occlusions.
    noise : float
        Standard deviation of the white noise per coordinate (m), >= 0.
    occlusion : float
        Probability that a marker is missing in a frame, in [0, 1].

    Returns
    -------
    ndarray, shape (N, P, 3)
        Marker positions (m); occluded markers are NaN rows.
    """
    if not noise >= 0.0 or not 0.0 <= occlusion <= 1.0:
        raise ValueError(f"noise: expected >= 0 m, got {noise}; occlusion: expected in [0, 1], got {occlusion}")
    frames = skeleton.markers_at(times)
    if noise > 0.0:
        frames += rng.normal(0.0, noise, frames.shape)
    if occlusion > 0.0:
        frames[rng.random(frames.shape[:2]) < occlusion] = np.nan
    return frames
