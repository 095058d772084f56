"""``jointfit_node`` stopped while it starts: no traceback; a real start-up error still raises.

SIGINT or SIGTERM between ``rclpy.init`` and the end of the node's construction makes rclpy's
signal handler shut the context down under the node, and the next rcl call fails ("error creating
node: the given context is not valid"): seen once in CI (test_graph's twin nodes, terminated while
one was still starting) and reproduced by terminating two starting nodes after 1.5 s (1 run in 4).
"""

from __future__ import annotations

import os

import pytest

pytestmark = pytest.mark.ros


class _StoppedWhileStarting:
    """A node whose construction meets a context a signal has shut down."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.impl.implementation_singleton import rclpy_implementation as impl

        rclpy.shutdown()  # what rclpy's SIGTERM handler does
        raise impl.RCLError("error creating node: the given context is not valid")


class _BrokenAtStart:
    """A node whose construction fails while the context is fine (a real error)."""

    def __init__(self) -> None:
        raise RuntimeError("a real start-up failure")


@pytest.fixture
def ros_env(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("ROS_DOMAIN_ID", str(60 + os.getpid() % 30))


def test_a_signal_while_the_node_starts_stops_it_quietly(
    ros_env: None, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("rclpy")
    from jointfit_ros import node

    monkeypatch.setattr(node, "JointfitNode", _StoppedWhileStarting)
    node.main(["jointfit_node"])  # returns: no exception, no traceback
    err = capsys.readouterr().err
    assert "stopped while starting" in err and "Traceback" not in err


def test_a_start_up_error_with_the_context_running_still_raises(ros_env: None, monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("rclpy")
    import rclpy

    from jointfit_ros import node

    monkeypatch.setattr(node, "JointfitNode", _BrokenAtStart)
    with pytest.raises(RuntimeError, match="a real start-up failure"):
        node.main(["jointfit_node"])
    assert not rclpy.ok()  # shut down on the way out
