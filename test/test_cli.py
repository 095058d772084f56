"""``jointfit fit``: bags, C3D and TRC in; calibrations, summary and report out; bad input refused cleanly.

No ROS is started here (test_cli_round_trip.py replays a bag into the node).
The same synthetic recording (jointfit_ros.fake_mocap: a hip ball joint and a
knee hinge with known truth) is written as a bag and as a TRC file; ``fit``
must give the estimates of an :class:`OnlineJoint` fed the same frames
directly, in every input format, and the real fixtures must produce readable
report files.
"""

from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

from jointfit_core.calibration import load_calibration
from jointfit_core.estimator import OnlineJoint
from jointfit_core.io import MarkerData, write_trc
from jointfit_ros.cli import fit_main
from jointfit_ros.fake_mocap import frame_at, make_rigs, marker_names
from jointfit_ros.params import node_config, params_from_file
from jointfit_ros.runner import JointRunner

pytest.importorskip("rosbags")
from bagtools import write_marker_bag

DATA = Path(__file__).parent / "data"
CONFIG = Path(__file__).parents[1] / "config"
RATE = 100.0
N_FRAMES = 1500


def _recording(seed: int = 3) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Frames (N, 16, 3) in mm of the fake hip + knee, 2 % occlusions, and their stamps (ns)."""
    rigs = make_rigs(seed)
    rng = np.random.default_rng(seed)
    t = np.arange(N_FRAMES) / RATE
    frames = np.stack([frame_at(rigs, float(tk), rng, 0.5, 0.02) for tk in t])
    return frames, (1_000_000_000_000 + np.rint(t * 1e9)).astype(np.int64)


@pytest.fixture(scope="module")
def recording() -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    return _recording()


def _config(path: Path, *, hip_markers: str = "[PELV1, PELV2, PELV3, PELV4]", extra: str = "") -> Path:
    text = f"""jointfit:
  ros__parameters:
    joints: [hip, knee]
    marker_names: [{", ".join(marker_names(0))}]
    marker_topic: /mocap/markers
{extra}    hip:
      type: ball
      parent_markers: {hip_markers}
      child_markers: [THIGH1, THIGH2, THIGH3, THIGH4]
      window: 500
      template_frames: 30
      calibration_file: "{path.parent / "installed" / "hip.yaml"}"
    knee:
      type: hinge
      parent_markers: [FEMUR1, FEMUR2, FEMUR3, FEMUR4]
      child_markers: [SHANK1, SHANK2, SHANK3, SHANK4]
      window: 500
      template_frames: 30
