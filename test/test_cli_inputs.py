"""`jointfit fit` on broken inputs: one line naming the file and the place, exit 1, nothing written."""

from __future__ import annotations

import json
import signal
from pathlib import Path

import numpy as np
import pytest
from bagtools import write_raw_bag

from jointfit_core.io import MarkerData, write_trc
from jointfit_ros.cli import fit_main
from jointfit_ros.raw import pointcloud2_bytes

ROOT = Path(__file__).resolve().parents[1]
HIP = ROOT / "test/data/biobuddy/right_hip.c3d"
HIP_CONFIG = ROOT / "config/offline_right_hip.yaml"


def _fit(capsys: pytest.CaptureFixture[str], *args: object) -> tuple[int, str]:
    code = fit_main([str(a) for a in args])
    return code, capsys.readouterr().err


def _one_error_line(stderr: str) -> str:
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in stderr, stderr
    return lines[0]


def test_truncated_c3d_is_an_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("ezc3d")
    data = HIP.read_bytes()
    cut = tmp_path / "half.c3d"
    cut.write_bytes(data[: len(data) // 2])
    out = tmp_path / "out"
    code, err = _fit(capsys, cut, "--config", HIP_CONFIG, "--out", out)
    line = _one_error_line(err)
    assert code == 1 and str(cut) in line and ("truncated" in line or "not a readable C3D" in line), line
    assert not out.exists()


def _trc(tmp_path: Path) -> tuple[Path, list[str]]:
    rng = np.random.default_rng(0)
    markers = rng.normal(0.0, 100.0, (20, 3, 3))
    path = tmp_path / "m.trc"
    write_trc(path, MarkerData(markers, ("A", "B", "C"), 100.0, "mm"))
    return path, path.read_text().splitlines()


def test_trc_row_cut_short_and_absurd_cells_name_the_line(tmp_path: Path) -> None:
    from jointfit_core.errors import InputError
    from jointfit_core.io import read_trc

    path, lines = _trc(tmp_path)
    cut = list(lines)
    cells = cut[9].split("\t")
    cut[9] = "\t".join(cells[:-2])  # the last marker loses two of its three cells
    path.write_text("\n".join(cut) + "\n")
    with pytest.raises(InputError, match=r"line 10: the row is cut short"):
        read_trc(path)
    huge = list(lines)
    cells = huge[12].split("\t")
    cells[4] = "1e300"
    huge[12] = "\t".join(cells)
    path.write_text("\n".join(huge) + "\n")
    with pytest.raises(InputError, match=r"line 13: marker 0 has the coordinate 1e\+300"):
        read_trc(path)


def _config(tmp_path: Path) -> Path:
    path = tmp_path / "p.yaml"
    path.write_text("""jointfit:
  ros__parameters:
    joints: [hip]
    marker_names: [A, B, C, D, E, F]
    hip: {type: ball, parent_markers: [A, B, C], child_markers: [D, E, F]}
""")
    return path


def test_bag_topic_with_other_bytes_is_an_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    messages = [("/markers", "geometry_msgs/msg/PoseArray", 10**9 + k * 10**7,
                 pointcloud2_bytes(10**9 + k * 10**7, "world", np.zeros((6, 3)))) for k in range(50)]
    bag = write_raw_bag(tmp_path / "bag", messages)
    out = tmp_path / "out"
    code, err = _fit(capsys, bag, "--config", _config(tmp_path), "--out", out)
    line = _one_error_line(err)
    assert code == 1 and "none of the 50 messages on markers could be read as pose_array" in line, line
    assert not out.exists()


def test_bag_with_an_empty_topic_is_an_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = write_raw_bag(tmp_path / "bag", [], empty_topics={"/markers": "geometry_msgs/msg/PoseArray"})
    out = tmp_path / "out"
    code, err = _fit(capsys, bag, "--config", _config(tmp_path), "--out", out)
    line = _one_error_line(err)
    assert code == 1 and "topic /markers holds no messages" in line, line
    assert not out.exists()


def test_ctrl_c_during_the_writes_leaves_nothing(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("ezc3d")
    import jointfit_core.atomic as atomic

    real_fsync = atomic.os.fsync
    calls = {"n": 0}

    def interrupted(fd: int) -> None:
        calls["n"] += 1
        if calls["n"] == 2:  # after the first file of the output is written
            signal.raise_signal(signal.SIGINT)
        real_fsync(fd)

    monkeypatch.setattr(atomic.os, "fsync", interrupted)
    out = tmp_path / "out"
    code, err = _fit(capsys, HIP, "--config", HIP_CONFIG, "--out", out, "--no-report")
    assert code == 130 and "interrupted" in err
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_a_still_recording_says_no_estimate_once(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Exact copies of one frame: the summary line said "no estimate: no estimate: ..." (offline hunt)."""
    rng = np.random.default_rng(1)
    frame = rng.normal(0.0, 100.0, (6, 3))
    path = tmp_path / "still.trc"
    write_trc(path, MarkerData(np.repeat(frame[None], 200, axis=0), ("A", "B", "C", "D", "E", "F"), 100.0, "mm"))
    out = tmp_path / "out"
    fit_main([str(path), "--config", str(_config(tmp_path)), "--out", str(out)])
    line = capsys.readouterr().out
    assert "hip (ball): no estimate: no relative rotation" in line, line
    joint = json.loads((out / "summary.json").read_text())["joints"][0]
    assert joint["status"] == "no estimate" and joint["message"].startswith("no relative rotation"), joint["message"]
