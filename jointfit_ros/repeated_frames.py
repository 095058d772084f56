"""Marker frames received before: a looped replay sends the same frames again, and they are no new data.

A looped bag (``jointfit_replay --loop``, ``ros2 bag play --loop``) sends
every frame again with its own stamp and its own markers. The time line
re-anchors the loop (:mod:`jointfit_ros.timeline`) so that the joints keep
publishing; but a frame that entered a joint's window once and enters it
again is counted as a second, independent measurement, and the window's
covariance shrinks with every loop while the error stays: measured on the
live node, a hip calibration saved after a minute of ``--loop --rate max``
of a 20 s bag was 5.9-8.2 sd off (the status said OK). :class:`RepeatedFrames`
remembers the stamp and a digest of the markers of the latest frames, and
when each entered, so that the router can tell such a frame (the same stamp,
the same markers, bit for bit) from a new one while its first copy may still
be in a window (:attr:`RepeatedFrames.horizon_ns`): the joints publish its
outputs but do not add it to their windows. Once the first copy has left the
longest window, the frame enters again, so that a window shorter than the loop
keeps a copy of every frame and one longer than it never holds two. A
recording that restarts its stamps with new markers is new data and is added
as before.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from numpy.typing import NDArray

__all__ = ["REPEAT_MEMORY", "RepeatedFrames", "window_horizon"]

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
        self._digest: dict[int, tuple[int, int]] = {}  # stamp -> (digest, time it entered the windows)
        self._order: deque[int] = deque()
        self.count = 0

    def clear(self) -> None:
        """Forget every frame (the joints' windows were emptied: what comes next is new to them)."""
        self._digest.clear()
        self._order.clear()
        self.count = 0

    def repeated(self, stamp_ns: int, frame: NDArray[np.float64], time_ns: int, horizon_ns: float) -> bool:
        """Whether a frame of this stamp and these markers (bit for bit) entered the windows less than ``horizon_ns`` ago.

        If not, it enters now (it is remembered with ``time_ns``).

        Parameters
        ----------
        stamp_ns : int
            The frame's own stamp (the message's, not the time line's).
        frame : ndarray, shape (P, 3)
            Its markers (NaN where missing).
        time_ns : int
            Its time on the time line (which goes on over a loop).
        horizon_ns : float
            How long a frame may stay in the longest window (``inf``: for ever).
        """
        digest = hash(np.ascontiguousarray(frame).tobytes())
        known = self._digest.get(stamp_ns)
        if known is not None and known[0] == digest and time_ns - known[1] < horizon_ns:
            self.count += 1
            return True
        if known is None:
            self._order.append(stamp_ns)
            if len(self._order) > self.capacity:
                self._digest.pop(self._order.popleft(), None)
        self._digest[stamp_ns] = (digest, time_ns)
        return False

    def repeated_many(
        self, stamps_ns: NDArray[np.int64], frames: NDArray[np.float64], times_ns: NDArray[np.int64], horizon_ns: float
    ) -> NDArray[np.bool_]:
        """:meth:`repeated` of each frame of a block (K,), (K, P, 3), (K,), in order."""
        return np.fromiter(
            (self.repeated(int(s), f, int(t), horizon_ns)
             for s, f, t in zip(stamps_ns.tolist(), frames, times_ns.tolist(), strict=True)),
            dtype=bool,
            count=len(stamps_ns),
        )


def window_horizon(
    windows: list[tuple[int, float, float]], frame_interval_ns: float
) -> float:
    """How long (ns) a frame may stay in the longest of some windows: :attr:`RepeatedFrames.repeated`'s horizon.

    Parameters
    ----------
    windows : list of (int, float, float)
        Per joint, ``(window frames, window_s, half_life_s)`` as configured (one of them in use: ``window_s``
        if positive, else ``half_life_s``, else ``window``).
    frame_interval_ns : float
        The stream's frame interval (ns), for windows in frames.

    Returns
    -------
    float
        The largest span: ``window_s``, 5 half-lives (a weight of 3 %), or ``window`` frames; ``inf`` when
        none can be told (no joint, or a window in frames before an interval is known).
    """
    spans = []
    for frames, seconds, half_life in windows:
        if seconds > 0.0:
            spans.append(seconds * 1e9)
        elif half_life > 0.0:
            spans.append(5.0 * half_life * 1e9)
        else:
            spans.append(frames * frame_interval_ns if frame_interval_ns > 0.0 else math.inf)
    return max(spans) if spans else math.inf
