"""``jointfit status`` / ``jointfit call`` through their entry point, and the done signal, against a live node.

The node runs in its own process, fed with the fake mocap's hip (ball) and
knee (hinge) by a publisher in the test process (test_node's client); the CLI
commands run as ``python -m jointfit_ros.cli ...`` subprocesses.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")

from test_node import RATE, _Client, _start_node, _stop

from jointfit_ros.conversions import diagnostic_status, pose_array_bytes
from jointfit_ros.fake_mocap import frame_at, make_rigs, marker_names
from jointfit_ros.shell import status_lines
from jointfit_ros.status_log import ERROR, OK, WARN, StatusLog

DOMAIN = str(1 + os.getpid() % 19)
ENV = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": DOMAIN}
TARGET_MM = 0.5


def _cli(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "jointfit_ros.cli", *args], env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True,
    )


# ---------------------------------------------------------------------------- without a node


def test_status_lines_read_units_estimate_coverage_and_done() -> None:
    hip = diagnostic_status(
        "jointfit: hip", 0, "estimating; done: centre sd 0.0008 m <= target 0.001 m",
        {"centre_parent (m)": [0.01, -0.02, 0.3], "centre sd (m)": 0.0008, "coverage (%)": 100.0, "done": True,
         "frames in window": 1200, "parent gated (%)": 0.0, "child gated (%)": 0.5},
        hardware_id="/jointfit",
    )
    knee = diagnostic_status(
        "jointfit: knee", 1, "not identifiable",
        {"direction_parent (unit vector)": [1.0, 0.0, 0.0], "direction sd (deg)": 7.5, "point_parent (mm)": [1, 2, 3],
         "point sd (mm)": 4.0, "coverage (%)": 44.4, "frames in window": 300},
        hardware_id="/jointfit",
    )
    other = diagnostic_status("jointfit: hip", 2, "another node's", {}, hardware_id="/lab1/jointfit")
    inp = diagnostic_status("jointfit: input", 0, "receiving", {"messages": 5, "input rate (Hz)": 250.0},
                            hardware_id="/jointfit")
    lines = status_lines([hip, knee, other, inp], "/jointfit")
    assert len(lines) == 3 and lines[0].startswith("input OK | 5 messages | 250 Hz"), lines
    assert lines[1].startswith("hip OK | centre (0.01, -0.02, 0.3) m sd 0.0008 m | coverage 100 % | DONE"), lines[1]
    assert "gated 0/0.5 %" in lines[1]
    assert lines[2].startswith("knee WARN | axis (1, 0, 0) sd 7.5 deg, point (1, 2, 3) mm sd 4 mm | coverage 44.4 %")
    assert status_lines([other], "/jointfit") == []
    live = diagnostic_status(  # the live anatomical results (jointfit_ros.live_geometry) in the line
        "jointfit: hip", 0, "estimating",
        {"centre_parent (mm)": [46.1, -90.7, -79.7], "centre in ISB pelvis (mm, right side)": [-59.0, -85.2, 90.3]},
        hardware_id="/jointfit",
    )
    assert "| ISB pelvis (-59, -85.2, 90.3) mm |" in status_lines([live], "/jointfit")[0]
    epi = diagnostic_status("jointfit: knee", 0, "estimating", {"axis to epicondyle line (deg)": 11.2},
                            hardware_id="/jointfit")
    assert "| 11.2 deg from the epicondyle line |" in status_lines([epi], "/jointfit")[0]


def test_status_log_once_per_condition() -> None:
    log = StatusLog()
    assert log.change("jointfit: hip", 3, "no frames yet") is None  # STALE at start is no news
    first = log.change("jointfit: hip", WARN, "not identifiable: rms spread ~2.1 deg")
    assert first == (WARN, "jointfit: hip: not identifiable: rms spread ~2.1 deg")
    assert log.change("jointfit: hip", WARN, "not identifiable: rms spread ~3.7 deg") is None  # same condition
    assert log.change("jointfit: hip", WARN, "marker clusters are 50 m in rms radius") is not None  # another one
    assert log.change("jointfit: hip", ERROR, "marker clusters are 50 m in rms radius") is not None  # worse
    assert log.change("jointfit: hip", OK, "estimating") == (OK, "jointfit: hip: OK again: estimating")
    assert log.change("jointfit: hip", OK, "estimating; centre sd 2 mm") is None
    assert log.change("jointfit: knee", OK, "estimating") is None


def test_call_and_status_without_a_node_exit_1_with_one_line() -> None:
    calls = {
        "no service /lab1/jointfit/freeze within 1 s": _cli("call", "freeze", "--node", "/lab1/jointfit", "--timeout", "1"),
        "no /diagnostics from /jointfit within 1 s": _cli("status", "--once", "--timeout", "1"),
    }
    for text, proc in calls.items():
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == 1, (out, err)
        assert out == "" and len(err.strip().splitlines()) == 1 and text in err and "Traceback" not in err, err
    bad = _cli("call", "save", "true")
    out, err = bad.communicate(timeout=60)
    assert bad.returncode == 2 and "save takes no value" in err and len(err.strip().splitlines()) == 1


# ---------------------------------------------------------------------------- against a node


def _params(path: Path, tmp: Path) -> Path:
    path.write_text(f"""jointfit:
  ros__parameters:
    joints: [hip, knee]
    marker_names: [{", ".join(marker_names(0))}]
    estimate_period: 0.05
    diagnostics_period: 0.25
    solver_process: false         # solves at once from the start (a worker may take seconds to start here)
    hip:
      type: ball
      parent_markers: [PELV1, PELV2, PELV3, PELV4]
      child_markers: [THIGH1, THIGH2, THIGH3, THIGH4]
      template_frames: 30
      attachment: rigid             # the fake mocap's markers (skin would add its detection-limit part)
      calibration_file: "{tmp / "hip.yaml"}"
      target_sd: {TARGET_MM / 1000.0}
      auto_freeze: true
    knee:
      type: hinge
      parent_markers: [FEMUR1, FEMUR2, FEMUR3, FEMUR4]
      child_markers: [SHANK1, SHANK2, SHANK3, SHANK4]
      template_frames: 30
      attachment: rigid
      target_sd: 1.0