"""
    path.write_text(text)
    return path


def _direct(frames: NDArray[np.float64], stamps_ns: NDArray[np.int64], config: Path) -> dict[str, OnlineJoint]:
    """The estimators of the config fed every frame directly, windows covering the recording."""
    cfg = node_config(params_from_file(config))
    out = {}
    for j in cfg.joints:
        runner = JointRunner(j, cfg)
        est = OnlineJoint(j.type, window=len(frames) + 1, template_frames=j.template_frames, attachment=j.attachment)
        for frame, stamp in zip(frames, stamps_ns, strict=True):
            est.update(frame[runner.parent_rows], frame[runner.child_rows], stamp * 1e-9)
        est.estimate()
        out[j.name] = est
    return out


def _fit(capsys: pytest.CaptureFixture[str], *args: str | Path) -> tuple[int, str, str]:
    assert args[0] == "fit"
    code = fit_main([str(a) for a in args[1:]])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _same_estimate(a: dict[str, object], b: dict[str, object], rtol: float = 1e-9) -> None:
    for key in a:
        va, vb = a[key], b[key]
        if isinstance(va, list):
            np.testing.assert_allclose(np.array(va, dtype=float), np.array(vb, dtype=float), rtol=rtol, atol=1e-9)
        elif isinstance(va, float):
            assert va == pytest.approx(vb, rel=rtol), key  # the fit adds all frames without a ring: rounding
        else:
            assert va == vb, key


@pytest.mark.parametrize(("storage", "msgtype"), [("sqlite3", "pose_array"), ("mcap", "pointcloud2")])
def test_fit_bag_equals_direct_estimators(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], recording: tuple[NDArray[np.float64], NDArray[np.int64]],
    storage: str, msgtype: str,
) -> None:
    frames, stamps = recording
    bag = write_marker_bag(tmp_path / "rec", frames, stamps, storage=storage, topic="/mocap/markers", msgtype=msgtype)
    extra = "    marker_type: pointcloud2\n    label_field: label\n" if msgtype == "pointcloud2" else ""
    config = _config(tmp_path / "params.yaml", extra=extra)
    out = tmp_path / "out"
    code, stdout, _ = _fit(capsys, "fit", bag, "--config", config, "--out", out, "--no-report")
    assert code == 0, stdout
    assert sorted(p.name for p in out.iterdir()) == ["hip.calibration.yaml", "knee.calibration.yaml", "summary.json"]
    direct = _direct(frames, stamps, config)
    for name, est in direct.items():
        saved = load_calibration(out / f"{name}.calibration.yaml")
        _same_estimate(saved["estimate"], est.to_dict()["estimate"])
        np.testing.assert_allclose(saved["template_parent"], est.templates[0], rtol=0, atol=1e-12)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["inputs_read"] == N_FRAMES and summary["input_kind"] == "bag"
    hip, knee = summary["joints"]
    assert hip["status"] == knee["status"] == "ok"
    assert [hip["frames_in_window"], knee["frames_in_window"]] == [direct["hip"].n_window, direct["knee"].n_window]
    assert direct["hip"].n_window > N_FRAMES - 20  # (frames with fewer than 3 markers on a segment are dropped)


def test_fit_trc_equals_bag(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], recording: tuple[NDArray[np.float64], NDArray[np.int64]]
) -> None:
    frames, stamps = recording
    frames = np.round(frames, 5)  # what a TRC file holds
    trc = tmp_path / "rec.trc"
    write_trc(trc, MarkerData(frames, tuple(marker_names(0)), RATE, "mm"))
    bag = write_marker_bag(tmp_path / "rec", frames, stamps, topic="/mocap/markers")
    config = _config(tmp_path / "params.yaml")
    assert _fit(capsys, "fit", trc, "--config", config, "--out", tmp_path / "a", "--no-report")[0] == 0
    assert _fit(capsys, "fit", bag, "--config", config, "--out", tmp_path / "b", "--no-report")[0] == 0
    for name in ("hip", "knee"):
        a = load_calibration(tmp_path / "a" / f"{name}.calibration.yaml")["estimate"]
        b = load_calibration(tmp_path / "b" / f"{name}.calibration.yaml")["estimate"]
        # TRC text holds fewer digits than the bag's float64, and its stamps are the rate's seconds where the
        # bag's are nanoseconds 1000 s later: a lag pair at the edge of the pairs' tolerance can fall in one and
        # not the other, which moves the skin part (its detection limit on clean data) by ~1e-4
        _same_estimate(a, b, rtol=1e-3)
    summary = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert summary["units"] == "mm" and summary["rate_hz"] == RATE


def test_window_config_is_what_the_node_holds(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], recording: tuple[NDArray[np.float64], NDArray[np.int64]]
) -> None:
    frames, stamps = recording
    bag = write_marker_bag(tmp_path / "rec", frames, stamps, topic="/mocap/markers")
    config = _config(tmp_path / "params.yaml")
    assert _fit(capsys, "fit", bag, "--config", config, "--out", tmp_path / "o", "--window", "config", "--no-report")[0] == 0
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert [j["frames_in_window"] for j in summary["joints"]] == [500, 500]
    assert summary["window"] == "config"


def test_write_calibration_installs_for_the_node(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], recording: tuple[NDArray[np.float64], NDArray[np.int64]]
) -> None:
    frames, stamps = recording
    bag = write_marker_bag(tmp_path / "rec", frames, stamps, topic="/mocap/markers")
    config = _config(tmp_path / "params.yaml")
    installed = tmp_path / "installed" / "hip.yaml"
    installed.parent.mkdir()
    installed.write_text("old: calibration\n")
    code, stdout, _ = _fit(capsys, "fit", bag, "--config", config, "--out", tmp_path / "o", "--no-report", "--write-calibration")
    assert code == 0 and f"installed calibration {installed}" in stdout
    assert (installed.parent / "hip.yaml.bak").read_text() == "old: calibration\n"
    # The node's runner loads it and starts frozen with the fitted estimate; the offline fit
    # itself never loaded the old file (it estimated from the recording).
    cfg = node_config(params_from_file(config))
    runner = JointRunner(cfg.joints[0], cfg)
    assert runner.loaded_from == str(installed) and runner.estimator.frozen
    assert runner.estimator.spec.frames == 500  # thawed, it resumes with the configured window
    saved = load_calibration(tmp_path / "o" / "hip.calibration.yaml")["estimate"]
    np.testing.assert_allclose(runner.estimator.solution.centre_parent, saved["centre_parent"], rtol=1e-12)


def test_write_calibration_writes_the_node_file_when_configured(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], recording: tuple[NDArray[np.float64], NDArray[np.int64]]
) -> None:
    from jointfit_core.node_calibration import load_node_calibration
    from jointfit_ros.calibration_store import NodeCalibrationFile

    frames, stamps = recording
    bag = write_marker_bag(tmp_path / "rec", frames, stamps, topic="/mocap/markers")
    node_file = tmp_path / "installed" / "subject.yaml"
    config = _config(tmp_path / "params.yaml", extra=f'    calibration_file: "{node_file}"\n')
    config.write_text(config.read_text().replace(f'calibration_file: "{tmp_path / "installed" / "hip.yaml"}"', ""))
    code, stdout, _ = _fit(capsys, "fit", bag, "--config", config, "--out", tmp_path / "o", "--no-report", "--write-calibration")
    assert code == 0 and f"installed calibration {node_file}" in stdout, stdout
    doc = load_node_calibration(node_file)
    assert list(doc["joints"]) == ["hip", "knee"] and doc["units"] == "m"
    for name in ("hip", "knee"):  # each joint's entry is the fit's calibration
        assert doc["joints"][name]["calibration"] == load_calibration(tmp_path / "o" / f"{name}.calibration.yaml")
    # the node loads it: both joints frozen with the fitted estimates
    cfg = node_config(params_from_file(config))
    runners = [JointRunner(j, cfg) for j in cfg.joints]
    store = NodeCalibrationFile(cfg.calibration_file, runners, "/jointfit", cfg.units)
    store.load()
    assert store.problem == "" and all(r.estimator.frozen for r in runners), [r.last_error for r in runners]


@pytest.mark.parametrize(
    ("fixture", "config", "joint", "identifiable"),
    [
        ("biobuddy/right_hip.c3d", "offline_right_hip.yaml", "right_hip", True),
        ("biobuddy/right_knee.c3d", "offline_right_knee.yaml", "right_knee", True),
        ("kineticstoolkit/kinematics_racing_full.c3d", "offline_right_elbow.yaml", "right_elbow", False),
    ],
)
def test_real_fixtures_report(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], fixture: str, config: str, joint: str, identifiable: bool
) -> None:
    pytest.importorskip("ezc3d")
    pytest.importorskip("matplotlib")
    out = tmp_path / "report"
    code, stdout, stderr = _fit(capsys, "fit", DATA / fixture, "--config", CONFIG / config, "--out", out, "--html")
    assert code == (0 if identifiable else 3), stderr
    png = (out / f"{joint}.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = struct.unpack(">II", png[16:24])
    assert (width, height) == (1530, 1215) and len(png) > 100_000  # eight panels of data, not an empty canvas
    html = (out / "report.html").read_text()
    assert f"src='{joint}.png'" in html and "identifiable" in html
    summary = json.loads((out / "summary.json").read_text())
    j = summary["joints"][0]
    assert j["status"] == ("ok" if identifiable else "not identifiable")
    assert (out / f"{joint}.calibration.yaml").exists() == identifiable
    assert all(v is not None and v > 0 for v in j["marker_residual_rms"].values())
    if joint == "right_knee":
        # Skin markers: the reported sd is the statistical part plus the soft-tissue-artefact part (issue 17).
        # The statistical part is the closed form's as before (< 2 deg: the verdict and the sign are judged on
        # it); the total covers the 0.1-0.4 deg between jointfit and SARA on this trial (bench/results/peers.md) and
        # the 1.8-2.1 deg between the two- and one-segment axes (test_real_fixtures.py; 2.1 for the closed form,
        # which the batch skin fit reports too, 1.8 for the refinement it reported before). The online hinge also
        # reads the artefact from the axis-alignment residual (the shank cluster turning about the shank,
        # which the point residual cannot see), projected on the turns that follow the hinge angle: the total
        # is 2.6 deg here against the batch fit's 1.7 (5.2 while that reading was an energy ratio, which took
        # this knee's coupled rotation for artefact); below 5 deg, the bound before that reading.
        stat, total = j["direction_sd_deg_parent_statistical"], j["direction_sd_deg_parent"]
        assert stat < 2.0 and 0.4 < stat <= total < 5.0, (stat, total)
        assert total > 1.8, total  # covers the spread between the methods
        # joint_angles.csv: the flexion about the fitted axis, over the range the summary reports
        table = np.genfromtxt(out / "joint_angles.csv", delimiter=",", names=True)
        flexion = np.degrees(table["right_knee"][np.isfinite(table["right_knee"])])
        assert flexion.size > 0.9 * table.size
        assert abs(np.ptp(flexion) - j["range_of_motion"]["flexion_range_deg"]) < 5.0
        # subject.urdf: thigh and shank links, the knee a continuous joint, lengths in metres (the file is in mm)
        yourdfpy = pytest.importorskip("yourdfpy")
        robot = yourdfpy.URDF.load(str(out / "subject.urdf"))
        assert robot.joint_map["right_knee"].type == "continuous"
        assert {"RTHI", "RLEG"} <= set(robot.link_map)
        assert all(np.abs(jt.origin[:3, 3]).max() < 1.0 for jt in robot.robot.joints if jt.origin is not None)
        assert summary["exports"] and "urdf" not in summary
    if joint == "right_elbow":
        assert "not a hinge" in j["reason"] and "NOT identifiable" in stdout


def _error_line(stderr: str) -> str:
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    return lines[0]


def test_bad_inputs_one_line_nothing_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], recording: tuple[NDArray[np.float64], NDArray[np.int64]]
) -> None:
    frames, stamps = recording
    bag = write_marker_bag(tmp_path / "rec", frames[:50], stamps[:50], topic="/other/markers")
    config = _config(tmp_path / "params.yaml")
    out = tmp_path / "out"
    cases = {
        "missing file": ([tmp_path / "nope.c3d", "--config", config], "no such file"),
        "bag without the topic": ([bag, "--config", config], "topics not in the bag: /mocap/markers"),
        "c3d without the markers": ([DATA / "biobuddy/right_hip.c3d", "--config", config], "markers not found"),
        "config names unknown markers": (
            [bag, "--config", _config(tmp_path / "bad.yaml", hip_markers="[PELV1, PELV2, NOPE]")],
            "hip.parent_markers: ['NOPE'] are not in marker_names",
        ),
        "missing config": ([bag, "--config", tmp_path / "none.yaml"], "no such parameter file"),
        "not a recording": ([config, "--config", config], "expected a rosbag2 bag"),
    }
    for name, (args, expected) in cases.items():
        code, _, stderr = _fit(capsys, "fit", *args, "--out", out)
        assert code == 1, name
        line = _error_line(stderr)
        assert line.startswith("jointfit fit: error: ") and expected in line, (name, line)
        assert not out.exists(), name
    code, _, stderr = _fit(capsys, "fit", bag)
    assert code == 2 and "--config" in _error_line(stderr)


def test_pose_array_bag_read_as_pointcloud2_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], recording: tuple[NDArray[np.float64], NDArray[np.int64]]
) -> None:
    frames, stamps = recording
    bag = write_marker_bag(tmp_path / "rec", frames[:50], stamps[:50], topic="/mocap/markers")
    config = _config(tmp_path / "params.yaml", extra="    marker_type: pointcloud2\n")
    code, _, stderr = _fit(capsys, "fit", bag, "--config", config, "--out", tmp_path / "o")
    assert code == 1 and "holds geometry_msgs/msg/PoseArray" in _error_line(stderr)
    assert not (tmp_path / "o").exists()


def test_failed_write_leaves_complete_files(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    recording: tuple[NDArray[np.float64], NDArray[np.int64]],
) -> None:
    """A write failing half-way (disk full) leaves the previous run's files as they were and no temporary file."""
    import jointfit_core.atomic as atomic

    frames, stamps = recording
    bag = write_marker_bag(tmp_path / "rec", frames, stamps, topic="/mocap/markers")
    config = _config(tmp_path / "params.yaml")
    out = tmp_path / "o"
    assert _fit(capsys, "fit", bag, "--config", config, "--out", out, "--no-report")[0] == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    real_fsync = os.fsync

    def full_disk(fd: int) -> None:
        if os.readlink(f"/proc/self/fd/{fd}").find("summary.json") >= 0:
            raise OSError(28, "No space left on device")
        real_fsync(fd)

    monkeypatch.setattr(atomic.os, "fsync", full_disk)
    code, _, stderr = _fit(capsys, "fit", bag, "--config", config, "--out", out, "--no-report")
    assert code == 1 and "No space left on device" in _error_line(stderr)
    after = {p.name: p.read_bytes() for p in out.iterdir()}
    assert after == before  # all or nothing: not one file of the failed run was written
    json.loads(after["summary.json"])
    assert not [p.name for p in tmp_path.iterdir() if p.name.endswith(".partial")]  # nor left half-way


