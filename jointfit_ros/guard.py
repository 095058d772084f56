"""A guard around the node's callbacks and timers: an unexpected exception is logged once, counted, survived.

Pure Python (no rclpy), so that it is tested without ROS. One exception in a
subscription callback, a timer or a service would otherwise end the node
(rclpy re-raises it from the executor): every output, the diagnostics and
the services with it. :class:`CallbackGuard` wraps each of them; the node
reports :attr:`CallbackGuard.count` and :attr:`CallbackGuard.last` in
``/diagnostics`` (ERROR while recent).
"""

from __future__ import annotations

import time
import traceback
from collections.abc import Callable
from typing import Any, TypeVar

__all__ = ["CallbackGuard", "RECENT_S"]

T = TypeVar("T")

#: An error this recent (s, monotonic) keeps the input status at ERROR.
RECENT_S = 10.0


def _where(exc: BaseException) -> str:
    frames = traceback.extract_tb(exc.__traceback__)
    if not frames:
        return ""
    last = frames[-1]
    return f" at {last.filename.rsplit('/', 1)[-1]}:{last.lineno} ({last.name})"


class CallbackGuard:
    """Catch, count and describe the exceptions of wrapped callbacks.

    Parameters
    ----------
    log : callable
        ``log(text)``: called once per callback and exception type (an error
        that repeats every frame must not flood the console).

    Attributes
    ----------
    count : int
        Exceptions caught.
    last : str
        The latest, in one line: the callback, the exception and where it was raised.
    """

    def __init__(self, log: Callable[[str], None]) -> None:
        self._log = log
        self._logged: set[tuple[str, str]] = set()
        self.count = 0
        self.last = ""
        self._last_time = -float("inf")

    def caught(self, where: str, exc: Exception) -> None:
        """Record an exception of callback ``where`` (log it the first time of its kind)."""
        self.count += 1
        self._last_time = time.monotonic()
        self.last = f"{where}: {type(exc).__name__}: {exc}{_where(exc)}"
        key = (where, type(exc).__name__)
        if key not in self._logged:
            self._logged.add(key)
            self._log(f"unexpected error in {self.last}; the node goes on (logged once; counted in /diagnostics)")

    def wrap(self, where: str, fn: Callable[..., T]) -> Callable[..., T | None]:
        """``fn`` that returns None instead of raising (KeyboardInterrupt and SystemExit pass)."""

        def guarded(*args: Any) -> T | None:
            try:
                return fn(*args)
            except Exception as exc:
                self.caught(where, exc)
                return None

        return guarded

    def wrap_service(self, where: str, fn: Callable[[Any, Any], Any]) -> Callable[[Any, Any], Any]:
        """A service handler that answers ``success=False`` with the error instead of raising."""

        def guarded(request: Any, response: Any) -> Any:
            try:
                return fn(request, response)
            except Exception as exc:
                self.caught(where, exc)
                response.success = False
                response.message = f"internal error: {type(exc).__name__}: {exc}"
                return response

        return guarded

    @property
    def recent(self) -> bool:
        """Whether the latest error is less than :data:`RECENT_S` old."""
        return time.monotonic() - self._last_time < RECENT_S