""")
    return path


class _Feed:
    """The fake mocap, published at RATE: stamps always advance, the motion only when moving."""

    def __init__(self, client: _Client) -> None:
        self.client, self.rigs, self.rng = client, make_rigs(7), np.random.default_rng(7)
        self.stamp, self.motion = 1000.0, 0.0

    def run(self, seconds: float, moving: bool = True) -> None:
        start = time.monotonic()
        for k in range(int(seconds * RATE)):
            frame = frame_at(self.rigs, self.motion, self.rng, 0.5, 0.0) / 1000.0
            self.client.pub.publish(pose_array_bytes(int(self.stamp * 1e9), "world", frame))
            self.stamp += 1.0 / RATE
            self.motion += 1.0 / RATE if moving else 0.0
            self.client.executor.spin_once(timeout_sec=0.0)
            lag = start + (k + 1) / RATE - time.monotonic()
            if lag > 0:
                self.client.spin_until(lambda: False, lag)

    def until_done(self, *procs: subprocess.Popen[str], moving: bool = True, limit: float = 60.0) -> tuple[str, str]:
        """Keep publishing while CLI subprocesses run; the first one's output."""
        end = time.monotonic() + limit
        while any(p.poll() is None for p in procs) and time.monotonic() < end:
            self.run(0.2, moving)
        return procs[0].communicate(timeout=10)


@pytest.fixture
def client() -> Iterator[_Client]:
    c = _Client(DOMAIN)
    yield c
    c.close()


