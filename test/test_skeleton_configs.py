"""config/lower_body.yaml and config/full_body.yaml: they load in the node and identify every joint of the fake skeleton.

The node's per-message path (MessageRouter -> JointRunner -> OnlineJoint, no ROS)
runs over 10 s of the skeleton stream at 100 Hz (0.5 mm white noise, 2 % occluded
markers), in blocks as ``jointfit fit`` does. Each estimate is compared with the
truth in the node's own parent template frame (the true template frame mapped onto
the node's estimated template by the rigid fit of their markers,
``Skeleton.joint_in_template``; the run is ``skeleton_runs.run_stream``): the error against
the reported covariance, e = err^T W^+ err / rank, over every ball centre, hinge
direction and hinge point.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers import mahalanobis
from skeleton_runs import run_stream

from jointfit_core.skeleton_truth import make_skeleton, skeleton_frames
from jointfit_ros.params import node_config, params_from_file
from jointfit_ros.skeleton_params import skeleton_parameters

CONFIG = Path(__file__).resolve().parents[1] / "config"
FILES = {"lower": CONFIG / "lower_body.yaml", "full": CONFIG / "full_body.yaml"}
RATE = 100.0


@pytest.mark.parametrize("name", ["lower", "full"])
def test_config_file_matches_the_skeleton(name: str) -> None:
    sk = make_skeleton(name)
    values = params_from_file(FILES[name])
    cfg = node_config(values)
    assert [j.name for j in cfg.joints] == list(sk.joints)
    assert list(cfg.marker_names) == sk.marker_names()
    for key, value in skeleton_parameters(sk).items():
        assert values[key] == value, key
    # a shared segment is one marker list: the hip's child is the knee's parent
    by_name = {j.name: j for j in cfg.joints}
    assert by_name["r_hip"].child_markers == by_name["r_knee"].parent_markers
    # Every key with a value is commented where it first appears: inline, or by the comment heading
    # its run of key lines (joint blocks after the first repeat the first block's keys uncommented).
    lines = FILES[name].read_text(encoding="utf-8").splitlines()
    first: dict[str, bool] = {}
    for k, line in enumerate(lines):
        key, sep, value = line.strip().partition(":")
        if sep and value.strip() and not key.startswith("#") and key not in first:
            above = k - 1
            while above > 0 and ":" in lines[above] and not lines[above].lstrip().startswith("#"):
                above -= 1
            first[key] = "#" in line or lines[above].lstrip().startswith("#")
    assert len(first) >= 12 and all(first.values()), [key for key, ok in first.items() if not ok]


def test_skeleton_parameters_subsets_and_errors() -> None:
    sk = make_skeleton("full")
    values = skeleton_parameters(sk, ["r_hip", "r_knee"])
    assert values["joints"] == ["r_hip", "r_knee"] and len(values["marker_names"]) == 56
    assert values["r_knee.type"] == "hinge" and values["r_knee.parent"] == values["r_hip.child"] == "r_thigh"
    assert values["segments"] == ["pelvis", "r_thigh", "r_shank"] and values["r_thigh.markers"] == ["RTHI1", "RTHI2", "RTHI3", "RTHI4"]
    with pytest.raises(ValueError, match="not joints of the full skeleton"):
        skeleton_parameters(sk, ["neck"])


@pytest.mark.parametrize("name", ["lower", "full"])
def test_the_configs_identify_every_joint_within_its_uncertainty(name: str) -> None:
    sk = make_skeleton(name, seed=1)
    values = params_from_file(FILES[name])
    # the fake skeleton's markers are rigid: told so (the configs' default, skin, is cautious on such clean
    # data: its undetected soft-tissue part is taken at its detection limit; test_skeleton_sta has skin data)
    values.update({f"{j}.attachment": "rigid" for j in values["joints"]})
    cfg = node_config(values)
    t = np.arange(int(10.0 * RATE)) / RATE
    frames = skeleton_frames(sk, t, np.random.default_rng(1), 0.0005, 0.02)
    runners = run_stream(cfg, t, frames)
    indices = []
    for r in runners:
        assert r.estimate(force=True), r.last_error
        sol = r.estimator.solution
        assert sol is not None and sol.identifiable, (r.cfg.name, sol)
        template = r.estimator.templates[0]
        assert template is not None
        point, direction = sk.joint_in_template(r.cfg.name, template)
        if direction is None:
            err = sol.centre_parent - point
            assert np.linalg.norm(err) < 1e-3, r.cfg.name  # within 1 mm (sd ~0.1 mm)
            indices.append(mahalanobis(err, sol.cov_parent))
        else:
            d = sol.direction_parent * np.sign(sol.direction_parent @ direction)
            assert np.degrees(np.arccos(min(1.0, d @ direction))) < 0.5, r.cfg.name  # sd ~0.05 deg
            assert np.linalg.norm(sol.point_parent - point) < 1e-3, r.cfg.name
            indices.append(mahalanobis(d - direction, sol.cov_direction_parent))
            indices.append(mahalanobis(sol.point_parent - point, sol.cov_point_parent))
    # Calibrated covariances give a mean of 1 (sd ~0.2-0.3 over these 9 or 18 indices).
    print(f"{name}: mean e/rank {np.mean(indices):.2f} over {len(indices)}, max {max(indices):.2f}")
    assert 0.3 < float(np.mean(indices)) < 2.5, indices
    assert max(indices) < 12.0, indices  # no joint off by more than ~3.5 sd
