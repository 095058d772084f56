"""SIGINT and SIGTERM as a request to stop a spin loop, never as an exception inside a callback.

rclpy's own signal handling makes Python raise ``KeyboardInterrupt`` wherever
the main thread happens to be. A node that is busy (a full body at 100 Hz
spends most of its time in the marker callback) is then interrupted inside a
callback, and the ``EventsExecutor`` logs the exception as FATAL with a
traceback: 4 of 5 Ctrl-C stops of ``jointfit_node`` on the full-body stream
did (2026-12-03). :class:`StopRequest` instead turns the signal into a flag
that the spin loop reads between callbacks; a second signal while stopping
raises ``KeyboardInterrupt`` as usual, so a stop that hangs can still be
forced. Pure Python, no ROS.
"""

from __future__ import annotations

import signal
import threading
from types import FrameType, TracebackType
from typing import Any

__all__ = ["StopRequest"]


class StopRequest:
    """A context manager that installs SIGINT and SIGTERM handlers setting :attr:`requested`.

    Attributes
    ----------
    requested : bool
        True once SIGINT or SIGTERM arrived.
    signal_name : str or None
        The first signal's name (``"SIGINT"``, ``"SIGTERM"``).

    Notes
    -----
    Signal handlers can only be installed from the main thread; elsewhere the
    manager installs nothing (the flag then stays False and the process keeps
    the handlers it had). The previous handlers are restored on exit.
    """

    def __init__(self, signals: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM)) -> None:
        self.requested = False
        self.signal_name: str | None = None
        self._signals = signals
        self._previous: dict[signal.Signals, Any] = {}

    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        if self.requested:  # a second signal while stopping: stop now
            raise KeyboardInterrupt
        self.requested = True
        self.signal_name = signal.Signals(signum).name

    def __enter__(self) -> StopRequest:
        if threading.current_thread() is threading.main_thread():
            for sig in self._signals:
                self._previous[sig] = signal.signal(sig, self._on_signal)
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)
        self._previous.clear()
