"""Node names, namespaces and parameter-file entries: which node a status, a service or an entry is for.

Pure Python (no rclpy), so that it is tested without ROS. Several jointfit
nodes (one per subject, ``--ros-args -r __ns:=/subject_a``) share one ROS
graph; each is known by its fully qualified name (``/subject_a/jointfit``):
its services are ``<full name>/freeze`` ..., its ``/diagnostics`` statuses
carry the full name in ``hardware_id`` and are named ``<prefix>: <joint>``
(:func:`status_prefix`), and its entry in a ROS 2 parameter file is keyed by
the full name or by a wildcard (``/**``, ``/*/jointfit``), matched as rcl
matches them (:func:`entry_matches`).
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence

__all__ = ["DEFAULT_NODE", "node_path", "status_prefix", "entry_matches", "is_wildcard", "params_files", "entry_hint"]

DEFAULT_NODE = "/jointfit"


def node_path(name: str) -> str:
    """The fully qualified node name: ``jointfit`` -> ``/jointfit``; ``/lab1/jointfit`` as given."""
    name = name.strip().rstrip("/")
    return name if name.startswith("/") else "/" + name


def status_prefix(full_name: str) -> str:
    """The prefix of a node's ``/diagnostics`` status names.

    ``jointfit`` for the node ``/jointfit`` (status ``jointfit: hip``, as
    before namespaces), else the full name without its leading slash
    (``/subject_a/jointfit`` -> ``subject_a/jointfit: hip``), so that the
    statuses of two subjects' nodes stay apart in any diagnostics viewer
    (``rqt_robot_monitor`` and the aggregator key statuses by name).
    """
    return node_path(full_name).lstrip("/")


def _entry_regex(key: str) -> re.Pattern[str]:
    """A parameter-file entry's key as a regex over full node names (rcl: ``*`` one token, ``**`` any)."""
    tokens = node_path(key).strip("/").split("/")
    parts = []
    for token in tokens:
        if token == "**":
            parts.append("(/[^/]+)*")
        elif token == "*":
            parts.append("/[^/]+")
        else:
            parts.append("/" + re.escape(token))
    return re.compile("".join(parts) + "$")


def entry_matches(key: str, full_name: str) -> bool:
    """Whether the parameter-file entry ``key`` applies to the node ``full_name``.

    Parameters
    ----------
    key : str
        A top-level key of a ROS 2 parameter file: a node's full name with or
        without its leading slash (``/subject_a/jointfit``, ``jointfit``:
        ``/jointfit``), or with the wildcards rcl accepts as whole tokens,
        ``*`` (one namespace level or name) and ``**`` (any number of levels):
        ``/**``, ``/*/jointfit``, ``/**/jointfit``.
    full_name : str
        The node's fully qualified name (``/subject_a/jointfit``).

    Examples
    --------
    >>> entry_matches("/**", "/subject_a/jointfit"), entry_matches("jointfit", "/subject_a/jointfit")
    (True, False)
    """
    return _entry_regex(str(key)).match(node_path(full_name)) is not None


def is_wildcard(key: str) -> bool:
    """Whether a parameter-file key holds a wildcard token (``*`` or ``**``)."""
    return any(token in ("*", "**") for token in node_path(str(key)).strip("/").split("/"))


def params_files(argv: Sequence[str]) -> list[str]:
    """The ``--params-file`` paths among ROS arguments (``--ros-args ... --params-file F``), in order."""
    files = []
    inside = False
    for k, arg in enumerate(argv):
        if arg == "--ros-args":
            inside = True
        elif arg == "--":
            inside = False
        elif inside and arg == "--params-file" and k + 1 < len(argv):
            files.append(argv[k + 1])
    return files


def entry_hint(entries_by_file: Iterable[tuple[str, Sequence[str]]], full_name: str) -> str:
    """A sentence for a node whose parameter files hold no entry for it ("" when one does, or none were given).

    Parameters
    ----------
    entries_by_file : iterable of (str, sequence of str)
        Each parameter file and its top-level keys.
    full_name : str
        The node's fully qualified name.
    """
    found = [(path, list(keys)) for path, keys in entries_by_file]
    if not found or any(entry_matches(k, full_name) for _, keys in found for k in keys):
        return ""
    listed = "; ".join(f"{path}: {', '.join(keys) or 'none'}" for path, keys in found)
    return (
        f"no entry of the parameter file is for this node, {full_name} (entries: {listed}); key its entry "
        f"'{full_name}:' (or '/**:' for every node)"
    )
