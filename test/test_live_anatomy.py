"""The live node's anatomical results and range of motion in ``/diagnostics`` (the runner's status, no rclpy):
a synthetic pelvis with known spines and hip centre, and the real fixtures against `jointfit fit`'s summary."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from jointfit_core.rom import range_of_motion
from jointfit_core.synthetic import TwoSegmentMotion, two_segment_motion
from jointfit_ros.geometry import landmark_stat
from jointfit_ros.live_geometry import MIN_SAMPLES, LiveGeometry
from jointfit_ros.offline import read_marker_file, run_fit, with_file_marker_names
from jointfit_ros.params import node_config, params_from_file
from jointfit_ros.report import fit_summary
from jointfit_ros.runner import JointRunner

REPO = Path(__file__).resolve().parents[1]
W, D = 230.0, 160.0  # inter-ASIS width, mid-ASIS to mid-PSIS depth (mm)
SPINES = np.array([[0, 0, W / 2], [0, 0, -W / 2], [-D, 0, 45.0], [-D, 0, -45.0]])  # RASI LASI RPSI LPSI, ISB axes
HIP_ISB = np.array([-60.0, -80.0, 85.0])  # a right hip centre in the ISB pelvis frame (mm)
NAMES = ["RASI", "LASI", "RPSI", "LPSI", "T0", "T1", "T2", "T3"]


def _runner(**extra: Any) -> JointRunner:
    values: dict[str, Any] = {
        "joints": ["hip"], "units": "mm", "marker_names": NAMES,
        "hip.parent_markers": NAMES[:4], "hip.child_markers": NAMES[4:], "hip.attachment": "rigid",
        "hip.anatomical.rasis": "RASI", "hip.anatomical.lasis": "LASI",
        "hip.anatomical.rpsis": "RPSI", "hip.anatomical.lpsis": "LPSI",
    }
    values.update(extra)
    cfg = node_config(values)
    return JointRunner(cfg.joints[0], cfg)


def _motion() -> TwoSegmentMotion:
    """The spines as the pelvis cluster, the hip at HIP_ISB, a thigh cluster 300 mm below it."""
    return dataclasses.replace(
        two_segment_motion(np.random.default_rng(18)),
        template_parent=SPINES, centre_parent=HIP_ISB, centre_child=np.array([0.0, 300.0, 0.0]),
    )


def _pelvis_stream(seconds: float, rate: float = 100.0, noise: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (N,) s and frames (N, 8, 3) mm: the spines as the pelvis cluster, a thigh cluster below the hip."""
    rng = np.random.default_rng(19)
    motion = _motion()
    t = np.arange(int(seconds * rate)) / rate
    yp, yc = motion.markers_at(t)
    frames = np.concatenate([yp, yc], axis=1) + rng.normal(0.0, noise, (t.size, 8, 3))
    return t, frames


def test_a_live_hip_is_given_in_the_isb_pelvis_frame_within_its_sd() -> None:
    runner = _runner()
    t, frames = _pelvis_stream(40.0)
    stamps_ns = np.round(t * 1e9).astype(np.int64) + 10**9
    half = t.size // 2
    runner.markers_block(stamps_ns[:half], frames[:half])  # the node's block path, then frame by frame
    for k in range(half, t.size):
        runner.markers_frame(int(stamps_ns[k]), frames[k])
    runner.estimate(force=True)
    status = runner.status()
    values = status.values
    assert values["identifiable"] is True, (status.message, values)
    centre = np.array(values["centre in ISB pelvis (mm, right side)"])
    sd = np.array(values["centre sd in ISB pelvis (mm)"])
    assert np.all(sd > 0) and np.all(np.abs(centre - HIP_ISB) < np.maximum(3.0 * sd, 0.2)), (centre, sd)
    assert values["inter-ASIS width (mm)"] == pytest.approx(W, abs=0.3)
    np.testing.assert_allclose(values["centre (% of inter-ASIS width)"], 100.0 * HIP_ISB / W, atol=0.5)
    # Harrington et al. (2007) from this pelvis, by hand
    np.testing.assert_allclose(
        values["harrington_2007 regression (mm)"], [-0.24 * D - 9.9, -0.30 * W - 10.9, 0.33 * W + 7.3], atol=0.3
    )
    key = next(k for k in values if k.startswith("range of motion (deg"))
    ranges = values[key]
    # against the range of motion of the true relative rotations over the same 40 s
    R_p, _, R_c, _ = _motion().poses_at(t[::10])
    np.testing.assert_allclose(ranges, range_of_motion(np.swapaxes(R_p, 1, 2) @ R_c).ranges_deg, atol=1.5)
    assert "flexion range (deg)" not in values and "anatomical" not in values


