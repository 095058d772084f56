"""Report helpers (jointfit_ros.report): long series summarised for the figures; figures drawn in forked processes."""

from __future__ import annotations

import multiprocessing
from pathlib import Path

import numpy as np
import pytest
from bagtools import write_marker_bag
from test_offline_blocks import _frames, _values

from jointfit_ros.offline import run_fit
from jointfit_ros.params import node_config
from jointfit_ros.report import PLOT_BINS, binned, joint_reports


def test_short_series_are_drawn_as_they_are() -> None:
    t = np.arange(4 * PLOT_BINS, dtype=np.float64)
    assert binned(t, np.ones_like(t)) is None


def test_binned_median_and_maximum_per_run_with_gaps_and_a_spike() -> None:
    rng = np.random.default_rng(3)
    n, bins = 10_007, 50  # not a multiple: the last run is shorter
    t = np.arange(n) / 100.0
    y = rng.normal(1.0, 0.1, n)
    y[rng.random(n) < 0.1] = np.nan
    y[5 * 201 : 6 * 201] = np.nan  # a whole run (of 201 samples) undefined
    y[4321] = 25.0  # one-sample spike
    out = binned(t, y, bins)
    assert out is not None
    mid, median, peak = out
    size = -(-n // bins)
    assert mid.shape == median.shape == peak.shape == (-(-n // size),)
    for k in range(mid.size):
        run = y[k * size : (k + 1) * size]
        finite = run[np.isfinite(run)]
        assert t[k * size] <= mid[k] <= t[min((k + 1) * size, n) - 1]
        if finite.size:
            assert median[k] == np.median(finite) and peak[k] == finite.max()
        else:
            assert np.isnan(median[k]) and np.isnan(peak[k])
    assert size == 201 and np.isnan(median[5]) and np.isfinite(median[[4, 6]]).all()
    assert np.nanmax(peak) == 25.0 and peak[4321 // size] == 25.0
    assert np.all(np.diff(mid) > 0)


def test_joint_reports_in_forked_processes_equal_the_serial_ones(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    pytest.importorskip("rosbags")
    frames, stamps = _frames()
    bag = write_marker_bag(tmp_path / "rec", frames, stamps, topic="/markers")
    run = run_fit(bag, node_config(_values(marker_topic="/markers")))
    geos, figures = joint_reports(run, parallel=False)
    geos_forked, figures_forked = joint_reports(run, parallel=True)
    assert list(figures) == ["hip", "knee"] and figures == figures_forked  # the same PNG bytes
    for name, geo in geos.items():
        other = geos_forked[name]
        assert geo is not None and other is not None
        for field in ("t", "residual_parent", "residual_child", "child_in_parent", "joint_residual"):
            np.testing.assert_array_equal(getattr(geo, field), getattr(other, field), err_msg=f"{name}.{field}")
    assert multiprocessing.active_children() == []
