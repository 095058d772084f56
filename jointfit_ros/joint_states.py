"""``~/joint_states``: every frame's joint angles as a ``sensor_msgs/JointState`` (pure Python, no rclpy).

:class:`JointStates` turns one input frame's joint outputs (the
:class:`~jointfit_ros.inputs.Routed` of a message) into names, angles (rad),
velocities (rad/s) and the hinge angles' sd (:mod:`jointfit_core.joint_angles`);
:func:`joint_state_bytes` encodes them as CDR bytes for ``publish(bytes)``.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from jointfit_core.hinge_from_sums import PoseSumsAxis
from jointfit_core.joint_angles import cardan_xyz, hinge_angle, hinge_angle_sd
from jointfit_core.urdf import joint_state_names

from .inputs import Routed
from .raw import _cdr_header, _pad

__all__ = ["FrameAngles", "JointStates", "joint_state_bytes", "VELOCITY_MAX_GAP_S"]

FloatArray = NDArray[np.float64]

#: A joint's velocity is NaN when its previous angle is older than this (s): an occlusion, not a difference.
VELOCITY_MAX_GAP_S = 0.1


@dataclass(frozen=True)
class FrameAngles:
    """One frame's joint angles.

    Attributes
    ----------
    names : list of str
        ``<joint>`` (hinge) and ``<joint>_x, _y, _z`` (ball), joints in the node's order,
        only those with an angle in this frame.
    position : ndarray, shape (K,)
        Angles (rad).
    velocity : ndarray, shape (K,)
        Backward differences over the stamps (rad/s); NaN without a previous angle within
        :data:`VELOCITY_MAX_GAP_S`.
    sd : ndarray, shape (K,)
        Hinges: the angle's sd (rad) from the axis covariance and this frame's pose noise
        (:func:`~jointfit_core.joint_angles.hinge_angle_sd`); NaN for ball angles.
    """

    names: list[str]
    position: FloatArray
    velocity: FloatArray
    sd: FloatArray


class JointStates:
    """Joint angles per frame from the joints' outputs, with velocities from the previous frames.

    Parameters
    ----------
    joints : sequence of (str, str)
        ``(name, kind)`` of every joint, in the node's order.
    """

    def __init__(self, joints: Sequence[tuple[str, str]]) -> None:
        self._columns: dict[str, slice] = {}
        names: list[str] = []
        for name, kind in joints:
            cols = joint_state_names(name, kind)
            self._columns[name] = slice(len(names), len(names) + len(cols))
            names += cols
        self.names = names
        self.reset()

    def reset(self) -> None:
        """Forget the previous angles (velocities start afresh)."""
        self._last = np.full(len(self.names), np.nan)
        self._last_t = np.full(len(self.names), -np.inf)

    def frame(self, stamp_ns: int, routed: Sequence[Routed]) -> FrameAngles | None:
        """The angles of the joints in ``routed`` (one frame's outputs); None when none has a relative rotation."""
        hinges = [r for r in routed if r.output.rotation is not None and isinstance(r.runner.estimator.solution, PoseSumsAxis)]
        balls = [r for r in routed if r.output.rotation is not None and r.output.kind == "ball"]
        if not hinges and not balls:
            return None
        n = len(self.names)
        angle = np.full(n, np.nan)
        sd = np.full(n, np.nan)
        if hinges:
            Q = np.stack([r.output.rotation for r in hinges])  # type: ignore[misc]
            sols = [r.runner.estimator.solution for r in hinges]
            a = np.stack([s.direction_parent for s in sols])  # type: ignore[union-attr]
            Ca = np.stack([s.cov_direction_parent for s in sols])  # type: ignore[union-attr]
            CQ = np.stack([r.output.rotation_cov for r in hinges])  # type: ignore[misc]
            cols = [self._columns[r.runner.cfg.name].start for r in hinges]
            angle[cols] = hinge_angle(Q, a)
            sd[cols] = hinge_angle_sd(Q, a, Ca, CQ)
        if balls:
            Q = np.stack([r.output.rotation for r in balls])  # type: ignore[misc]
            cols_b = np.concatenate([np.arange(3) + self._columns[r.runner.cfg.name].start for r in balls])
            angle[cols_b] = cardan_xyz(Q).ravel()
        have = ~np.isnan(angle)
        t = stamp_ns * 1e-9
        dt = t - self._last_t
        step = (angle - self._last + math.pi) % (2.0 * math.pi) - math.pi
        ok = have & (dt > 0.0) & (dt <= VELOCITY_MAX_GAP_S) & ~np.isnan(self._last)
        velocity = np.where(ok, step / np.where(ok, dt, 1.0), np.nan)
        self._last = np.where(have, angle, self._last)
        self._last_t = np.where(have, t, self._last_t)
        idx = np.flatnonzero(have)
        return FrameAngles([self.names[i] for i in idx], angle[idx], velocity[idx], sd[idx])


def joint_state_bytes(stamp_ns: int, frame_id: str, angles: FrameAngles) -> bytes:
    """CDR bytes (little-endian) of a ``sensor_msgs/JointState`` with ``angles`` (effort empty).

    Checked against rclpy's serializer in the tests.
    """
    out = _cdr_header(stamp_ns, frame_id, "<")
    _pad(out, 4)
    out += struct.pack("<I", len(angles.names))
    for name in angles.names:
        _pad(out, 4)
        raw = name.encode("utf-8") + b"\x00"
        out += struct.pack("<I", len(raw)) + raw
    for values in (angles.position, angles.velocity):
        _pad(out, 4)
        out += struct.pack("<I", values.size)
        if values.size:
            _pad(out, 8)
            out += np.asarray(values, dtype="<f8").tobytes()
    _pad(out, 4)
    out += struct.pack("<I", 0)
    return bytes(out)