def test_console_entry_point(tmp_path: Path) -> None:
    """``python -m jointfit_ros.cli``: usage errors, unknown commands, and fit end to end in a process."""
    run = [sys.executable, "-m", "jointfit_ros.cli"]
    done = subprocess.run([*run, "bogus"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "unknown command 'bogus'" in done.stderr
    shutil.copy(DATA / "biobuddy/right_knee.c3d", tmp_path / "knee.c3d")
    done = subprocess.run(
        [*run, "fit", "knee.c3d", "--config", str(CONFIG / "offline_right_knee.yaml"), "--no-report"],
        capture_output=True, text=True, timeout=120, cwd=tmp_path,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("right_knee (hinge): direction_parent (")
    assert (tmp_path / "knee_jointfit" / "right_knee.calibration.yaml").exists()


def test_write_calibration_node_file_records_the_recording_unit(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], recording: tuple[NDArray[np.float64], NDArray[np.int64]]
) -> None:
    """A TRC in mm fitted with the default ``units: m``: the node file says mm, as its numbers are.

    It said ``units: m`` (the parameter) over millimetre numbers, so a node in metres would take
    it as its own and a reader would scale every length by 1000.
    """
    from jointfit_core.node_calibration import load_node_calibration

    frames, _ = recording
    trc = tmp_path / "rec.trc"
    write_trc(trc, MarkerData(frames, tuple(marker_names(0)), RATE, "mm"))
    node_file = tmp_path / "installed" / "subject.yaml"
    config = _config(tmp_path / "params.yaml", extra=f'    calibration_file: "{node_file}"\n')
    config.write_text(config.read_text().replace(f'calibration_file: "{tmp_path / "installed" / "hip.yaml"}"', ""))
    code, stdout, _ = _fit(capsys, "fit", trc, "--config", config, "--out", tmp_path / "o", "--no-report", "--write-calibration")
    assert code == 0 and f"installed calibration {node_file}" in stdout, stdout
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["length_unit"] == "mm"
    assert load_node_calibration(node_file)["units"] == "mm"


def test_trc_gaps_written_as_zeros_are_missing_markers(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], recording: tuple[NDArray[np.float64], NDArray[np.int64]]
) -> None:
    """A TRC whose occluded markers are 0 0 0 (as some exporters write gaps) fits as with empty cells.

    ``zero_is_missing`` (default) holds for TRC as for C3D and the node: the zeros used to be taken
    as marker positions, so the gate rejected those frames and the exit status said to look for
    swapped labels, while the same file converted to a bag gave the estimate of the gaps.
    """
    frames, _ = recording
    assert np.isnan(frames).any()  # the recording has occlusions
    names = tuple(marker_names(0))
    blank, zeros = tmp_path / "blank.trc", tmp_path / "zeros.trc"
    write_trc(blank, MarkerData(frames, names, RATE, "mm"))
    write_trc(zeros, MarkerData(np.nan_to_num(frames, nan=0.0), names, RATE, "mm"))
    config = _config(tmp_path / "params.yaml")
    results = []
    for trc in (blank, zeros):
        code, stdout, stderr = _fit(capsys, "fit", trc, "--config", config, "--out", tmp_path / trc.stem, "--no-report")
        assert code == 0, stdout + stderr
        results.append(json.loads((tmp_path / trc.stem / "summary.json").read_text())["joints"])
    for a, b in zip(*results, strict=True):
        assert a["gated"] == b["gated"] and a["frames_in_window"] == b["frames_in_window"]
        for key in ("centre_parent", "cov_parent", "direction_parent", "point_parent"):
            if key in a:
                np.testing.assert_allclose(b[key], a[key], rtol=1e-9, atol=1e-12)


def test_recording_in_the_wrong_unit_is_flagged(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], recording: tuple[NDArray[np.float64], NDArray[np.int64]]
) -> None:
    """Millimetre markers in a TRC that declares metres: a units warning, not a silent 1000x fit.

    The node warns about such a stream (``units``); the fit wrote a calibration and a URDF with
    thigh clusters tens of metres wide and said nothing. (The exit status stays that of the fit.)
    """
    frames, _ = recording
    trc = tmp_path / "rec.trc"
    write_trc(trc, MarkerData(frames, tuple(marker_names(0)), RATE, "m"))
    code, stdout, _ = _fit(capsys, "fit", trc, "--config", _config(tmp_path / "params.yaml"), "--out", tmp_path / "o", "--no-report")
    assert code == 0
    assert stdout.count("WARNING: marker clusters are") == 2 and "looks like mm" in stdout
    joints = json.loads((tmp_path / "o" / "summary.json").read_text())["joints"]
    assert all("implausible for units 'm'" in j["units_warning"] for j in joints)
    write_trc(trc, MarkerData(frames, tuple(marker_names(0)), RATE, "mm"))  # the same numbers, declared right
    code, stdout, _ = _fit(capsys, "fit", trc, "--config", _config(tmp_path / "params.yaml"), "--out", tmp_path / "p", "--no-report")
    assert code == 0 and "WARNING" not in stdout
    assert all(j["units_warning"] == "" for j in json.loads((tmp_path / "p" / "summary.json").read_text())["joints"])


