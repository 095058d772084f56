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
when each joint last took each, so that the router can tell such a frame (the
same stamp, the same markers, bit for bit) from a new one while a joint's copy
may still be in its window (:meth:`RepeatedFrames.fresh`): the joint publishes
its output but does not add it again. Once its copy has left its window, the
frame enters again, so that a window shorter than the loop keeps a copy of
every frame and one longer than it never holds two. A
recording that restarts its stamps with new markers is new data and is added
as before.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

__all__ = ["REPEAT_MEMORY", "PoseRepeats", "RepeatedFrames", "window_horizon"]

#: Frames remembered (their stamp and a 64-bit digest of their markers: a few MB): 22 min at 100 Hz, 131 s at
#: 1 kHz. A loop longer than that is not recognised and enters the windows again, as before.
REPEAT_MEMORY = 1 << 17


class RepeatedFrames:
    """The stamps and marker digests of the latest frames received, and when each joint last took each.

    Parameters
    ----------
    n_joints : int
        The joints the frames go to (each has its own window, so its own horizon).
    capacity : int
        Frames remembered (oldest forgotten first).

    Attributes
    ----------
    count : int
        Frames that some joint did not take again, since the start (or :meth:`clear`).
    """

    def __init__(self, n_joints: int, capacity: int = REPEAT_MEMORY) -> None:
        self.n_joints = int(n_joints)
        self.capacity = int(capacity)
        # stamp -> (digest, per joint the time (ns, time line) it last took the frame)
        self._seen: dict[int, tuple[int, NDArray[np.float64]]] = {}
        self._order: deque[int] = deque()
        self.count = 0

    def clear(self) -> None:
        """Forget every frame (the joints' windows were emptied: what comes next is new to them)."""
        self._seen.clear()
        self._order.clear()
        self.count = 0

    def fresh(
        self, stamp_ns: int, frame: NDArray[np.float64], time_ns: int, horizons_ns: NDArray[np.float64]
    ) -> NDArray[np.bool_]:
        """Per joint, whether this frame is new to its window; the joints it is new to take it now.

        A frame of this stamp and these markers (bit for bit) that a joint took less than its
        horizon ago may still be in its window: not new to it.

        Parameters
        ----------
        stamp_ns : int
            The frame's own stamp (the message's, not the time line's).
        frame : ndarray, shape (P, 3)
            Its markers (NaN where missing).
        time_ns : int
            Its time on the time line (which goes on over a loop).
        horizons_ns : ndarray, shape (n_joints,)
            How long a frame may stay in each joint's window (``inf``: for ever; :func:`window_horizon`).

        Returns
        -------
        ndarray of bool, shape (n_joints,)
        """
        digest = hash(np.ascontiguousarray(frame).tobytes())
        known = self._seen.get(stamp_ns)
        if known is not None and known[0] == digest:
            taken = known[1]
            new = (time_ns - taken) >= horizons_ns
            taken[new] = time_ns
            if not new.all():
                self.count += 1
            return new
        if known is None:
            self._order.append(stamp_ns)
            if len(self._order) > self.capacity:
                self._seen.pop(self._order.popleft(), None)
        self._seen[stamp_ns] = (digest, np.full(self.n_joints, float(time_ns)))
        return np.ones(self.n_joints, dtype=bool)

    def fresh_many(
        self,
        stamps_ns: NDArray[np.int64],
        frames: NDArray[np.float64],
        times_ns: NDArray[np.int64],
        horizons_ns: NDArray[np.float64],
    ) -> NDArray[np.bool_]:
        """:meth:`fresh` of each frame of a block (K,), (K, P, 3), (K,), in order: (K, n_joints)."""
        out = np.ones((len(stamps_ns), self.n_joints), dtype=bool)
        for k, (s, t) in enumerate(zip(stamps_ns.tolist(), times_ns.tolist(), strict=True)):
            out[k] = self.fresh(int(s), frames[k], int(t), horizons_ns)
        return out


def window_horizon(windows: list[tuple[int, float, float]], frame_interval_ns: float) -> NDArray[np.float64]:
    """How long (ns) a frame may stay in each of some windows: :meth:`RepeatedFrames.fresh`'s horizons.

    Parameters
    ----------
    windows : list of (int, float, float)
        Per joint, ``(window frames, window_s, half_life_s)`` as configured (one of them in use: ``window_s``
        if positive, else ``half_life_s``, else ``window``).
    frame_interval_ns : float
        The stream's frame interval (ns), for windows in frames (0: not known yet).

    Returns
    -------
    ndarray, shape (n_joints,)
        ``window_s``, 5 half-lives (a weight of 3 %), or ``window`` frames; ``inf`` for a window in frames
        before the interval is known.
    """
    spans = []
    for frames, seconds, half_life in windows:
        if seconds > 0.0:
            spans.append(seconds * 1e9)
        elif half_life > 0.0:
            spans.append(5.0 * half_life * 1e9)
        else:
            spans.append(frames * frame_interval_ns if frame_interval_ns > 0.0 else math.inf)
    return np.array(spans, dtype=np.float64)


class PoseRepeats:
    """The poses received on each pose topic (stamp, position and orientation): a looped replay of rigid bodies.

    A :class:`RepeatedFrames` per topic, for the joints that take it (a pose completes a pair only with its
    partner of the same stamp, which comes round with it in a loop).

    Parameters
    ----------
    windows : mapping of str to list of (int, float, float)
        Per pose topic, its joints' ``(window frames, window_s, half_life_s)`` (:func:`window_horizon`).

    Attributes
    ----------
    count : int
        Poses that some joint did not take again, over the topics, since the start (or :meth:`clear`).
    """

    def __init__(self, windows: Mapping[str, list[tuple[int, float, float]]]) -> None:
        self._windows = {topic: list(w) for topic, w in windows.items()}
        self._seen = {topic: RepeatedFrames(len(w)) for topic, w in self._windows.items()}
        # per topic, the horizons and the frame interval they were taken at (taken again when it changes)
        self._horizons: dict[str, tuple[float, NDArray[np.float64]]] = {}

    @property
    def count(self) -> int:
        return sum(r.count for r in self._seen.values())

    def clear(self) -> None:
        """Forget every pose (the joints' windows were emptied)."""
        for repeats in self._seen.values():
            repeats.clear()

    def fresh(
        self, topic: str, stamp_ns: int, values: NDArray[np.float64], time_ns: int, frame_interval_ns: float
    ) -> NDArray[np.bool_]:
        """Per joint of ``topic``, whether this pose (``values``: position and quaternion, (7,)) is new to its window.

        ``frame_interval_ns``: the interval that windows in frames count at (the marker topic's; 0 when not
        known: a looped pose then stays out for as long as it is remembered).
        """
        repeats = self._seen.get(topic)
        if repeats is None:
            return np.ones(0, dtype=bool)
        cached = self._horizons.get(topic)
        if cached is None or cached[0] != frame_interval_ns:
            cached = (frame_interval_ns, window_horizon(self._windows[topic], frame_interval_ns))
            self._horizons[topic] = cached
        return repeats.fresh(stamp_ns, values, time_ns, cached[1])
