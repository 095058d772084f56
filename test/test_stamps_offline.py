"""``jointfit fit`` on a bag whose stamps loop back to the start, with single bad stamps in it.

The recording is played twice into the bag with the same header stamps (a
looped replay recorded again), plus one message stamped 2^31-1 s and one
with nanosec 0xFFFFFFFF. The fit must drop the two bad messages and the
loop's first RESTART_FRAMES - 1 frames (which go back in time), count a
timeline restart, and give the estimates of the estimators fed the frames
that are left.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

pytest.importorskip("rosbags")
from bagtools import MSGTYPES, write_raw_bag
from test_cli import _config, _direct, _fit, _recording, _same_estimate

from jointfit_core.calibration import load_calibration
from jointfit_ros.offline import run_fit
from jointfit_ros.params import node_config, params_from_file
from jointfit_ros.raw import pose_array_bytes
from jointfit_ros.timeline import RESTART_FRAMES

HALF = 750  # frames per pass
BAD_AT = 300  # the bad messages come after this frame of the first pass


def _looped_bag(path: Path) -> tuple[Path, NDArray[np.float64], NDArray[np.int64]]:
    """The bag, and the frames (mm) a correct fit uses with continuous stamps (for the direct estimators)."""
    frames, stamps = _recording()
    frames, stamps = frames[: 2 * HALF], stamps[:HALF]
    looped = np.concatenate([stamps, stamps])
    topic, msgtype = "/mocap/markers", MSGTYPES["pose_array"]
    messages = []
    for k in range(2 * HALF):
        log_ns = int(stamps[0]) + k * 10_000_000  # the recorder's clock goes on
        messages.append((topic, msgtype, log_ns, pose_array_bytes(int(looped[k]), "world", frames[k])))
        if k == BAD_AT:
            far = pose_array_bytes((2**31 - 1) * 1_000_000_000, "world", frames[k])
            nanosec = bytearray(pose_array_bytes(int(looped[k]) + 1, "world", frames[k]))
            nanosec[8:12] = (0xFFFFFFFF).to_bytes(4, "little")
            messages += [(topic, msgtype, log_ns + 1, far), (topic, msgtype, log_ns + 2, bytes(nanosec))]
    bag = write_raw_bag(path, messages)
    used = np.r_[0:HALF, HALF + RESTART_FRAMES - 1 : 2 * HALF]
    return bag, frames[used], stamps[0] + np.arange(used.size) * 10_000_000


def test_fit_of_a_looped_bag_with_bad_stamps(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag, used_frames, used_stamps = _looped_bag(tmp_path / "looped")
    config = _config(tmp_path / "params.yaml")
    out = tmp_path / "out"
    code, stdout, _ = _fit(capsys, "fit", bag, "--config", config, "--out", out, "--no-report")
    assert code == 0, stdout
    summary = json.loads((out / "summary.json").read_text())
    router = summary["router"]
    assert router["timeline_restarts"] == 1 and router["stamps_ahead"] == 1 and router["malformed"] == 1, router
    direct = _direct(used_frames, used_stamps, config)
    for name, est in direct.items():
        saved = load_calibration(out / f"{name}.calibration.yaml")
        _same_estimate(saved["estimate"], est.to_dict()["estimate"])
    for joint in summary["joints"]:
        assert joint["frames_in_window"] == direct[joint["name"]].n_window


def test_fit_reader_process_and_one_by_one_agree_on_the_stamps(tmp_path: Path) -> None:
    bag, _, _ = _looped_bag(tmp_path / "looped")
    cfg = node_config(params_from_file(_config(tmp_path / "params.yaml")))
    runs = [run_fit(bag, cfg, reader_process=flag, keep_frames=True) for flag in (False, True)]
    assert runs[0].router is not None and runs[1].router is not None
    assert runs[0].router.counters == runs[1].router.counters
    assert runs[0].router.counters["timeline_restarts"] == 1
    for run in runs:
        # the report's time axis goes on over the loop (but for the loop's first frames, which went back)
        assert run.stamps.size == 2 * HALF and np.count_nonzero(np.diff(run.stamps) < 0) == 1
        assert run.stamps[HALF + RESTART_FRAMES - 1] > run.stamps[HALF - 1]


def test_a_joint_without_estimate_says_which_frames_were_dropped(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A bag whose messages all carry one stamp: the one-line summary names the dropped frames.

    It said only 'no estimate: building templates from fully visible frames: parent 1/30, child
    1/30', as if the markers had been hidden, while 1499 of the 1500 frames were dropped for
    their stamps.
    """
    frames, stamps = _recording()
    topic, msgtype = "/mocap/markers", MSGTYPES["pose_array"]
    messages = [(topic, msgtype, int(stamps[k]), pose_array_bytes(int(stamps[0]), "world", frames[k]))
                for k in range(len(frames))]
    bag = write_raw_bag(tmp_path / "one_stamp", messages)
    code, stdout, _ = _fit(capsys, "fit", bag, "--config", _config(tmp_path / "params.yaml"), "--out", tmp_path / "out",
                           "--no-report")
    assert code == 3
    lines = [line for line in stdout.splitlines() if "no estimate" in line]
    assert len(lines) == 2, stdout
    assert all(f"({len(frames) - 1} stamp not increasing; {len(frames)} frames received)" in line for line in lines), lines
