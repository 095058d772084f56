"""Offline demo on the real fixtures: hip centre, knee axis, and an elbow that is no hinge.

Run with ``make demo-offline`` (``make demo`` runs it after the live ROS demo),
or ``python -m jointfit_core.demo [DATA_DIR]``. It reads the C3D recordings
shipped in ``test/data`` and prints each estimate with its uncertainty and
verdict, next to what the literature or anatomy says.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from .frames import pelvis_frame, to_frame
from .io import read_c3d
from .segments import fit_axis_two_segments, fit_centre_two_segments

__all__ = ["main"]

DEFAULT_DATA = Path(__file__).resolve().parents[1] / "test" / "data"


def _sd(cov: np.ndarray) -> str:
    return "(" + ", ".join(f"{s:.1f}" for s in np.sqrt(np.clip(np.diag(cov), 0, None))) + ")"


def _vec(v: np.ndarray, digits: int = 1) -> str:
    return "(" + ", ".join(f"{x:.{digits}f}" for x in v) + ")"


def hip(data_dir: Path) -> None:
    """Right hip centre from pelvis + thigh cluster (ball joint, both moving)."""
    data = read_c3d(data_dir / "biobuddy" / "right_hip.c3d")
    pelvis = data.select(["RASIS", "LASIS", "RPSIS", "LPSIS"])
    thigh = data.select(["RTHI1", "RTHI2", "RTHI3"])
    R_world_pelvis, origin = pelvis_frame(*(pelvis[:, i] for i in range(4)))
    print(f"Right hip: {data.n_frames} frames at {data.rate:g} Hz ({data.units}), pelvis x4 + thigh x3 markers")
    # (method="sphere" has no soft-tissue term: it refuses skin markers rather than understate their error)
    for method, weighted in (("poses", True), ("poses", False)):
        fit = fit_centre_two_segments(pelvis, thigh, method=method, weighted=weighted)
        centre_pelvis = np.nanmean(to_frame(fit.centre_world, R_world_pelvis, origin), axis=0)
        label = f"{method}{' (weighted)' if method == 'poses' and weighted else ''}"
        print(
            f"  {label:18s} centre in pelvis frame {_vec(centre_pelvis)} {data.units}, "
            f"sd {_sd(fit.cov_parent)}, joint residual rms {fit.rms:.1f}, "
            f"{'identifiable' if fit.identifiable else 'NOT identifiable: ' + fit.reason}"
        )
    print("  published methods on this trial: x -57..-63, y -72..-98, z -76..-95 mm (mid-ASIS origin, x anterior)")


def knee(data_dir: Path) -> None:
    """Right knee axis from thigh + shank clusters (hinge)."""
    data = read_c3d(data_dir / "biobuddy" / "right_knee.c3d")
    fit = fit_axis_two_segments(data.select(["RTHI1", "RTHI2", "RTHI3"]), data.select(["RLEG1", "RLEG2", "RLEG3"]))
    epi = data.select(["RLFE", "RMFE"])
    line = epi[:, 1] - epi[:, 0]
    line /= np.linalg.norm(line, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip(np.abs(np.einsum("ni,ni->n", fit.direction_world, line)), 0, 1)))
    mid = epi.mean(axis=1) - fit.point_world
    off = mid - np.einsum("ni,ni->n", mid, fit.direction_world)[:, None] * fit.direction_world
    sd_deg = np.degrees(np.sqrt(max(np.linalg.eigvalsh(fit.cov_direction_parent)[-1], 0.0)))
    print(f"Right knee: {data.n_frames} frames, thigh x3 + shank x3 markers")
    print(
        f"  axis (thigh frame) {_vec(fit.direction_parent, 3)} sd {sd_deg:.2f} deg; "
        f"{np.nanmean(angle):.1f} deg from the epicondyle line, {np.nanmean(np.linalg.norm(off, axis=1)):.1f} "
        f"{data.units} from their midpoint; residual rms {fit.rms:.1f} {data.units}; "
        f"{'identifiable' if fit.identifiable else 'NOT identifiable: ' + fit.reason}"
    )


def elbow(data_dir: Path) -> None:
    """Right elbow in wheelchair racing: flexion mixed with pronation, not a hinge."""
    data = read_c3d(data_dir / "kineticstoolkit" / "kinematics_racing_full.c3d")
    arm = data.select(["ArmR1", "ArmR2", "ArmR3"])
    forearm = data.select(["ForearmR1", "ForearmR2", "ForearmR3"])
    fit = fit_axis_two_segments(arm, forearm)
    print(f"Right elbow (racing): {data.n_frames} frames ({data.units}), arm x3 + forearm x3 markers")
    print(
        f"  hinge fit residual rms {fit.rms * 1000:.1f} mm; "
        f"{'identifiable' if fit.identifiable else 'NOT identifiable: ' + fit.reason}"
    )


def main(argv: list[str] | None = None) -> int:
    """Run the demo; ``argv[0]`` may name the data folder (default ``test/data``)."""
    args = sys.argv[1:] if argv is None else argv
    data_dir = Path(args[0]) if args else DEFAULT_DATA
    if not (data_dir / "biobuddy" / "right_hip.c3d").is_file():
        print(f"demo: no fixtures under {data_dir} (expected biobuddy/right_hip.c3d)", file=sys.stderr)
        return 2
    np.set_printoptions(precision=2, suppress=True)
    hip(data_dir)
    knee(data_dir)
    elbow(data_dir)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
