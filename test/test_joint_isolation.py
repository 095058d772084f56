"""One joint that raises on a frame does not take the frame from the joints after it (hunt D6).

Before, the exception left the router's loop over the joints: the node's callback guard kept the
node alive, but every joint after the one that raised lost that frame (the hip raised on a finite
1e160 and the knee never received those frames).
"""

from __future__ import annotations

from typing import Any

import pytest
from helpers import rig_frames, rig_router

from jointfit_ros.raw import pose_array_bytes

S = 1_000_000_000
STEP = 4_000_000


def _messages(n: int) -> list[bytes]:
    return [pose_array_bytes(100 * S + k * STEP, "world", f) for k, f in enumerate(rig_frames(n, 1))]


def _failing_first_joint(runners: list[Any], every: int) -> None:
    hip = runners[0]
    original = hip.markers_frame
    calls = {"n": 0}

    def markers_frame(*args: Any, **kwargs: Any) -> Any:
        calls["n"] += 1
        if calls["n"] % every == 0:
            raise RuntimeError("a bug in the first joint")
        return original(*args, **kwargs)

    hip.markers_frame = markers_frame


def test_the_joints_after_one_that_raises_still_get_the_frame() -> None:
    router, runners = rig_router()
    _failing_first_joint(runners, every=7)
    errors: list[tuple[str, str]] = []
    router.on_joint_error = lambda runner, exc: errors.append((runner.cfg.name, str(exc)))
    msgs = _messages(400)
    outputs = {"hip": 0, "knee": 0}
    for raw in msgs:
        for routed in router.markers(raw):
            outputs[routed.runner.cfg.name] += 1
    hip, knee = runners
    assert len(errors) == 400 // 7 and errors[0] == ("hip", "a bug in the first joint")
    assert knee.counters["frames"] == 400  # every frame reached the second joint
    assert hip.counters["frames"] == 400 - 400 // 7
    assert knee.estimate(force=True)
    more = [pose_array_bytes(100 * S + (400 + k) * STEP, "world", f) for k, f in enumerate(rig_frames(50, 2))]
    published = [r for raw in more for r in router.markers(raw) if r.runner is knee]
    assert len(published) == 50  # and the second joint publishes for every frame, the first one's failures or not


def test_without_a_handler_the_exception_propagates() -> None:
    """Offline (jointfit fit) sets no handler: a bug stops the fit rather than thinning one joint's frames."""
    router, runners = rig_router()
    _failing_first_joint(runners, every=1)
    with pytest.raises(RuntimeError, match="a bug in the first joint"):
        router.markers(_messages(1)[0])
    assert runners[1].counters["frames"] == 0
