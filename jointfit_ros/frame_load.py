"""How long the node takes per input frame, and what share of its time that is.

Pure Python. When frames go missing (gaps in a regular stream's stamps,
:mod:`jointfit_ros.stamp_gaps`), the cause is either the node, which cannot
handle them as fast as they come (a 12-joint body takes ~3-4 ms of CPU per frame,
so 1 kHz cannot be kept up), or the network or the driver. The two need
different fixes, so the input status tells them apart by how busy the node was:
:class:`FrameLoad` adds up the wall time of every input callback and, at each
diagnostics tick, gives the mean time per frame and the busy share over the last
few seconds.
"""

from __future__ import annotations

from collections import deque

__all__ = ["BUSY_LIMIT", "FrameLoad"]

#: A node busy with frames this share of its time (or more) is the likely cause of frames that never
#: arrived: a single-threaded executor that also runs its timers has little left, and DDS drops what waits.
BUSY_LIMIT = 0.8


class FrameLoad:
    """The wall time the node's input callbacks took, and its recent rate.

    Attributes
    ----------
    frames : int
        Input callbacks timed since the start.
    seconds : float
        Their total wall time (s).
    """

    def __init__(self) -> None:
        self.frames = 0
        self.seconds = 0.0
        self._ticks: deque[tuple[float, int, float]] = deque()  # (tick time, frames, seconds)

    def add(self, seconds: float) -> None:
        """One input callback took ``seconds`` of wall time."""
        self.frames += 1
        self.seconds += seconds

    def sample(self, now: float, window_s: float) -> tuple[float | None, float | None]:
        """The mean time per frame (s) and the busy share over about the last ``window_s`` seconds at ``now``.

        ``now``: monotonic seconds of this diagnostics tick. (None, None) at the first tick or when the
        window holds no time; the time per frame is None when no frame came.
        """
        ticks = self._ticks
        ticks.append((now, self.frames, self.seconds))
        while len(ticks) > 2 and ticks[1][0] <= now - window_s:
            ticks.popleft()
        then, frames, seconds = ticks[0]
        if not now > then:
            return None, None
        n = self.frames - frames
        spent = self.seconds - seconds
        return (spent / n if n else None), min(spent / (now - then), 1.0)
