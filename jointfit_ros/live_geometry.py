"""The live node's anatomical results and range of motion: a sample of recent frames in the parent's template frame.

ROS-free. ``jointfit fit`` reads a joint's anatomy and range of motion from
every kept frame (:func:`jointfit_ros.report.segment_geometry`); the live
node cannot keep every frame, so :class:`LiveGeometry` keeps one frame per
:attr:`LiveGeometry.period` (10 Hz) of the last :attr:`LiveGeometry.size`
(a minute), posed with the estimator's own templates, and
:meth:`LiveGeometry.values` turns it into ``/diagnostics`` values with the
same functions as the summary (:mod:`jointfit_ros.anatomy_report`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from jointfit_core.errors import InputError
from jointfit_core.hinge_from_sums import PoseSumsAxis
from jointfit_core.pose import poses_from_markers
from jointfit_core.segments import PoseSumsCentre

from .anatomy_report import anatomical_summary, joint_rom
from .geometry import SegmentGeometry, landmark_stat
from .params import JointConfig

__all__ = ["LiveGeometry"]

FloatArray = NDArray[np.float64]
Templates = tuple[FloatArray | None, FloatArray | None]
FramePoses = tuple[FloatArray, FloatArray, tuple[bool, bool]] | None

#: Samples needed before anything is said (a second at the sampling rate).
MIN_SAMPLES = 10


class LiveGeometry:
    """Recent frames of a marker joint, sampled, in the parent template frame.

    Parameters
    ----------
    cfg : JointConfig
        The joint (its ``anatomical`` landmarks).
    landmark_rows : dict of str to int
        Each landmark marker's row in the node's marker frames.
    parent_rows, child_rows : ndarray of int
        The segments' rows in the node's marker frames.
    period : float
        Seconds between samples (at most one frame per period is kept).
    size : int
        Samples kept (the oldest are overwritten).
    """

    def __init__(
        self,
        cfg: JointConfig,
        landmark_rows: dict[str, int],
        parent_rows: NDArray[np.intp],
        child_rows: NDArray[np.intp],
        period: float = 0.1,
        size: int = 600,
    ) -> None:
        self.cfg = cfg
        self.period = period
        self.size = size
        self._names = tuple(landmark_rows)
        self._landmark_rows = np.array([landmark_rows[m] for m in self._names], dtype=np.intp)
        self._parent_rows = parent_rows
        self._child_rows = child_rows
        self._landmarks = np.full((size, len(self._names), 3), np.nan)
        self._child_in_parent = np.full((size, len(child_rows), 3), np.nan)
        self._R_parent_child = np.full((size, 3, 3), np.nan)
        self._templates: Templates = (None, None)
        self.clear()

    def clear(self) -> None:
        """Forget every sample (the templates changed: the old samples are in another frame)."""
        self.count = 0
        self._head = 0
        self._last_slot = -np.inf

    def offer_one(self, stamp: float, frame: FloatArray, templates: Templates, poses: FramePoses = None) -> None:
        """Sample one frame (P, 3) of ``stamp`` s when its period has no sample yet (the per-frame path).

        ``poses``: the estimator's poses of this frame
        (:attr:`OnlineJoint.frame_poses <jointfit_core.estimator.OnlineJoint.frame_poses>`, after the
        gate), used instead of posing the frame again; None: posed here.
        """
        if math.floor(stamp / self.period) <= self._last_slot:
            return
        if poses is None:
            self.offer(np.array([stamp]), frame[None], templates)
            return
        if not self._same_templates(templates) or not poses[2][0]:
            return
        self._last_slot = float(math.floor(stamp / self.period))
        R, d, posed = poses
        R_c = R[1:2] if posed[1] else np.full((1, 3, 3), np.nan)
        self._store(frame[None], R[0:1], d[0:1], R_c)

    def _same_templates(self, templates: Templates) -> bool:
        """Whether both templates exist; a new one clears the samples (they are in the old frame)."""
        tp, tc = templates
        if tp is None or tc is None:
            return False
        if tp is not self._templates[0] or tc is not self._templates[1]:
            self.clear()
            self._templates = (tp, tc)
        return True

    def offer(self, stamps: FloatArray, frames: FloatArray, templates: Templates) -> None:
        """Sample frames (K, P, 3) of stamps (K,) s, oldest first: one per period, posed with ``templates``.

        Frames that cannot be posed are kept as NaN (left out of the
        medians); nothing is sampled while a template is missing.
        """
        if not self._same_templates(templates):
            return
        tp, tc = self._templates
        assert tp is not None and tc is not None
        slots = np.floor(np.asarray(stamps, dtype=np.float64) / self.period)
        uniq, first = np.unique(slots, return_index=True)
        pick = first[uniq > self._last_slot][-self.size :]
        if not pick.size:
            return
        self._last_slot = float(slots[pick[-1]])
        picked = frames[pick]
        try:
            with np.errstate(invalid="ignore"):
                pp = poses_from_markers(picked[:, self._parent_rows], tp)
                pc = poses_from_markers(picked[:, self._child_rows], tc)
        except InputError:
            return
        self._store(picked, pp.R_world_local, pp.d_world_local, pc.R_world_local)

    def _store(self, picked: FloatArray, R_p: FloatArray, d_p: FloatArray, R_c: FloatArray) -> None:
        """Keep frames (K, P, 3) posed ``R_p`` (K, 3, 3), ``d_p`` (K, 3) (parent) and ``R_c`` (child)."""
        k = picked.shape[0]
        rel = d_p[:, None, :]
        idx = (self._head + np.arange(k)) % self.size
        self._landmarks[idx] = (picked[:, self._landmark_rows] - rel) @ R_p  # R_p^T (y - d_p)
        self._child_in_parent[idx] = (picked[:, self._child_rows] - rel) @ R_p
        self._R_parent_child[idx] = np.swapaxes(R_p, 1, 2) @ R_c
        self._head = int((self._head + k) % self.size)
        self.count = min(self.count + k, self.size)

    def geometry(self) -> SegmentGeometry | None:
        """The samples as the summary's geometry (None with fewer than :data:`MIN_SAMPLES`)."""
        if self.count < MIN_SAMPLES:
            return None
        n = self.count
        landmarks: dict[str, tuple[FloatArray, float, int]] = {}
        for k, name in enumerate(self._names):
            stat = landmark_stat(self._landmarks[:n, k])
            if stat is not None:
                landmarks[name] = stat
        empty = np.empty((n, 0))
        return SegmentGeometry(
            np.arange(n, dtype=np.float64) * self.period, empty, empty, self._child_in_parent[:n], None, self._R_parent_child[:n], landmarks
        )

    def values(self, sol: PoseSumsCentre | PoseSumsAxis, unit: str) -> dict[str, Any]:
        """``/diagnostics`` values: the estimate in the landmarks' frames and the range of motion, with units.

        Empty until :data:`MIN_SAMPLES` samples exist. Keys: ``hip centre in ISB pelvis (mm)``, its sd,
        ``% of inter-ASIS width``, each regression's centre and distance (ball joints with pelvis
        landmarks); ``axis to epicondyle line (deg)``, ``epicondyle midpoint to axis (mm)`` (hinges with
        epicondyles); ``range of motion (deg)`` (principal ranges) and, for hinges, ``flexion range (deg)``.
        A landmark result that cannot be made gives ``anatomical: <why>``.
        """
        geo = self.geometry()
        if geo is None:
            return {}
        out: dict[str, Any] = {}
        anat = anatomical_summary(self.cfg, sol, geo, unit) if self.cfg.anatomical else {}
        pelvis, knee = anat.get("pelvis"), anat.get("epicondyles")
        for part in (anat, pelvis or {}, knee or {}):
            if "error" in part:
                out["anatomical"] = part["error"]
            if "warning" in part:
                out["anatomical warning"] = part["warning"]
        if pelvis and "error" not in pelvis:
            u = pelvis["unit"]
            out[f"centre in ISB pelvis ({u}, {pelvis['side']} side)"] = pelvis["centre"]
            out[f"centre sd in ISB pelvis ({u})"] = pelvis["sd"]
            out["centre (% of inter-ASIS width)"] = pelvis["percent_width"]
            out[f"inter-ASIS width ({u})"] = pelvis["width"]
            for name, reg in pelvis["regressions"].items():
                out[f"{name} regression ({u})"] = reg["centre"]
                out[f"distance to {name} regression ({u})"] = reg["distance"]
        if knee and "error" not in knee:
            u = knee["unit"]
            out["axis to epicondyle line (deg)"] = knee["angle_to_epicondyle_line_deg"]
            out[f"epicondyle midpoint to axis ({u})"] = knee["distance_to_epicondyle_midpoint"]
            out[f"epicondyle width ({u})"] = knee["epicondyle_width"]
        rom = joint_rom(sol, geo)
        if rom is not None:
            out[f"range of motion (deg, last {geo.t.shape[0] * self.period:.0f} s)"] = np.round(rom.ranges_deg, 1).tolist()
            if rom.flexion_range_deg is not None:
                out["flexion range (deg)"] = round(rom.flexion_range_deg, 1)
        return out
