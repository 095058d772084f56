"""Namespaced nodes without ROS: parameter-file entries, status names, several nodes in `jointfit status`."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from jointfit_ros.conversions import diagnostic_status
from jointfit_ros.naming import entry_hint, entry_matches, params_files, status_prefix
from jointfit_ros.params import ConfigError, node_config, params_from_file
from jointfit_ros.shell import StatusRounds, status_lines, status_nodes

CONFIG = Path(__file__).resolve().parents[1] / "config" / "two_subjects"


@pytest.mark.parametrize(
    ("key", "node", "expected"),
    [
        ("/**", "/subject_a/jointfit", True),
        ("/**", "/jointfit", True),
        ("/subject_a/jointfit", "/subject_a/jointfit", True),
        ("subject_a/jointfit", "/subject_a/jointfit", True),  # rcl: no leading slash is the same name
        ("/subject_a/jointfit", "/subject_b/jointfit", False),
        ("jointfit", "/subject_a/jointfit", False),  # /jointfit, a node in the root namespace
        ("jointfit", "/jointfit", True),
        ("/*/jointfit", "/subject_a/jointfit", True),
        ("/*/jointfit", "/jointfit", False),
        ("/*/jointfit", "/lab/subject_a/jointfit", False),
        ("/**/jointfit", "/lab/subject_a/jointfit", True),
        ("/**/jointfit", "/jointfit", True),
        ("/**/jointfit", "/subject_a/jf", False),
        ("/subject_a/*", "/subject_a/jf", True),
    ],
)
def test_entry_matches_as_rcl_does(key: str, node: str, expected: bool) -> None:
    # (checked against the node: /*/jointfit, /**/jointfit and subject_a/jointfit reach /subject_a/jointfit,
    # jointfit does not)
    assert entry_matches(key, node) is expected


def test_status_prefix_keeps_the_root_node_and_names_the_namespace() -> None:
    assert status_prefix("/jointfit") == "jointfit"
    assert status_prefix("/subject_a/jointfit") == "subject_a/jointfit"
    assert status_prefix("jointfit_b") == "jointfit_b"


def test_params_files_and_the_hint_for_an_entry_of_another_node() -> None:
    argv = ["--ros-args", "-r", "__ns:=/subject_a", "--params-file", "a.yaml", "-p", "x:=1", "--params-file", "b.yaml"]
    assert params_files(argv) == ["a.yaml", "b.yaml"]
    assert params_files(["--params-file", "a.yaml"]) == []  # not a ROS argument
    hint = entry_hint([("a.yaml", ["jointfit"])], "/subject_a/jointfit")
    assert "/subject_a/jointfit" in hint and "a.yaml: jointfit" in hint and "'/subject_a/jointfit:'" in hint
    assert entry_hint([("a.yaml", ["/**"])], "/subject_a/jointfit") == ""
    assert entry_hint([], "/subject_a/jointfit") == ""


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_params_from_file_reads_the_entries_a_namespaced_node_gets(tmp_path: Path) -> None:
    both = _write(tmp_path / "both.yaml", """
