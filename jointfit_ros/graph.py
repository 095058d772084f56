"""Who else is on the ROS graph: a second node of the same name, a publisher of the wrong type, a second publisher.

Pure functions of what rclpy's graph queries return, so that they are tested
without ROS. ROS 2 does not keep node names unique: a second ``jointfit``
started with the same name and namespace publishes every output again and
answers the same services (two ``~/save`` writing the same files). A
publisher of another message type on the marker topic never delivers a
message to the node, which would otherwise only say "waiting for markers".
Two publishers of an input topic (a mocap driver started twice, a replay
beside the live driver) interleave their frames into what the node takes for
one stream at twice the rate: every joint mixes two subjects' (or two
sessions') frames, and the node would otherwise only say that frames are
missing and that the joint test rejects a third of them.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

__all__ = ["graph_problems"]


def _full(name: str, namespace: str) -> str:
    return f"{namespace.rstrip('/')}/{name}" if namespace not in ("", "/") else f"/{name}"


def graph_problems(
    node_names: Iterable[tuple[str, str]],
    me: tuple[str, str],
    publisher_types: Mapping[str, Iterable[str]],
    expected_types: Mapping[str, str],
) -> list[str]:
    """What is wrong on the graph, in words (empty: nothing).

    Parameters
    ----------
    node_names : iterable of (str, str)
        ``(name, namespace)`` of every node on the graph
        (``Node.get_node_names_and_namespaces()``), this one included.
    me : (str, str)
        This node's name and namespace.
    publisher_types : mapping of str to iterable of str
        Per input topic, the message type of each of its publishers
        (``Node.get_publishers_info_by_topic``), e.g. ``geometry_msgs/msg/PoseArray``;
        more than one of the expected type is a problem too.
    expected_types : mapping of str to str
        Per input topic, the type this node subscribes with.
    """
    problems = []
    twins = sum(1 for n in node_names if tuple(n) == tuple(me))
    if twins > 1:
        problems.append(
            f"{twins} nodes named {_full(*me)} are running: each publishes every output and answers ~/save; "
            "stop the others or start this one in another namespace (--ros-args -r __ns:=/name)"
        )
    for topic, wanted in expected_types.items():
        others = sorted({t for t in publisher_types.get(topic, ()) if t != wanted})
        if others:
            problems.append(
                f"{topic} has publishers of {', '.join(others)}, which this node cannot read (it expects {wanted}); "
                "their messages never arrive: set marker_type or fix the publisher"
            )
        same = sum(1 for t in publisher_types.get(topic, ()) if t == wanted)
        if same > 1:
            problems.append(
                f"{topic} has {same} publishers of {wanted}: if more than one sends frames, they interleave into one "
                "stream that the joints cannot tell apart (a driver started twice, or a replay beside the live driver), "
                "and the node holds such frames back; stop all but one"
            )
    return problems
