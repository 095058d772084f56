"""``jointfit status`` and ``jointfit call``: watch a running node and call its services from the shell.

Usage::

    jointfit status [--node NAME ... | --all] [--once] [--timeout S]
    jointfit call {reset,freeze,save} [true|false] [--node NAME] [--timeout S]

``status`` subscribes to ``/diagnostics`` and prints one line per joint of the
node (level, estimate with its sd and units, coverage, frames, gated shares,
the status message), refreshed at every diagnostics message; ``--once`` prints
one round and exits. ``--node`` given more than once, or ``--all`` (every
jointfit node heard), watches several nodes (one per subject,
``/subject_a/jointfit``, ``/subject_b/jointfit``): each line then starts with
its node's full name; ``--once`` waits for a round of every named node (with
``--all``: until the first node heard is heard a third time, every node a second
time and every ``/diagnostics`` publisher in the ROS graph heard or silent for 8 s,
the graph watched for at least 5 s, or ``--timeout``). ``call`` calls ``<node>/reset`` (std_srvs/Trigger),
``<node>/freeze`` (std_srvs/SetBool, default true) or ``<node>/save``
(std_srvs/Trigger) and prints the node's answer.

Exit status: 0 success (``call``: the node answered success true); 1 the node
answered success false, or nothing arrived within ``--timeout`` (one line on
stderr); 2 bad arguments; 130 interrupted (``call``; ``status`` ends with 0 on
Ctrl-C). ROS is reached as any rclpy program does: same ``ROS_DOMAIN_ID``,
``ROS_AUTOMATIC_DISCOVERY_RANGE``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any, NoReturn

from .naming import node_path, status_prefix

__all__ = ["status_main", "call_main", "status_lines", "status_nodes", "StatusRounds", "node_path"]

LEVELS = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        print(f"{self.prog}: error: {message}", file=sys.stderr)
        raise SystemExit(2)


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, got {text!r}") from None
    if not value > 0.0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a positive number of seconds, got {text!r}")
    return value


def _add_node(p: argparse.ArgumentParser, many: bool = False) -> None:
    if many:
        p.add_argument(
            "--node",
            action="append",
            default=None,
            help="the node's name, with its namespace if any (default jointfit; e.g. /subject_a/jointfit); "
            "give it again for more nodes",
        )
        return
    p.add_argument(
        "--node",
        default="jointfit",
        help="the node's name, with its namespace if any (default jointfit; e.g. /subject_a/jointfit)",
    )


# ---------------------------------------------------------------------------- status lines


def _unit(key: str) -> str:
    return key[key.rfind("(") + 1 : -1] if key.endswith(")") else ""


def _find(values: dict[str, str], prefix: str) -> tuple[str, str] | None:
    """The value and unit of the first key starting with ``prefix`` (keys end in ``(unit)``)."""
    for key, value in values.items():
        if key.startswith(prefix):
            return value, _unit(key)
    return None


def _vector(text: str) -> str:
    try:
        numbers = [float(v) for v in text.strip("[] ").split(",")]
    except ValueError:
        return text
    return "(" + ", ".join(f"{v:.4g}" for v in numbers) + ")"


def _estimate(values: dict[str, str]) -> str:
    """The estimate with its sd and units, e.g. ``centre (0.0123, -0.045, 0.078) m sd 0.0011 m``."""
    centre, sd = _find(values, "centre_parent ("), _find(values, "centre sd (")
    if centre is not None:
        text = f"centre {_vector(centre[0])} {centre[1]}"
        return text + (f" sd {float(sd[0]):.3g} {sd[1]}" if sd else "")
    direction = _find(values, "direction_parent (")
    if direction is None:
        return "no estimate yet"
    text = f"axis {_vector(direction[0])}"
    dir_sd = values.get("direction sd (deg)")
    if dir_sd is not None:
        text += f" sd {float(dir_sd):.3g} deg"
    point, point_sd = _find(values, "point_parent ("), _find(values, "point sd (")
    if point is not None:
        text += f", point {_vector(point[0])} {point[1]}"
        if point_sd is not None:
            text += f" sd {float(point_sd[0]):.3g} {point_sd[1]}"
    return text


def _anatomical(values: dict[str, str]) -> str:
    """The live anatomical result in words (``ISB pelvis (-59, -85.2, 90.3) mm``, ``11.2 deg from the
    epicondyle line``), or empty (:mod:`jointfit_ros.live_geometry`)."""
    pelvis = _find(values, "centre in ISB pelvis (")
    if pelvis is not None:
        return f"ISB pelvis {_vector(pelvis[0])} {pelvis[1].split(',')[0]}"
    angle = values.get("axis to epicondyle line (deg)")
    return f"{angle} deg from the epicondyle line" if angle is not None else ""


def _joint_line(name: str, level: str, message: str, values: dict[str, str]) -> str:
    parts = [f"{name} {level}", _estimate(values)]
    anatomical = _anatomical(values)
    if anatomical:
        parts.append(anatomical)
    if "coverage (%)" in values:
        parts.append(f"coverage {values['coverage (%)']} %")
    if values.get("done") == "True":
        parts.append("DONE")
    parts.append(f"{values.get('frames in window', '0')} frames in window")
    gated = [values.get(f"{side} gated (%)") for side in ("parent", "child")]
    if all(g is not None for g in gated):
        parts.append(f"gated {gated[0]}/{gated[1]} %")
    if values.get("frozen") == "True":
        parts.append("frozen")
    parts.append(message)
    return " | ".join(parts)


def _input_line(level: str, message: str, values: dict[str, str]) -> str:
    parts = [f"input {level}", f"{values.get('messages', '0')} messages"]
    if "input rate (Hz)" in values:
        parts.append(f"{values['input rate (Hz)']} Hz")
    parts.append(message)
    return " | ".join(parts)


def _joint_name(st: Any, node: str) -> str | None:
    """The joint (or ``input``) a status names, when it is ``node``'s; else None.

    A node's statuses carry its full name in ``hardware_id`` and are named
    ``<status_prefix(node)>: <joint>`` (``jointfit: hip``, in a namespace
    ``subject_a/jointfit: hip``); ``jointfit: <joint>`` with an empty
    ``hardware_id`` (an older node) is taken for any node.
    """
    if st.hardware_id not in ("", node):
        return None
    for prefix in {f"{status_prefix(node)}: " if st.hardware_id else "jointfit: ", "jointfit: "}:
        if st.name.startswith(prefix):
            return str(st.name[len(prefix) :])
    return None


def status_nodes(statuses: Sequence[Any]) -> list[str]:
    """The full names of the jointfit nodes whose statuses are among ``statuses`` (from their ``hardware_id``)."""
    found: list[str] = []
    for st in statuses:
        node = st.hardware_id
        if node.startswith("/") and node not in found and _joint_name(st, node) is not None:
            found.append(node)
    return found


def status_lines(statuses: Sequence[Any], node: str) -> list[str]:
    """One line for the node's input status and one per joint, from ``diagnostic_msgs/DiagnosticStatus`` messages.

    Parameters
    ----------
    statuses : sequence of DiagnosticStatus
        A ``/diagnostics`` message's statuses (any node's).
    node : str
        Fully qualified node name (:func:`node_path`); statuses whose
        ``hardware_id`` names another node are left out (an empty one, from
        a node that does not set it, is kept).

    Returns
    -------
    list of str
        Empty when none of the statuses is this node's.
    """
    lines: list[str] = []
    for st in statuses:
        name = _joint_name(st, node)
        if name is None:
            continue
        level = LEVELS.get(st.level[0] if isinstance(st.level, bytes) else int(st.level), "?")
        values = {kv.key: kv.value for kv in st.values}
        if name == "input":
            lines.insert(0, _input_line(level, st.message, values))
        else:
            lines.append(_joint_line(name, level, st.message, values))
    return lines


# ---------------------------------------------------------------------------- ROS


class _Session:
    """An rclpy context, node and executor of its own (closed by :meth:`close`)."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node

        self._rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(args=[], context=self.context)
        self.node = Node(f"jointfit_shell_{os.getpid()}", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def spin_until(self, done: Callable[[], bool], timeout: float | None) -> bool:
        end = None if timeout is None else time.monotonic() + timeout
        while end is None or time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.05)
            if done():
                return True
        return done()

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self._rclpy.try_shutdown(context=self.context)


