"""``jointfit urdf CALIBRATION... > subject.urdf``: a URDF of saved calibrations (:mod:`jointfit_core.urdf`).

A calibration is a joint's file or a node's (:mod:`jointfit_core.node_calibration`: every joint in it).

Exit status: 0 written to stdout, 1 a file cannot be read or the calibrations do
not make one tree (one line on stderr), 2 usage.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from jointfit_core.calibration import load_calibration
from jointfit_core.errors import JointfitError
from jointfit_core.node_calibration import NODE_CALIBRATION_FORMAT, check_node_calibration
from jointfit_core.urdf import urdf_from_calibrations

USAGE = "usage: jointfit urdf [--name ROBOT] CALIBRATION.yaml... > subject.urdf"


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
        for path in args:
            data = load_calibration(path)
            if data.get("format") == NODE_CALIBRATION_FORMAT:  # a node's file: every joint in it
                doc = check_node_calibration(data, f"node calibration {path}")
                calibrations += [entry["calibration"] for entry in doc["joints"].values()]
            else:
                calibrations.append(data)
        text = urdf_from_calibrations(calibrations, robot_name=name)
    except (JointfitError, OSError, ValueError) as exc:
        print(f"jointfit urdf: error: {exc}", file=sys.stderr)
        return 1
    sys.stdout.write(text)
    return 0