def test_write_calibration_keeps_the_node_file_entry_of_a_joint_not_identified(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], recording: tuple[NDArray[np.float64], NDArray[np.int64]]
) -> None:
    """A second fit that identifies the knee only keeps the hip's entry in the node file, as ``~/save`` does.

    It wrote the identified joints only, so the hip's calibration left the file (and, with the next
    fit, its ``.bak``).
    """
    from jointfit_core.node_calibration import load_node_calibration

    frames, _ = recording
    names = tuple(marker_names(0))
    node_file = tmp_path / "installed" / "subject.yaml"
    config = _config(tmp_path / "params.yaml", extra=f'    calibration_file: "{node_file}"\n')
    config.write_text(config.read_text().replace(f'calibration_file: "{tmp_path / "installed" / "hip.yaml"}"', ""))
    first = tmp_path / "both.trc"
    write_trc(first, MarkerData(frames, names, RATE, "mm"))
    code, _, _ = _fit(capsys, "fit", first, "--config", config, "--out", tmp_path / "o1", "--no-report", "--write-calibration")
    assert code == 0
    no_pelvis = frames.copy()
    no_pelvis[:, [k for k, n in enumerate(names) if n.startswith("PELV")]] = np.nan  # the hip cannot be estimated
    second = tmp_path / "knee_only.trc"
    write_trc(second, MarkerData(no_pelvis, names, RATE, "mm"))
    code, stdout, _ = _fit(capsys, "fit", second, "--config", config, "--out", tmp_path / "o2", "--no-report", "--write-calibration")
    assert code == 3 and not (tmp_path / "o2" / "hip.calibration.yaml").exists()
    assert f"hip: not identified here, its entry is kept ({node_file})" in stdout, stdout
    doc = load_node_calibration(node_file)
    assert list(doc["joints"]) == ["hip", "knee"]
    assert doc["joints"]["hip"]["calibration"] == load_calibration(tmp_path / "o1" / "hip.calibration.yaml")
    assert doc["joints"]["knee"]["calibration"] == load_calibration(tmp_path / "o2" / "knee.calibration.yaml")


