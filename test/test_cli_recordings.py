"""Recordings in and out: ``marker_names`` from the file, ``jointfit convert`` and ``jointfit fit --export``.

A synthetic recording with known joints (the fake mocap's hip ball joint and
knee hinge, mm) is written as a TRC file; converted to a bag (metres) it
must fit to the same estimates, scaled; the exported per-frame joints must
lie on the truth within their reported sd; the virtual markers must read
back from TRC and C3D. The real hip fixture is converted and fitted without
anyone typing ``marker_names``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from numpy.typing import NDArray

from jointfit_core.io import MarkerData, read_c3d, read_trc, write_trc
from jointfit_ros.cli import fit_main
from jointfit_ros.convert import PARAMS_FILE, convert_main
from jointfit_ros.fake_mocap import frame_at, make_rigs, marker_names, truth_at

pytest.importorskip("rosbags")

ROOT = Path(__file__).resolve().parents[1]
HIP = ROOT / "test/data/biobuddy/right_hip.c3d"
RATE = 100.0
N_FRAMES = 800
#: Frames in which the hip's pelvis cluster keeps only 2 markers (not posed: NaN in the export); longer
#: than a block of the fit (N_FRAMES / 60 frames): a block in which a segment is never posed.
HIDDEN = slice(400, 420)

JOINTS: dict[str, Any] = {
    "joints": ["hip", "knee"],
    "hip": {"type": "ball", "parent_markers": ["PELV1", "PELV2", "PELV3", "PELV4"],
            "child_markers": ["THIGH1", "THIGH2", "THIGH3", "THIGH4"], "template_frames": 30},
    "knee": {"type": "hinge", "parent_markers": ["FEMUR1", "FEMUR2", "FEMUR3", "FEMUR4"],
             "child_markers": ["SHANK1", "SHANK2", "SHANK3", "SHANK4"], "template_frames": 30},
}


def _cli(*args: object, timeout: float = 120.0) -> subprocess.CompletedProcess[str]:
    """``python -m jointfit_ros.cli ARGS`` (the worktree's code: PYTHONPATH is inherited)."""
    return subprocess.run([sys.executable, "-m", "jointfit_ros.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout)


def _one_line(stderr: str) -> str:
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in stderr, stderr
    return lines[0]


def _params(path: Path, values: dict[str, Any]) -> Path:
    path.write_text(yaml.safe_dump({"jointfit": {"ros__parameters": values}}, sort_keys=False))
    return path


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, NDArray[np.float64], Any]:
    """A TRC file of the fake hip + knee (mm, 0.5 mm noise, 2 % occlusions), its frames and its rigs."""
    rigs = make_rigs(5)
    rng = np.random.default_rng(5)
    t = np.arange(N_FRAMES) / RATE
    frames = np.stack([frame_at(rigs, float(tk), rng, 0.5, 0.02) for tk in t])
    frames[HIDDEN, 0:2] = np.nan  # PELV1, PELV2 gone: the pelvis is not posed
    frames = np.round(frames, 6)
    path = tmp_path_factory.mktemp("rec") / "walk.trc"
    write_trc(path, MarkerData(frames, tuple(marker_names(0)), RATE, "mm"))
    return path, read_trc(path).markers, rigs


def _summary(out: Path) -> dict[str, Any]:
    return {j["name"]: j for j in json.loads((out / "summary.json").read_text())["joints"]}


def _assert_scaled(a: dict[str, Any], b: dict[str, Any], scale: float) -> None:
    """Two joints' summaries (a in units of b times ``scale``) agree to float rounding."""
    assert a["frames_in_window"] == b["frames_in_window"] and a["identifiable"] == b["identifiable"]
    for key, power in (("centre_parent", 1), ("sd_parent", 1), ("rms_residual", 1), ("direction_parent", 0),
                       ("point_parent", 1), ("direction_sd_deg_parent", 0)):
        if key in b:
            np.testing.assert_allclose(np.array(a[key]) * scale**power, b[key], rtol=1e-7, atol=1e-9, err_msg=key)


@pytest.mark.parametrize(("kind", "storage"), [("posearray", "mcap"), ("pointcloud2", "sqlite3")])
def test_converted_bag_fits_as_the_file(tmp_path: Path, recording: tuple[Path, Any, Any], kind: str, storage: str) -> None:
    trc, markers, _ = recording
    bag = tmp_path / "walk_bag"
    done = _cli("convert", trc, "--to", bag, "--type", kind, "--storage", storage, "--topic", "/mocap/markers")
    assert done.returncode == 0, done.stderr
    assert f"marker_names: [{', '.join(marker_names(0))}]" in done.stdout
    # The file without marker_names (its labels); the bag with the parameters convert wrote beside it.
    code = fit_main([str(trc), "--config", str(_params(tmp_path / "file.yaml", JOINTS)), "--out",
                     str(tmp_path / "from_file"), "--no-report"])
    assert code == 0
    snippet = yaml.safe_load((bag / PARAMS_FILE).read_text())
    params = snippet["jointfit"]["ros__parameters"]
    assert params["marker_topic"] == "/mocap/markers" and params["units"] == "m"
    assert params["marker_type"] == ("pose_array" if kind == "posearray" else "pointcloud2")
    code = fit_main([str(bag), "--config", str(_params(tmp_path / "bag.yaml", {**params, **JOINTS})), "--out",
                     str(tmp_path / "from_bag"), "--no-report"])
    assert code == 0
    from_file, from_bag = _summary(tmp_path / "from_file"), _summary(tmp_path / "from_bag")
    for name in ("hip", "knee"):
        _assert_scaled(from_bag[name], from_file[name], 1000.0)  # m -> mm
    assert from_file["knee"]["axis_points"] == from_bag["knee"]["axis_points"]

    # What the node and jointfit replay read: the bag's messages, parsed independently by rosbags.
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    from jointfit_ros.bag import supported_topics

    assert list(supported_topics(bag)) == ["/mocap/markers"]
    store = get_typestore(Stores.ROS2_JAZZY)
    with Reader(bag) as reader:
        stamps = []
        for k, (conn, log_ns, raw) in enumerate(reader.messages()):
            msg = store.deserialize_cdr(raw, conn.msgtype)
            stamps.append((log_ns, msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec))
            if k == HIDDEN.start:
                assert msg.header.frame_id == "world"
                if kind == "posearray":
                    got = np.array([[p.position.x, p.position.y, p.position.z] for p in msg.poses])
                    np.testing.assert_array_equal(np.isnan(got), np.isnan(markers[k]))
                    np.testing.assert_allclose(got, markers[k] * 1e-3, rtol=1e-15)
                else:
                    assert msg.width == int((~np.isnan(markers[k, :, 0])).sum()) and msg.width < markers.shape[1]
    assert stamps == [(round(k * 1e7),) * 2 for k in range(N_FRAMES)]  # 100 Hz from 0 s, log time = stamp


def test_export_is_the_truth_frame_by_frame(tmp_path: Path, recording: tuple[Path, Any, Any]) -> None:
    pytest.importorskip("ezc3d")
    trc, markers, rigs = recording
    out = tmp_path / "out"
    done = _cli("fit", trc, "--config", _params(tmp_path / "p.yaml", JOINTS), "--out", out, "--no-report",
                "--export", "csv,trc,c3d")
    assert done.returncode == 0, done.stderr
    assert "joints.csv, joints.trc, joints.c3d" in done.stdout
    table = np.genfromtxt(out / "joints.csv", delimiter=",", names=True)
    assert table.shape == (N_FRAMES,)
    np.testing.assert_array_equal(table["frame"], np.arange(1, N_FRAMES + 1))
    np.testing.assert_allclose(table["time"], np.arange(N_FRAMES) / RATE, atol=1e-9)
    hip = np.column_stack([table[f"hip_{a}"] for a in "xyz"])
    hip_sd = np.column_stack([table[f"hip_sd_{a}"] for a in "xyz"])
    knee = np.column_stack([table[f"knee_{a}"] for a in "xyz"])
    knee_dir = np.column_stack([table[f"knee_d{a}"] for a in "xyz"])
    assert np.isnan(hip[HIDDEN]).all() and not np.isnan(knee[HIDDEN]).any()  # pelvis not posed there
    posed = ~np.isnan(hip[:, 0])
    assert posed.sum() > N_FRAMES - 60
    truth = [truth_at(rigs, k / RATE) for k in range(N_FRAMES)]
    true_hip = np.array([tr.centres["hip"] for tr in truth])
    # The reported sd (the estimate's and the frame's pose noise at the centre, ~0.5 m from the pelvis
    # cluster) is the scale of the per-frame error: z ~ N(0, 1) per axis.
    z = (hip[posed] - true_hip[posed]) / hip_sd[posed]
    rms_z = float(np.sqrt(np.mean(z**2)))
    assert 0.7 < rms_z < 1.4 and float(np.abs(z).max()) < 5.0, (rms_z, np.abs(z).max())
    true_point = np.array([tr.centres["knee"] for tr in truth])
    true_axis = np.array([tr.axes["knee"] for tr in truth])
    off = knee - true_point
    off_axis = off - true_axis * np.sum(off * true_axis, axis=1, keepdims=True)  # distance from the true axis line
    knee_sd = np.column_stack([table[f"knee_sd_{a}"] for a in "xyz"])
    z = off_axis / knee_sd  # (the along-axis part of the error, which the truth leaves open, is taken out)
    assert np.isnan(z[:, 0]).sum() < 20  # frames with fewer than 3 femur markers (2 % occlusions)
    assert float(np.sqrt(np.nanmean(z**2))) < 1.4 and float(np.nanmax(np.abs(z))) < 5.0
    cos = np.abs(np.sum(knee_dir * true_axis, axis=1))
    angle = np.degrees(np.arccos(np.clip(cos, None, 1.0))) / table["knee_dsd_deg"]  # in units of the largest sd
    assert float(np.sqrt(np.nanmean(angle**2))) < 1.6 and float(np.nanmax(angle)) < 5.0, np.nanmax(angle)
    np.testing.assert_allclose(np.linalg.norm(knee_dir, axis=1)[~np.isnan(cos)], 1.0, rtol=1e-12)

    # Virtual markers: the recording's markers plus <joint>_JC, <joint>_AX1/_AX2 50 mm along the axis.
    names = [*marker_names(0), "hip_JC", "knee_JC", "knee_AX1", "knee_AX2"]
    back = read_trc(out / "joints.trc")
    assert list(back.labels) == names and back.units == "mm" and back.rate == RATE
    np.testing.assert_array_equal(back.markers[:, :16], markers)
    np.testing.assert_array_equal(back.markers[:, 16], hip)
    np.testing.assert_allclose(back.markers[:, 18], knee - 50.0 * knee_dir, rtol=1e-15, atol=1e-9)
    np.testing.assert_allclose(back.markers[:, 19], knee + 50.0 * knee_dir, rtol=1e-15, atol=1e-9)
    c3d = read_c3d(out / "joints.c3d")
    assert list(c3d.labels) == names and c3d.units == "mm" and c3d.rate == RATE
    np.testing.assert_allclose(c3d.markers, back.markers, rtol=0, atol=1e-3)  # float32 at ~4 m in mm
    np.testing.assert_array_equal(np.isnan(c3d.markers), np.isnan(back.markers))


def test_real_hip_converted_and_fitted_without_marker_names(tmp_path: Path) -> None:
    pytest.importorskip("ezc3d")
    joints = yaml.safe_load((ROOT / "config/offline_right_hip.yaml").read_text())["jointfit"]["ros__parameters"]
    del joints["marker_names"], joints["right_hip"]["calibration_file"]
    bag = tmp_path / "hip_bag"
    done = _cli("convert", HIP, "--to", bag)
    assert done.returncode == 0, done.stderr
    params = yaml.safe_load((bag / PARAMS_FILE).read_text())["jointfit"]["ros__parameters"]
    assert len(params["marker_names"]) == 13  # every label of the file, in file order
    assert fit_main([str(HIP), "--config", str(_params(tmp_path / "c3d.yaml", joints)), "--out",
                     str(tmp_path / "a"), "--no-report"]) == 0
    assert fit_main([str(bag), "--config", str(_params(tmp_path / "bag.yaml", {**params, **joints})), "--out",
                     str(tmp_path / "b"), "--no-report"]) == 0
    a, b = _summary(tmp_path / "a")["right_hip"], _summary(tmp_path / "b")["right_hip"]
    _assert_scaled(b, a, 1000.0)
    # every frame but those the joint-consistency test rejected (0.5 %: the hip's skin clusters jump at times)
    # and those in which the outlier gate held a segment out whole
    lost = a["gated"]["joint"]["frames"] + sum(a["dropped"].get(f"{s}_gated", 0) for s in ("parent", "child"))
    assert a["identifiable"] and a["frames_in_window"] == 1690 - lost == b["frames_in_window"]
    assert lost - a["gated"]["joint"]["frames"] <= 2
    assert a["gated"]["joint"]["frames"] < 0.01 * 1690
    # the unit-free lever ratios alike; the white noise in metres a thousandth of the millimetres
    assert a["lever_ratio"] == b["lever_ratio"] and set(a["lever_ratio"]) == {"parent", "child"}
    np.testing.assert_allclose([1000.0 * b["white_noise_sd"][k] for k in ("parent", "child")],
                               [a["white_noise_sd"][k] for k in ("parent", "child")], rtol=1e-6)  # fmt: skip


def test_a_label_the_file_lacks_is_one_line(tmp_path: Path, recording: tuple[Path, Any, Any],
                                             capsys: pytest.CaptureFixture[str]) -> None:
    trc, _, _ = recording
    values = json.loads(json.dumps(JOINTS))
    values["hip"]["child_markers"][1] = "THIHG2"
    out = tmp_path / "out"
    code = fit_main([str(trc), "--config", str(_params(tmp_path / "p.yaml", values)), "--out", str(out)])
    line = _one_line(capsys.readouterr().err)
    assert code == 1 and not out.exists()
    assert "hip.child_markers: 'THIHG2' is not a marker label of walk.trc (did you mean 'THIGH2'?" in line, line
    assert "its labels: PELV1, PELV2" in line
    # Given marker_names still rule (as before): the file must hold them.
    values = {**JOINTS, "marker_names": [*marker_names(0), "EXTRA"]}
    code = fit_main([str(trc), "--config", str(_params(tmp_path / "q.yaml", values)), "--out", str(out)])
    assert code == 1 and "markers not found: ['EXTRA']" in _one_line(capsys.readouterr().err)


def test_bad_convert_and_export_arguments(tmp_path: Path, recording: tuple[Path, Any, Any],
                                          capsys: pytest.CaptureFixture[str]) -> None:
    trc, _, _ = recording
    bag = tmp_path / "bag"

    def convert(*args: object) -> tuple[int, str]:
        code = convert_main([str(a) for a in args])
        return code, capsys.readouterr().err

    cases: list[tuple[tuple[object, ...], int, str]] = [
        ((trc,), 2, "the following arguments are required: --to"),
        ((trc, "--to", bag, "--type", "pose"), 2, "argument --type: invalid choice"),
        ((trc, "--to", bag, "--start", "-1"), 2, "--start: expected a stamp >= 0 s"),
        ((trc, "--to", bag, "--start", "nan"), 2, "--start: expected a stamp >= 0 s"),
        ((trc, "--to", tmp_path / "x.mcap"), 2, "--to: expected the name of a bag directory"),
        ((trc, "--to", bag, "--topic", "a b"), 2, "--topic: expected a ROS topic name"),
        ((tmp_path / "none.trc", "--to", bag), 1, "no such file"),
        ((ROOT / "config/offline_right_hip.yaml", "--to", bag), 1, "expected a .c3d or .trc file"),
    ]
    for args, expected_code, expected in cases:
        code, err = convert(*args)
        line = _one_line(err)
        assert code == expected_code and line.startswith("jointfit convert: error: ") and expected in line, (args, line)
        assert not bag.exists()
    assert convert(trc, "--to", bag)[0] == 0
    before = sorted(p.name for p in bag.iterdir())
    code, err = convert(trc, "--to", bag, "--storage", "sqlite3")
    assert code == 1 and f"{bag}: exists; give --force to replace it" in _one_line(err)
    assert sorted(p.name for p in bag.iterdir()) == before  # untouched
    assert convert(trc, "--to", bag, "--storage", "sqlite3", "--force", "--start", "5")[0] == 0
    assert sorted(p.suffix for p in bag.iterdir()) == [".db3", ".yaml", ".yaml"]  # the mcap bag is gone
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag"]  # no temporary directory left

    code = fit_main([str(trc), "--config", str(_params(tmp_path / "p.yaml", JOINTS)), "--export", "csv,xls"])
    assert code == 2 and "argument --export: expected formats from csv, trc, c3d" in _one_line(capsys.readouterr().err)
    poses = {"joints": ["hip"], "marker_names": ["A"], "hip": {"parent_pose_topic": "/pelvis",
                                                                "child_pose_topic": "/thigh"}}
    code = fit_main([str(bag), "--config", str(_params(tmp_path / "r.yaml", poses)), "--out", str(tmp_path / "o"),
                     "--export", "csv"])
    assert code == 1 and "export covers marker joints only" in _one_line(capsys.readouterr().err)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(("rate", "expected"), [(1e300, "less than 1 ns apart"), (1e-300, "beyond any time stamp")])
def test_a_rate_no_stamp_can_carry_is_one_line(tmp_path: Path, recording: tuple[Path, Any, Any],
                                               capsys: pytest.CaptureFixture[str], rate: float, expected: str) -> None:
    """A TRC whose DataRate cannot stamp its frames is refused by fit and convert, naming the rate.

    At 1e300 Hz every frame fell on stamp 0 and the fit said 'building templates ... 1/30' (all but
    the first frame dropped as not increasing), convert wrote a bag of 800 messages at one stamp;
    at 1e-300 Hz numpy's overflow warnings preceded the same misleading fit.
    """
    _, frames, _ = recording
    odd = tmp_path / "odd.trc"
    write_trc(odd, MarkerData(frames, tuple(marker_names(0)), rate, "mm"))
    out = tmp_path / "out"
    code = fit_main([str(odd), "--config", str(_params(tmp_path / "p.yaml", JOINTS)), "--out", str(out)])
    line = _one_line(capsys.readouterr().err)
    assert code == 1 and not out.exists() and f"{odd}: the frame rate {rate:g} Hz" in line and expected in line, line
    code = convert_main([str(odd), "--to", str(tmp_path / "bag")])
    line = _one_line(capsys.readouterr().err)
    assert code == 1 and not (tmp_path / "bag").exists() and line.startswith("jointfit convert: error: "), line


def test_exports_keep_the_recordings_frame_numbers(tmp_path: Path, recording: tuple[Path, Any, Any]) -> None:
    """A recording that starts at frame 500: joints.c3d starts there too, as joints.trc and joints.csv do.

    joints.c3d started at frame 1 whatever the input, so software that lines the virtual markers up
    with the trial by frame number put them 499 frames early.
    """
    pytest.importorskip("ezc3d")
    _, frames, _ = recording
    late = tmp_path / "late.trc"
    write_trc(late, MarkerData(frames, tuple(marker_names(0)), RATE, "mm", first_frame=499))
    out = tmp_path / "out"
    done = _cli("fit", late, "--config", _params(tmp_path / "p.yaml", JOINTS), "--out", out, "--no-report",
                "--export", "csv,trc,c3d")
    assert done.returncode == 0, done.stderr
    assert read_c3d(out / "joints.c3d").first_frame == read_trc(out / "joints.trc").first_frame == 499
    assert (out / "joints.csv").read_text().splitlines()[1].startswith("500,")
