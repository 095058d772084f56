"""Labels with a subject prefix (Vicon Nexus's ``Subject:RTHI1``) are found by their marker names.

Real recordings from other labs: a trial with a labelled subject has every label prefixed. A
configuration names the markers (``RTHI1``); before (2026-12-06) every such file was refused with
"markers not found". Known truth: the real hip recording, fitted with and without the prefix.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from jointfit_core.errors import InputError
from jointfit_core.io import read_c3d, write_trc
from jointfit_ros.cli import fit_main

ROOT = Path(__file__).resolve().parents[1]
HIP = ROOT / "test" / "data" / "biobuddy" / "right_hip.c3d"
CONFIG = ROOT / "config" / "offline_right_hip.yaml"


def test_select_takes_the_one_label_with_the_name_after_its_prefix() -> None:
    data = read_c3d(HIP)
    names = ["RTHI1", "RASIS", "LPSIS"]
    prefixed = dataclasses.replace(data, labels=tuple(f"Bob:{label}" for label in data.labels))
    np.testing.assert_array_equal(prefixed.select(names), data.select(names))
    np.testing.assert_array_equal(prefixed.select(["Bob:RTHI1"]), data.select(["RTHI1"]))
    two = dataclasses.replace(data, labels=tuple(f"{'Ann' if k % 2 else 'Bob'}:X" for k in range(len(data.labels))))
    with pytest.raises(InputError, match="markers not found: \\['X'\\]"):
        two.select(["X"])  # two subjects' X: which one is not guessed


def _fit(tmp_path: Path, name: str, trc: Path, drop_marker_names: bool) -> dict[str, object]:
    values = yaml.safe_load(CONFIG.read_text())
    params = values["jointfit"]["ros__parameters"]
    params["right_hip"]["calibration_file"] = ""
    if drop_marker_names:
        del params["marker_names"]
    config = tmp_path / f"{name}.yaml"
    config.write_text(yaml.safe_dump(values))
    out = tmp_path / name
    assert fit_main([str(trc), "--config", str(config), "--out", str(out), "--no-report"]) == 0
    summary: dict[str, object] = json.loads((out / "summary.json").read_text())["joints"][0]
    return summary


@pytest.mark.parametrize("drop_marker_names", [False, True])
def test_a_prefixed_recording_fits_as_the_plain_one(tmp_path: Path, drop_marker_names: bool) -> None:
    data = read_c3d(HIP)
    plain, prefixed = tmp_path / "plain.trc", tmp_path / "prefixed.trc"
    write_trc(plain, data)
    write_trc(prefixed, dataclasses.replace(data, labels=tuple(f"Subject01:{label}" for label in data.labels)))
    a = _fit(tmp_path, "a", plain, drop_marker_names)
    b = _fit(tmp_path, "b", prefixed, drop_marker_names)
    assert a["centre_parent"] == b["centre_parent"] and a["sd_parent"] == b["sd_parent"]