def test_a_joint_without_landmarks_has_only_its_range_of_motion_and_a_reset_forgets_the_samples() -> None:
    runner = _runner(**dict.fromkeys(("hip.anatomical.rasis", "hip.anatomical.lasis", "hip.anatomical.rpsis",
                                      "hip.anatomical.lpsis"), ""))
    t, frames = _pelvis_stream(20.0)
    runner.markers_block(np.round(t * 1e9).astype(np.int64) + 10**9, frames)
    runner.estimate(force=True)
    values = runner.status().values
    assert not any("ISB" in k or "regression" in k for k in values)
    assert any(k.startswith("range of motion (deg") for k in values)
    assert runner.live_geometry is not None and runner.live_geometry.count == 200  # 10 Hz over 20 s
    runner.reset()
    assert runner.live_geometry.count == 200  # the samples stay until the new templates exist ...
    runner.markers_block(np.round(t[:300] * 1e9).astype(np.int64) + 10**10, frames[:300])
    assert runner.live_geometry.count == 30  # ... then start afresh in the new template frame (3 s at 10 Hz)


def test_samples_are_one_per_period_and_the_ring_keeps_the_newest() -> None:
    runner = _runner()
    geo = LiveGeometry(runner.cfg, {m: NAMES.index(m) for m in NAMES[:4]}, runner.parent_rows, runner.child_rows, size=50)
    t, frames = _pelvis_stream(12.0)
    templates = (frames[0, :4] - frames[0, :4].mean(axis=0), frames[0, 4:] - frames[0, 4:].mean(axis=0))
    geo.offer(t[:5], frames[:5], templates)
    assert geo.count == 1  # five frames of one 0.1 s period
    for k in range(5, 400):
        geo.offer_one(float(t[k]), frames[k], templates)
    assert geo.count == 40
    geo.offer(t[400:], frames[400:], templates)
    assert geo.count == 50 and geo.geometry() is not None
    # a frame where the parent cannot be posed is sampled as NaN, left out of the landmarks' medians
    assert landmark_stat(np.full((MIN_SAMPLES, 3), np.nan)) is None


def _live_and_offline(tmp_path: Path, fixture: str, config: str) -> tuple[dict[str, Any], dict[str, Any]]:
    pytest.importorskip("ezc3d")
    path = REPO / "test" / "data" / fixture
    values = params_from_file(REPO / "config" / config, "jointfit")
    recording = read_marker_file(path)
    assert recording is not None
    values = with_file_marker_names(values, recording.labels, path.name)
    values.update({k: str(tmp_path / "cal.yaml") for k in values if k.endswith(".calibration_file")})
    values["units"] = recording.units  # a node on this stream says its unit (the summary takes the file's)
    run = run_fit(path, node_config(values), reader_process=False, data=recording)
    joint = fit_summary(run, elapsed_s=0.0, version="test")["joints"][0]
    live = run.traces[0].runner.status().values  # what the node would say at the recording's end
    return live, joint


def test_live_hip_fixture_agrees_with_the_offline_summary(tmp_path: Path) -> None:
    live, joint = _live_and_offline(tmp_path, "biobuddy/right_hip.c3d", "offline_right_hip.yaml")
    pelvis = joint["anatomical"]["pelvis"]
    centre = np.array(live["centre in ISB pelvis (mm, right side)"])
    # the same estimate; landmarks from a 10 Hz sample against every frame (the spines move < 5 mm on the cluster)
    np.testing.assert_allclose(centre, pelvis["centre"], atol=1.0)
    assert live["inter-ASIS width (mm)"] == pytest.approx(pelvis["width"], abs=1.0)
    assert live["distance to harrington_2007 regression (mm)"] == pytest.approx(
        pelvis["regressions"]["harrington_2007"]["distance"], abs=1.5
    )


