"""The node's one calibration file (version 2): segments in one frame each, every joint's calibration, through the
runners of the lower-body skeleton (no ROS): a round trip to the last bit, a chain's hip centre and knee axis in the
one thigh frame against the truth, refusals per joint that keep the file, and atomic writes."""

from __future__ import annotations

import copy
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from jointfit_core.calibration import fit_to_dict
from jointfit_core.calibration_fit import JOINT_MISFIT_FRAMES
from jointfit_core.errors import InputError
from jointfit_core.node_calibration import (
    NODE_CALIBRATION_VERSION,
    check_node_calibration,
    load_node_calibration,
    node_calibration,
    save_node_calibration,
)
from jointfit_core.skeleton_truth import make_skeleton, skeleton_frames
from jointfit_core.urdf import kabsch
from jointfit_ros.calibration_store import NodeCalibrationFile
from jointfit_ros.inputs import MessageRouter
from jointfit_ros.params import ConfigError, NodeConfig, node_config, params_from_file
from jointfit_ros.raw import pose_array_bytes
from jointfit_ros.runner import JointRunner

CONFIG = Path(__file__).resolve().parents[1] / "config" / "lower_body.yaml"
RATE, NOISE, T0, SEED = 100.0, 0.0005, 1_000_000_000_000, 3


def _config(path: Path, **extra: Any) -> NodeConfig:
    values = params_from_file(CONFIG)
    values["calibration_file"] = str(path)
    values.update(extra)
    return node_config(values)


def _raws(seconds: float, start: float = 0.0) -> tuple[np.ndarray, list[bytes]]:
    sk = make_skeleton("lower", seed=SEED)
    t = start + np.arange(int(seconds * RATE)) / RATE
    frames = skeleton_frames(sk, t, np.random.default_rng(SEED), NOISE, 0.02)
    return t, [pose_array_bytes(T0 + round(tk * 1e9), "world", f) for tk, f in zip(t, frames, strict=True)]


def _start(cfg: NodeConfig) -> tuple[list[JointRunner], MessageRouter, NodeCalibrationFile]:
    """What the node does at start: the runners, the router, the node calibration file loaded."""
    runners = [JointRunner(j, cfg) for j in cfg.joints]
    store = NodeCalibrationFile(cfg.calibration_file, runners, "/jointfit", cfg.units)
    store.load()
    return runners, MessageRouter(cfg, runners), store


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The six joints estimated from 8 s of the skeleton, frozen and saved to one node file (its content)."""
    path = tmp_path_factory.mktemp("node") / "subject.yaml"
    runners, router, store = _start(_config(path))
    _, raws = _raws(8.0)
    for start in range(0, len(raws), 100):
        router.markers_many(raws[start : start + 100])
    for r in runners:
        assert r.estimate(force=True), r.last_error
        r.freeze(True)
    texts = store.save()
    assert texts == [f"{r.cfg.name}: saved {path}" for r in runners]
    return {"path": path, "doc": load_node_calibration(path), "runners": runners}


def _assert_same(a: Any, b: Any, atol: float = 1e-12, where: str = "") -> None:
    """Nested dicts and lists equal, numbers to ``atol`` (a reloaded template is re-centred: last-bit changes)."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and list(a) == list(b), where
        for k in a:
            _assert_same(a[k], b[k], atol, f"{where}.{k}")
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), where
        for k, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_same(x, y, atol, f"{where}[{k}]")
    elif isinstance(a, float) and not isinstance(b, bool) and isinstance(b, (int, float)):
        assert abs(a - b) <= atol, (where, a, b)
    else:
        assert a == b, (where, a, b)


def _write(path: Path, doc: dict[str, Any]) -> bytes:
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path.read_bytes()


