"""The ``--skeleton lower|full`` source of :mod:`jointfit_ros.fake_mocap` (no rclpy).

Wraps :mod:`jointfit_core.skeleton_truth` (metres) in the fake stream's interface,
which works in millimetres like its two-rig source: marker names, one noisy frame
at a motion time, the truth at that time, and the truth lines logged at start.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from jointfit_core.skeleton_truth import make_skeleton

__all__ = ["SkeletonSource"]

FloatArray = NDArray[np.float64]
_MM = 1000.0


class SkeletonSource:
    """A synthetic skeleton as a marker source, in millimetres.

    Parameters
    ----------
    name : {"lower", "full"}
        See :func:`~jointfit_core.skeleton_truth.make_skeleton`.
    seed : int
        Seed of the motion phases.
    cycle_s : float
        Motion time scale (s): every joint goes through its range within it.
    extra : ndarray, shape (K, 3)
        Static extra markers (mm) appended to every frame.

    Attributes
    ----------
    skeleton : Skeleton
    kinds : dict of str to str
        Joint name -> ``ball`` or ``hinge``, in the skeleton's order.
    """

    def __init__(self, name: str, seed: int, cycle_s: float, extra: FloatArray) -> None:
        self.skeleton = make_skeleton(name, cycle_s=cycle_s, seed=seed)
        self.extra = np.asarray(extra, dtype=np.float64).reshape(-1, 3)
        self.kinds = {j: self.skeleton.joint_segment(j).kind for j in self.skeleton.joints}

    def marker_names(self) -> list[str]:
        """The skeleton's markers then ``EXTRA1..K``."""
        return self.skeleton.marker_names() + [f"EXTRA{i}" for i in range(1, len(self.extra) + 1)]

    def frame(self, t: float, rng: np.random.Generator, noise: float, occlusion: float) -> FloatArray:
        """One noisy frame (P, 3) in mm at motion time ``t`` (s); ``noise`` sd per coordinate in mm."""
        if noise < 0.0 or not 0.0 <= occlusion <= 1.0:
            raise ValueError(
                f"noise: expected >= 0 mm, got {noise}; occlusion: expected in [0, 1], got {occlusion}"
            )
        frame = np.concatenate([self.skeleton.markers_at([t])[0] * _MM, self.extra])
        if noise > 0.0:
            frame += rng.normal(0.0, noise, frame.shape)
        if occlusion > 0.0:
            frame[rng.random(frame.shape[0]) < occlusion] = np.nan
        return frame

    def truth(self, t: float) -> tuple[dict[str, FloatArray], dict[str, FloatArray]]:
        """World joint points (mm) and unit hinge directions at motion time ``t`` (s), by joint."""
        world = self.skeleton.joints_world_at([t])
        centres = {j: point[0] * _MM for j, (point, _) in world.items()}
        axes = {j: direction[0] for j, (_, direction) in world.items() if direction is not None}
        return centres, axes

    def truth_lines(self, scale: float, unit: str) -> list[str]:
        """One log line per joint: the truth in the parent's template frame (node convention, t_ref = 0) and the world at t = 0.

        ``scale`` converts mm to the published unit ``unit``.
        """
        centres, axes = self.truth(0.0)
        lines = []
        for j, tr in self.skeleton.joints_local(0.0).items():
            point = np.round(tr.point * _MM * scale, 6).tolist()
            what = "centre" if tr.direction is None else "axis point (nearest the parent centroid)"
            text = (
                f"truth {j} ({tr.kind}, {tr.parent} -> {tr.child}) in the parent's template frame (origin at its "
                f"markers' centroid, world axes at motion time 0): {what} {point} {unit}"
            )
            if tr.direction is not None:
                text += f", direction {np.round(tr.direction, 6).tolist()}"
            text += f"; world at t = 0: {np.round(centres[j] * scale, 6).tolist()} {unit}"
            if j in axes:
                text += f", direction {np.round(axes[j], 6).tolist()}"
            lines.append(text)
        return lines