def test_live_knee_fixture_agrees_with_the_offline_summary(tmp_path: Path) -> None:
    live, joint = _live_and_offline(tmp_path, "biobuddy/right_knee.c3d", "offline_right_knee.yaml")
    epi = joint["anatomical"]["epicondyles"]
    assert live["axis to epicondyle line (deg)"] == pytest.approx(epi["angle_to_epicondyle_line_deg"], abs=1.0)
    assert live["epicondyle midpoint to axis (mm)"] == pytest.approx(epi["distance_to_epicondyle_midpoint"], abs=1.5)
    assert live["flexion range (deg)"] == pytest.approx(joint["range_of_motion"]["flexion_range_deg"], abs=5.0)


def _same_output(a: object, b: object) -> bool:
    """Whether two JointOutputs are equal field by field (arrays bit for bit)."""
    for f in dataclasses.fields(a):  # type: ignore[arg-type]
        u, v = getattr(a, f.name), getattr(b, f.name)
        if isinstance(u, np.ndarray):
            if not (isinstance(v, np.ndarray) and np.array_equal(u, v, equal_nan=True)):
                return False
        elif u != v and not (u != u and v != v):  # (NaN equals NaN here)
            return False
    return True


def test_the_bookkeeping_after_the_outputs_leaves_the_same_state() -> None:
    """The node publishes a frame's outputs before its stamp-gap count and live-geometry samples
    (``MessageRouter.defer_bookkeeping``, then ``after_outputs()``): the same outputs, samples and
    counts as doing them inline, and nothing of it done before ``after_outputs``."""
    from jointfit_ros.inputs import MessageRouter
    from jointfit_ros.raw import pose_array_bytes

    t, frames = _pelvis_stream(8.0)
    frames[::37, 5] = 1e9  # absurd markers (treated as missing): the samples are of the cleaned frames
    kept = np.ones(t.size, dtype=bool)
    kept[400:403] = False  # three frames never arrive: gaps in the stamps
    messages = [pose_array_bytes(10**9 + round(t[k] * 1e9), "world", frames[k]) for k in np.flatnonzero(kept)]
    inline, deferred = _runner(), _runner()
    routers = [MessageRouter(r.node, [r]) for r in (inline, deferred)]
    routers[1].defer_bookkeeping = True
    outputs = 0
    for k, raw in enumerate(messages):
        a = routers[0].markers(raw)
        assert deferred.live_geometry is not None
        count, received = deferred.live_geometry.count, routers[1].gaps.received
        b = routers[1].markers(raw)
        assert deferred.live_geometry.count == count and routers[1].gaps.received == received  # not yet
        routers[1].after_outputs()
        routers[1].after_outputs()  # a second call does nothing
        assert len(a) == len(b) and all(_same_output(x.output, y.output) for x, y in zip(a, b, strict=True))
        outputs += len(a)
        if k % 50 == 49:
            assert inline.estimate(force=True) == deferred.estimate(force=True)
    assert outputs > 500
    assert routers[1].gaps.received == routers[0].gaps.received == len(messages)
    assert routers[1].gaps.missed == routers[0].gaps.missed == 3
    geo_a, geo_b = inline.live_geometry, deferred.live_geometry
    assert geo_a is not None and geo_b is not None and geo_a.count == geo_b.count >= MIN_SAMPLES
    for name in ("_landmarks", "_child_in_parent", "_R_parent_child"):
        np.testing.assert_array_equal(getattr(geo_a, name), getattr(geo_b, name), err_msg=name)
    assert np.isfinite(geo_b._landmarks[: geo_b.count]).all()  # no absurd marker entered a sample
    assert inline.counters == deferred.counters and inline.counters["absurd_markers"] > 0
    assert inline.status().values == deferred.status().values
