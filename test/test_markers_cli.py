"""`jointfit markers FILE`: labels ready for marker_names, rate, units, frames and each marker's gaps."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from jointfit_core.io import MarkerData, write_trc
from jointfit_ros.markers_cli import marker_gaps, markers_main

ROOT = Path(__file__).resolve().parents[1]


def test_marker_gaps_against_a_loop() -> None:
    rng = np.random.default_rng(1)
    m = rng.normal(size=(300, 5, 3))
    m[rng.random((300, 5)) < 0.2] = np.nan
    m[100:140, 2] = np.nan
    missing, longest = marker_gaps(m)
    for k in range(5):
        gone = np.isnan(m[:, k]).any(axis=1)
        run = best = 0
        for g in gone:
            run = run + 1 if g else 0
            best = max(best, run)
        assert missing[k] == gone.sum() and longest[k] == best
    assert longest[2] >= 40


def test_markers_of_a_trc_and_a_c3d(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    m = np.zeros((50, 2, 3)) + 1.0
    m[10:15, 1] = np.nan
    path = tmp_path / "x.trc"
    write_trc(path, MarkerData(m, ("HEEL", "TOE"), 120.0, "mm"))
    assert markers_main([str(path)]) == 0
    out = capsys.readouterr().out
    assert "50 frames at 120 Hz" in out and "units mm" in out and "marker_names: [HEEL, TOE]" in out
    assert [line.split() for line in out.splitlines()[-2:]] == [["HEEL", "0", "0.0", "0"], ["TOE", "5", "10.0", "5"]]
    pytest.importorskip("ezc3d")
    assert markers_main([str(ROOT / "test/data/kineticstoolkit/kinematics_racing_full.c3d")]) == 0
    assert "units m," in capsys.readouterr().out


def test_markers_entry_point_and_errors(tmp_path: Path) -> None:
    proc = subprocess.run([sys.executable, "-m", "jointfit_ros.cli", "markers", str(tmp_path / "nope.trc")],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1 and proc.stderr.startswith("jointfit markers: error:") and "Traceback" not in proc.stderr


def test_markers_of_a_bag_lists_its_topics(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from bagtools import write_marker_bag

    bag = write_marker_bag(tmp_path / "b", np.zeros((7, 3, 3)), np.arange(7) * 10**7, topic="/mocap/markers")
    assert markers_main([str(bag)]) == 0
    out = capsys.readouterr().out
    assert "/mocap/markers" in out and "geometry_msgs/msg/PoseArray" in out and out.rstrip().endswith("7")


def test_the_marker_names_line_pastes_into_yaml(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The printed ``marker_names: [...]`` reads back as the labels, whatever they are.

    It was the labels joined by commas: ``#C7`` began a comment, ``a, b`` became two names and
    ``yes`` / ``1`` a bool and an int when pasted into the parameter file.
    """
    import yaml

    labels = ("RTHI1", "1", "yes", "#C7", "a, b", "null", "[x]", "C7: top", "*star", "R LEG É")
    path = tmp_path / "odd.trc"
    write_trc(path, MarkerData(np.zeros((2, len(labels), 3)) + 1.0, labels, 100.0, "mm"))
    assert markers_main([str(path)]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("marker_names:"))
    assert yaml.safe_load(line) == {"marker_names": list(labels)}, line