def test_the_file_holds_segments_and_joints(calibrated: dict[str, Any]) -> None:
    doc, runners = calibrated["doc"], calibrated["runners"]
    assert doc["format"] == "jointfit-node-calibration" and doc["version"] == NODE_CALIBRATION_VERSION == 2
    assert doc["units"] == "m" and doc["node"] == "/jointfit"
    assert list(doc["segments"]) == ["pelvis", "r_thigh", "r_shank", "r_foot", "l_thigh", "l_shank", "l_foot"]  # as ~/segments
    assert list(doc["joints"]) == [r.cfg.name for r in runners]
    thigh = doc["segments"]["r_thigh"]
    assert thigh["markers"] == ["RTHI1", "RTHI2", "RTHI3", "RTHI4"] and thigh["pose_topic"] == ""
    assert thigh["owner"] == {"joint": "r_hip", "side": "child"}
    hip = doc["joints"]["r_hip"]
    assert thigh["template"] == hip["calibration"]["template_child"]  # the owner's template is the frame
    assert (hip["kind"], hip["parent"], hip["child"]) == ("ball", "pelvis", "r_thigh")
    knee = doc["joints"]["r_knee"]
    assert (knee["kind"], knee["parent"], knee["child"]) == ("hinge", "r_thigh", "r_shank")
    # each joint's calibration is what its own file would hold (estimator state and the joint's record)
    for r in runners:
        cal = doc["joints"][r.cfg.name]["calibration"]
        assert cal == r.calibration() and cal["version"] == 1


@pytest.mark.parametrize("side", ["r", "l"])
def test_a_chains_hip_centre_and_knee_axis_are_in_one_thigh_frame(calibrated: dict[str, Any], side: str) -> None:
    doc = calibrated["doc"]
    hip, knee = doc["joints"][f"{side}_hip"], doc["joints"][f"{side}_knee"]
    thigh = f"{side}_thigh"
    assert hip["child"] == knee["parent"] == thigh
    centre = np.array(hip["in_child"]["point"])
    point, direction = np.array(knee["in_parent"]["point"]), np.array(knee["in_parent"]["direction"])
    assert abs(np.linalg.norm(direction) - 1.0) < 1e-12
    lever = point - centre
    femur = np.linalg.norm(lever - direction * (lever @ direction))  # hip centre to knee axis, read off the file
    sk = make_skeleton("lower", seed=SEED)
    truth = sk.joints_world_at([1.234])
    p_hip, _ = truth[f"{side}_hip"]
    p_knee, d_knee = truth[f"{side}_knee"]
    assert d_knee is not None
    true_lever = p_knee[0] - p_hip[0]
    true_femur = np.linalg.norm(true_lever - d_knee[0] * (true_lever @ d_knee[0]))
    assert true_femur > 0.3 and abs(femur - true_femur) < 2e-3, (femur, true_femur)
    # the knee axis in the thigh frame is the knee's own parent-frame axis carried over by Kabsch: the knee's
    # template of the thigh put onto the owner's (the hip's) by the same rotation and translation
    cal = knee["calibration"]
    A, a = kabsch(np.array(doc["segments"][thigh]["template"]), np.array(cal["template_parent"]))
    np.testing.assert_allclose(point, A @ np.array(cal["estimate"]["point_parent"]) + a, atol=1e-12)
    np.testing.assert_allclose(np.array(knee["in_parent"]["cov_point"]),
                               A @ np.array(cal["estimate"]["cov_point_parent"]) @ A.T, atol=1e-15)
    # the two templates of the thigh agree within the noise once aligned
    assert np.abs(np.array(cal["template_parent"]) @ A.T + a - np.array(doc["segments"][thigh]["template"])).max() < 2e-3