/**:
  ros__parameters: {units: mm, stale_after: 5.0}
/subject_a/jointfit:
  ros__parameters: {joints: [hip], stale_after: 7.0}
/subject_b/jointfit:
  ros__parameters: {joints: [knee]}
""")
    a = params_from_file(both, "/subject_a/jointfit")
    assert a == {"units": "mm", "stale_after": 7.0, "joints": ["hip"]}  # the node's own entry overrides /**
    assert params_from_file(both, "subject_b/jointfit") == {"units": "mm", "stale_after": 5.0, "joints": ["knee"]}
    assert params_from_file(both) == {"units": "mm", "stale_after": 5.0}  # two named entries: /jointfit gets /**
    with pytest.raises(ConfigError, match=r"no entry for node /subject_c/x .*entries"):
        params_from_file(_write(tmp_path / "a.yaml", "/subject_a/jointfit: {ros__parameters: {joints: [hip]}}\n"),
                         "/subject_c/x")
    one = _write(tmp_path / "one.yaml", "/**:\n  ros__parameters: {units: mm}\n/subject_a/jointfit:\n"
                 "  ros__parameters: {joints: [hip]}\n")
    assert params_from_file(one) == {"units": "mm", "joints": ["hip"]}  # its only node entry, with /**


@pytest.mark.parametrize("subject", ["a", "b"])
def test_the_two_subject_configs_are_each_for_their_own_node(subject: str) -> None:
    path = CONFIG / f"subject_{subject}.yaml"
    cfg = node_config(params_from_file(path, f"/subject_{subject}/jointfit"))
    assert [j.name for j in cfg.joints] == ["hip", "knee"] and cfg.marker_topic == "markers"
    assert {j.calibration_file for j in cfg.joints} == {
        f"~/.ros/jointfit/subject_{subject}/hip.yaml", f"~/.ros/jointfit/subject_{subject}/knee.yaml"
    }
    other = "b" if subject == "a" else "a"
    with pytest.raises(ConfigError, match="no entry for node"):
        params_from_file(path, f"/subject_{other}/jointfit")  # the other subject's node gets nothing from it


def _statuses(node: str, level: int, legacy: bool = False) -> list[object]:
    prefix = "jointfit" if legacy else status_prefix(node)
    return [
        diagnostic_status(f"{prefix}: input", 0, "receiving", {"messages": 5}, hardware_id=node),
        diagnostic_status(f"{prefix}: hip", level, f"{node} hip", {"frames in window": 10}, hardware_id=node),
    ]


def test_status_lines_keep_two_namespaced_nodes_apart() -> None:
    a, b = _statuses("/subject_a/jointfit", 0), _statuses("/subject_b/jointfit", 1)
    both = a + b
    assert status_nodes(both) == ["/subject_a/jointfit", "/subject_b/jointfit"]
    lines = status_lines(both, "/subject_a/jointfit")
    assert len(lines) == 2 and lines[1].startswith("hip OK") and lines[1].endswith("/subject_a/jointfit hip")
    assert status_lines(both, "/subject_b/jointfit")[1].startswith("hip WARN")
    assert status_lines(both, "/jointfit") == []
    # an older node in a namespace named its statuses "jointfit: hip" (hardware_id set): still read
    assert status_lines(_statuses("/lab1/jointfit", 2, legacy=True), "/lab1/jointfit")[1].startswith("hip ERROR")


def test_status_rounds_once_waits_for_every_named_node_and_names_them() -> None:
    a, b = _statuses("/subject_a/jointfit", 0), _statuses("/subject_b/jointfit", 1)
    rounds = StatusRounds(["/subject_a/jointfit", "/subject_b/jointfit"])
    rounds.add(a)
    assert not rounds.complete() and rounds.missing() == ["/subject_b/jointfit"]
    rounds.add(b)
    assert rounds.complete()
    text = rounds.text("/subject_b/jointfit", rounds.first["/subject_b/jointfit"])
    assert text.splitlines()[1].startswith("/subject_b/jointfit hip WARN")
    single = StatusRounds(["/subject_a/jointfit"])
    single.add(b + a)
    assert single.text("/subject_a/jointfit", single.first["/subject_a/jointfit"]).startswith("input OK")
    every = StatusRounds(None)
    every.add(a)
    every.add(b)
    assert not every.complete(now=10.0) and every.nodes == ["/subject_a/jointfit", "/subject_b/jointfit"]
    every.add(a)  # the first node heard again: b, discovered later, not yet twice
    assert not every.complete(now=10.0)
    every.add(b)
    every.add(a)  # the first node three times, every node twice: a node a period late is waited for
    assert every.complete(now=10.0) and every.missing() == []
    late = StatusRounds(None)
    for arr in (b, b, a, b):  # b heard twice before a was first heard (the CI race): not yet a round
        late.add(arr)
        assert not late.complete(now=10.0)
    late.add(a)
    assert late.complete(now=10.0)


def test_a_silent_node_in_the_graph_is_called_running_and_maybe_busy_not_absent() -> None:
    """``--once`` at a 12-joint node busy 97 % of its time at 1 kHz said "is the node running?" (2026-12-07): its
    /diagnostics reached a new subscriber only after ~10 s on the loaded machine."""
    rounds = StatusRounds(["/jointfit"])
    assert "(is the node running, with the same ROS_DOMAIN_ID=7?)" in rounds.silence(5.0, "7")
    rounds.note_graph(["/fake_mocap"], now=0.0)
    assert "is the node running" in rounds.silence(5.0, "7")
    rounds.note_graph(["/fake_mocap", "/jointfit"], now=1.0)
    text = rounds.silence(5.0, "7")
    assert text.startswith("jointfit status: /jointfit is running (it publishes /diagnostics) but none reached this")
    assert "within 5 s: on a busy machine" in text and "--timeout 30" in text


def test_status_rounds_every_node_waits_for_each_diagnostics_publisher_in_the_graph() -> None:
    a, b = _statuses("/subject_a/jointfit", 0), _statuses("/subject_b/jointfit", 1)
    every = StatusRounds(None)
    every.note_graph(["/subject_a/jointfit", "/fake_mocap"], now=0.0)
    for arr in (a, a, a):
        every.add(arr)
    quiet, discovery = StatusRounds.QUIET, StatusRounds.DISCOVERY  # 8 s and 5 s
    assert not every.complete(now=0.5)  # the graph changed 0.5 s ago
    assert not every.complete(now=quiet - 0.1)  # /fake_mocap silent: maybe a node whose messages are on the way
    assert every.complete(now=quiet)  # /fake_mocap silent for QUIET s: not a jointfit node
    every.note_graph(["/subject_a/jointfit", "/fake_mocap", "/subject_b/jointfit"], now=quiet + 1.0)  # b late
    assert not every.complete(now=quiet + 2.5)  # b in the graph, not heard yet: waited for
    every.add(b)
    every.add(b)
    assert every.complete(now=quiet + 2.5) and every.nodes == ["/subject_a/jointfit", "/subject_b/jointfit"]
    silent = StatusRounds(None)
    silent.note_graph(["/subject_a/jointfit", "/subject_b/jointfit"], now=0.0)
    for arr in (a, a, a):
        silent.add(arr)
    # b never speaks: printed without it, after QUIET (the CI run of 2026-12-07 had a node silent for over 3 s)
    assert not silent.complete(now=quiet - 0.1) and silent.complete(now=quiet)
    early = StatusRounds(None)
    early.note_graph(["/subject_a/jointfit"], now=0.0)  # b's participant not discovered yet
    for arr in (a, a, a):
        early.add(arr)
    assert not early.complete(now=discovery - 0.5)  # a heard three times, the graph settled: too early to know b is not there
    early.note_graph(["/subject_a/jointfit", "/subject_b/jointfit"], now=discovery - 0.5)
    early.add(b)
    early.add(b)
    assert not early.complete(now=discovery) and early.complete(now=discovery + 0.5)  # (the graph settles first)
    assert early.nodes == ["/subject_a/jointfit", "/subject_b/jointfit"]


def _node(tmp_path: Path, *ros_args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": str(200 + os.getpid() % 10)}
    return subprocess.run(
        [sys.executable, "-m", "jointfit_ros.node", "--ros-args", *ros_args], env=env, capture_output=True,
        text=True, timeout=60, cwd=tmp_path,
    )


@pytest.mark.ros
def test_a_namespaced_node_says_which_entry_it_needs_and_rcl_errors_are_one_line(tmp_path: Path) -> None:
    pytest.importorskip("rclpy")
    plain = _write(tmp_path / "plain.yaml", "jointfit:\n  ros__parameters: {joints: [hip]}\n")
    run = _node(tmp_path, "-r", "__ns:=/subject_a", "--params-file", str(plain))
    assert run.returncode == 2 and "Traceback" not in run.stderr, run.stderr
    assert "no entry of the parameter file is for this node, /subject_a/jointfit" in run.stderr, run.stderr
    assert "key its entry '/subject_a/jointfit:'" in run.stderr and run.stderr.count("\n") == 1, run.stderr
    for bad in ("missing.yaml", str(_write(tmp_path / "bad.yaml", "/subject_*/jointfit: {ros__parameters: {}}\n"))):
        run = _node(tmp_path, "--params-file", bad)
        assert run.returncode == 2 and "Traceback" not in run.stderr, run.stderr
        line = [ln for ln in run.stderr.splitlines() if ln.startswith("jointfit_node: cannot start: ")]
        assert len(line) == 1 and "params file" in line[0] and "/project/src" not in line[0], run.stderr
