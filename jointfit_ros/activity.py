"""What an input stream did lately, by the wall clock: rate, silence, and whether anything got through.

Pure Python (no rclpy). A status that only looks at totals and at the stamps
of the frames it kept says OK with the last rate forever after the input has
stopped, or while every frame is dropped. :class:`InputActivity` is sampled
at each diagnostics tick with a stream's totals and tells, over the recent
ticks: the rate (falls to 0 when the input stops), how long nothing has
arrived, and how many inputs arrived and were used since the last tick.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass

__all__ = ["Activity", "InputActivity"]


@dataclass(frozen=True)
class Activity:
    """The recent activity of a stream (see :meth:`InputActivity.sample`).

    Attributes
    ----------
    rate_hz : float or None
        Inputs per second over the last ``window_s`` seconds of samples (wall
        clock); None at the first sample.
    silent_s : float or None
        Seconds since an input last arrived (as seen at the samples); None
        when none has arrived yet.
    recent : int
        Inputs that arrived since the previous sample.
    recent_used : int
        Of those, the ones used.
    recent_dropped : dict of str to int
        Why the others were dropped: the growth of each reason since the
        previous sample, largest first.
    since_s : float
        Seconds since the previous sample (0 at the first).
    """

    rate_hz: float | None
    silent_s: float | None
    recent: int
    recent_used: int
    recent_dropped: dict[str, int]
    since_s: float

    @property
    def all_dropped(self) -> bool:
        """Inputs arrived since the previous sample and none was used."""
        return self.recent > 0 and self.recent_used == 0

    def dropped_text(self, what: str = "inputs") -> str:
        """``"all 250 inputs of the last 1.0 s were dropped (stamp_not_increasing 250)"``."""
        reasons = ", ".join(f"{k} {v}" for k, v in self.recent_dropped.items())
        return f"all {self.recent} {what} of the last {self.since_s:.1f} s were dropped" + (
            f" ({reasons})" if reasons else ""
        )


class InputActivity:
    """Samples of a stream's totals at the diagnostics ticks.

    Parameters
    ----------
    window_s : float
        Seconds of samples the rate is measured over (the node: ``stale_after``).

    Notes
    -----
    Totals that go down (a reset) start the samples afresh. The rate is the
    growth of ``arrived`` between the newest sample and the oldest one within
    ``window_s`` (one older sample is kept as the base), so it is 0 once
    nothing has arrived for ``window_s``.
    """

    def __init__(self, window_s: float = 3.0) -> None:
        self.window_s = float(window_s)
        self._samples: deque[tuple[float, int]] = deque()
        self._last: tuple[float, int, int, dict[str, int]] | None = None
        self._arrived_at: float | None = None

    def sample(self, now: float, arrived: int, used: int, dropped: Mapping[str, int] | None = None) -> Activity:
        """Record the totals at ``now`` (seconds, monotonic) and describe the recent activity.

        Parameters
        ----------
        now : float
            Seconds (``time.monotonic()``).
        arrived : int
            Inputs that arrived so far.
        used : int
            Of those, the ones used (entered the estimate, or gave an output).
        dropped : mapping of str to int, optional
            Totals of the reasons inputs were dropped.
        """
        reasons = dict(dropped or {})
        last = self._last
        if last is not None and (arrived < last[1] or used < last[2] or now < last[0]):
            self._samples.clear()
            self._arrived_at = None
            last = None
        if last is None:
            recent, recent_used, since, grown = 0, 0, 0.0, {}
            if arrived > 0:
                self._arrived_at = now
        else:
            recent, recent_used, since = arrived - last[1], used - last[2], now - last[0]
            grown = {k: v - last[3].get(k, 0) for k, v in reasons.items() if v > last[3].get(k, 0)}
            if recent > 0:
                self._arrived_at = now
        self._last = (now, arrived, used, reasons)
        samples = self._samples
        samples.append((now, arrived))
        while len(samples) > 2 and samples[1][0] <= now - self.window_s:
            samples.popleft()
        rate = None
        if len(samples) >= 2 and now > samples[0][0]:
            rate = (arrived - samples[0][1]) / (now - samples[0][0])
        return Activity(
            rate_hz=rate,
            silent_s=None if self._arrived_at is None else now - self._arrived_at,
            recent=recent,
            recent_used=recent_used,
            recent_dropped=dict(sorted(grown.items(), key=lambda kv: -kv[1])),
            since_s=since,
        )
