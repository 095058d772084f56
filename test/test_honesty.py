"""Never a confident wrong answer: hinge signs from identified estimates, unidentified joints, absurd values.

Through the per-joint runner (the node's pure-Python part, no rclpy) and the
offline CLI; the node's own process is exercised in test_node.py.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from jointfit_core.errors import JointfitError
from jointfit_core.synthetic import TwoSegmentMotion, two_segment_motion
from jointfit_ros.params import ConfigError, node_config
from jointfit_ros.runner import WARN, JointRunner

FloatArray = NDArray[np.float64]
NAMES = [f"P{i}" for i in range(4)] + [f"C{i}" for i in range(4)] + ["LAT", "MED"]


def _values(**extra: Any) -> dict[str, Any]:
    values: dict[str, Any] = {
        "joints": ["knee"],
        "units": "mm",
        "marker_names": NAMES,
        "knee.type": "hinge",
        "knee.parent_markers": NAMES[:4],
        "knee.child_markers": NAMES[4:8],
        "knee.template_frames": 20,
        "knee.window": 5000,
    }
    values.update(extra)
    return values


def _stream(kind: str, seconds: float, *, still_s: float = 0.0, seed: int = 0, rate: float = 100.0,
            motion_kind: str | None = None) -> tuple[FloatArray, FloatArray, TwoSegmentMotion, FloatArray]:
    """Markers (N, 10, 3) mm: a still stance of ``still_s`` then the motion; LAT/MED on the parent, +-60 mm along the axis."""
    rng = np.random.default_rng(seed)
    motion = two_segment_motion(rng, kind=motion_kind or kind)
    times = np.arange(int(seconds * rate)) / rate
    t_motion = np.maximum(times - still_s, 0.0)
    R_p, d_p, _, _ = motion.poses_at(t_motion)
    yp, yc = motion.markers_at(t_motion)
    epi = motion.centre_parent + np.outer([1.0, -1.0], motion.axis) * 60.0
    ye = np.einsum("nij,pj->npi", R_p, epi) + d_p[:, None, :]
    frames = np.concatenate([yp, yc, ye], axis=1) + rng.normal(0.0, 0.5, (times.size, 10, 3))
    return frames, times, motion, t_motion


def _run(runner: JointRunner, frames: FloatArray, times: FloatArray) -> list[tuple[int, Any]]:
    outs = []
    for k in range(frames.shape[0]):
        out = runner.markers_frame(int(times[k] * 1e9), frames[k])
        runner.estimate(times[k])
        if out is not None:
            outs.append((k, out))
    return outs


# --------------------------------------------------------------------------- hinge sign


@pytest.mark.parametrize(("toward", "frm"), [("LAT", "MED"), ("MED", "LAT")])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_hinge_sign_after_a_still_stance_points_from_to(toward: str, frm: str, seed: int, tmp_path: Path) -> None:
    path = tmp_path / "knee.yaml"
    cfg = node_config(_values(**{
        "knee.axis_toward_marker": toward, "knee.axis_from_marker": frm, "knee.calibration_file": str(path),
    }))
    runner = JointRunner(cfg.joints[0], cfg)
    frames, times, _, _ = _stream("hinge", 12.0, still_s=3.0, seed=seed)
    t, f = NAMES.index(toward), NAMES.index(frm)
    stance = frames[:300]
    outs = _run(runner, stance, times[:300])
    assert outs == []  # the stance identifies nothing: no output, no sign, no save
    assert runner.counters["withheld_unidentified"] > 0
    assert "not chosen yet" in runner.status().values["axis points"]
    with pytest.raises(JointfitError, match="not identifiable"):
        runner.save()
    assert not path.exists()
    outs = _run(runner, frames[300:], times[300:])
    assert len(outs) > 500
    for k, out in outs:
        k += 300
        assert out.direction @ (frames[k, t] - frames[k, f]) > 0.0
    assert runner.status().values["axis points"] == f"from {frm} toward {toward}"
    runner.save()
    again = JointRunner(cfg.joints[0], cfg)
    assert again.estimator.frozen
    outs = _run(again, frames[-50:], times[-50:] + 100.0)
    assert all(out.direction @ (frames[k + frames.shape[0] - 50, t] - frames[k + frames.shape[0] - 50, f]) > 0.0
               for k, out in outs)


def test_no_axis_output_until_the_sign_convention_is_honoured() -> None:
    """The epicondyles hidden when the knee becomes identifiable: its axis is withheld (counted), not published
    pointing either way, until a frame shows them; from then on every output points from MED toward LAT."""
    cfg = node_config(_values(**{"knee.axis_toward_marker": "LAT", "knee.axis_from_marker": "MED"}))
    runner = JointRunner(cfg.joints[0], cfg)
    frames, times, _, _ = _stream("hinge", 12.0, seed=3)
    hidden = frames.copy()
    hidden[:800, 8:] = np.nan  # LAT and MED unseen for the first 8 s
    outs = _run(runner, hidden, times)
    assert runner.counters["withheld_unsigned"] > 100  # identifiable well before 8 s: withheld meanwhile
    assert runner.status().values["outputs withheld (hinge sign not chosen yet)"] == runner.counters["withheld_unsigned"]
    assert outs and min(k for k, _ in outs) >= 800
    lat, med = NAMES.index("LAT"), NAMES.index("MED")
    assert all(out.direction @ (frames[k, lat] - frames[k, med]) > 0.0 for k, out in outs)
    assert runner.status().values["axis points"] == "from MED toward LAT"


def test_one_marker_inside_the_clusters_is_ambiguous_and_said() -> None:
    cfg = node_config(_values(**{"knee.axis_toward_marker": "C0"}))
    runner = JointRunner(cfg.joints[0], cfg)
    frames, times, _, _ = _stream("hinge", 8.0)
    assert _run(runner, frames, times)
    st = runner.status()
    assert st.level == WARN and "ambiguous" in st.message
    assert st.values["axis points"].startswith("default")


def test_one_marker_beyond_the_clusters_decides() -> None:
    # LAT lies 60 mm along the axis from the joint; the clusters sit ~500 mm away along the
    # segments, with the axis through them at random: decided only if it is beyond them.
    for seed in range(6):
        cfg = node_config(_values(**{"knee.axis_toward_marker": "LAT"}))
        runner = JointRunner(cfg.joints[0], cfg)
        frames, times, _, _ = _stream("hinge", 8.0, seed=seed)
        outs = _run(runner, frames, times)
        text = runner.status().values["axis points"]
        if text.startswith("toward"):
            k, out = outs[-1]
            p = frames[k, :8].mean(axis=0)
            q = out.position + out.direction * (out.direction @ (p - out.position))
            assert out.direction @ (frames[k, 8] - q) > 0.0
        else:
            assert "ambiguous" in text


def test_from_marker_needs_toward_marker() -> None:
    with pytest.raises(ConfigError, match="needs axis_toward_marker"):
        node_config(_values(**{"knee.axis_from_marker": "MED"}))
    with pytest.raises(ConfigError, match="must differ"):
        node_config(_values(**{"knee.axis_from_marker": "MED", "knee.axis_toward_marker": "MED"}))


# --------------------------------------------------------------------------- unidentified joints


def _ball_on_a_hinge(**extra: Any) -> tuple[JointRunner, FloatArray, FloatArray, TwoSegmentMotion, FloatArray]:
    cfg = node_config(_values(**{"knee.type": "ball", **extra}))
    runner = JointRunner(cfg.joints[0], cfg)
    frames, times, motion, t_motion = _stream("ball", 15.0, motion_kind="hinge", seed=4)
    return runner, frames, times, motion, t_motion


def test_unidentified_joint_publishes_nothing_and_refuses_freeze_and_save(tmp_path: Path) -> None:
    path = tmp_path / "hip.yaml"
    runner, frames, times, _, _ = _ball_on_a_hinge(**{"knee.calibration_file": str(path)})
    assert _run(runner, frames, times) == []
    sol = runner.estimator.solution
    assert sol is not None and not sol.identifiable
    assert runner.counters["withheld_unidentified"] > 1000 and runner.counters["outputs"] == 0
    st = runner.status()
    assert st.level == WARN and "no per-frame output" in st.message
    with pytest.raises(JointfitError, match="freeze_unidentified"):
        runner.freeze(True)
    assert not runner.estimator.frozen
    with pytest.raises(JointfitError, match="not identifiable"):
        runner.save()
    assert not path.exists()


def test_unidentified_calibration_is_not_loaded_unless_allowed(tmp_path: Path) -> None:
    path = tmp_path / "hip.yaml"
    runner, frames, times, _, _ = _ball_on_a_hinge(
        **{"knee.calibration_file": str(path), "knee.freeze_unidentified": True}
    )
    _run(runner, frames, times)
    assert runner.freeze(True).endswith("frozen")
    runner.save()
    before = path.read_bytes()
    cfg = node_config(_values(**{"knee.type": "ball", "knee.calibration_file": str(path)}))
    fresh = JointRunner(cfg.joints[0], cfg)
    assert not fresh.estimator.frozen and "not identifiable" in fresh.last_error
    assert path.read_bytes() == before  # kept untouched
    allowed = node_config(_values(**{"knee.type": "ball", "knee.calibration_file": str(path),
                                     "knee.freeze_unidentified": True}))
    assert JointRunner(allowed.joints[0], allowed).estimator.frozen


def test_published_unidentified_outputs_cover_the_truth() -> None:
    runner, frames, times, motion, t_motion = _ball_on_a_hinge(**{"knee.publish_unidentified": True})
    outs = _run(runner, frames, times)
    assert len(outs) > 1000
    truth = motion.centre_world_at(t_motion)
    e = np.array([(o.position - truth[k]) @ np.linalg.solve(o.cov, o.position - truth[k]) for k, o in outs[-500:]])
    # the estimate is 40-160 mm off along the undetermined axis; the widened covariance covers it
    assert np.linalg.norm(outs[-1][1].position - truth[outs[-1][0]]) > 10.0
    assert np.mean(e / 3) < 1.5
    assert "widened covariance" in runner.status().message


# --------------------------------------------------------------------------- absurd values


@pytest.mark.parametrize("frozen", [False, True])
def test_absurd_marker_never_reaches_an_output(frozen: bool) -> None:
    cfg = node_config(_values(**{"knee.type": "ball", "knee.outlier_gate": 0.0}))
    runner = JointRunner(cfg.joints[0], cfg)
    frames, times, _, _ = _stream("ball", 12.0, seed=5)
    _run(runner, frames[:900], times[:900])
    if frozen:
        runner.freeze(True)
    bad = frames[900:].copy()
    bad[10, 5] = [2.5e299, 0.0, 0.0]
    bad[20, 1] = [0.0, -1e12, 3.0]
    outs = _run(runner, bad, times[900:])
    assert len(outs) >= bad.shape[0] - 5
    for _, out in outs:
        assert np.abs(out.position).max() < 1e4 and np.sqrt(np.diag(out.cov)).max() < 100.0
    assert 2 <= runner.counters["absurd_markers"] <= 8  # the bad marker, and its segment's others in that frame
    assert runner.counters["estimate_failures"] == 0
    assert runner.status().values["absurd markers (treated as missing)"] == runner.counters["absurd_markers"]


def test_no_non_finite_output_even_without_a_workspace() -> None:
    from jointfit_core.estimator import JointOutput
    from jointfit_ros.runner import output_sane

    good = JointOutput("ball", np.zeros(3), np.eye(3), None, None, 0.0)
    assert output_sane(good, float("inf"))
    assert not output_sane(JointOutput("ball", np.full(3, np.nan), np.eye(3), None, None, 0.0), float("inf"))
    assert not output_sane(JointOutput("ball", np.zeros(3), np.diag([np.inf, 1.0, 1.0]), None, None, 0.0), float("inf"))
    assert not output_sane(JointOutput("ball", np.array([2e5, 0, 0]), np.eye(3), None, None, 0.0), 1e5)
    assert not output_sane(JointOutput("ball", np.zeros(3), np.eye(3) * 1e12, None, None, 0.0), 1e5)
    inf_both = np.diag([np.inf, -np.inf, 1.0])  # +inf and -inf entries (their sum is NaN)
    assert not output_sane(JointOutput("ball", np.zeros(3), inf_both, None, None, 0.0), float("inf"))
    z = np.array([0.0, 0.0, 1.0])
    assert output_sane(JointOutput("hinge", np.zeros(3), np.eye(3), z, np.eye(3) * 1e-4, 0.0), float("inf"))
    for bad in (np.array([np.nan, 0.0, 1.0]), None):
        d, c = (z, bad) if bad is None else (bad, np.eye(3))
        assert not output_sane(JointOutput("hinge", np.zeros(3), np.eye(3), d, c, 0.0), float("inf"))
    cov_nan = np.eye(3)
    cov_nan[0, 1] = np.nan
    assert not output_sane(JointOutput("hinge", np.zeros(3), np.eye(3), z, cov_nan, 0.0), float("inf"))


def test_workspace_drops_markers_and_poses_beyond_it() -> None:
    cfg = node_config(_values(**{"knee.type": "ball", "workspace": 3.0}))  # metres; the stream is in mm
    runner = JointRunner(cfg.joints[0], cfg)
    frames, times, _, _ = _stream("ball", 3.0, seed=6)
    frames[5:10, 2] += 5000.0  # 5 m off: beyond a 3 m workspace, before any template exists
    _run(runner, frames, times)
    assert runner.counters["absurd_markers"] == 5


def test_knee_fixture_sign_does_not_depend_on_the_frame_rate(tmp_path: Path) -> None:
    """The real knee: all 922 frames and every 8th (12.5 Hz) point the same way, from RMFE toward RLFE."""
    pytest.importorskip("ezc3d")
    from jointfit_core.io import MarkerData, read_c3d, write_trc
    from jointfit_ros.cli import fit_main

    root = Path(__file__).resolve().parents[1]
    data = read_c3d(root / "test/data/biobuddy/right_knee.c3d")
    directions = []
    for step in (1, 8):
        trc = tmp_path / f"knee{step}.trc"
        write_trc(trc, MarkerData(data.markers[::step], data.labels, data.rate / step, data.units))
        out = tmp_path / f"out{step}"
        assert fit_main([str(trc), "--config", str(root / "config/offline_right_knee.yaml"), "--out", str(out),
                         "--no-report", "--quiet"]) == 0
        joint = json.loads((out / "summary.json").read_text())["joints"][0]
        assert joint["axis_points"] == "from RMFE toward RLFE"
        directions.append(np.array(joint["direction_parent"]))
    assert directions[0] @ directions[1] > 0.99
