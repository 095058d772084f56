"""The node's pure-Python parts: parameters, stamp pairing and the per-joint runner (no rclpy)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from jointfit_core.calibration_fit import JOINT_MISFIT_FRAMES
from jointfit_core.errors import InputError, NotIdentifiableError
from jointfit_core.estimator import solve_window
from jointfit_core.synthetic import two_segment_motion
from jointfit_ros.params import JOINT_PARAMS, NODE_PARAMS, ConfigError, check_value, node_config
from jointfit_ros.runner import OK, STALE, WARN, JointRunner
from jointfit_ros.sync import StampMatcher

FloatArray = NDArray[np.float64]
NAMES = [f"P{i}" for i in range(4)] + [f"C{i}" for i in range(4)]


def _values(**extra: Any) -> dict[str, Any]:
    values: dict[str, Any] = {
        "joints": ["hip"],
        "units": "mm",  # the synthetic streams here are in millimetres
        "marker_names": NAMES,
        "hip.parent_markers": NAMES[:4],
        "hip.child_markers": NAMES[4:],
    }
    values.update(extra)
    return values


# --------------------------------------------------------------------------- parameters


def test_every_parameter_is_described_with_a_valid_default() -> None:
    for spec in NODE_PARAMS + JOINT_PARAMS:
        assert spec.description.endswith(".") and len(spec.description) > 20, spec.name
        assert check_value(spec, None) == spec.default
        check_value(spec, spec.default)  # the default passes its own checks


def _flat(params: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested keys at any depth (``hip.anatomical.rasis``), as rclpy reads a parameter file."""
    out: dict[str, Any] = {}
    for key, value in params.items():
        name = f"{prefix}.{key}" if prefix else key
        out.update(_flat(value, name) if isinstance(value, dict) else {name: value})
    return out


def test_example_configs_are_valid() -> None:
    """Every config/*.yaml passes the node's checks (nested keys become <joint>.<name>)."""
    yaml = pytest.importorskip("yaml")
    paths = sorted((Path(__file__).resolve().parents[1] / "config").glob("*.yaml"))
    assert len(paths) >= 4
    for path in paths:
        params = yaml.safe_load(path.read_text())["jointfit"]["ros__parameters"]
        cfg = node_config(_flat(params))
        assert [j.name for j in cfg.joints] == params["joints"], path