@pytest.mark.parametrize("victim", ["recording", "config"])
def test_write_calibration_refuses_to_replace_an_input(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], recording: tuple[NDArray[np.float64], NDArray[np.int64]], victim: str
) -> None:
    """A calibration_file naming the recording or the parameter file: one line, exit 1, nothing written.

    The fit replaced the recording (or its own parameter file) with the calibration, keeping the
    original only as ``.bak`` until the next fit.
    """
    frames, _ = recording
    trc = tmp_path / "rec.trc"
    write_trc(trc, MarkerData(frames, tuple(marker_names(0)), RATE, "mm"))
    config = tmp_path / "params.yaml"
    target = trc if victim == "recording" else config
    _config(config, extra=f'    calibration_file: "{target}"\n')
    config.write_text(config.read_text().replace(f'calibration_file: "{tmp_path / "installed" / "hip.yaml"}"', ""))
    before = {p.name: p.read_bytes() for p in (trc, config)}
    out = tmp_path / "o"
    code, stdout, stderr = _fit(capsys, "fit", trc, "--config", config, "--out", out, "--no-report", "--write-calibration")
    assert code == 1 and stdout == "" and f"calibration_file {target} is an input of this fit" in stderr, stderr
    assert {p.name: p.read_bytes() for p in (trc, config)} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["params.yaml", "rec.trc"]


