"""Calibration files validated on load: a bad, foreign or stale file is kept untouched, named, and not used."""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from jointfit_core.atomic import STALE_TEMPORARY_S, remove_stale_temporaries
from jointfit_core.calibration import load_calibration, save_calibration
from jointfit_core.synthetic import two_segment_motion
from jointfit_ros.params import ConfigError, node_config
from jointfit_ros.runner import JointRunner

NAMES = [f"P{i}" for i in range(4)] + [f"C{i}" for i in range(4)]


def _values(path: Path, **extra: Any) -> dict[str, Any]:
    values: dict[str, Any] = {
        "joints": ["hip"],
        "units": "mm",
        "marker_names": NAMES,
        "hip.parent_markers": NAMES[:4],
        "hip.child_markers": NAMES[4:],
        "hip.template_frames": 20,
        "hip.window": 2000,
        "hip.calibration_file": str(path),
    }
    values.update(extra)
    return values


def _runner(path: Path, **extra: Any) -> JointRunner:
    cfg = node_config(_values(path, **extra))
    return JointRunner(cfg.joints[0], cfg)


@pytest.fixture(scope="module")
def saved(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """A valid calibration of the joint ``hip`` (as ~/save writes it)."""
    path = tmp_path_factory.mktemp("cal") / "hip.yaml"
    runner = _runner(path)
    rng = np.random.default_rng(2)
    motion = two_segment_motion(rng, kind="ball")
    t = np.arange(1500) / 100.0
    yp, yc = motion.markers_at(t)
    frames = np.concatenate([yp, yc], axis=1) + rng.normal(0.0, 0.5, (t.size, 8, 3))
    for k in range(t.size):
        runner.markers_frame(int(t[k] * 1e9), frames[k])
        runner.estimate(t[k])
    runner.save()
    return load_calibration(path)


def test_a_valid_file_loads_and_records_its_joint(tmp_path: Path, saved: dict[str, Any]) -> None:
    assert saved["joint"] == "hip" and saved["parent_markers"] == NAMES[:4] and saved["child_markers"] == NAMES[4:]
    path = tmp_path / "hip.yaml"
    save_calibration(path, saved)
    runner = _runner(path)
    assert runner.estimator.frozen and runner.loaded_from == str(path) and runner.load_notes == []
    differs = _runner(path, **{"hip.window": 300})
    assert differs.estimator.frozen
    assert any("window is 2000, the configuration's 300" in n for n in differs.load_notes), differs.load_notes


def _broken(saved: dict[str, Any], case: str) -> dict[str, Any] | bytes:
    import copy

    d = copy.deepcopy(saved)
    est = d["estimate"]
    if case == "nan":
        est["centre_parent"][0] = float("nan")
    elif case == "huge":
        est["centre_parent"] = [1e300, 0.0, 0.0]
    elif case == "null":
        est["centre_parent"] = None
    elif case == "no estimate":
        d["estimate"] = None
    elif case == "noise -1":
        d["noise_std_parent"] = -1.0
    elif case == "noise nan":
        d["noise_std_child"] = float("nan")
    elif case == "n_markers":
        d["n_markers"] = [3, 4]
    elif case == "negative variance":
        est["cov_parent"][0][0] = -1.0
    elif case == "another joint":
        d["joint"] = "knee"
    elif case == "markers reordered":
        d["parent_markers"] = [NAMES[1], NAMES[0], NAMES[2], NAMES[3]]
    elif case == "hinge":
        d["kind"] = "hinge"
    elif case == "newer":
        d["version"] = 99
    elif case == "not utf-8":
        return b"\xff\xfe\x00garbage\x81"
    return d


@pytest.mark.parametrize(
    "case",
    ["nan", "huge", "null", "no estimate", "noise -1", "noise nan", "n_markers", "negative variance",
     "another joint", "markers reordered", "hinge", "newer", "not utf-8"],
)
def test_a_bad_file_is_kept_untouched_named_and_not_used(tmp_path: Path, saved: dict[str, Any], case: str) -> None:
    path = tmp_path / "hip.yaml"
    content = _broken(saved, case)
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        import yaml

        path.write_text(yaml.safe_dump(content))
    before = path.read_bytes()
    runner = _runner(path)
    assert not runner.estimator.frozen and runner.loaded_from == ""
    assert str(path) in runner.last_error and "not loaded (kept as it is)" in runner.last_error
    assert path.read_bytes() == before
    assert runner.status().message  # says something (STALE: no frames yet), never raises


def test_a_fifo_does_not_block_the_start(tmp_path: Path) -> None:
    path = tmp_path / "hip.yaml"
    os.mkfifo(path)
    runner = _runner(path)
    assert "not a regular file" in runner.last_error


def test_two_joints_may_not_share_a_file(tmp_path: Path) -> None:
    values = _values(tmp_path / "x.yaml", joints=["hip", "knee"])
    values.update({"knee.parent_markers": NAMES[:4], "knee.child_markers": NAMES[4:],
                   "knee.calibration_file": str(tmp_path / "." / "x.yaml")})
    with pytest.raises(ConfigError, match=r"knee\.calibration_file.*also hip's"):
        node_config(values)


def test_stale_temporaries_are_removed_and_nothing_else(tmp_path: Path) -> None:
    target = tmp_path / "hip.yaml"
    target.write_text("x")
    old = [tmp_path / ".hip.yaml.abcd1234.tmp", tmp_path / ".hip.yaml.zz_9y8x7.bak.tmp"]
    fresh = tmp_path / ".hip.yaml.fresh123.tmp"
    others = [tmp_path / ".knee.yaml.abcd1234.tmp", tmp_path / "hip.yaml.bak", tmp_path / ".hip.yaml.toolong123.tmp"]
    for p in [*old, fresh, *others]:
        p.write_text("t")
    past = time.time() - STALE_TEMPORARY_S - 10.0
    for p in [*old, *others]:
        os.utime(p, (past, past))
    assert sorted(remove_stale_temporaries(target)) == sorted(old)
    assert all(p.exists() for p in [fresh, *others, target])
    runner = _runner(target)  # the runner cleans at start (here: nothing left to clean)
    assert runner.load_notes == [] and fresh.exists()


def _frames(seed: int = 2) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    motion = two_segment_motion(rng, kind="ball")
    t = np.arange(1500) / 100.0
    yp, yc = motion.markers_at(t)
    return np.concatenate([yp, yc], axis=1) + rng.normal(0.0, 0.5, (t.size, 8, 3)), t


@pytest.mark.parametrize("changed", [False, True])
def test_a_file_without_names_is_checked_against_the_live_markers(tmp_path: Path, saved: dict[str, Any],
                                                                  changed: bool) -> None:
    """An old file (no marker names) whose markers no longer match: discarded after the first frames, kept on disk."""
    old = {k: v for k, v in saved.items() if k not in ("joint", "parent_markers", "child_markers",
                                                       "parent_pose_topic", "child_pose_topic")}
    path = tmp_path / "hip.yaml"
    save_calibration(path, old)
    before = path.read_bytes()
    order = [NAMES[1], NAMES[0], NAMES[2], NAMES[3]] if changed else NAMES[:4]  # two pelvis markers swapped
    runner = _runner(path, **{"hip.parent_markers": order})
    assert runner.estimator.frozen
    frames, t = _frames()
    for k in range(30):
        runner.markers_frame(int((100.0 + t[k]) * 1e9), frames[k])
    assert runner.estimator.frozen is (not changed)
    if changed:
        assert "discarded (kept as it is)" in runner.last_error and "differ from its templates" in runner.last_error
        assert runner.loaded_from == ""
    assert path.read_bytes() == before


def test_environment_variables_in_the_path_are_expanded(tmp_path: Path, saved: dict[str, Any],
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("JOINTFIT_TEST_DIR", str(tmp_path / "lab"))
    save_calibration(tmp_path / "lab" / "hip.yaml", saved)
    runner = _runner(Path("$JOINTFIT_TEST_DIR/hip.yaml"))
    assert runner.calibration_path == tmp_path / "lab" / "hip.yaml" and runner.estimator.frozen
    assert runner.loaded_from == str(tmp_path / "lab" / "hip.yaml")
    monkeypatch.delenv("JOINTFIT_TEST_DIR")
    with pytest.raises(ConfigError, match="environment variable that is not set"):
        node_config(_values(Path("$JOINTFIT_TEST_DIR/hip.yaml")))
