"""A marker never seen holds its segment's template back: the status names it instead of counting to nowhere.

Before (2026-12-06) the lower body with RTHI4 never visible said, for 15 s and forever, "building
templates from fully visible frames: parent 0/50, child 0/50" for both joints on the thigh: the
pelvis's built template read 0/50 and nothing said which marker was missing.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jointfit_core.skeleton_truth import make_skeleton, skeleton_frames
from jointfit_ros.inputs import MessageRouter
from jointfit_ros.joint_diagnostics import OK, WARN
from jointfit_ros.params import node_config, params_from_file
from jointfit_ros.raw import pose_array_bytes
from jointfit_ros.runner import JointRunner

ROOT = Path(__file__).resolve().parent.parent


def _run(hidden: str, share: float, seconds: float = 6.0) -> dict[str, JointRunner]:
    rng = np.random.default_rng(0)
    sk = make_skeleton("lower", seed=0)
    names = sk.marker_names()
    t = np.arange(round(seconds * 100)) / 100.0
    frames = skeleton_frames(sk, t, rng, 0.0005, 0.0)
    frames[rng.random(t.size) < share, names.index(hidden)] = np.nan
    cfg = node_config(params_from_file(ROOT / "config" / "lower_body.yaml"))
    runners = [JointRunner(j, cfg) for j in cfg.joints]
    router = MessageRouter(cfg, runners)
    for k in range(t.size):
        router.markers(pose_array_bytes(10**12 + round(t[k] * 1e9), "world", frames[k]))
        if k % 50 == 49:
            for r in runners:
                r.estimate(force=True)
    return {r.cfg.name: r for r in runners}


def test_a_marker_never_seen_is_named_while_the_templates_wait() -> None:
    runners = _run("RTHI4", 1.0)
    hip, knee = runners["r_hip"].status(), runners["r_knee"].status()
    assert hip.level == knee.level == WARN
    assert "parent 50/50, child 0/50; RTHI4 missing from nearly every frame" in hip.message, hip.message
    assert "parent 0/50, child 50/50; RTHI4 missing from nearly every frame" in knee.message, knee.message
    assert runners["l_hip"].status().level == OK


def test_a_marker_often_occluded_is_not_named_and_the_templates_build() -> None:
    runners = _run("RTHI4", 0.5)
    for name in ("r_hip", "r_knee"):
        est = runners[name].estimator
        assert est.templates_ready and est.rarely_seen() == ([], []), name
        assert "missing from nearly every frame" not in runners[name].waiting()