def test_round_trip_restores_every_joint_exactly_and_frozen_joints_publish_once_judged(
    calibrated: dict[str, Any], tmp_path: Path
) -> None:
    path = tmp_path / "subject.yaml"
    path.write_bytes(calibrated["path"].read_bytes())
    runners, router, store = _start(_config(path))
    assert store.problem == "" and store.notes == []
    before = {r.cfg.name: r for r in calibrated["runners"]}
    for r in runners:
        assert r.estimator.frozen and r.loaded_from == f"{path} (joint {r.cfg.name})", r.last_error
        old, new = before[r.cfg.name].estimator.solution, r.estimator.solution
        assert type(old) is type(new)
        for name in old.__dataclass_fields__:
            a, b = getattr(old, name), getattr(new, name)
            if isinstance(a, np.ndarray):
                np.testing.assert_allclose(b, a, rtol=0.0, atol=1e-12)
            else:
                assert a == b, name
        assert "calibration loaded from" in r.status().values
    # after the restart each joint judges its calibration against the markers over its first JOINT_MISFIT_FRAMES
    # posed frames (outputs held), then publishes exactly what the joints before the restart would
    _, raws = _raws(1.3, start=20.0)
    first: dict[str, int] = {}
    for k, raw in enumerate(raws[:-1]):
        for o in router.markers(raw):
            first.setdefault(o.runner.cfg.name, k)
    assert sorted(first) == sorted(before) and all(JOINT_MISFIT_FRAMES - 1 <= k < 110 for k in first.values()), first
    restored = {o.runner.cfg.name: o.output for o in router.markers(raws[-1])}
    original = {o.runner.cfg.name: o.output
                for o in MessageRouter(calibrated["runners"][0].node, calibrated["runners"]).markers(raws[-1])}
    assert sorted(restored) == sorted(original) == sorted(before)
    for name, out in restored.items():
        np.testing.assert_allclose(out.position, original[name].position, rtol=0.0, atol=1e-12)
        np.testing.assert_allclose(out.cov, original[name].cov, rtol=0.0, atol=1e-15)
    # saving again writes the same calibrations, the previous file kept as .bak
    store.save()
    again = load_node_calibration(path)
    _assert_same(again, calibrated["doc"])
    for a, b in zip(again["joints"].values(), calibrated["doc"]["joints"].values(), strict=True):
        assert a["calibration"]["estimate"] == b["calibration"]["estimate"]  # the estimates to the last bit
    assert path.with_name("subject.yaml.bak").read_bytes() == calibrated["path"].read_bytes()


def _refused(doc: dict[str, Any], case: str) -> dict[str, Any]:
    d = copy.deepcopy(doc)
    knee = d["joints"]["r_knee"]["calibration"]
    if case == "joint newer":
        knee["version"] = 99
    elif case == "joint nan":
        knee["estimate"]["point_parent"][1] = float("nan")
    elif case == "markers reordered":
        m = knee["parent_markers"]
        m[0], m[1] = m[1], m[0]
    elif case == "joint of another layout":
        knee["kind"] = "ball"
    elif case == "another joint's":
        knee["joint"] = "l_knee"
    elif case == "no record":
        del knee["child_markers"]
    return d


@pytest.mark.parametrize(
    "case", ["joint newer", "joint nan", "markers reordered", "joint of another layout", "another joint's", "no record"]
)
def test_a_refused_joint_is_named_estimates_and_the_others_load(
    calibrated: dict[str, Any], tmp_path: Path, case: str
) -> None:
    path = tmp_path / "subject.yaml"
    before = _write(path, _refused(calibrated["doc"], case))
    runners, router, store = _start(_config(path))
    by = {r.cfg.name: r for r in runners}
    knee = by.pop("r_knee")
    assert not knee.estimator.frozen and knee.loaded_from == ""
    assert f"calibration file {path} (joint r_knee) not loaded (kept as it is)" in knee.last_error, knee.last_error
    assert knee.status().values["calibration not loaded"] == knee.last_error  # named in its /diagnostics status
    assert all(r.estimator.frozen for r in by.values())
    assert path.read_bytes() == before
    # it estimates: frames reach its window
    _, raws = _raws(1.0, start=30.0)
    router.markers_many(raws)
    assert knee.estimator.n_window > 50
    assert path.read_bytes() == before
    # the first save keeps the file aside (it was not loaded entirely), then replaces it
    store.save(["r_hip"])
    aside = [p for p in tmp_path.iterdir() if p.name.startswith("subject.yaml.unloadable-")]
    assert len(aside) == 1 and aside[0].read_bytes() == before
    saved = load_node_calibration(path)
    assert "r_knee" not in saved["joints"] and sorted(saved["joints"]) == sorted(by)


