"""rosbag2 recordings (sqlite3 ``.db3`` and ``.mcap``) read as raw CDR bytes, without ROS.

The offline tools (``jointfit replay``, the CLI's bag input) read bags with the
pure-Python `rosbags <https://gitlab.com/ternaris/rosbags>`_ package (extra
``jointfit[bag]``), imported only when a bag is opened: importing this module
needs neither ``rosbags`` nor ROS.

Messages are handed out as the serialized bytes stored in the bag, which are
exactly what a ``raw=True`` subscription receives (CDR, 4-byte encapsulation
header included), so the parsers of :mod:`jointfit_ros.raw`
(:func:`~jointfit_ros.raw.parse_pose_array`,
:func:`~jointfit_ros.raw.parse_pointcloud2`,
:func:`~jointfit_ros.raw.parse_pose_stamped`) apply unchanged and no message
object is ever built.

Accepted paths (what ``ros2 bag record`` writes, any storage plugin rosbags
reads):

* a bag directory holding ``metadata.yaml`` (split and zstd-compressed bags
  included);
* that ``metadata.yaml`` itself;
* a single storage file, ``*.db3`` or ``*.mcap`` (its own topic table or
  summary replaces the metadata);
* a bag directory without ``metadata.yaml`` (a recording that was killed
  before writing it) holding exactly one ``.db3`` or ``.mcap`` file.

Topic names match with or without the leading slash: ``markers`` selects the
bag's ``/markers`` (``ros2 bag record`` stores absolute names).

Example::

    from jointfit_ros.bag import bag_topics, iter_bag_messages
    from jointfit_ros.raw import parse_pose_array

    print(bag_topics("recording"))
    for msg in iter_bag_messages("recording", ["/mocap/markers"]):
        points = parse_pose_array(msg.raw).points  # (P, 3), the bag's units
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from jointfit_core.errors import InputError, MissingDependencyError

__all__ = [
    "SUPPORTED_MSGTYPES",
    "BagTopic",
    "BagMessage",
    "bag_topics",
    "supported_topics",
    "select_topics",
    "iter_bag_messages",
    "iter_selected_messages",
]

#: Message types that jointfit reads from a bag, as rosbag2 names them.
SUPPORTED_MSGTYPES: tuple[str, ...] = (
    "geometry_msgs/msg/PoseArray",
    "sensor_msgs/msg/PointCloud2",
    "geometry_msgs/msg/PoseStamped",
)

_STORAGE_SUFFIXES = (".db3", ".mcap")
_INSTALL_HINT = "reading rosbag2 files needs the rosbags package: pip install 'jointfit[bag]' (or rosbags)"


@dataclass(frozen=True)
class BagTopic:
    """One topic of a bag.

    Attributes
    ----------
    name : str
        Topic name as stored in the bag (``ros2 bag record`` stores absolute
        names such as ``/markers``).
    msgtype : str
        Message type as rosbag2 writes it, e.g. ``geometry_msgs/msg/PoseArray``.
        A topic recorded with several types lists them joined by ``" | "``.
    count : int
        Number of messages of the topic in the bag.
    """

    name: str
    msgtype: str
    count: int


@dataclass(frozen=True)
class BagMessage:
    """One message of a bag, still serialized.

    Attributes
    ----------
    topic : str
        Topic name as stored in the bag.
    msgtype : str
        Message type, e.g. ``sensor_msgs/msg/PointCloud2``.
    log_time_ns : int
        Time the recorder received (logged) the message, ns since the epoch
        of the recording clock. Not the ``header.stamp`` inside ``raw``.
    raw : bytes
        The CDR bytes, 4-byte encapsulation header included: what a
        ``raw=True`` subscription delivers and ``Publisher.publish`` accepts.
    """

    topic: str
    msgtype: str
    log_time_ns: int
    raw: bytes


def _rosbag2() -> Any:
    """The ``rosbags.rosbag2`` module, or :class:`MissingDependencyError` with an install hint."""
    try:
        import rosbags.rosbag2 as rosbag2
    except ImportError:
        raise MissingDependencyError(_INSTALL_HINT) from None
    return rosbag2


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _storage_path(path: str | os.PathLike[str]) -> Path:
    """The path rosbags should open (directory or storage file), after the checks of the module docstring."""
    try:
        given = Path(path)
    except TypeError:
        raise InputError(f"path: expected a str or os.PathLike, got {type(path).__name__}") from None
    if not given.exists():
        raise InputError(f"no such bag: {given}")
    if given.is_file() and given.name == "metadata.yaml":
        return given.parent
    if given.is_dir():
        if (given / "metadata.yaml").is_file():
            return given
        files = sorted(p for p in given.iterdir() if p.is_file() and p.suffix in _STORAGE_SUFFIXES)
        if len(files) == 1:
            return files[0]
        if not files:
            raise InputError(
                f"not a rosbag2 bag: directory {given} has no metadata.yaml and no .db3 or .mcap file"
            )
        raise InputError(
            f"not a rosbag2 bag: directory {given} has no metadata.yaml and {len(files)} storage files "
            f"({', '.join(p.name for p in files)}); pass one of them"
        )
    if given.suffix == ".zstd":
        raise InputError(
            f"not a rosbag2 bag: {given} is a zstd-compressed storage file; "
            "pass its bag directory (with metadata.yaml)"
        )
    if given.suffix not in _STORAGE_SUFFIXES:
        raise InputError(
            f"not a rosbag2 bag: {given}: expected a bag directory with metadata.yaml, "
            f"a .db3 or a .mcap file, got a {given.suffix or 'suffix-less'} file"
        )
    return given


class _OpenBag:
    """Context manager: an open ``rosbags.rosbag2.Reader`` whose failures become :class:`InputError`."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.given = path
        self.path = _storage_path(path)
        self.reader: Any = None

    def __enter__(self) -> Any:
        rosbag2 = _rosbag2()
        try:
            reader = rosbag2.Reader(self.path)
            reader.open()
        except Exception as exc:  # ReaderError, OSError, struct/yaml errors on corrupt files
            hint = ""
            if "end magic" in str(exc):  # an MCAP file without its footer: the recorder was killed
                hint = "; the MCAP file looks truncated: repair it with `mcap recover` (mcap CLI)"
            raise InputError(f"not a readable rosbag2 bag: {self.given} ({_one_line(exc)}){hint}") from None
        self.reader = reader
        return reader

    def __exit__(self, *exc_info: object) -> None:
        reader, self.reader = self.reader, None
        if reader is not None and reader.is_open:
            reader.close()


