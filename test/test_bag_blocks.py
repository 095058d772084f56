"""The offline fit's bag reader process (jointfit_ros.bag_blocks): the same fit, errors passed on, no stray child.

``jointfit fit`` reads and parses a bag in a forked child while the estimators
run. Everything it computes must be what the in-process path computes, bit for
bit (the same blocks, parsed by the same function), with every kind of bad
message in the stream, across many blocks (so that the shared-memory slots are
reused), in both storages. The child's errors reach the caller as one-line
InputErrors; a child that dies, a caller that stops early and a parent that
dies all leave no process behind.
"""

from __future__ import annotations

import multiprocessing
import os
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from bagtools import write_raw_bag
from test_offline_blocks import T0, N, _stream, _values

import jointfit_ros.bag_blocks as bag_blocks
import jointfit_ros.offline as offline
from jointfit_core.errors import InputError
from jointfit_ros.offline import FitRun, run_fit
from jointfit_ros.params import node_config

pytest.importorskip("rosbags")

MSGTYPES = {"pose_array": "geometry_msgs/msg/PoseArray", "pointcloud2": "sensor_msgs/msg/PointCloud2"}


def _bag(tmp_path: Path, marker_type: str, labelled: bool, storage: str) -> Path:
    stream = _stream(marker_type, labelled, np.random.default_rng(3))
    msgs = [("/markers", MSGTYPES[marker_type], T0 + k * 1000, raw) for k, raw in enumerate(stream)]
    return write_raw_bag(tmp_path / f"bag_{storage}", msgs, storage=storage)


def _everything(run: FitRun) -> dict[str, Any]:
    assert run.router is not None
    out: dict[str, Any] = {
        "router": dict(run.router.counters),
        "last_problem": run.router.last_problem,
        "frame_id": run.router.frame_id,
        "n_inputs": run.n_inputs,
        "stamps": run.stamps,
        "frames": run.frames,
    }
    for t in run.traces:
        name = t.runner.cfg.name
        out[f"{name}.counters"] = dict(t.runner.counters)
        out[f"{name}.dropped"] = dict(t.runner.estimator.dropped)
        out[f"{name}.state"] = repr(t.runner.estimator.to_dict())
        out[f"{name}.checkpoints"] = repr(t.checkpoints)
        out[f"{name}.outputs"] = (t.output_stamps, t.residuals)
    return out


def _assert_same(a: dict[str, Any], b: dict[str, Any]) -> None:
    assert a.keys() == b.keys()
    for key in a:
        if isinstance(a[key], np.ndarray):
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)
        else:
            assert a[key] == b[key], key


@pytest.mark.parametrize(
    ("marker_type", "labelled", "extra", "storage"),
    [
        ("pose_array", False, {}, "sqlite3"),
        ("pointcloud2", True, {"label_field": "label"}, "mcap"),
    ],
)
def test_reader_process_fit_is_the_in_process_fit(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, marker_type: str, labelled: bool, extra: dict[str, Any], storage: str
) -> None:
    monkeypatch.setattr(offline, "MAX_BLOCK", 37)  # ~25 blocks: every slot used many times
    bag = _bag(tmp_path, marker_type, labelled, storage)
    cfg = node_config(_values(marker_topic="/markers", marker_type=marker_type, **extra))
    a = _everything(run_fit(bag, cfg, n_checkpoints=7, reader_process=False))
    b = _everything(run_fit(bag, cfg, n_checkpoints=7, reader_process=True))
    _assert_same(a, b)
    c = a["router"]
    assert c["malformed"] > 0 and c["wrong_frame_id"] > 0 and a["frames"].shape[0] > N - 10
    assert (c["label_problems"] > 0) == labelled
    assert multiprocessing.active_children() == []


def test_block_boundaries_and_pose_messages() -> None:
    """Blocks end at multiples of ``step`` and after ``max_block``; pose messages keep their positions."""

    class Msg:
        def __init__(self, k: int) -> None:
            self.topic = "/pose" if k % 5 == 4 else "/markers"
            self.raw = bytes([k % 256])

    blocks = list(bag_blocks.split_blocks((Msg(k) for k in range(100)), "/markers", 30, 8))
    assert [len(b) for b in blocks] == [8, 8, 8, 6, 8, 8, 8, 6, 8, 8, 8, 6, 8, 2]
    flat = [m for b in blocks for m in b]
    assert [raw[0] for _, raw in flat] == list(range(100))
    assert [t for t, _ in flat] == [("/pose" if k % 5 == 4 else None) for k in range(100)]


def _parsed_blocks(bag: Path, cfg: Any, max_block: int) -> Any:
    return bag_blocks.parsed_blocks(bag, ["/markers"], "/markers", cfg, 10**9, max_block, process=True)


