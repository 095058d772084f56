"""A calibration file survives SIGKILL at any instant of a save: always the old or the new complete version.

Two levels: a process that saves two different calibrations in a tight loop
is killed at random instants (many kills, cheap); and the node itself,
started frozen from a calibration and answering ``~/save`` calls in a loop,
is killed with SIGKILL several times. After every kill the file at the
configured path must load and be one of the complete versions, and the
restarted node must load it.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from jointfit_core.atomic import STALE_TEMPORARY_S
from jointfit_core.calibration import load_calibration, save_calibration
from jointfit_core.estimator import OnlineJoint
from jointfit_core.synthetic import two_segment_motion

REPO = Path(__file__).resolve().parents[1]


def _calibration(seed: int) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    motion = two_segment_motion(rng, kind="ball")
    t = np.arange(300) / 100.0
    parent, child = motion.markers_at(t)
    est = OnlineJoint("ball", window=1000, template_frames=20)
    for k in range(t.size):
        est.update(parent[k] + rng.normal(0, 0.5, (4, 3)), child[k] + rng.normal(0, 0.5, (4, 3)), t[k])
    return est.to_dict()


_SAVER = textwrap.dedent(
    """
    import sys, yaml
    from jointfit_core.calibration import save_calibration
    path, a, b = sys.argv[1:]
    versions = [yaml.safe_load(open(a)), yaml.safe_load(open(b))]
    print("ready", flush=True)
    k = 0
    while True:
        save_calibration(path, versions[k % 2])
        k += 1
    """
)


def test_sigkill_during_save_loop_leaves_old_or_new(tmp_path: Path) -> None:
    a, b = _calibration(1), _calibration(2)
    assert a != b
    save_calibration(tmp_path / "a.yaml", a)
    save_calibration(tmp_path / "b.yaml", b)
    target = tmp_path / "calib" / "joint.yaml"
    save_calibration(target, a)
    rng = np.random.default_rng(0)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    for _ in range(12):
        proc = subprocess.Popen(
            [sys.executable, "-c", _SAVER, str(target), str(tmp_path / "a.yaml"), str(tmp_path / "b.yaml")],
            env=env, stdout=subprocess.PIPE, text=True,
        )
        assert proc.stdout is not None and proc.stdout.readline() == "ready\n"
        time.sleep(float(rng.uniform(0.005, 0.15)))  # dozens of saves per kill window
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        assert load_calibration(target) in (a, b)
        backup = target.with_name(target.name + ".bak")
        assert load_calibration(backup) in (a, b)
    leftovers = [p.name for p in target.parent.iterdir() if p.name not in ("joint.yaml", "joint.yaml.bak")]
    assert all(name.startswith(".joint.yaml.") for name in leftovers), leftovers  # only hidden temporaries


@pytest.mark.ros
def test_node_killed_during_saves_reloads(tmp_path: Path) -> None:
    pytest.importorskip("rclpy")
    import rclpy
    from rclpy.node import Node
    from std_srvs.srv import Trigger

    from jointfit_ros.fake_mocap import marker_names

    domain = str(30 + os.getpid() % 30)
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": domain}
    calibration = tmp_path / "hip.yaml"
    original = _calibration(3)
    save_calibration(calibration, original)
    params = tmp_path / "params.yaml"
    params.write_text(
        f"""jointfit:
  ros__parameters:
    joints: [hip]
    marker_names: [{", ".join(marker_names(0))}]
    hip:
      type: ball
      parent_markers: [PELV1, PELV2, PELV3, PELV4]
      child_markers: [THIGH1, THIGH2, THIGH3, THIGH4]
      calibration_file: "{calibration}"
