"""Console lines for ``/diagnostics`` statuses: a WARN or ERROR once per change of its condition.

Pure Python (no rclpy). A status message carries numbers that change at every
diagnostics period ("no input for 3.2 s", "rms spread ~12 deg"); the
*condition* is the message with its numbers blanked out, so a warning is
logged when it appears or changes into another warning, not every period,
and its end is logged once when the status is OK again.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from typing import Any

__all__ = ["StatusLog", "condition"]

#: diagnostic_msgs/DiagnosticStatus levels.
OK, WARN, ERROR, STALE = 0, 1, 2, 3

_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


def condition(message: str) -> str:
    """A status message with its numbers replaced by ``#`` (what stays the same while the condition lasts)."""
    return _NUMBER.sub("#", message)


class StatusLog:
    """Which status changes deserve a console line.

    Call :meth:`change` with every status of every diagnostics tick; it
    returns ``(level, text)`` for a line to log (``level`` WARN or ERROR for a
    new condition, OK for the end of one) or None.
    """

    def __init__(self) -> None:
        self._last: dict[str, tuple[int, str]] = {}

    def change(self, name: str, level: int, message: str) -> tuple[int, str] | None:
        """The console line for ``name``'s status now, when its condition changed (else None).

        Parameters
        ----------
        name : str
            Status name, e.g. ``"jointfit: hip"``.
        level : int
            0 OK, 1 WARN, 2 ERROR, 3 STALE.
        message : str
            The status message.
        """
        key = (level, condition(message)) if level in (WARN, ERROR) else (level, "")
        before = self._last.get(name)
        self._last[name] = key
        if key == before:
            return None
        if level in (WARN, ERROR):
            return level, f"{name}: {message}"
        if level == OK and before is not None and before[0] in (WARN, ERROR):
            return OK, f"{name}: OK again: {message}"
        return None

    def log(self, statuses: Iterable[tuple[str, int, str]], logger: Any) -> None:
        """Log, through ``logger`` (``error``, ``warning``, ``info``), the line of each ``(name, level, message)`` that changed.

        Each status that turned WARN or ERROR is logged once per condition, and its return to OK once.
        """
        for name, level, message in statuses:
            line = self.change(name, level, message)
            if line is None:
                continue
            severity, text = line
            # (one call site per severity: rclpy refuses to change a call site's severity)
            if severity == ERROR:
                logger.error(text)
            elif severity == WARN:
                logger.warning(text)
            else:
                logger.info(text)