class StatusRounds:
    """Rounds of ``/diagnostics`` lines per node, for one node, several, or every jointfit node heard.

    Parameters
    ----------
    nodes : sequence of str or None
        Full node names (:func:`node_path`) in the order to show them; None:
        every jointfit node whose statuses arrive, in the order heard.
    """

    def __init__(self, nodes: Sequence[str] | None) -> None:
        self.nodes: list[str] = list(nodes) if nodes is not None else []
        self.every = nodes is None
        self.first: dict[str, list[str]] = {}  # each node's first round (what --once prints)
        self.latest: dict[str, list[str]] = {}
        self.heard: dict[str, int] = {}  # rounds per node
        self.pending: list[tuple[str, list[str]]] = []  # new rounds not printed yet
        self.publishers: dict[str, float] = {}  # /diagnostics publishers in the graph -> when first seen (s)
        self.graph_changed = 0.0  # when a publisher last appeared (s)
        self.started: float | None = None  # when the graph was first looked at (s)

    @property
    def many(self) -> bool:
        """Whether lines name their node (more than one node asked for, or --all)."""
        return self.every or len(self.nodes) > 1

    def add(self, statuses: Sequence[Any]) -> None:
        """Take one ``/diagnostics`` message's statuses."""
        for node in status_nodes(statuses) if self.every else self.nodes:
            lines = status_lines(statuses, node)
            if not lines:
                continue
            if node not in self.nodes:
                self.nodes.append(node)
            self.first.setdefault(node, lines)
            self.latest[node] = lines
            self.heard[node] = self.heard.get(node, 0) + 1
            self.pending.append((node, lines))

    def note_graph(self, publishers: Sequence[str], now: float) -> None:
        """Take the full names of the nodes that publish ``/diagnostics`` now (from the ROS graph), at ``now`` s."""
        if self.started is None:
            self.started = now
        for node in publishers:
            if node not in self.publishers:
                self.publishers[node] = now
                self.graph_changed = now

    def complete(self, now: float = 0.0) -> bool:
        """One round of every node: each named node heard; or (every node) the first node heard heard three
        times, every node heard twice, and every ``/diagnostics`` publisher in the graph either heard or
        silent for :attr:`QUIET` s since it appeared (not a jointfit node), the graph unchanged for
        :attr:`SETTLE` s and looked at for :attr:`DISCOVERY` s. A node discovered later than another is
        still waited for: DDS discovery of a participant can take seconds on a loaded machine (a node
        not yet in the graph when the first node had spoken three times was left out, 2026-12-02)."""
        if not self.every:
            return all(node in self.first for node in self.nodes)
        counts = list(self.heard.values())
        if not counts or counts[0] <= 2 or min(counts) <= 1 or now - self.graph_changed < self.SETTLE:
            return False
        if self.started is not None and now - self.started < self.DISCOVERY:
            return False
        return all(node in self.heard or now - seen >= self.QUIET for node, seen in self.publishers.items())

    # A jointfit node in the graph may stay silent for seconds after it appears: it sends to this process's
    # subscription only once it has discovered it in turn. In a clean-clone CI run (two subjects' nodes and
    # mocaps, another live test beside them) the frozen subject's node was left out of the round at 3 s
    # (2026-12-07), so these wait longer; --once --all still prints what it has at --timeout (5 s by default).
    QUIET = 8.0  # s a /diagnostics publisher may stay silent before it is taken for another kind of node
    SETTLE = 1.0  # s without a new /diagnostics publisher before --all --once prints
    DISCOVERY = 5.0  # s --all --once looks at the ROS graph at least (the other nodes' discovery)

    def missing(self) -> list[str]:
        """The named nodes not heard yet (every node: none heard at all, ``["any jointfit node"]``)."""
        if self.every:
            return [] if self.heard else ["any jointfit node"]
        return [node for node in self.nodes if node not in self.first]

    def silence(self, timeout: float, domain: str) -> str:
        """The line for nodes not heard within ``timeout`` s: not running, or running and silent (a busy node).

        A named node that publishes ``/diagnostics`` in the ROS graph (:meth:`note_graph`) is running: on a
        busy machine its messages reach a new subscriber late (a 12-joint node at 1 kHz beside the mocap
        stream on 2 cores, 2026-12-07: it published every 1 s, the first message reached a new subscriber
        after ~10 s, and ``--once`` said "is the node running?").
        """
        missing = self.missing()
        running = [node for node in missing if node in self.publishers]
        if running:
            return (
                f"jointfit status: {', '.join(running)} is running (it publishes /diagnostics) but none reached this "
                f"command within {timeout:g} s: on a busy machine (a node that cannot keep up with its input, the "
                "mocap driver) they arrive later; --timeout 30 waits longer"
            )
        return (
            f"jointfit status: no /diagnostics from {', '.join(missing)} within {timeout:g} s (is the node running, "
            f"with the same ROS_DOMAIN_ID={domain}?)"
        )

    def text(self, node: str, lines: Sequence[str]) -> str:
        """A node's round as printed: its lines, each after the node's full name when several are watched."""
        return "\n".join(f"{node} {line}" if self.many else line for line in lines)


