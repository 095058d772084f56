"""Input stamps checked and made into one increasing time line for the estimators.

Pure Python (no rclpy). The estimators' stamp-time windows, their
"stamps must increase" rule and the pairing of pose topics
(:class:`~jointfit_ros.sync.StampMatcher`) all assume one clock that only
goes forward. Streams break that in three ways, handled here:

* a stamp that is no time at all: seconds outside the int32 of
  ``builtin_interfaces/Time`` (it could not be written back into an output
  header). Dropped and counted (``invalid_stamps``). (A ``nanosec`` of 10^9
  or more is refused by the parsers, :mod:`jointfit_ros.raw`, as a malformed
  message.)
* a single stamp far ahead of the stream (a corrupt stamp, a clock glitch):
  more than ``max_jump`` after the source's latest stamp (and, with a clock,
  more than the time that has passed since it arrived). Dropped and counted
  (``stamps_ahead``), not adopted, so the frames after it go on.
* a jump back in time that runs on steadily: a looped bag, a restarted
  recording. After ``restart_frames`` messages in a row that run on from
  each other (each a little after the one before) but not from the stream,
  the time line is re-anchored (``timeline_restarts``): from then on an
  offset is added, so that the times handed to the estimators continue from
  where they were. A stamp-time window keeps its frames and forgets them as
  if the recording had gone on; outputs keep carrying the real stamps. A
  steady run far ahead (a stream that resumed after a pause, seen without
  a clock) is adopted the same way, without an offset.

A single stamp going back, and a repeated stamp, are passed on as they are:
the estimators drop them (``stamp_not_increasing``) as before.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["Timeline", "STAMP_NS_RANGE", "RESTART_FRAMES"]

IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

_NS_PER_S = 1_000_000_000
#: Stamps (ns) an output header can carry: int32 seconds, nanosec in [0, 1e9).
STAMP_NS_RANGE = (-(2**31) * _NS_PER_S, 2**31 * _NS_PER_S)
#: Messages in a steady run, off the stream, that make a restart of the time line.
RESTART_FRAMES = 3


@dataclass
class _Run:
    """Messages of one source off its time line that run on from each other (real stamps, ns)."""

    first: int
    last: int
    count: int


class Timeline:
    """Check stamps, drop single outliers and re-anchor a restarted stream, for several sources.

    Parameters
    ----------
    max_jump_ns : int
        Largest step (ns) ahead of a source's latest stamp that is taken as
        the stream going on (the node's ``max_stamp_jump``).
    restart_frames : int
        Messages in a steady run that confirm a restart (>= 2).
    clock : callable returning int, optional
        Arrival time in nanoseconds (the node: ``time.monotonic_ns``). With a
        clock, a step ahead is also accepted when it is at most ``max_jump_ns``
        more than the time since the source's latest message arrived (a live
        stream resuming after a pause). Without one (recordings read as fast as
        they can be) such a gap is adopted after ``restart_frames`` messages.
    counters : dict of str to int, optional
        Where to count (the router's counters); a new dict when not given.

    Attributes
    ----------
    counters : dict of str to int
        ``invalid_stamps``, ``stamps_ahead`` (dropped) and ``timeline_restarts``.
    offset_ns : int
        Added to the real stamps to give the estimators' times (ns).
    last_event : tuple of (str, str) or None
        ``(key, text)`` of the latest drop or restart, for a log line.

    Notes
    -----
    Each source (topic) has its own latest time, so that topics stamped
    alike (a parent and a child pose of the same frame) do not look like
    repeated stamps; the offset is shared, so that they still pair. On a
    restart the new offset puts the run's first message one step of the run
    after the latest time of every source; another topic of the same
    recording, looping with it, then continues at once.
    """

    def __init__(
        self,
        max_jump_ns: int,
        restart_frames: int = RESTART_FRAMES,
        clock: Callable[[], int] | None = None,
        counters: dict[str, int] | None = None,
    ) -> None:
        if max_jump_ns <= 0:
            raise ValueError(f"max_jump_ns: expected a positive number of nanoseconds, got {max_jump_ns!r}")
        if restart_frames < 2:
            raise ValueError(f"restart_frames: expected at least 2, got {restart_frames!r}")
        self.max_jump_ns = int(max_jump_ns)
        self.restart_frames = int(restart_frames)
        self.clock = clock
        self.counters = {} if counters is None else counters
        for key in ("invalid_stamps", "stamps_ahead", "timeline_restarts"):
            self.counters.setdefault(key, 0)
        self.offset_ns = 0
        self.last_event: tuple[str, str] | None = None
        self._last: dict[str, int] = {}  # latest time (stamp + offset) of each source
        self._arrived: dict[str, int] = {}  # when it arrived (clock), with a clock
        self._runs: dict[str, _Run] = {}

    def time_of(self, stamp_ns: int, source: str = "") -> int | None:
        """The estimators' time (ns) of a message, or None when it is dropped (and counted).

        Parameters
        ----------
        stamp_ns : int
            The message's ``header.stamp`` (ns).
        source : str
            Its topic.

        Returns
        -------
        int or None
            ``stamp_ns + offset_ns`` (after a restart this message confirms:
            the new offset); a repeated or backward stamp is returned too, not
            after the latest (the estimators drop it).
        """
        stamp_ns = int(stamp_ns)
        if not STAMP_NS_RANGE[0] <= stamp_ns < STAMP_NS_RANGE[1]:
            self.counters["invalid_stamps"] += 1
            self.last_event = (
                f"stamp_invalid:{source}",
                f"dropped a message on {source} stamped {stamp_ns} ns: seconds outside int32, "
                "not a time an output header can carry",
            )
            return None
        now = self.clock() if self.clock is not None else None
        t = stamp_ns + self.offset_ns
        last = self._last.get(source)
        if last is None:
            return self._take(source, t, now)
        step = t - last
        if step <= 0:
            if step < 0 and self._extend_run(source, stamp_ns):
                return self._restart(source, stamp_ns, now)
            return t  # repeated or backward: the estimators drop it, as they always have
        if step <= self.max_jump_ns or (now is not None and step <= now - self._arrived[source] + self.max_jump_ns):
            return self._take(source, t, now)
        if self._extend_run(source, stamp_ns):
            return self._restart(source, stamp_ns, now)
        self.counters["stamps_ahead"] += 1
        self.last_event = (
            f"stamp_ahead:{source}",
            f"dropped a message on {source} stamped {step * 1e-9:.6g} s ahead of the stream (more than "
            f"max_stamp_jump, {self.max_jump_ns * 1e-9:g} s): a corrupt stamp or a clock glitch",
        )
        return None

    def times_of(self, stamps_ns: IntArray, source: str = "") -> tuple[BoolArray, IntArray]:
        """:meth:`time_of` of many stamps of one source, oldest first (a block of a recording).

        Parameters
        ----------
        stamps_ns : ndarray, shape (K,), int64
        source : str

        Returns
        -------
        kept : ndarray, shape (K,), bool
            Messages not dropped.
        times_ns : ndarray, shape (K,), int64
            Their times (meaningless where not kept).

        Notes
        -----
        A block that runs on steadily from the source's latest stamp (every
        step in ``[0, max_jump_ns]``, no run pending) is done in array
        operations; any other block message by message, as :meth:`time_of`.
        """
        stamps = np.asarray(stamps_ns, dtype=np.int64)
        n = stamps.shape[0]
        last = self._last.get(source)
        if n and last is not None and source not in self._runs and self.clock is None:
            lo, hi = STAMP_NS_RANGE
            times = stamps + self.offset_ns
            steps = np.diff(times, prepend=np.int64(last))
            if (
                int(stamps.min()) >= lo and int(stamps.max()) < hi
                and bool(((steps >= 0) & (steps <= self.max_jump_ns)).all())
            ):
                self._last[source] = max(last, int(times.max()))
                return np.ones(n, dtype=bool), times
        kept = np.ones(n, dtype=bool)
        out = np.zeros(n, dtype=np.int64)
        for k, s in enumerate(stamps.tolist()):
            t = self.time_of(s, source)
            if t is None:
                kept[k] = False
            else:
                out[k] = t
        return kept, out

    def _take(self, source: str, t: int, now: int | None) -> int:
        self._last[source] = t
        if now is not None:
            self._arrived[source] = now
        self._runs.pop(source, None)
        return t

    def _extend_run(self, source: str, stamp_ns: int) -> bool:
        """Add an off-line stamp to the source's run; True when the run is long enough for a restart.

        A stamp repeating the run's latest neither extends nor breaks it: a stream that stamps
        some frames alike (two frames per stamp) would otherwise never make a run, and after a
        jump (ahead, or back: a loop) every message would be dropped for good.
        """
        run = self._runs.get(source)
        if run is not None and stamp_ns == run.last:
            return False
        if run is not None and 0 < stamp_ns - run.last <= self.max_jump_ns:
            run.last = stamp_ns
            run.count += 1
        else:
            run = self._runs[source] = _Run(stamp_ns, stamp_ns, 1)
        return run.count >= self.restart_frames

    def _restart(self, source: str, stamp_ns: int, now: int | None) -> int:
        """Re-anchor the time line on the source's run (its last message is ``stamp_ns``); its time."""
        run = self._runs.pop(source)
        old = self._last[source]
        jump = run.first + self.offset_ns - old
        if jump < 0:
            step = max(1, (run.last - run.first) // max(1, run.count - 1))
            self.offset_ns = max(self._last.values()) + step - run.first
            what = f"went back {-jump * 1e-9:.6g} s"
        else:
            what = f"jumped {jump * 1e-9:.6g} s ahead"
        self.counters["timeline_restarts"] += 1
        self.last_event = (
            "timeline_restart",
            f"the stamps on {source} {what} and ran on steadily for {run.count} messages: a looped or "
            "restarted recording (or a stream resumed); the stamp-time windows go on from where they were "
            "and the outputs keep the input stamps",
        )
        return self._take(source, stamp_ns + self.offset_ns, now)

    def clear(self) -> None:
        """Forget the sources' latest times and runs (the offset and the counters are kept)."""
        self._last.clear()
        self._arrived.clear()
        self._runs.clear()
