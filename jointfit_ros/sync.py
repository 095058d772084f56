"""Pairing parent and child data that arrive on different topics, by header stamp.

Driver frame counters are not reliable across topics, so two inputs belong to
the same frame when their stamps differ by at most a tolerance. Pure Python,
no rclpy.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

__all__ = ["StampMatcher"]


@dataclass
class StampMatcher:
    """Match items from two sources (``0`` parent, ``1`` child) by stamp.

    Parameters
    ----------
    tolerance_ns : int
        Largest stamp difference of a pair (nanoseconds).
    max_pending : int
        Items kept per source while waiting for a partner.

    Attributes
    ----------
    unmatched : int
        Items discarded without a partner (older than a matched pair, pushed
        out of a full queue, or with a stamp that went backwards).
    matched : int
        Pairs returned.

    Notes
    -----
    Each source's stamps must increase; an item whose stamp is not newer
    than the last one of its source is discarded (and counted). When an
    item arrives, the other source's queue is searched for the item nearest
    in stamp; if it is within the tolerance the pair is returned and every
    older item of both queues is discarded as unmatched (it can no longer
    find a partner, since stamps only increase).
    """

    tolerance_ns: int
    max_pending: int = 50
    unmatched: int = 0
    matched: int = 0
    _queues: tuple[deque[tuple[int, Any]], deque[tuple[int, Any]]] = field(
        default_factory=lambda: (deque(), deque()), repr=False
    )
    _last: list[int | None] = field(default_factory=lambda: [None, None], repr=False)

    def add(self, source: int, stamp_ns: int, item: Any) -> tuple[int, Any, Any] | None:
        """Add an item; return ``(stamp_ns, parent_item, child_item)`` when it completes a pair.

        The returned stamp is the parent's.
        """
        if source not in (0, 1):
            raise ValueError(f"source: expected 0 (parent) or 1 (child), got {source!r}")
        last = self._last[source]
        if last is not None and stamp_ns <= last:
            self.unmatched += 1
            return None
        self._last[source] = stamp_ns
        other = self._queues[1 - source]
        best = None
        best_gap = None
        for k, (s, _) in enumerate(other):
            gap = abs(s - stamp_ns)
            if best_gap is None or gap < best_gap:
                best, best_gap = k, gap
        if best is not None and best_gap is not None and best_gap <= self.tolerance_ns:
            for _ in range(best):
                other.popleft()
                self.unmatched += 1
            s_other, item_other = other.popleft()
            own = self._queues[source]
            while own and own[0][0] < stamp_ns:
                own.popleft()
                self.unmatched += 1
            self.matched += 1
            if source == 0:
                return stamp_ns, item, item_other
            return s_other, item_other, item
        queue = self._queues[source]
        queue.append((stamp_ns, item))
        if len(queue) > self.max_pending:
            queue.popleft()
            self.unmatched += 1
        return None

    def clear(self) -> None:
        """Forget pending items and the last stamps (counters are kept)."""
        self._queues[0].clear()
        self._queues[1].clear()
        self._last = [None, None]