def test_node_config_defaults_and_window_choice() -> None:
    cfg = node_config(_values())
    hip = cfg.joints[0]
    assert hip.type == "ball" and hip.window_kwargs() == {"window": 3000}
    assert hip.local_frame_id == "hip_parent"
    assert cfg.marker_index("C0") == 4
    assert node_config(_values(**{"hip.window_s": 2.0})).joints[0].window_kwargs() == {"window_s": 2.0}
    assert node_config(_values(**{"hip.half_life_s": 1.0})).joints[0].window_kwargs() == {"half_life_s": 1.0}


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"joints": []}, "at least one joint"),
        ({"joints": ["hip", "hip"]}, "twice"),
        ({"joints": ["9lives"]}, "not a valid name"),
        ({"marker_type": "csv"}, "one of"),
        ({"qos_depth": 0}, ">= 1"),
        ({"estimate_period": "fast"}, "finite number"),
        ({"marker_names": [*NAMES, "P0"]}, "twice"),
        ({"hip.parent_markers": NAMES[:2]}, "at least 3"),
        ({"hip.child_markers": ["C0", "C1", "X9"]}, "not in marker_names"),
        ({"hip.child_markers": ["P0", "C1", "C2"]}, "both the parent and the child"),
        ({"hip.type": "saddle"}, "one of"),
        ({"hip.window": 2}, ">= 3"),
        ({"hip.window_s": 1.0, "hip.half_life_s": 1.0}, "not both"),
        ({"hip.axis_toward_marker": "C0"}, "only for hinges"),
        ({"hip.type": "hinge", "hip.axis_toward_marker": "Z"}, "from marker_names"),
        ({"hip.parent_pose_topic": "/pelvis/pose"}, "not both"),
        ({"unlabelled": True}, "pointcloud2"),
    ],
)
def test_bad_parameters_name_the_parameter(change: dict[str, Any], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        node_config(_values(**change))


# --------------------------------------------------------------------------- stamp pairing


def test_stamp_matcher_pairs_within_tolerance_and_counts_the_rest() -> None:
    m = StampMatcher(tolerance_ns=1000, max_pending=3)
    assert m.add(0, 10_000, "p0") is None
    assert m.add(1, 10_500, "c0") == (10_000, "p0", "c0")
    assert m.add(1, 20_000, "c1") is None
    assert m.add(0, 25_000, "p1") is None  # too far from c1
    assert m.add(0, 30_000, "p2") is None
    assert m.add(1, 30_200, "c2") == (30_000, "p2", "c2")  # c1, p1 can no longer pair
    assert m.unmatched == 2 and m.matched == 2
    assert m.add(0, 29_000, "late") is None  # backwards
    assert m.unmatched == 3
    for k in range(5):
        m.add(1, 40_000 + 10_000 * k, k)
    assert m.unmatched == 5  # the child queue holds at most 3


# --------------------------------------------------------------------------- runner


def _stream(kind: str, n: int, seed: int = 0) -> tuple[FloatArray, FloatArray, object]:
    rng = np.random.default_rng(seed)
    motion = two_segment_motion(rng, kind=kind)
    times = np.arange(n) / 100.0
    yp, yc = motion.markers_at(times)
    frames = np.concatenate([yp, yc], axis=1) + rng.normal(0.0, 0.5, (n, 8, 3))
    return frames, times, motion


def test_runner_estimates_reports_and_saves(tmp_path: Any) -> None:
    path = tmp_path / "hip.yaml"
    cfg = node_config(_values(**{"hip.window": 800, "hip.template_frames": 20, "hip.calibration_file": str(path)}))
    runner = JointRunner(cfg.joints[0], cfg)
    assert runner.status().level == STALE
    frames, times, motion = _stream("ball", 1000)
    outputs = 0
    for k in range(frames.shape[0]):
        out = runner.markers_frame(int(times[k] * 1e9), frames[k])
        runner.estimate(times[k])
        outputs += out is not None
    # skin (the default): the outputs start once the window holds 2 s of movement (SKIN_MIN_MOVEMENT_S)
    assert outputs > 1000 - 20 - 200 - 50, outputs  # templates, movement, a few estimate ticks
    truth = motion.centre_world_at(times[-1:])[0]  # type: ignore[attr-defined]
    assert np.linalg.norm(out.position - truth) < 5.0  # type: ignore[union-attr]
    st = runner.status()
    assert st.level == OK and st.values["frames in window"] == 800
    assert st.values["input rate (Hz)"] == pytest.approx(100.0, rel=0.01)
    assert runner.save() == str(path) and path.exists()
    assert "frozen" in runner.freeze(True)

    # A new runner (a restarted node) loads the file and starts frozen; its markers are judged against the
    # calibration over the first JOINT_MISFIT_FRAMES frames (outputs held, the status says why), then it publishes.
    again = JointRunner(cfg.joints[0], cfg)
    assert again.estimator.frozen and again.loaded_from == str(path)
    n = frames.shape[0]
    held = [again.markers_frame(int(times[k] * 1e9), frames[k]) for k in range(n - 150, n - 150 + JOINT_MISFIT_FRAMES)]
    assert all(o is None for o in held[:-1]) and held[-1] is not None  # judged at the last of them
    assert again.estimator.dropped.get("calibration_being_checked") == JOINT_MISFIT_FRAMES - 1
    out2 = again.markers_frame(int(times[-1] * 1e9), frames[-1])
    assert out2 is not None and np.linalg.norm(out2.position - truth) < 5.0
    again.reset()
    assert not again.estimator.frozen and again.estimator.solution is None



def test_runner_drops_an_answer_for_the_estimator_it_replaced() -> None:
    """reset() gives the runner a new estimator: a solve sent before it must not land in the new one."""
    cfg = node_config(_values(**{"hip.window": 800, "hip.template_frames": 20}))
    runner = JointRunner(cfg.joints[0], cfg)
    frames, times, _ = _stream("ball", 600, seed=4)
    for k in range(frames.shape[0]):
        runner.markers_frame(int(times[k] * 1e9), frames[k])
    request = runner.solve_request(force=True)
    assert request is not None
    answer = solve_window(request)
    runner.reset()
    for k in range(30):  # the new estimator's first frames
        runner.markers_frame(int((times[-1] + 1 + k / 100) * 1e9), frames[k])
    assert not runner.install(answer) and runner.estimator.solution is None
    before = JointRunner(cfg.joints[0], cfg)  # and without the reset it would have been installed
    for k in range(frames.shape[0]):
        before.markers_frame(int(times[k] * 1e9), frames[k])
    assert before.install(solve_window(before.solve_request(force=True)))  # type: ignore[arg-type]


def test_runner_drops_an_error_about_a_window_that_is_gone() -> None:
    """An error answer (the solve raised) counts against the estimator it was about, not its successor."""
    cfg = node_config(_values(**{"hip.window": 800, "hip.template_frames": 20}))
    frames, times, _ = _stream("ball", 300, seed=5)
    error = NotIdentifiableError("the window's motion does not identify the joint")
    for change in ("reset", "freeze", None):
        runner = JointRunner(cfg.joints[0], cfg)
        for k in range(frames.shape[0]):
            runner.markers_frame(int(times[k] * 1e9), frames[k])
        request = runner.solve_request(force=True)
        assert request is not None
        if change == "reset":
            runner.reset()
        elif change == "freeze":
            runner.estimate(force=True)
            runner.estimator.freeze()
        failures = runner.counters["estimate_failures"]
        assert not runner.install(error, request)
        assert runner.counters["estimate_failures"] == failures + (change is None), change
        assert ("does not identify" in runner.last_error) == (change is None), change


def test_runner_survives_bad_frames_and_bad_files(tmp_path: Any) -> None:
    broken = tmp_path / "broken.yaml"
    broken.write_text("format: jointfit-calibration\nversion: 1\nkind: [unclosed\n")
    cfg = node_config(_values(**{"hip.calibration_file": str(broken)}))
    runner = JointRunner(cfg.joints[0], cfg)
    assert "not loaded (kept as it is)" in runner.last_error and not runner.estimator.frozen
    assert runner.process(1, np.zeros((3, 3)), np.zeros((4, 3))) is None  # wrong marker count: first frame
    assert runner.process(2, np.full((4, 3), np.inf), np.zeros((4, 3))) is None
    assert runner.counters["malformed"] == 2
    with pytest.raises(InputError, match="no frame has entered"):
        runner.freeze(True)
    assert runner.status().level in (WARN, STALE)


def test_hinge_sign_from_a_cluster_marker_is_ambiguous() -> None:
    """A cluster's own marker lies within the clusters' extent along the axis: no sign is claimed from it.

    (The markers' side of an axis point near the clusters flips with where the
    clusters sit; test_honesty.py checks the from -> toward form.)
    """
    frames, times, _ = _stream("hinge", 600, seed=3)
    for marker in ("C0", "C3", "P1"):
        cfg = node_config(
            _values(**{"hip.type": "hinge", "hip.axis_toward_marker": marker, "hip.template_frames": 20})
        )
        runner = JointRunner(cfg.joints[0], cfg)
        for k in range(frames.shape[0]):
            runner.markers_frame(int(times[k] * 1e9), frames[k])
            runner.estimate(times[k])
        st = runner.status()
        assert st.level == WARN and "ambiguous" in st.message, marker
        assert st.values["axis points"].startswith("default"), marker


def test_pose_inputs_are_paired_by_stamp() -> None:
    rng = np.random.default_rng(5)
    motion = two_segment_motion(rng, kind="ball")
    values = _values(
        **{
            "hip.parent_markers": [],
            "hip.child_markers": [],
            "hip.parent_pose_topic": "/pelvis",
            "hip.child_pose_topic": "/thigh",
            "hip.pose_translation_sd": 0.3,
            "hip.pose_rotation_sd_deg": 0.2,
            "sync_tolerance": 0.001,
        }
    )
    cfg = node_config(values)
    runner = JointRunner(cfg.joints[0], cfg)
    times = np.arange(600) / 100.0
    R_p, d_p, R_c, d_c = motion.poses_at(times)
    outs = []
    for k in range(times.size):
        stamp = int(times[k] * 1e9)
        runner.pose(0, stamp, R_p[k], d_p[k])
        if k % 10 == 5:
            continue  # a lost child message
        out = runner.pose(1, stamp + 200_000, R_c[k], d_c[k])  # child stamped 0.2 ms later
        runner.estimate(times[k])
        outs.append(out)
    assert runner.counters["unmatched"] == 60
    assert runner.counters["frames"] == 540
    last = next(o for o in reversed(outs) if o is not None)
    # noise-free poses: exact but for the bias correction of the stated pose noise (micrometres)
    assert np.linalg.norm(last.position - motion.centre_world_at(times[-1:])[0]) < 0.05


def test_markers_for_one_segment_and_a_pose_topic_for_the_other() -> None:
    frames, times, motion = _stream("ball", 700, seed=9)
    values = _values(
        **{
            "hip.child_markers": [],
            "hip.child_pose_topic": "/thigh",
            "hip.pose_translation_sd": 0.5,
            "hip.pose_rotation_sd_deg": 0.3,
            "hip.template_frames": 20,
        }
    )
    cfg = node_config(values)
    runner = JointRunner(cfg.joints[0], cfg)
    _, _, R_c, d_c = motion.poses_at(times)  # type: ignore[attr-defined]
    out = None
    for k in range(times.size):
        stamp = int(times[k] * 1e9)
        runner.markers_frame(stamp, frames[k])
        got = runner.pose(1, stamp, R_c[k], d_c[k])
        out = got if got is not None else out
        runner.estimate(times[k])
    assert runner.counters["unmatched"] == 0 and out is not None
    truth = motion.centre_world_at(times[-1:])[0]  # type: ignore[attr-defined]
    assert np.linalg.norm(out.position - truth) < 5.0
    assert runner.estimator.noise_std[1] == pytest.approx(1.0)  # 2 x the stated translation sd


def test_unloadable_calibration_is_never_overwritten(tmp_path: Any) -> None:
    """A corrupt or incompatible file at start is kept aside (once) before the first save replaces it."""
    path = tmp_path / "hip.yaml"
    path.write_text("format: jointfit-calibration\nversion: 99\nkind: ball\n")  # a newer jointfit's file
    cfg = node_config(_values(**{"hip.window": 800, "hip.template_frames": 20, "hip.calibration_file": str(path)}))
    runner = JointRunner(cfg.joints[0], cfg)
    assert "version 99 is not supported" in runner.last_error and not runner.estimator.frozen
    frames, times, _ = _stream("ball", 400)
    for k in range(frames.shape[0]):
        runner.markers_frame(int(times[k] * 1e9), frames[k])
    text = runner.save()
    assert text.startswith(str(path)) and "unloadable previous file is kept as" in text
    kept = [p for p in tmp_path.iterdir() if ".unloadable-" in p.name]
    assert len(kept) == 1 and kept[0].read_text().endswith("version: 99\nkind: ball\n")
    assert JointRunner(cfg.joints[0], cfg).estimator.frozen  # the new file loads
    assert runner.save() == str(path)  # later saves replace the (now own) file, .bak kept
    assert len([p for p in tmp_path.iterdir() if ".unloadable-" in p.name]) == 1


def test_too_few_markers_are_explained_by_the_identifiability_rules() -> None:
    """A joint configured with fewer than 3 markers on a side is refused with Pham et al.'s verdict."""
    names = ["A1", "A2", "B1", "B2"]
    base = {"joints": ["hip"], "marker_names": names, "hip.parent_markers": ["A1", "A2"]}
    with pytest.raises(ConfigError, match=r"\(2, 1\) markers is not identifiable.*Add a marker"):
        node_config({**base, "hip.child_markers": ["B1"]})
    with pytest.raises(ConfigError, match=r"only with the batch minimal-marker method jointfit_core\.fit_centre_minimal"):
        node_config({**base, "hip.child_markers": ["B1", "B2"]})
    with pytest.raises(ConfigError, match=r"revolute joint with \(1, 1\) markers is not identifiable"):
        node_config({**base, "hip.type": "hinge", "hip.parent_markers": ["A1"], "hip.child_markers": ["B1"]})
