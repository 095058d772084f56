"""Marker frames received before: a looped replay sends the same frames again, and they are no new data.

A looped bag (``jointfit_replay --loop``, ``ros2 bag play --loop``) sends
every frame again with its own stamp and its own markers. The time line
re-anchors the loop (:mod:`jointfit_ros.timeline`) so that the joints keep
publishing; but a frame that entered a joint's window once and enters it
again is counted as a second, independent measurement, and the window's
covariance shrinks with every loop while the error stays: measured on the
live node, a hip calibration saved after a minute of ``--loop --rate max``
of a 20 s bag was 5.9-8.2 sd off (the status said OK). :class:`RepeatedFrames`
remembers the stamp and a digest of the markers of the latest frames, so
that the router can tell such a frame (the same stamp, the same markers,
bit for bit) from a new one: the joints publish its outputs but do not add
it to their windows. A recording that restarts its stamps with new markers
is new data and is added as before.
"""

from __future__ import annotations

from collections import deque

import numpy as np
from numpy.typing import NDArray

__all__ = ["REPEAT_MEMORY", "RepeatedFrames"]

#: Frames remembered (their stamp and a 64-bit digest of their markers: a few MB): 22 min at 100 Hz, 131 s at
#: 1 kHz. A loop longer than that is not recognised and enters the windows again, as before.
REPEAT_MEMORY = 1 << 17


class RepeatedFrames:
    """The stamps and marker digests of the latest frames received, to tell a frame received again.

    Parameters
    ----------
    capacity : int
        Frames remembered (oldest forgotten first).

    Attributes
    ----------
    count : int
        Frames recognised as received before, since the start (or :meth:`clear`).
    """

    def __init__(self, capacity: int = REPEAT_MEMORY) -> None:
        self.capacity = int(capacity)
        self._digest: dict[int, int] = {}
        self._order: deque[int] = deque()
        self.count = 0

    def clear(self) -> None:
        """Forget every frame (the joints' windows were emptied: what comes next is new to them)."""
        self._digest.clear()
        self._order.clear()
        self.count = 0

    def repeated(self, stamp_ns: int, frame: NDArray[np.float64]) -> bool:
        """Whether a frame of this stamp and these markers (bit for bit) was received before; remembers it if not.

        Parameters
        ----------
        stamp_ns : int
            The frame's own stamp (the message's, not the time line's).
        frame : ndarray, shape (P, 3)
            Its markers (NaN where missing).
        """
        digest = hash(np.ascontiguousarray(frame).tobytes())
        known = self._digest.get(stamp_ns)
        if known == digest:
            self.count += 1
            return True
        if known is None:
            self._order.append(stamp_ns)
            if len(self._order) > self.capacity:
                self._digest.pop(self._order.popleft(), None)
        self._digest[stamp_ns] = digest
        return False

    def repeated_many(self, stamps_ns: NDArray[np.int64], frames: NDArray[np.float64]) -> NDArray[np.bool_]:
        """:meth:`repeated` of each frame of a block (K,), (K, P, 3), in order."""
        return np.fromiter(
            (self.repeated(int(s), f) for s, f in zip(stamps_ns.tolist(), frames, strict=True)),
            dtype=bool,
            count=len(stamps_ns),
        )