def test_an_entry_whose_templates_do_not_match_the_live_markers_is_discarded_and_not_saved_again(
    calibrated: dict[str, Any], tmp_path: Path
) -> None:
    """An entry whose record matches but whose template does not (two thigh markers swapped on the subject since):
    loaded, discarded after the first frames (as a per-joint file is), and left out of the next save."""
    doc = copy.deepcopy(calibrated["doc"])
    tpl = doc["joints"]["r_knee"]["calibration"]["template_parent"]
    tpl[0], tpl[2] = tpl[2], tpl[0]
    path = tmp_path / "subject.yaml"
    before = _write(path, doc)
    runners, router, store = _start(_config(path))
    knee = {r.cfg.name: r for r in runners}["r_knee"]
    assert knee.estimator.frozen
    _, raws = _raws(0.3, start=40.0)
    router.markers_many(raws)
    assert not knee.estimator.frozen and "discarded (kept as it is)" in knee.last_error, knee.last_error
    assert knee.status().values["calibration not loaded"] == knee.last_error
    assert all(r.estimator.frozen for r in runners if r is not knee)
    texts = store.save()
    assert any(t.startswith("r_knee: not saved:") and "previous entry" not in t for t in texts), texts
    assert [p.read_bytes() for p in tmp_path.glob("subject.yaml.unloadable-*")] == [before]
    saved = load_node_calibration(path)
    assert "r_knee" not in saved["joints"] and len(saved["joints"]) == 5
    assert "calibration not loaded" not in knee.status().values  # kept aside and replaced: said until then


@pytest.mark.parametrize("case", ["newer", "units", "not yaml", "per-joint file", "not utf-8", "directory"])
def test_a_refused_file_is_kept_untouched_and_every_joint_estimates(
    calibrated: dict[str, Any], tmp_path: Path, case: str
) -> None:
    path = tmp_path / "subject.yaml"
    doc = copy.deepcopy(calibrated["doc"])
    if case == "newer":
        doc["version"] = NODE_CALIBRATION_VERSION + 1
        _write(path, doc)
    elif case == "units":
        doc["units"] = "mm"
        _write(path, doc)
    elif case == "not yaml":
        path.write_text("joints: [unclosed\n")
    elif case == "per-joint file":
        _write(path, doc["joints"]["r_hip"]["calibration"])
    elif case == "not utf-8":
        path.write_bytes(b"\xff\xfe\x00garbage\x81")
    else:
        path.mkdir()
    before = None if path.is_dir() else path.read_bytes()
    runners, _, store = _start(_config(path))
    expect = {
        "newer": "version 3 is not supported", "units": "lengths are in 'mm'", "not yaml": "not valid YAML",
        "per-joint file": "give it as <joint>.calibration_file", "not utf-8": "codec", "directory": "not a regular file",
    }[case]
    assert expect in store.problem, store.problem
    for r in runners:
        assert not r.estimator.frozen and f"calibration file {path} not loaded (kept as it is)" in r.last_error
    if before is not None:
        assert path.read_bytes() == before


def test_a_joint_that_cannot_save_keeps_its_entry(calibrated: dict[str, Any], tmp_path: Path) -> None:
    path = tmp_path / "subject.yaml"
    path.write_bytes(calibrated["path"].read_bytes())
    runners, _, store = _start(_config(path))
    by = {r.cfg.name: r for r in runners}
    by["r_ankle"].reset()  # no estimate now: ~/save says so and writes its previous entry again
    texts = store.save()
    assert any(t.startswith("r_ankle: not saved:") and "previous entry is kept" in t for t in texts), texts
    assert store.unsaved == ["r_ankle"]  # what ~/save answers success false for
    saved = load_node_calibration(path)
    assert saved["joints"]["r_ankle"] == calibrated["doc"]["joints"]["r_ankle"]  # carried over as it was
    _assert_same(saved, calibrated["doc"])
    # auto_freeze saves through the node file, only its own joint: the others keep their entries as they are
    by["r_knee"].reset()
    assert by["r_hip"].saver is not None
    assert by["r_hip"].saver() == str(path)  # as a per-joint save says it: "auto_freeze: frozen, saved <path>"
    assert store.unsaved == []
    again = load_node_calibration(path)
    assert {n: j["calibration"] for n, j in again["joints"].items() if n != "r_hip"} == {
        n: j["calibration"] for n, j in saved["joints"].items() if n != "r_hip"
    }
    _assert_same(again, calibrated["doc"])


