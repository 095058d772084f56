"""Issue 17, item 6: the joint's lever over each marker cluster's size, by hand, as properties, and as the node reports it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jointfit_core.errors import InputError
from jointfit_core.lever import lever_ratio, lever_ratios
from jointfit_core.skeleton_truth import make_skeleton, skeleton_frames
from jointfit_ros.inputs import MessageRouter
from jointfit_ros.joint_diagnostics import joint_status
from jointfit_ros.params import node_config, params_from_file
from jointfit_ros.raw import pose_array_bytes
from jointfit_ros.runner import JointRunner

CONFIG = Path(__file__).resolve().parents[1] / "config" / "lower_body.yaml"

#: A square cluster of side 2a in the z = 0 plane: rms radius sqrt(2) a.
SQUARE = np.array([[1.0, 1.0, 0.0], [-1.0, 1.0, 0.0], [-1.0, -1.0, 0.0], [1.0, -1.0, 0.0]]) * 0.03


def test_a_ball_centre_and_a_hinge_axis_by_hand() -> None:
    radius = np.sqrt(2.0) * 0.03
    centre = np.array([0.0, 0.0, -0.25])  # 250 mm below the cluster's centroid
    assert lever_ratio(SQUARE, centre) == pytest.approx(0.25 / radius)
    # a hinge axis along x through that centre: the same distance wherever the point is taken on it
    for along in (0.0, 0.4, -1.0):
        assert lever_ratio(SQUARE, centre + np.array([along, 0.0, 0.0]), [2.0, 0.0, 0.0]) == pytest.approx(0.25 / radius)
    # an axis through the centroid: no lever
    assert lever_ratio(SQUARE, [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]) == pytest.approx(0.0, abs=1e-12)
    both = lever_ratios((SQUARE, 2.0 * SQUARE), (centre, centre))
    assert both == pytest.approx((0.25 / radius, 0.25 / (2.0 * radius)))


def test_rigid_motion_units_and_marker_order_do_not_change_it() -> None:
    rng = np.random.default_rng(3)
    x = rng.normal(scale=0.05, size=(5, 3))
    p, n = rng.normal(scale=0.2, size=3), rng.normal(size=3)
    base = lever_ratio(x, p, n)
    R = Rotation.random(random_state=4).as_matrix()
    t = rng.normal(size=3)
    assert lever_ratio(x @ R.T + t, R @ p + t, R @ n) == pytest.approx(base, rel=1e-12)
    assert lever_ratio(1000.0 * x, 1000.0 * p, n) == pytest.approx(base, rel=1e-12)  # metres to millimetres
    assert lever_ratio(x[::-1], p, -n) == pytest.approx(base, rel=1e-12)


@pytest.mark.parametrize(
    ("template", "point", "direction"),
    [
        (np.zeros((4, 2)), np.zeros(3), None),
        (SQUARE, np.zeros(2), None),
        (SQUARE, [np.nan, 0.0, 0.0], None),
        (SQUARE, np.zeros(3), [0.0, 0.0, 0.0]),
        (SQUARE, np.zeros(3), "x"),
    ],
)
def test_bad_input_is_refused(template: object, point: object, direction: object) -> None:
    with pytest.raises(InputError):
        lever_ratio(template, point, direction)  # type: ignore[arg-type]


def test_the_node_reports_each_clusters_lever_against_the_truth() -> None:
    """Lower body, rigid markers, 0.5 mm noise: every joint's ratios within 3 % of the skeleton's own geometry."""
    sk = make_skeleton("lower", seed=5)
    cfg = node_config(params_from_file(CONFIG))
    t = np.arange(600) / 100.0
    frames = skeleton_frames(sk, t, np.random.default_rng(5), 0.0005, 0.0)
    raws = [pose_array_bytes(10**12 + round(tk * 1e9), "world", f) for tk, f in zip(t, frames, strict=True)]
    runners = [JointRunner(j, cfg) for j in cfg.joints]
    MessageRouter(cfg, runners).markers_many(raws)
    names = sk.marker_names()
    world = sk.markers_at([t[0]])[0]
    joints = sk.joints_world_at([t[0]])
    for r in runners:
        assert r.estimate(force=True), r.last_error
        got = r.lever_ratios()
        point, direction = joints[r.cfg.name]
        for side, markers in (("parent", r.cfg.parent_markers), ("child", r.cfg.child_markers)):
            cluster = world[[names.index(m) for m in markers]]
            truth = lever_ratio(cluster, point[0], None if direction is None else direction[0])
            assert got[side] == pytest.approx(truth, rel=0.03, abs=0.02), (r.cfg.name, side, got, truth)
        values = joint_status(r)[0].values
        assert values["lever / cluster radius child"] == got["child"]
        assert values["lever / cluster radius parent"] == got["parent"]
