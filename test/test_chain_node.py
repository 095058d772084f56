"""Skeleton chains in the node's path (Pham et al. V-B): an earlier joint's centre is a virtual marker of the next.

A hip (pelvis 3 markers, thigh 3 markers) and a knee hinge whose thigh side
has only two real markers plus the hip centre (``parent_chain: [hip]``): the
knee is estimated from a segment that could not be posed from its markers
alone. Checked through the MessageRouter (what the node runs) and through
``jointfit fit`` on a TRC file, against the true knee axis.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from jointfit_core.io import MarkerData, write_trc
from jointfit_core.synthetic import two_segment_motion
from jointfit_ros.inputs import MessageRouter
from jointfit_ros.offline import run_fit
from jointfit_ros.params import ConfigError, node_config
from jointfit_ros.raw import pose_array_bytes
from jointfit_ros.runner import JointRunner

NAMES = ["P1", "P2", "P3", "T1", "T2", "T3", "S1", "S2", "S3"]
RATE = 100.0


def _leg(seed: int, n: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Frames (n, 9, 3) mm of pelvis, thigh and shank markers, and the true knee axis (n, 3) in the world."""
    rng = np.random.default_rng(seed)
    hip = two_segment_motion(rng, kind="ball", n_markers=(3, 3))
    t = np.arange(n) / RATE
    _, _, R_th, d_th = hip.poses_at(t)
    pelvis, thigh = hip.markers_at(t)
    knee_point = hip.centre_child + np.array([0.0, 0.0, -420.0])  # thigh frame
    axis = np.array([1.0, 0.2, 0.0]) / np.linalg.norm([1.0, 0.2, 0.0])
    shank_local = knee_point + np.array([[40.0, 60.0, -150.0], [-50.0, 40.0, -250.0], [30.0, -60.0, -320.0]])
    angle = 0.9 * np.sin(2 * np.pi * 0.4 * t + 0.3) - 0.4
    R_knee = Rotation.from_rotvec(angle[:, None] * axis).as_matrix()  # shank turns about the axis in the thigh frame
    local = np.einsum("nij,pj->npi", R_knee, shank_local - knee_point) + knee_point
    shank = np.einsum("nij,npj->npi", R_th, local) + d_th[:, None, :]
    frames = np.concatenate([pelvis, thigh, shank], axis=1) + rng.normal(0.0, 0.5, (n, 9, 3))
    return frames, np.einsum("nij,j->ni", R_th, axis)


def _config(**extra: Any) -> Any:
    values: dict[str, Any] = {
        "joints": ["hip", "knee"],
        "marker_names": NAMES,
        "units": "mm",
        "hip.type": "ball",
        "hip.parent_markers": ["P1", "P2", "P3"],
        "hip.child_markers": ["T1", "T2", "T3"],
        "hip.template_frames": 20,
        "knee.type": "hinge",
        "knee.parent_markers": ["T1", "T2"],  # two real thigh markers ...
        "knee.parent_chain": ["hip"],  # ... and the hip centre
        "knee.child_markers": ["S1", "S2", "S3"],
        "knee.template_frames": 20,
    }
    values.update(extra)
    return node_config(values)


def test_chain_through_the_router() -> None:
    frames, axis = _leg(2, 2500)
    cfg = _config()
    runners = [JointRunner(j, cfg) for j in cfg.joints]
    router = MessageRouter(cfg, runners)
    knee_out = None
    for k, frame in enumerate(frames):
        for routed in router.markers(pose_array_bytes(int(1e9 + k * 1e7), "world", frame)):
            if routed.runner.cfg.name == "knee":
                knee_out = routed.output
        if k % 50 == 49:
            for r in runners:
                r.estimate(force=True)
    hip, knee = runners
    assert hip.estimator.solution is not None and hip.estimator.solution.identifiable
    sol = knee.estimator.solution
    assert sol is not None and sol.identifiable, None if sol is None else sol.reason
    assert knee.estimator.n_markers == (3, 3)
    assert knee_out is not None and knee_out.direction is not None and knee_out.cov_direction is not None
    err = np.degrees(np.arccos(min(1.0, abs(float(knee_out.direction @ axis[-1])))))
    sd = np.degrees(np.sqrt(np.linalg.eigvalsh(knee_out.cov_direction)[-1]))
    assert err < max(4 * sd, 0.5), (err, sd)
    # Without the chain the knee's thigh side has two markers: refused at configuration time.
    with pytest.raises(ConfigError, match=r"knee\.parent_markers: expected at least 3"):
        _config(**{"knee.parent_chain": []})


def test_chain_in_jointfit_fit(tmp_path: Path) -> None:
    frames, _ = _leg(3, 2000)
    trc = tmp_path / "leg.trc"
    write_trc(trc, MarkerData(np.round(frames, 5), tuple(NAMES), RATE, "mm"))
    run = run_fit(trc, _config(), keep_frames=True)
    hip, knee = run.traces
    assert hip.final is not None and hip.final.identifiable
    assert knee.final is not None and knee.final.identifiable, None if knee.final is None else knee.final.reason
    # the knee's frames enter once the hip centre is published: after the hip's templates and 2 s of movement
    # (skin, the default: SKIN_MIN_MOVEMENT_S), about 230 frames here
    assert knee.runner.estimator.n_window > 2000 - 300, knee.runner.estimator.n_window


def test_chain_config_errors() -> None:
    with pytest.raises(ConfigError, match="'ankle' is not a joint listed before 'knee'"):
        _config(**{"knee.parent_chain": ["ankle"]})
    with pytest.raises(ConfigError, match="'knee' is not a joint listed before 'hip'"):
        _config(**{"hip.child_chain": ["knee"], "hip.child_markers": ["T1", "T2"]})
