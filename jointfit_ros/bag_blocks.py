"""A bag's messages in blocks, optionally read and parsed in a second process while the estimators run.

ROS-free. ``jointfit fit`` reads a bag, parses its marker messages and runs
the estimators; the first two take about as long as the third. A
:class:`BagReaderProcess` (or :func:`parsed_blocks` with ``process=True``) is
a forked child that opens the bag at once (while the parent checks the
topics), then reads and parses each block
(:func:`~jointfit_ros.marker_parser.parse_markers`) while the parent routes the
previous one to the estimators, so that on two cores the wall time is nearer
the larger of the two than their sum.

The child writes each block's frames, stamps and positions into one of
``SLOTS`` slots of an anonymous shared memory map and sends the rest (frame
ids, problems, pose messages: usually well under the pipe's buffer, so that
the child does not wait on the parent's reading) through a pipe; the parent
copies the arrays out and frees the slot. The blocks, and so every number
the fit computes, are the same as when they are read and parsed in-process
(tested).

The child ignores SIGINT (the parent handles it and stops the child), and it
exits when the parent goes away: a send to a closed pipe fails, and a wait for
a free slot checks the parent every second.
"""

from __future__ import annotations

import dataclasses
import itertools
import mmap
import multiprocessing
import os
import signal
import threading
from collections.abc import Iterable, Iterator, Sequence
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from jointfit_core.errors import InputError

from .bag import iter_selected_messages
from .inputs import Message, PoseMessage, split_block
from .marker_parser import ParsedMarkers, parse_markers
from .params import NodeConfig

__all__ = ["BagReaderProcess", "can_fork", "parsed_blocks", "split_blocks"]

FloatArray = NDArray[np.float64]

#: Shared-memory slots: the child reads and parses up to ``SLOTS - 1`` blocks ahead of the parent.
SLOTS = 3
#: A child waiting for a free slot checks this often (s) that its parent is still there.
PARENT_CHECK_S = 1.0


def split_blocks(
    messages: Iterable[Any], marker_topic: str | None, step: int, max_block: int
) -> Iterator[list[Message]]:
    """Messages (objects with ``topic`` and ``raw``) in blocks of at most ``max_block``.

    A block also ends where the message count reaches a multiple of ``step``
    (where the offline fit takes its checkpoints). Messages on ``marker_topic``
    become ``(None, raw)``, the others ``(topic, raw)``.
    """
    pending: list[Message] = []
    done = 0
    limit = min(max_block, step)  # the block's length: to the next multiple of step, at most max_block
    for msg in messages:
        pending.append((None if msg.topic == marker_topic else msg.topic, msg.raw))
        if len(pending) >= limit:
            yield pending
            done += len(pending)
            pending = []
            limit = min(max_block, step - done % step)
    if pending:
        yield pending


def _parse_block(cfg: NodeConfig, block: Sequence[Message]) -> tuple[ParsedMarkers, list[PoseMessage]]:
    raws, poses = split_block(block)
    return parse_markers(cfg, raws), poses


def can_fork() -> bool:
    """Whether the fit may fork its reader: ``fork`` exists and this process runs no other Python thread.

    (A fork copies only the calling thread; one holding a lock elsewhere could leave it locked in the child.)
    """
    return "fork" in multiprocessing.get_all_start_methods() and threading.active_count() == 1


def parsed_blocks(
    path: str | os.PathLike[str],
    topics: Sequence[str],
    marker_topic: str | None,
    cfg: NodeConfig,
    step: int,
    max_block: int,
    *,
    process: bool,
) -> Iterator[tuple[ParsedMarkers, list[PoseMessage]]]:
    """A bag's messages in blocks (:func:`split_blocks`), the marker messages parsed.

    Parameters
    ----------
    path : str or os.PathLike
        The bag.
    topics : sequence of str
        Topics to read, as :func:`~jointfit_ros.bag.select_topics` named them
        (:func:`~jointfit_ros.bag.iter_selected_messages`: the bag is opened once).
    marker_topic : str or None
        The one holding marker messages (None: none does).
    cfg : NodeConfig
        For :func:`~jointfit_ros.marker_parser.parse_markers` (not ``unlabelled``).
    step, max_block : int
        Block boundaries (:func:`split_blocks`).
    process : bool
        Read and parse in a forked child process (:class:`BagReaderProcess`).

    Yields
    ------
    parsed : ParsedMarkers
    poses : list of (int, str, bytes)
        The block's pose-topic messages; the two are what
        :meth:`~jointfit_ros.inputs.MessageRouter.route_parsed` takes.

    Raises
    ------
    InputError
        The bag cannot be read (the child's error, re-raised here), or the child stopped.
    """
    if not process:
        for block in split_blocks(iter_selected_messages(path, topics), marker_topic, step, max_block):
            yield _parse_block(cfg, block)
        return
    yield from BagReaderProcess(path, topics, cfg, max_block).blocks(marker_topic, step)