def _hip_history(client: _Client) -> list[dict[str, str]]:
    out = []
    for arr in client.diag:
        for st in arr.status:
            if st.name == "jointfit: hip":
                out.append({"message": st.message, "level": str(st.level[0]), **{kv.key: kv.value for kv in st.values}})
    return out


@pytest.mark.ros
def test_shell_commands_and_done_signal_against_a_live_node(client: _Client, tmp_path: Path) -> None:
    params = _params(tmp_path / "params.yaml", tmp_path)
    proc = _start_node(params, ENV)
    try:
        assert client.spin_until(lambda: client.pub.get_subscription_count() > 0, 30.0), "node not discovered"
        feed = _Feed(client)
        feed.run(2.0, moving=False)  # a still stance first: not identifiable, coverage low
        out, err = feed.until_done(_cli("status", "--once", "--timeout", "20"), moving=False)
        assert err == "" and out.splitlines()[0].startswith("input "), (out, err)
        assert any(line.startswith("hip WARN") for line in out.splitlines()), out
        end = time.monotonic() + 30.0
        while client.status("hip").get("frozen") != "True" and time.monotonic() < end:
            feed.run(0.5)
        assert client.status("hip").get("frozen") == "True", client.status("hip")
        feed.run(1.0)
        hip = _hip_history(client)
        covered = [float(h["coverage (%)"]) for h in hip if "coverage (%)" in h]
        assert covered[0] < 50.0 and covered[-1] == 100.0, covered  # rising from the still stance
        done = [h for h in hip if h.get("done") == "True"]
        assert done, "never done"
        for h in done:  # done: identifiable, no warning, sd at most the target
            assert h["identifiable"] == "True" and h["level"] == "0" and float(h["centre sd (m)"]) <= TARGET_MM / 1e3
        first_done = hip.index(done[0])
        assert any(float(h["centre sd (m)"]) > TARGET_MM / 1e3 for h in hip[:first_done] if "centre sd (m)" in h)
        assert (tmp_path / "hip.yaml").exists(), "auto_freeze did not save"
        assert "auto_freeze: frozen, saved" in client.status("hip")["message"]
        assert client.status("knee")["frozen"] == "False"  # no auto_freeze for the knee

        # The shell: the knee too is identifiable by now, so freeze succeeds; save writes the hip's file.
        status, freeze = _cli("status", "--once"), _cli("call", "freeze")
        line = feed.until_done(status, freeze)[0]
        assert "hip OK | centre (" in line and " m sd " in line and "DONE" in line and "| frozen |" in line, line
        assert "knee OK | axis (" in line, line
        out, err = freeze.communicate(timeout=10)
        assert freeze.returncode == 0 and "hip: frozen; knee: frozen" in out and err == "", (out, err)
        out, err = feed.until_done(_cli("call", "save"))
        assert "hip: saved" in out and "knee: no calibration_file configured" in out, (out, err)
        reset = _cli("call", "reset")  # from here on a still stance: nothing to identify
        out, err = feed.until_done(reset, moving=False)
        assert reset.returncode == 0 and out.startswith("reset hip, knee"), (out, err)
        assert client.spin_until(lambda: client.status("hip").get("frozen") == "False", 5.0)
        thaw, refused = _cli("call", "freeze", "false"), _cli("call", "freeze")  # after the reset: nothing identifiable
        out, _ = feed.until_done(thaw, refused, moving=False)
        assert thaw.returncode == 0 and "hip: estimating" in out
        out, _ = refused.communicate(timeout=10)
        assert refused.returncode == 1 and "cannot freeze" in out, out
        assert proc.poll() is None, "the node died"
    finally:
        log = _stop(proc)
    assert "Traceback" not in log, log
    assert log.count("auto_freeze: frozen") == 1, log  # once, logged
    warned = [ln for ln in log.splitlines() if "jointfit: hip: not identifiable" in ln]
    statuses = [h for h in hip if h["level"] == "1"]
    assert 1 <= len(warned) < len(statuses), (len(warned), len(statuses))  # once per condition, not per period
