"""Which frames an online estimator's sums cover: a frame or time window, or exponential forgetting.

:class:`WindowSpec` names the choice (exactly one of four fields) and
:func:`window_spec` checks the estimators' keyword arguments and builds it;
:class:`~jointfit_core.stats.SlidingSums` keeps the sums.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError

__all__ = ["WindowSpec", "window_spec"]


@dataclass(frozen=True)
class WindowSpec:
    """Which frames the sums cover. Exactly one field is set.

    Attributes
    ----------
    frames : int or None
        The last ``frames`` accepted frames.
    seconds : float or None
        Frames whose stamp is within ``seconds`` of the newest stamp
        (``stamp > newest - seconds``); needs stamps.
    half_life : float or None
        Exponential forgetting: a frame's weight halves every ``half_life``
        frames. ``inf``: no forgetting, the sums of every frame since the
        start, in O(1) memory (what ``jointfit fit`` uses for a whole
        recording).
    half_life_s : float or None
        Exponential forgetting in time: a frame's weight halves every
        ``half_life_s`` seconds of stamp time; needs stamps.
    """

    frames: int | None = None
    seconds: float | None = None
    half_life: float | None = None
    half_life_s: float | None = None

    @property
    def exponential(self) -> bool:
        """True for exponential forgetting (no ring buffer)."""
        return self.half_life is not None or self.half_life_s is not None

    @property
    def needs_stamps(self) -> bool:
        """True when every update must carry a stamp."""
        return self.seconds is not None or self.half_life_s is not None

    def describe(self) -> str:
        """Short human-readable form, e.g. ``"500 frames"``."""
        if self.frames is not None:
            return f"{self.frames} frames"
        if self.seconds is not None:
            return f"{self.seconds:g} s"
        if self.half_life == np.inf or self.half_life_s == np.inf:
            return "all frames (no forgetting)"
        if self.half_life is not None:
            return f"half-life {self.half_life:g} frames"
        return f"half-life {self.half_life_s:g} s"


def window_spec(
    window: int | None = None,
    *,
    window_s: float | None = None,
    half_life: float | None = None,
    half_life_s: float | None = None,
) -> WindowSpec:
    """Check and build a :class:`WindowSpec` from the estimators' keyword arguments.

    Raises
    ------
    InputError
        Not exactly one of the four given, or a value that is not positive
        (``window`` must be an integer >= 3).
    """
    given = {
        k: v
        for k, v in (("window", window), ("window_s", window_s), ("half_life", half_life), ("half_life_s", half_life_s))
        if v is not None
    }
    if len(given) != 1:
        raise InputError(
            "window: give exactly one of window (frames), window_s (seconds), half_life (frames) or "
            f"half_life_s (seconds), got {sorted(given) or 'none'}"
        )
    name, value = next(iter(given.items()))
    if name == "window":
        if isinstance(value, bool) or not float(value).is_integer() or int(value) < 3:
            raise InputError(f"window: expected an integer number of frames >= 3, got {value!r}")
        return WindowSpec(frames=int(value))
    try:
        num = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected a positive number, got {value!r}") from None
    if np.isnan(num) or num <= 0.0 or (num == np.inf and name == "window_s"):
        raise InputError(f"{name}: expected a positive finite number (half-lives may be inf), got {value!r}")
    if name == "window_s":
        return WindowSpec(seconds=num)
    if name == "half_life":
        return WindowSpec(half_life=num)
    return WindowSpec(half_life_s=num)