def _diagnostics_publishers(node: Any) -> list[str]:
    """The full names of the nodes that publish ``/diagnostics`` in the ROS graph, as ``node`` sees it."""
    infos = node.get_publishers_info_by_topic("/diagnostics")
    return [node_path(f"{i.node_namespace.rstrip('/')}/{i.node_name}") for i in infos]


def _status_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="jointfit status",
        description="Watch running jointfit nodes' /diagnostics: one line per joint, refreshed as they arrive.",
    )
    _add_node(p, many=True)
    p.add_argument("--all", action="store_true", help="every jointfit node heard on /diagnostics (lines name their node)")
    p.add_argument("--once", action="store_true", help="print one round and exit (1 if none arrives in time)")
    p.add_argument(
        "--timeout",
        type=_positive,
        default=None,
        help="seconds to wait for the first message (default 5 with --once, else wait until one comes)",
    )
    return p


def status_main(argv: Sequence[str]) -> int:
    """``jointfit status``; returns the exit status."""
    parser = _status_parser()
    opts = parser.parse_args(list(argv))
    if opts.all and opts.node:
        parser.error("give --node or --all, not both")
    nodes = None if opts.all else [node_path(n) for n in dict.fromkeys(opts.node or ["jointfit"])]
    timeout = opts.timeout if opts.timeout is not None else (5.0 if opts.once else None)
    from diagnostic_msgs.msg import DiagnosticArray

    session = _Session()
    rounds = StatusRounds(nodes)
    clear = sys.stdout.isatty() and not opts.once

    def on_diagnostics(msg: DiagnosticArray) -> None:
        rounds.add(msg.status)

    session.node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 10)
    me = session.node.get_fully_qualified_name()

    def round_done() -> bool:
        now = time.monotonic()
        if rounds.every:
            rounds.note_graph(_diagnostics_publishers(session.node), now)
            rounds.publishers.pop(me, None)
        return rounds.complete(now)

    try:
        waited = session.spin_until(round_done if opts.once else lambda: bool(rounds.pending), timeout)
        if not rounds.first or (opts.once and not waited and not opts.all):
            rounds.note_graph(_diagnostics_publishers(session.node), time.monotonic())
            print(rounds.silence(float(timeout or 0.0), os.environ.get("ROS_DOMAIN_ID", "0")), file=sys.stderr)
            return 1
        if opts.once:
            print("\n".join(rounds.text(node, rounds.first[node]) for node in rounds.nodes), flush=True)
            return 0
        while True:
            while rounds.pending:
                node, lines = rounds.pending.pop(0)
                if clear:
                    print("\x1b[H\x1b[J" + "\n".join(rounds.text(n, rounds.latest[n]) for n in rounds.latest), flush=True)
                    continue
                print(f"-- {node} {time.strftime('%H:%M:%S')}")
                print(rounds.text(node, lines), flush=True)
            session.spin_until(lambda: bool(rounds.pending), None)
    except KeyboardInterrupt:
        return 0
    finally:
        session.close()


