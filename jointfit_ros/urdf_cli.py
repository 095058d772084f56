"""``jointfit urdf CALIBRATION... > subject.urdf``: a URDF of saved calibrations (:mod:`jointfit_core.urdf`).

A calibration is a joint's file (lengths taken as metres) or a node's (:mod:`jointfit_core.node_calibration`:
every joint in it, lengths in its ``units``); one the node would not load is refused.

Exit status: 0 written to stdout, 1 a file cannot be read or the calibrations do
not make one tree (one line on stderr), 2 usage.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import Any

from jointfit_core.calibration import load_calibration
from jointfit_core.errors import InputError, JointfitError
from jointfit_core.estimator import OnlineJoint
from jointfit_core.io import METRES_PER_UNIT
from jointfit_core.node_calibration import NODE_CALIBRATION_FORMAT, check_node_calibration
from jointfit_core.urdf import urdf_from_calibrations

USAGE = "usage: jointfit urdf [--name ROBOT] CALIBRATION.yaml... > subject.urdf"


def _check_usable(calibration: dict[str, Any], source: str) -> None:
    """Refuse a calibration the node would not load: a newer version, malformed, or not identifiable.

    Raises
    ------
    InputError
        Naming ``source`` and why.
    """
    try:
        estimator = OnlineJoint.from_dict(calibration)
    except JointfitError as exc:
        raise InputError(f"{source}: {exc}") from None
    sol = estimator.solution
    if sol is None or not sol.identifiable:
        why = sol.reason if sol is not None else "no estimate"
        raise InputError(f"{source}: its estimate is not identifiable ({why}); a URDF of it would be arbitrary")


def _metres_per_unit(units: dict[str, str]) -> float:
    """Metres per length unit of the node files read (1 without any: per-joint files are taken as metres).

    Raises
    ------
    InputError
        A unit that is not m, cm or mm, or node files in different units.
    """
    bad = {path: unit for path, unit in units.items() if unit not in METRES_PER_UNIT}
    if bad:
        raise InputError(f"node calibration units must be m, cm or mm (URDF lengths are metres), got {bad}")
    if len(set(units.values())) > 1:
        raise InputError(f"the node calibration files are in different units: {units}")
    return METRES_PER_UNIT[next(iter(units.values()))] if units else 1.0


def urdf_main(argv: Sequence[str]) -> int:
    """Run ``jointfit urdf``; returns the exit status."""
    args = list(argv)
    if not args or args[0] in ("-h", "--help"):
        print(USAGE)
        return 0 if args else 2
    name = "subject"
    if args[0] == "--name":
        if len(args) < 3:
            print(f"jointfit urdf: error: --name needs a value and calibration files; {USAGE}", file=sys.stderr)
            return 2
        name, args = args[1], args[2:]
    try:
        calibrations = []
        units: dict[str, str] = {}  # node files' declared units (per-joint files declare none: metres)
        for path in args:
            data = load_calibration(path)
            if data.get("format") == NODE_CALIBRATION_FORMAT:  # a node's file: every joint in it
                doc = check_node_calibration(data, f"node calibration {path}")
                units[path] = doc["units"]
                entries = [(f"{path} (joint {j})", e["calibration"]) for j, e in doc["joints"].items()]
            else:
                entries = [(path, data)]
            for source, calibration in entries:
                _check_usable(calibration, source)
                calibrations.append(calibration)
        text = urdf_from_calibrations(calibrations, robot_name=name, metres_per_unit=_metres_per_unit(units))
    except (JointfitError, OSError, ValueError) as exc:
        print(f"jointfit urdf: error: {exc}", file=sys.stderr)
        return 1
    sys.stdout.write(text)
    return 0