def test_auto_freeze_writes_its_joints_entry_of_the_node_file(tmp_path: Path) -> None:
    path = tmp_path / "subject.yaml"
    cfg = _config(path, **{"r_hip.target_sd": 0.05, "r_hip.auto_freeze": True})
    runners, router, _ = _start(cfg)  # (the store is wired into the runners)
    _, raws = _raws(8.0)
    for start in range(0, len(raws), 100):
        router.markers_many(raws[start : start + 100])
    for r in runners:
        assert r.estimate(force=True), r.last_error
    hip = runners[0]
    assert hip.cfg.name == "r_hip" and hip.status().level == 0 and hip.done, hip.status().message
    assert hip.auto_freeze() == f"auto_freeze: frozen, saved {path}"
    assert hip.estimator.frozen and not runners[1].estimator.frozen
    doc = load_node_calibration(path)
    assert list(doc["joints"]) == ["r_hip"] and list(doc["segments"]) == ["pelvis", "r_thigh"]
    assert doc["joints"]["r_hip"]["calibration"] == hip.calibration()


def test_a_failed_write_leaves_the_file_and_its_backup(calibrated: dict[str, Any], tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "subject.yaml"
    path.write_bytes(calibrated["path"].read_bytes())
    runners, _, store = _start(_config(path))
    store.save()
    files = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    assert sorted(files) == ["subject.yaml", "subject.yaml.bak"]
    runners[0].freeze(False)

    def full_disk(fd: int) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", full_disk)
    with pytest.raises(OSError, match="No space left"):
        store.save()
    monkeypatch.undo()
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == files  # no temporaries, nothing changed


def test_core_round_trip_and_checks(calibrated: dict[str, Any], tmp_path: Path) -> None:
    doc = calibrated["doc"]
    calibrations = [j["calibration"] for j in doc["joints"].values()]
    labels = calibrated["runners"][0].node.segment_labels()  # the configured names (lower_body.yaml's segments)
    assert node_calibration(calibrations, node="/jointfit", units="m", segment_labels=labels) == doc
    unnamed = node_calibration(calibrations, node="/jointfit", units="m")  # without: the markers' prefixes
    assert list(unnamed["segments"]) == ["PELV", "RTHI", "RSHK", "RFOO", "LTHI", "LSHK", "LFOO"]
    assert [s["template"] for s in unnamed["segments"].values()] == [s["template"] for s in doc["segments"].values()]
    path = save_node_calibration(tmp_path / "a" / "n.yaml", doc)
    assert load_node_calibration(path) == doc
    with pytest.raises(InputError, match="own non-empty name"):
        node_calibration([calibrations[0], calibrations[0]])
    with pytest.raises(InputError, match="expected 'joints'"):
        check_node_calibration({**doc, "joints": []})
    with pytest.raises(InputError, match="no 'calibration' mapping"):
        check_node_calibration({**doc, "joints": {"r_hip": {}}})
    with pytest.raises(InputError, match="version 1 is not supported"):
        check_node_calibration({**doc, "version": 1})
    with pytest.raises(InputError):
        save_node_calibration(tmp_path / "b.yaml", {"format": "x"})
    assert not (tmp_path / "b.yaml").exists()


def test_jointfit_urdf_reads_a_node_file(calibrated: dict[str, Any], capsys: pytest.CaptureFixture[str]) -> None:
    from jointfit_core.urdf import urdf_from_calibrations
    from jointfit_ros.urdf_cli import urdf_main

    assert urdf_main([str(calibrated["path"])]) == 0
    expected = urdf_from_calibrations([j["calibration"] for j in calibrated["doc"]["joints"].values()])
    assert capsys.readouterr().out == expected and expected.count("<joint ") == 6 * 2 + 2 * 2


def test_the_node_file_and_per_joint_files_are_not_both_set(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"node's calibration file and r_knee\.calibration_file are set"):
        _config(tmp_path / "subject.yaml", **{"r_knee.calibration_file": str(tmp_path / "knee.yaml")})
    with pytest.raises(ConfigError, match="environment variable that is not set"):
        _config(Path("$JOINTFIT_NOT_SET_ANYWHERE/subject.yaml"))
    values = params_from_file(CONFIG)
    values["joints"] = ["calibration_file"]
    with pytest.raises(ConfigError, match="is the name of a node parameter"):
        node_config(values)


def test_pose_topic_segments_and_frames_owned_as_in_segments(calibrated: dict[str, Any]) -> None:
    """Hips whose pelvis is a pose topic: not in ~/segments, so the thighs' frames are the knees' (as ~/segments and
    TF have them); the hip centre is carried into them by Kabsch and the femur length read off the file holds."""
    calibrations = copy.deepcopy([j["calibration"] for j in calibrated["doc"]["joints"].values()])
    for cal in calibrations:
        if cal["joint"].endswith("_hip"):
            cal["parent_markers"], cal["parent_pose_topic"] = [], "/pelvis/pose"
    doc = node_calibration(calibrations, node="/jointfit", units="m")
    pose = [n for n, seg in doc["segments"].items() if seg["pose_topic"] == "/pelvis/pose"]
    assert len(pose) == 1 and doc["segments"][pose[0]]["markers"] == []
    assert doc["segments"][pose[0]]["owner"] == {"joint": "r_hip", "side": "parent"}
    assert doc["joints"]["r_hip"]["parent"] == doc["joints"]["l_hip"]["parent"] == pose[0]
    assert "PELV" not in doc["segments"]
    by = {c["joint"]: c for c in calibrations}
    for side in "rl":
        thigh = doc["segments"][f"{side.upper()}THI"]
        assert thigh["owner"] == {"joint": f"{side}_knee", "side": "parent"}
        assert thigh["template"] == by[f"{side}_knee"]["template_parent"]
        hip, knee = doc["joints"][f"{side}_hip"], doc["joints"][f"{side}_knee"]
        assert hip["child"] == knee["parent"] == f"{side.upper()}THI"
        np.testing.assert_allclose(knee["in_parent"]["point"], by[f"{side}_knee"]["estimate"]["point_parent"],
                                   rtol=0.0, atol=1e-15)  # the owner's own frame: unchanged
        centre = np.array(hip["in_child"]["point"])
        # the same hip centre as in the file where the hip owns the thigh, up to the two thigh templates' noise
        old = calibrated["doc"]
        A, a = kabsch(np.array(thigh["template"]), np.array(old["segments"][f"{side}_thigh"]["template"]))
        np.testing.assert_allclose(centre, A @ np.array(old["joints"][f"{side}_hip"]["in_child"]["point"]) + a,
                                   atol=1e-9)


def test_a_chained_joint_has_its_own_segment_and_round_trips(tmp_path: Path) -> None:
    """A knee whose thigh is two markers and the hip centre (``parent_chain``): a segment of its own
    (``[T1, T2, chain:hip]``), restored exactly."""
    from test_chain_node import _config as chain_config
    from test_chain_node import _leg

    path = tmp_path / "leg.yaml"
    cfg = chain_config(calibration_file=str(path))
    runners, router, store = _start(cfg)
    frames, _ = _leg(2, 2500)
    raws = [pose_array_bytes(int(1e9 + k * 1e7), "world", f) for k, f in enumerate(frames)]
    for start in range(0, len(raws), 50):  # the knee's virtual marker needs the hip's estimate: as the node solves
        router.markers_many(raws[start : start + 50])
        for r in runners:
            r.estimate(force=True)
    for r in runners:
        assert r.estimate(force=True), r.last_error
    assert store.save() == [f"hip: saved {path}", f"knee: saved {path}"]
    doc = load_node_calibration(path)
    segments = {n: (s["markers"], s["owner"]) for n, s in doc["segments"].items()}
    knee = doc["joints"]["knee"]
    assert segments[knee["parent"]] == (["T1", "T2", "chain:hip"], {"joint": "knee", "side": "parent"})
    assert segments[doc["joints"]["hip"]["child"]] == (["T1", "T2", "T3"], {"joint": "hip", "side": "child"})
    assert len(doc["segments"]) == 4
    again, _, _ = _start(cfg)
    for old, new in zip(runners, again, strict=True):
        assert new.estimator.frozen and new.loaded_from, new.last_error
        assert fit_to_dict(new.estimator.solution) == fit_to_dict(old.estimator.solution)


@pytest.mark.ros
def test_a_node_loads_its_file_and_save_rewrites_it(calibrated: dict[str, Any], tmp_path: Path) -> None:
    """The one real node: the node-level parameter, every joint loaded frozen at start, ~/save through the service."""
    pytest.importorskip("rclpy")
    import signal
    import subprocess
    import sys

    import rclpy
    from rclpy.node import Node
    from std_srvs.srv import Trigger

    domain = os.environ.get("ROS_DOMAIN_ID", "73")
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": domain}
    path = tmp_path / "subject.yaml"
    path.write_bytes(calibrated["path"].read_bytes())
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=int(domain))
    client_node = Node("node_calibration_client", context=context)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(client_node)
    client = client_node.create_client(Trigger, "/jointfit/save")
    proc = subprocess.Popen(
        [sys.executable, "-m", "jointfit_ros.node", "--ros-args", "--params-file", str(CONFIG),
         "-p", f"calibration_file:={path}", "-p", "solver_process:=false"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    try:
        assert client.wait_for_service(timeout_sec=30.0), "node's ~/save not available"
        future = client.call_async(Trigger.Request())
        executor.spin_until_future_complete(future, timeout_sec=10.0)
        answer = future.result()
        assert answer is not None
        # every joint loaded (frozen, with its estimate), so every one is saved: no frame was sent
        assert answer.success, answer.message
        assert answer.message == "; ".join(f"{r.cfg.name}: saved {path}" for r in calibrated["runners"])
    finally:
        proc.send_signal(signal.SIGINT)
        log, _ = proc.communicate(timeout=20)
        executor.shutdown()
        client_node.destroy_node()
        rclpy.try_shutdown(context=context)
    assert "Traceback" not in log, log
    for r in calibrated["runners"]:
        assert f"{r.cfg.name}: calibration loaded from {path} (joint {r.cfg.name}); starting frozen" in log, log
    saved = load_node_calibration(path)
    _assert_same(saved, calibrated["doc"])
    assert path.with_name("subject.yaml.bak").read_bytes() == calibrated["path"].read_bytes()


def test_jointfit_urdf_takes_a_node_files_units_and_refuses_what_the_node_would_not_load(
    calibrated: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A node file in mm gives a URDF in metres; a calibration the node refuses gives one line, exit 1.

    ``jointfit urdf`` took every length as metres whatever the node file's ``units`` (a 1000x
    skeleton from a millimetre fit), and wrote URDFs of not-identifiable, newer-version or zero-axis
    calibrations (a NaN axis), or stopped with a traceback on a string in a point.
    """
    import yaml

    from jointfit_core.urdf import urdf_from_calibrations
    from jointfit_ros.urdf_cli import urdf_main

    doc = yaml.safe_load(calibrated["path"].read_text())
    mm = tmp_path / "mm.yaml"
    mm.write_text(yaml.safe_dump(dict(doc, units="mm"), sort_keys=False))
    assert urdf_main([str(mm)]) == 0
    cals = [j["calibration"] for j in doc["joints"].values()]
    assert capsys.readouterr().out == urdf_from_calibrations(cals, metres_per_unit=1e-3)
    assert urdf_main([str(mm), str(calibrated["path"])]) == 1  # mm and m together: no common unit
    assert "different units" in capsys.readouterr().err

    knee = next(c for c in cals if c["kind"] == "hinge")
    est = knee["estimate"]
    bad = {
        "not identifiable": dict(knee, estimate=dict(est, identifiable=False, reason="flex the joint")),
        "newer version": dict(knee, version=99),
        "zero axis": dict(knee, estimate=dict(est, direction_parent=[0.0, 0.0, 0.0])),
        "string point": dict(knee, estimate=dict(est, point_parent=["1e300", 0.0, 0.0])),
    }
    for what, calibration in bad.items():
        path = tmp_path / f"{what.replace(' ', '_')}.yaml"
        path.write_text(yaml.safe_dump(calibration, sort_keys=False))
        assert urdf_main([str(path)]) == 1, what
        out, err = capsys.readouterr()
        assert out == "" and err.count("\n") == 1 and str(path) in err, (what, err)