SERVICES = {"reset": "Trigger", "freeze": "SetBool", "save": "Trigger"}


def _call_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="jointfit call",
        description="Call a running jointfit node's service and print its answer: reset (forget every joint's "
        "window and estimate), freeze true|false (fix or resume the estimates; default true), save (write the "
        "calibration files).",
    )
    p.add_argument("service", choices=sorted(SERVICES), help="the service (<node>/reset, /freeze, /save)")
    p.add_argument("value", nargs="?", choices=("true", "false"), help="freeze only: true (default) or false")
    _add_node(p)
    p.add_argument("--timeout", type=_positive, default=5.0, help="seconds to wait for the service and its answer (default 5)")
    return p


def call_main(argv: Sequence[str]) -> int:
    """``jointfit call``; returns the exit status."""
    parser = _call_parser()
    opts = parser.parse_args(list(argv))
    if opts.value is not None and opts.service != "freeze":
        parser.error(f"{opts.service} takes no value (only freeze takes true or false)")
    from std_srvs.srv import SetBool, Trigger

    name = f"{node_path(opts.node)}/{opts.service}"
    srv_type: Any = SetBool if opts.service == "freeze" else Trigger
    request = srv_type.Request()
    if opts.service == "freeze":
        request.data = opts.value != "false"
    session = _Session()
    try:
        client = session.node.create_client(srv_type, name)
        if not client.wait_for_service(timeout_sec=opts.timeout):
            print(
                f"jointfit call: no service {name} within {opts.timeout:g} s (is the node running, with the same "
                f"ROS_DOMAIN_ID={os.environ.get('ROS_DOMAIN_ID', '0')}?)",
                file=sys.stderr,
            )
            return 1
        future = client.call_async(request)
        if not session.spin_until(future.done, opts.timeout):
            print(f"jointfit call: {name} did not answer within {opts.timeout:g} s", file=sys.stderr)
            return 1
        response = future.result()
        print(response.message)
        return 0 if response.success else 1
    except KeyboardInterrupt:
        return 130
    finally:
        session.close()