"""
    )
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=int(domain))
    node = Node("persistence_client", context=context)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)
    client = node.create_client(Trigger, "/jointfit/save")
    rng = np.random.default_rng(1)
    try:
        for _ in range(3):
            proc = subprocess.Popen(
                [sys.executable, "-m", "jointfit_ros.node", "--ros-args", "--params-file", str(params)],
                env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            )
            try:
                assert client.wait_for_service(timeout_sec=30.0), "node's ~/save not available"
                # The killed node's service may linger in the graph: retry until the new node answers.
                end = time.monotonic() + 30.0
                while time.monotonic() < end:
                    first = client.call_async(Trigger.Request())
                    executor.spin_until_future_complete(first, timeout_sec=2.0)
                    if first.done():
                        break
                assert first.done() and first.result().success, "the new node never answered ~/save"
                saves = 0
                kill_at = time.monotonic() + float(rng.uniform(0.2, 0.8))
                pending = []
                while time.monotonic() < kill_at:
                    pending.append(client.call_async(Trigger.Request()))  # keep the node saving
                    executor.spin_once(timeout_sec=0.005)
                    saves += sum(f.done() for f in pending)
                    pending = [f for f in pending if not f.done()]
                assert saves > 0
            finally:
                proc.send_signal(signal.SIGKILL)
                proc.wait(timeout=10)
            saved = load_calibration(calibration)
            # Every save of a node that started frozen from the file writes the same estimate.
            est = OnlineJoint.from_dict(saved)
            assert est.frozen and saved["estimate"] == original["estimate"]
        # The kills leave temporaries beside the file; a node started later removes them (its own
        # pattern only, once they are STALE_TEMPORARY_S old), and touches nothing else.
        (tmp_path / "notes.txt").write_text("mine")
        time.sleep(STALE_TEMPORARY_S + 0.5)
        proc = subprocess.Popen(
            [sys.executable, "-m", "jointfit_ros.node", "--ros-args", "--params-file", str(params)],
            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )
        try:
            assert client.wait_for_service(timeout_sec=30.0)
            # the killed node's service may linger in the graph: the new node has started (and
            # cleaned up) once it answers
            end = time.monotonic() + 30.0
            answered = False
            while time.monotonic() < end and not answered:
                future = client.call_async(Trigger.Request())
                executor.spin_until_future_complete(future, timeout_sec=2.0)
                answered = future.done() and future.result().success
            assert answered, "the new node never answered ~/save"
        finally:
            proc.send_signal(signal.SIGINT)
            proc.wait(timeout=10)
        left = sorted(p.name for p in tmp_path.iterdir())
        assert left == ["hip.yaml", "hip.yaml.bak", "notes.txt", "params.yaml"], left
        assert load_calibration(calibration)["estimate"] == original["estimate"]
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def test_a_symlinked_calibration_is_written_through_and_the_link_kept(tmp_path: Path) -> None:
    """A calibration kept in a shared place and linked into the workspace: before, a save replaced the link
    with a file, so the shared calibration was never updated and the link was gone (hunt, offline)."""
    from jointfit_core.atomic import write_atomic

    shared = tmp_path / "shared" / "hip.yaml"
    shared.parent.mkdir()
    shared.write_text("old: 1\n")
    link = tmp_path / "work" / "hip.yaml"
    link.parent.mkdir()
    link.symlink_to(shared)
    written = write_atomic(link, "new: 2\n", keep_backup=True)
    assert link.is_symlink() and os.readlink(link) == str(shared)
    assert written == shared.resolve()
    assert shared.read_text() == "new: 2\n" and link.read_text() == "new: 2\n"
    assert (shared.parent / "hip.yaml.bak").read_text() == "old: 1\n"
    assert not (link.parent / "hip.yaml.bak").exists()
    # a link to a file that does not exist yet: created where it points
    dangling = tmp_path / "work" / "knee.yaml"
    dangling.symlink_to(tmp_path / "shared" / "knee.yaml")
    write_atomic(dangling, "k: 3\n")
    assert dangling.is_symlink() and (tmp_path / "shared" / "knee.yaml").read_text() == "k: 3\n"