def test_workspace_in_metres_holds_for_a_recording_in_mm(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], recording: tuple[NDArray[np.float64], NDArray[np.int64]]
) -> None:
    """``workspace`` (metres, converted by the units) bounds a TRC in mm by its own unit, not ``units: m``.

    A 5 m workspace took the file's millimetres for metres: every marker beyond 5 mm was treated as
    absurd and the fit said 'no estimate: N absurd marker position(s)'.
    """
    frames, _ = recording
    assert np.nanmax(np.abs(frames)) < 5000.0  # inside a 5 m volume
    trc = tmp_path / "rec.trc"
    write_trc(trc, MarkerData(frames, tuple(marker_names(0)), RATE, "mm"))
    config = _config(tmp_path / "params.yaml", extra="    workspace: 5.0\n")
    code, stdout, _ = _fit(capsys, "fit", trc, "--config", config, "--out", tmp_path / "o", "--no-report")
    assert code == 0 and "absurd" not in stdout, stdout
    assert all(j["absurd_markers"] == 0 for j in json.loads((tmp_path / "o" / "summary.json").read_text())["joints"])


def test_hinge_whose_sign_marker_is_never_seen_gets_no_calibration(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], recording: tuple[NDArray[np.float64], NDArray[np.int64]]
) -> None:
    """axis_toward_marker never visible: no calibration for the knee (exit 3), as ``~/save`` refuses it.

    The fit wrote one with the axis's arbitrary sign, which a node then restored as 'pointing from
    ... (as saved)', every flexion angle of the wrong sign.
    """
    frames, _ = recording
    names = tuple(marker_names(0))
    hidden = frames.copy()
    hidden[:, names.index("PELV1")] = np.nan  # the sign marker: never seen
    trc = tmp_path / "rec.trc"
    write_trc(trc, MarkerData(hidden, names, RATE, "mm"))
    config = tmp_path / "params.yaml"
    config.write_text(f"""jointfit:
  ros__parameters:
    joints: [knee]
    marker_names: [{", ".join(names)}]
    knee:
      type: hinge
      parent_markers: [FEMUR1, FEMUR2, FEMUR3, FEMUR4]
      child_markers: [SHANK1, SHANK2, SHANK3, SHANK4]
      axis_toward_marker: PELV1
""")
    code, stdout, _ = _fit(capsys, "fit", trc, "--config", config, "--out", tmp_path / "o", "--no-report")
    assert code == 3 and "NO calibration: the hinge sign (toward PELV1" in stdout, stdout
    assert not (tmp_path / "o" / "knee.calibration.yaml").exists()
    joint = json.loads((tmp_path / "o" / "summary.json").read_text())["joints"][0]
    assert joint["identifiable"] and joint["calibration_file"] is None and "not chosen" in joint["not_saved"]


