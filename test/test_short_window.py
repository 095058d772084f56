"""A not-identifiable joint whose full frame-count window spans only seconds says so (joint_diagnostics.short_window).

At high capture rates the default ``window: 3000`` holds only 3000 / rate seconds: measured on the lower-body
skin skeleton at 500 Hz (20 s), the knees stayed not identifiable with only the advice to "record more, and
more varied, movement cycles", which a sliding window drops as fast as they come.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from skeleton_runs import run_stream

from jointfit_core.skeleton_sta import skeleton_skin_frames, sta_amplitudes
from jointfit_core.skeleton_truth import make_skeleton
from jointfit_ros.joint_diagnostics import SHORT_WINDOW_S
from jointfit_ros.params import node_config, params_from_file

CONFIG = Path(__file__).resolve().parents[1] / "config" / "lower_body.yaml"
HINT = "so recording longer adds no movement to it: lengthen it (window_s, in seconds"


def _statuses(rate: float, window: int, seconds: float) -> dict[str, str]:
    values = params_from_file(CONFIG)
    for joint in ("r_hip", "r_knee"):
        values[f"{joint}.window"] = window
    for key in [k for k in values if k.split(".")[0] in ("r_ankle", "l_hip", "l_knee", "l_ankle")]:
        del values[key]
    values["joints"] = ["r_hip", "r_knee"]
    sk = make_skeleton("lower", seed=0)
    t = np.arange(round(seconds * rate)) / rate
    frames = skeleton_skin_frames(sk, t, np.random.default_rng(0), sta_amplitudes(sk), noise=0.0005, occlusion=0.02)
    runners = run_stream(node_config(values), t, frames, block=500, estimate_period=2.0)
    return {r.cfg.name: r.status().message for r in runners}


@pytest.mark.parametrize(("rate", "window"), [(500.0, 1000), (100.0, 400)])
def test_a_short_full_window_is_named_when_the_joint_is_not_identifiable(rate: float, window: int) -> None:
    statuses = _statuses(rate, window, 8.0)  # 2 s and 4 s of window
    assert any(m.startswith("not identifiable") for m in statuses.values()), statuses
    for message in statuses.values():
        if message.startswith("not identifiable"):
            span = window / rate
            assert f"the window holds only the last {window} frames ({span:.3g} s at {rate:.3g} Hz)" in message
            assert message.count(HINT) == 1


def test_a_window_that_is_not_full_or_spans_long_enough_is_not_blamed() -> None:
    statuses = _statuses(100.0, 3000, 8.0)  # not full: recording longer does add movement
    assert any(m.startswith("not identifiable") for m in statuses.values()), statuses
    assert not any(HINT in m for m in statuses.values()), statuses
    assert 3000 / 100.0 >= SHORT_WINDOW_S  # the default window at 100 Hz is never called short