class BagReaderProcess:
    """A forked child that reads a bag and parses its blocks; the parent's end of it.

    The child opens the bag (a sqlite3 bag's open counts its messages, and its
    query sorts them: ~0.3 s per 100 000) as soon as it starts, while the
    parent goes on (checking the topics itself, say); it splits the messages
    into blocks once :meth:`blocks` gives it the block boundaries.

    Parameters
    ----------
    path : str or os.PathLike
        The bag.
    topics : sequence of str
        Topics to read (:func:`~jointfit_ros.bag.iter_selected_messages`: checked in the child,
        whose errors :meth:`blocks` raises).
    cfg : NodeConfig
        For :func:`~jointfit_ros.marker_parser.parse_markers` (not ``unlabelled``).
    max_block : int
        Most messages in a block.
    """

    def __init__(self, path: str | os.PathLike[str], topics: Sequence[str], cfg: NodeConfig, max_block: int) -> None:
        ctx = multiprocessing.get_context("fork")
        self.path = Path(path)
        self.slots = _Slots(max_block, len(cfg.marker_names))
        self.free = ctx.Semaphore(SLOTS)
        self.conn, child_end = ctx.Pipe(duplex=True)
        self.proc = ctx.Process(
            target=_serve,
            args=(child_end, self.slots, self.free, os.getpid(), self.path, list(topics), cfg, max_block),
            name="jointfit-bag-reader",
            daemon=True,
        )
        self.proc.start()
        child_end.close()

    def blocks(self, marker_topic: str | None, step: int) -> Iterator[tuple[ParsedMarkers, list[PoseMessage]]]:
        """The blocks, as :func:`parsed_blocks` yields them (``marker_topic`` and ``step`` as there).

        The child stops when the iteration ends, fails or is closed.
        """
        try:
            try:
                self.conn.send((marker_topic, step))
            except OSError:
                pass  # the child is gone: its error or exit code is read below
            while True:
                try:
                    msg = self.conn.recv()
                except EOFError:
                    self.proc.join(5.0)
                    raise InputError(f"{self.path}: the bag reader process stopped (exit code {self.proc.exitcode})") from None
                if msg[0] == "end":
                    return
                if msg[0] == "error":
                    raise msg[1]
                _, slot, k, meta, poses = msg
                parsed = dataclasses.replace(
                    meta,
                    index=self.slots.index[slot, :k].copy(),
                    stamps_ns=self.slots.stamps[slot, :k].copy(),
                    frames=self.slots.frames[slot, :k].copy(),
                )
                self.free.release()
                yield parsed, poses
        finally:
            self.close()

    def close(self) -> None:
        """Stop the child (also before :meth:`blocks`)."""
        self.conn.close()
        if self.proc.is_alive():
            self.proc.terminate()
        self.proc.join(5.0)


class _Slots:
    """``SLOTS`` blocks' arrays in one anonymous shared map (inherited by the forked child)."""

    def __init__(self, max_block: int, n_markers: int) -> None:
        sizes = (max_block * n_markers * 3, max_block, max_block)  # frames, index, stamps: 8-byte items
        buf = mmap.mmap(-1, SLOTS * sum(sizes) * 8)
        flat = np.frombuffer(buf, dtype=np.uint8)
        cut = np.cumsum([0, *(SLOTS * z * 8 for z in sizes)])
        self.frames = flat[cut[0] : cut[1]].view(np.float64).reshape(SLOTS, max_block, n_markers, 3)
        self.index = flat[cut[1] : cut[2]].view(np.int64).reshape(SLOTS, max_block)
        self.stamps = flat[cut[2] : cut[3]].view(np.int64).reshape(SLOTS, max_block)


def _serve(
    conn: Connection,
    slots: _Slots,
    free: Any,
    parent: int,
    path: Path,
    topics: list[str],
    cfg: NodeConfig,
    max_block: int,
) -> None:
    """The child: open the bag, wait for the block boundaries, read, parse, hand each block over."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    no_frames = np.zeros((0, len(cfg.marker_names), 3))
    no_ints = np.zeros(0, dtype=np.int64)
    slot = 0
    try:
        messages = iter_selected_messages(path, topics)
        first = next(messages, None)  # open, select, query: while the parent checks the topics
        marker_topic, step = conn.recv()
        stream = messages if first is None else itertools.chain([first], messages)
        for block in split_blocks(stream, marker_topic, step, max_block):
            parsed, poses = _parse_block(cfg, block)
            while not free.acquire(timeout=PARENT_CHECK_S):
                if os.getppid() != parent:
                    return
            k = parsed.index.size
            slots.frames[slot, :k] = parsed.frames
            slots.index[slot, :k] = parsed.index
            slots.stamps[slot, :k] = parsed.stamps_ns
            meta = dataclasses.replace(parsed, index=no_ints, stamps_ns=no_ints, frames=no_frames)
            conn.send(("block", slot, k, meta, poses))
            slot = (slot + 1) % SLOTS
        conn.send(("end",))
    except (BrokenPipeError, ConnectionResetError, EOFError):
        return  # the parent has gone (or closed this reader before asking for blocks)
    except BaseException as exc:  # every error is the parent's to report
        try:
            conn.send(("error", exc))
        except (BrokenPipeError, ConnectionResetError):
            return
        except Exception:  # an exception that does not pickle
            conn.send(("error", InputError(f"{path}: {type(exc).__name__}: {exc}")))
    finally:
        conn.close()