def test_an_earlier_fits_calibration_left_in_the_output_directory_is_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], recording: tuple[NDArray[np.float64], NDArray[np.int64]]
) -> None:
    """A second fit into the same --out that does not identify the hip names the hip's old calibration there.

    The directory kept hip.calibration.yaml of the first fit beside a summary.json saying the hip has
    no estimate, without a word: copying the directory's calibrations installed a stale one.
    """
    frames, _ = recording
    names = tuple(marker_names(0))
    config, out = _config(tmp_path / "params.yaml"), tmp_path / "o"
    first = tmp_path / "first.trc"
    write_trc(first, MarkerData(frames, names, RATE, "mm"))
    assert _fit(capsys, "fit", first, "--config", config, "--out", out, "--no-report")[0] == 0
    no_pelvis = frames.copy()
    no_pelvis[:, [k for k, n in enumerate(names) if n.startswith("PELV")]] = np.nan
    second = tmp_path / "second.trc"
    write_trc(second, MarkerData(no_pelvis, names, RATE, "mm"))
    code, _, stderr = _fit(capsys, "fit", second, "--config", config, "--out", out, "--no-report", "--quiet")
    assert code == 3 and f"WARNING: {out}/ still holds hip.calibration.yaml of an earlier fit" in stderr, stderr
    assert json.loads((out / "summary.json").read_text())["stale_files"] == [str(out / "hip.calibration.yaml")]