def _topics_of(reader: Any) -> dict[str, BagTopic]:
    out: dict[str, BagTopic] = {}
    for conn in reader.connections:
        prev = out.get(conn.topic)
        if prev is None:
            out[conn.topic] = BagTopic(conn.topic, conn.msgtype, int(conn.msgcount))
        else:
            types = prev.msgtype.split(" | ")
            msgtype = prev.msgtype if conn.msgtype in types else f"{prev.msgtype} | {conn.msgtype}"
            out[conn.topic] = BagTopic(conn.topic, msgtype, prev.count + int(conn.msgcount))
    return dict(sorted(out.items()))


def _listing(topics: dict[str, BagTopic]) -> str:
    if not topics:
        return "the bag has no topics"
    return "the bag has " + ", ".join(f"{t.name} ({t.msgtype}, {t.count} messages)" for t in topics.values())


def _absolute(name: str) -> str:
    return name if name.startswith("/") else "/" + name


def bag_topics(path: str | os.PathLike[str]) -> dict[str, BagTopic]:
    """The topics of a rosbag2 bag, with their message types and counts.

    Parameters
    ----------
    path : str or os.PathLike
        Bag directory, its ``metadata.yaml``, or a ``.db3`` / ``.mcap`` file
        (see the module docstring).

    Returns
    -------
    dict of str to BagTopic
        Topic name (as stored) -> :class:`BagTopic`, sorted by name. Every
        topic is listed, whatever its type (including topics without messages).

    Raises
    ------
    InputError
        The path does not exist or is not a readable rosbag2 bag.
    MissingDependencyError
        ``rosbags`` is not installed.
    """
    with _OpenBag(path) as reader:
        return _topics_of(reader)


def supported_topics(path: str | os.PathLike[str]) -> list[str]:
    """Names of the bag's topics whose type is in :data:`SUPPORTED_MSGTYPES` and that hold messages.

    Parameters
    ----------
    path : str or os.PathLike
        As for :func:`bag_topics`.

    Returns
    -------
    list of str
        Topic names as stored, sorted; possibly empty.

    Raises
    ------
    InputError, MissingDependencyError
        As :func:`bag_topics`.
    """
    return [t.name for t in bag_topics(path).values() if t.msgtype in SUPPORTED_MSGTYPES and t.count > 0]


def select_topics(path: str | os.PathLike[str], topics: Sequence[str]) -> list[BagTopic]:
    """The bag's topics that a list of names asks for, checked for presence and type.

    Parameters
    ----------
    path : str or os.PathLike
        As for :func:`bag_topics`.
    topics : sequence of str
        Topic names; ``markers`` and ``/markers`` both select the bag's
        ``/markers`` (and ``/markers`` selects a bag's relative ``markers``).

    Returns
    -------
    list of BagTopic
        In the order asked, each bag topic once.

    Raises
    ------
    InputError
        ``topics`` is empty or not a sequence of names; a name is not in the
        bag (the message lists the bag's topics with types and counts); a
        topic's type is not one of :data:`SUPPORTED_MSGTYPES`; or as
        :func:`bag_topics`.
    MissingDependencyError
        ``rosbags`` is not installed.
    """
    _check_names(topics)
    return _select(path, bag_topics(path), topics)