@pytest.mark.parametrize("how", ["input_error", "unpicklable", "killed"])
def test_child_errors_reach_the_caller(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, how: str) -> None:
    bag = _bag(tmp_path, "pose_array", False, "mcap")
    cfg = node_config(_values(marker_topic="/markers"))
    calls = [0]
    real = bag_blocks._parse_block

    def failing(cfg: Any, block: Any) -> Any:  # runs in the child (inherited through fork)
        calls[0] += 1
        if calls[0] == 4:
            if how == "input_error":
                raise InputError("rec.mcap: bag unreadable after the start (truncated)")
            if how == "unpicklable":
                raise RuntimeError(threading.Lock())  # its argument does not pickle
            os._exit(7)
        return real(cfg, block)

    monkeypatch.setattr(bag_blocks, "_parse_block", failing)
    got = 0
    with pytest.raises(InputError) as info:
        for _ in _parsed_blocks(bag, cfg, 50):
            got += 1
    assert got == 3
    text = str(info.value)
    assert "\n" not in text
    assert {
        "input_error": "rec.mcap: bag unreadable after the start (truncated)",
        "unpicklable": "RuntimeError",
        "killed": "the bag reader process stopped (exit code 7)",
    }[how] in text
    assert multiprocessing.active_children() == []


def test_caller_that_stops_early_stops_the_child(tmp_path: Path) -> None:
    bag = _bag(tmp_path, "pose_array", False, "sqlite3")
    cfg = node_config(_values(marker_topic="/markers"))
    blocks = _parsed_blocks(bag, cfg, 20)
    next(blocks)
    (child,) = multiprocessing.active_children()
    blocks.close()
    assert not child.is_alive() and multiprocessing.active_children() == []


def _gone(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0]
    except FileNotFoundError:
        return True
    return state == "Z"  # exited, not yet reaped by its new parent


def test_child_exits_when_the_parent_dies(tmp_path: Path) -> None:
    bag = _bag(tmp_path, "pose_array", False, "mcap")
    script = textwrap.dedent(
        f"""
        import multiprocessing, os, sys
        sys.path[:0] = {sys.path!r}
        from test_offline_blocks import _values
        from jointfit_ros.bag_blocks import parsed_blocks
        from jointfit_ros.params import node_config
        cfg = node_config(_values(marker_topic="/markers"))
        blocks = parsed_blocks({str(bag)!r}, ["/markers"], "/markers", cfg, 10**9, 10, process=True)
        next(blocks)
        print(multiprocessing.active_children()[0].pid, flush=True)
        os._exit(0)  # no clean-up: the child is left waiting for a free slot
        """
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60, check=True)
    pid = int(out.stdout.split()[0])
    deadline = time.monotonic() + 10 * bag_blocks.PARENT_CHECK_S
    while not _gone(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert _gone(pid)


def test_no_fork_beside_other_threads() -> None:
    assert bag_blocks.can_fork() == (threading.active_count() == 1)
    stop = threading.Event()
    thread = threading.Thread(target=stop.wait)
    thread.start()
    try:
        assert not bag_blocks.can_fork()
    finally:
        stop.set()
        thread.join()


def test_reader_started_before_the_topics_are_checked_leaves_no_child(tmp_path: Path) -> None:
    """The reader opens the bag while the fit checks its topics: a bad bag stops both, with one clear line."""
    bag = _bag(tmp_path, "pose_array", False, "sqlite3")
    cfg = node_config(_values(marker_topic="/elsewhere"))
    with pytest.raises(InputError, match="topics not in the bag: /elsewhere") as info:
        run_fit(bag, cfg, reader_process=True)
    assert "\n" not in str(info.value)
    assert multiprocessing.active_children() == []
    reader = bag_blocks.BagReaderProcess(bag, ["/elsewhere"], cfg, 64)  # the child's own check
    with pytest.raises(InputError, match="topics not in the bag: /elsewhere"):
        next(reader.blocks("/elsewhere", 100))
    assert multiprocessing.active_children() == []


def test_default_reader_process_for_large_bags_only(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    bag = _bag(tmp_path, "pose_array", False, "mcap")
    cfg = node_config(_values(marker_topic="/markers"))
    started: list[int] = []
    real = bag_blocks.BagReaderProcess.__init__

    def spy(self: Any, *args: Any, **kwargs: Any) -> None:
        started.append(1)
        real(self, *args, **kwargs)

    monkeypatch.setattr(bag_blocks.BagReaderProcess, "__init__", spy)
    small = _everything(run_fit(bag, cfg))
    assert started == []  # a few hundred kB: not worth a fork
    monkeypatch.setattr(offline, "READER_PROCESS_MIN_BYTES", 1)
    large = _everything(run_fit(bag, cfg))
    assert started == ([1] if bag_blocks.can_fork() else [])
    _assert_same(small, large)
