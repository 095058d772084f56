"""What ``jointfit fit`` says in anatomical terms: landmark frames and the range of motion, as plain types.

ROS-free. :func:`anatomical_summary` expresses a joint's final estimate in
the frames its ``<joint>.anatomical.*`` landmarks define
(:mod:`jointfit_core.anatomy`); :func:`rom_summary` gives its range of
motion (:mod:`jointfit_core.rom`). Both read the
:class:`~jointfit_ros.report.SegmentGeometry` of the kept marker frames.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from jointfit_core.anatomy import axis_against_epicondyles, hip_in_pelvis
from jointfit_core.errors import InputError
from jointfit_core.hinge_from_sums import PoseSumsAxis
from jointfit_core.rom import RangeOfMotion, range_of_motion
from jointfit_core.segments import PoseSumsCentre

from .params import JointConfig

if TYPE_CHECKING:
    from .geometry import SegmentGeometry

__all__ = ["MM_PER_UNIT", "PELVIS_FRAME_TEXT", "anatomical_summary", "joint_rom", "rom_summary"]

#: Millimetres per length unit, for the results quoted in mm.
MM_PER_UNIT = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
PELVIS_FRAME_TEXT = "ISB pelvis axes (Wu et al. 2002), origin mid-ASIS: x anterior, y superior, z right"


def _r(values: Any, digits: int = 2) -> Any:
    return np.round(np.asarray(values, dtype=np.float64), digits).tolist()


#: A landmark moves with its segment when its rms scatter in the segment's frame is at most this many times
#: the rms pose-fit residual of the segment's own markers, or :data:`LANDMARK_SPREAD_MIN_MM` (skin over a
#: bony landmark slides 5-15 mm, Leardini et al. 2005); more, and it is on another segment or mislabelled:
#: measured, the shank marker RATT taken as an epicondyle scattered 46 mm, a thigh marker as an ASIS 94 mm.
LANDMARK_SPREAD_FACTOR = 4.0
#: See :data:`LANDMARK_SPREAD_FACTOR` (mm).
LANDMARK_SPREAD_MIN_MM = 25.0
#: A functional hip centre farther than this (mm) from both regressions' (plus 3 sd along that direction) is
#: not a hip in that pelvis frame: functional and regression centres differ by ~10-30 mm (Harrington et al.
#: 2007), while swapped ASIS (or PSIS) labels mirror the frame (measured: 152 and 161 mm).
REGRESSION_PLAUSIBLE_MM = 60.0


def _spread(geo: SegmentGeometry, markers: dict[str, str], scale: float) -> dict[str, float]:
    return {m: round(geo.landmarks_parent[m][1] * scale, 2) for m in markers.values()}


def _landmarks(
    cfg: JointConfig, group: str, geo: SegmentGeometry, mm_per_unit: float
) -> tuple[dict[str, str] | None, dict[str, Any] | None]:
    """A landmark group's markers by role, or None (not configured); and the error when some were never seen
    or do not move with the parent segment (:data:`LANDMARK_SPREAD_FACTOR`)."""
    roles = cfg.landmarks(group)
    if roles is None:
        return None, None
    missing = [m for m in roles.values() if m not in geo.landmarks_parent]
    if missing:
        return roles, {"error": f"landmarks {missing} are never visible in a frame where the parent is posed"}
    residual = geo.residual_parent[np.isfinite(geo.residual_parent)]
    own = float(np.sqrt(np.mean(residual**2))) if residual.size else 0.0
    limit = max(LANDMARK_SPREAD_FACTOR * own, LANDMARK_SPREAD_MIN_MM / mm_per_unit)
    loose = {m: geo.landmarks_parent[m][1] for m in roles.values() if geo.landmarks_parent[m][1] > limit}
    if loose:
        moved = ", ".join(f"{m} {v * mm_per_unit:.0f} mm" for m, v in loose.items())
        return roles, {
            "error": f"landmarks that do not move with the parent segment (rms scatter in its frame: {moved}; its own "
            f"markers' pose-fit residual {own * mm_per_unit:.1f} mm rms): on another segment or mislabelled, so "
            "no anatomical result is made",
            "landmark_spread": _spread(geo, roles, mm_per_unit),
        }
    return roles, None


def _pelvis(cfg: JointConfig, sol: PoseSumsCentre, geo: SegmentGeometry, unit: str) -> dict[str, Any] | None:
    scale = MM_PER_UNIT.get(unit)
    shown = "mm" if scale is not None else unit
    s = scale or 1.0
    roles, error = _landmarks(cfg, "pelvis", geo, s)
    if roles is None or error is not None:
        return error
    thigh = np.nanmedian(geo.child_in_parent.reshape(-1, 3), axis=0)
    ra, la, rp, lp = (geo.landmarks_parent[roles[r]][0] for r in ("rasis", "lasis", "rpsis", "lpsis"))
    hip = hip_in_pelvis(sol.centre_parent, sol.cov_parent, ra, la, rp, lp, thigh_point=thigh, mm_per_unit=s)
    out: dict[str, Any] = {
        "frame": PELVIS_FRAME_TEXT,
        "unit": shown,
        "side": hip.side,
        "centre": _r(hip.centre * s, 1),
        "sd": _r(np.sqrt(np.clip(np.diag(hip.cov), 0.0, None)) * s, 2),
        "percent_width": _r(hip.percent_width, 1),
        "width": round(hip.width * s, 1),
        "depth": round(hip.depth * s, 1),
        "regressions": {},
        "landmark_spread": _spread(geo, roles, s),
    }
    if scale is None:
        out["note"] = f"unit {unit!r} unknown: the regressions' offsets (mm) are taken as {unit}"
    for name, c in hip.regressions.items():
        out["regressions"][name] = {"centre": _r(c * s, 1), "distance": round(hip.distance_to(name) * s, 1)}
    nearest = min(hip.regressions, key=hip.distance_to, default=None)
    if nearest is not None:
        gap = hip.regressions[nearest] - hip.centre
        dist = float(np.linalg.norm(gap))
        sd_along = math.sqrt(max(float(gap @ hip.cov @ gap), 0.0)) / dist if dist > 0.0 else 0.0
        if dist * s > REGRESSION_PLAUSIBLE_MM + 3.0 * sd_along * s:
            out["warning"] = (
                f"the centre is {dist * s:.0f} mm from the nearest regression's ({nearest.replace('_', ' ')}; they "
                f"usually agree within 10-30 mm): check the pelvis landmarks' labels (ASIS or PSIS swapped?) and "
                "that the joint is the hip of this pelvis"
            )
    return out


def _epicondyles(cfg: JointConfig, sol: PoseSumsAxis, geo: SegmentGeometry, unit: str) -> dict[str, Any] | None:
    scale = MM_PER_UNIT.get(unit)
    s = scale or 1.0
    roles, error = _landmarks(cfg, "epicondyles", geo, s)
    if roles is None or error is not None:
        return error
    knee = axis_against_epicondyles(
        sol.point_parent,
        sol.direction_parent,
        sol.cov_direction_parent,
        geo.landmarks_parent[roles["lateral_epicondyle"]][0],
        geo.landmarks_parent[roles["medial_epicondyle"]][0],
    )
    return {
        "unit": "mm" if scale is not None else unit,
        "angle_to_epicondyle_line_deg": round(knee.angle_deg, 2),
        "direction_sd_deg": round(knee.angle_sd_deg, 2),
        "distance_to_epicondyle_midpoint": round(knee.distance * s, 1),
        "epicondyle_width": round(knee.epicondyle_width * s, 1),
        "landmark_spread": _spread(geo, roles, s),
    }


def anatomical_summary(
    cfg: JointConfig, sol: PoseSumsCentre | PoseSumsAxis | None, geo: SegmentGeometry | None, unit: str
) -> dict[str, Any]:
    """The ``anatomical`` entry of a joint's summary (empty without landmarks).

    Parameters
    ----------
    cfg : JointConfig
        Its ``anatomical`` landmarks.
    sol : PoseSumsCentre or PoseSumsAxis or None
        The final estimate (parent frame).
    geo : SegmentGeometry or None
        Of the kept frames (the landmarks' positions in the parent frame).
    unit : str
        The input's length unit; results are in mm when it is m, cm or mm.

    Returns
    -------
    dict
        ``pelvis`` (ball joints): ``centre`` and ``sd`` in the ISB pelvis axes, ``percent_width`` (x, y and
        lateral z as % of the inter-ASIS width), ``width``, ``depth``, ``side``, ``regressions`` (Bell 1990,
        Harrington 2007: their centre and its distance from the estimate), ``landmark_spread`` (rms scatter
        of each landmark in the parent frame). ``epicondyles`` (hinges): the axis's angle to the epicondyle
        line, the direction sd, the distance of the epicondyles' midpoint from the axis, their width. Each
        is ``{"error": ...}`` when it cannot be made.
    """
    if not cfg.anatomical:
        return {}
    if sol is None:
        return {"error": "no estimate"}
    if geo is None:
        return {"error": "needs the marker frames (not made for pose inputs, chain joints or --no-report)"}
    out: dict[str, Any] = {}
    try:
        if isinstance(sol, PoseSumsCentre):
            part = _pelvis(cfg, sol, geo, unit)
            if part is not None:
                out["pelvis"] = part
        else:
            part = _epicondyles(cfg, sol, geo, unit)
            if part is not None:
                out["epicondyles"] = part
    except InputError as exc:
        out["error"] = str(exc)
    return out


def joint_rom(sol: PoseSumsCentre | PoseSumsAxis | None, geo: SegmentGeometry | None) -> RangeOfMotion | None:
    """The range of motion of a joint's kept frames (None without them or with fewer than 2 posed frames)."""
    if geo is None or geo.R_parent_child is None:
        return None
    axis = sol.direction_parent if isinstance(sol, PoseSumsAxis) else None
    try:
        return range_of_motion(geo.R_parent_child, axis)
    except InputError:
        return None


def rom_summary(rom: RangeOfMotion | None) -> dict[str, Any]:
    """The ``range_of_motion`` entry of a joint's summary (empty without one)."""
    if rom is None:
        return {}
    out: dict[str, Any] = {
        "frames": rom.n_frames,
        "principal_ranges_deg": _r(rom.ranges_deg, 1),
        "principal_axes_parent": _r(rom.axes, 3),
    }
    if rom.flexion_range_deg is not None:
        out["flexion_range_deg"] = round(rom.flexion_range_deg, 1)
    return out