def _check_names(topics: Sequence[str]) -> None:
    if isinstance(topics, str | bytes) or not isinstance(topics, Sequence):
        raise InputError(f"topics: expected a sequence of topic names, got {topics!r}")
    if bad := [t for t in topics if not isinstance(t, str) or not t.strip("/")]:
        raise InputError(f"topics: expected non-empty topic names (str), got {bad!r}")


def _select(path: str | os.PathLike[str], available: dict[str, BagTopic], topics: Sequence[str]) -> list[BagTopic]:
    """:func:`select_topics` among a bag's topics already listed (``topics`` checked by :func:`_check_names`)."""
    if not topics:
        raise InputError(f"topics: expected at least one topic name; {_listing(available)}")
    by_absolute = {_absolute(name): info for name, info in available.items()}
    selected: list[BagTopic] = []
    missing: list[str] = []
    for name in topics:
        found = available.get(name) or by_absolute.get(_absolute(name))
        if found is None:
            missing.append(name)
        elif found not in selected:
            selected.append(found)
    if missing:
        raise InputError(f"{path}: topics not in the bag: {', '.join(missing)}; {_listing(available)}")
    for info in selected:
        if info.msgtype not in SUPPORTED_MSGTYPES:
            raise InputError(
                f"{path}: topic {info.name} has message type {info.msgtype}; "
                f"supported: {', '.join(SUPPORTED_MSGTYPES)}"
            )
    return selected


def iter_bag_messages(path: str | os.PathLike[str], topics: Sequence[str]) -> Iterator[BagMessage]:
    """The messages of some topics of a bag, raw, in log-time order across topics.

    Parameters
    ----------
    path : str or os.PathLike
        Bag directory, its ``metadata.yaml``, or a ``.db3`` / ``.mcap`` file
        (see the module docstring).
    topics : sequence of str
        Topic names; ``markers`` and ``/markers`` both select the bag's
        ``/markers``. Duplicates are read once.

    Returns
    -------
    iterator of BagMessage
        Lazily read; ``raw`` is the CDR with its encapsulation header (feed it
        to :mod:`jointfit_ros.raw`). Ordered by ``log_time_ns`` (the
        storage's order: SQL ``ORDER BY timestamp`` or the MCAP message index;
        equal log times in the storage's order). A split bag is read file after
        file, in the order of ``metadata.yaml``, which is chronological for
        ``ros2 bag record``.

    Raises
    ------
    InputError
        Raised by this call, before any message is read, when the path does
        not exist or is not a readable bag, when a requested topic is not in
        the bag (the message lists the bag's topics with their types and
        counts), or when a requested topic's type is not one of
        :data:`SUPPORTED_MSGTYPES`. Raised during the iteration when the bag
        is corrupt further in (e.g. a truncated file).
    MissingDependencyError
        ``rosbags`` is not installed.

    Notes
    -----
    The bag is opened twice: once here to check the request, once when the
    iteration starts (and closed when it ends or the iterator is closed), so
    a bag is never left open by an iterator that was not consumed.
    """
    selected = [info.name for info in select_topics(path, topics)]
    return iter_selected_messages(path, selected)


def iter_selected_messages(path: str | os.PathLike[str], topics: Sequence[str]) -> Iterator[BagMessage]:
    """:func:`iter_bag_messages` with the bag opened once, when the iteration starts.

    A sqlite3 bag's open counts its messages (~0.13 s per 100 000 here), and
    :func:`iter_bag_messages` opens it twice so as to raise its errors at the
    call. Here the topics are selected (:func:`select_topics`) on the reader
    the messages come from: the same errors, raised by the first ``next()``.
    """
    _check_names(topics)
    with _OpenBag(path) as reader:
        selected = {info.name for info in _select(path, _topics_of(reader), topics)}
        conns = [c for c in reader.connections if c.topic in selected]
        try:
            for conn, log_time_ns, raw in reader.messages(connections=conns):
                yield BagMessage(conn.topic, conn.msgtype, int(log_time_ns), bytes(raw))
        except Exception as exc:  # corrupt data further in (ReaderError, zstd/lz4 errors, ...)
            raise InputError(f"{path}: bag unreadable after the start ({_one_line(exc)})") from None
