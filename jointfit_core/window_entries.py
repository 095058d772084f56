"""Which frames enter a time window's sums when the input is faster than the window can hold.

A sliding window keeps every frame's contribution in a ring so that it can be
subtracted when the frame leaves (:class:`~jointfit_core.ring_sums.RingWindowSums`):
624 numbers (5 KB) per frame for a ball joint or a rigid hinge, 1074 (8.6 KB) for a
skin hinge. A window in seconds (``window_s``) therefore grows with the input rate: 30 s
at 1 kHz is 30 000 frames, 258 MB for one skin hinge and about 2.4 GB for a 12-joint
body (measured: 393 MB of resident memory for one skin hinge, the ring doubling on the
way). :class:`WindowEntries` bounds it: stamp time is cut into bins of
``window_s / max_frames`` seconds, and at most one frame per bin (the first) enters the
sums; the frames between are posed, gated and given their outputs as every frame is, but
add nothing to the window. So a window never holds more than ``max_frames + 1`` frames,
and a slower input is not touched (100 Hz with ``window_s`` up to 60 s keeps every frame
under the default :data:`WINDOW_MAX_FRAMES`).

What is lost: the white-noise averaging of the frames left out (at 1 kHz into a 30 s
window, 5 frames in 6 are left out: the white part of the covariance is that of 200 Hz,
sd ~2.4x larger, and it is computed from the frames that entered, so it stays honest).
Movement, which sets the soft-tissue part and identifiability, is sampled far above its
own frequencies either way.

*Lag pairs* (:class:`~jointfit_core.joint_sums.RelativePoseSums`): an entering frame is
paired with the frame that entered before it when every frame between them could have
entered (each was chained to its predecessor); a frame that could not (a segment not
posed, the joint test failed) breaks the chain as it does without thinning.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from .errors import InputError

__all__ = ["WINDOW_MAX_FRAMES", "WindowEntries", "check_window_max_frames"]

FloatArray = NDArray[np.float64]

#: Default most frames a time window holds (``window_max_frames``): 60 s at 100 Hz, 30 s at 200 Hz;
#: with the 12 joints of a full body about 490 MB of window rings (3000 frames, the default frame
#: window, is half that).
WINDOW_MAX_FRAMES = 6000


def check_window_max_frames(value: int | None) -> int | None:
    """``window_max_frames`` checked: a positive integer, or None / 0 (no bound)."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
        raise InputError(f"window_max_frames: expected a positive integer (0 or None: no bound), got {value!r}")
    return int(value) or None


class WindowEntries:
    """Which frames enter a time window: at most one per ``seconds / max_frames`` of stamp time.

    Parameters
    ----------
    seconds : float or None
        The time window's length (s); None: not a time window (every frame enters).
    max_frames : int or None
        Most frames the window holds; None: no bound (every frame enters).

    Attributes
    ----------
    bin_s : float or None
        The bin width (s), None when every frame enters.
    max_frames : int or None
        The bound when there is one (None when every frame enters).
    thinned : int
        Frames left out so far (since :meth:`clear`).
    """

    def __init__(self, seconds: float | None, max_frames: int | None) -> None:
        self.bin_s = seconds / max_frames if seconds is not None and max_frames else None
        self.max_frames = max_frames if self.bin_s is not None else None
        self.clear()

    def clear(self) -> None:
        """Forget the frames that entered (the next frame enters)."""
        self._last_bin: float | None = None
        self._gap_ok = True  # every frame left out since the last one that entered was chained
        self.thinned = 0

    @property
    def rate_cap(self) -> float:
        """Most frames per second that enter (inf: every frame)."""
        return math.inf if self.bin_s is None else 1.0 / self.bin_s

    def admit(self, stamp: float | None, paired: bool) -> bool | None:
        """One frame that could enter, stamped ``stamp`` (s), chained to the frame before it (``paired``).

        Returns
        -------
        bool or None
            None: the frame is left out. Else it enters, and whether it carries its lag pair
            with the frame that entered before it.
        """
        if self.bin_s is None or stamp is None:
            return paired
        b = math.floor(stamp / self.bin_s)
        if self._last_bin is not None and b <= self._last_bin:
            self._gap_ok = self._gap_ok and paired
            self.thinned += 1
            return None
        flag = paired and self._gap_ok
        self._last_bin = b
        self._gap_ok = True
        return flag

    def admit_block(
        self, stamps: FloatArray | None, paired: NDArray[np.bool_]
    ) -> tuple[NDArray[np.intp] | None, NDArray[np.bool_]]:
        """:meth:`admit` of a block of frames (stamps increasing): the rows that enter and their lag-pair flags.

        Returns ``(None, paired)`` when every frame enters.
        """
        if self.bin_s is None or stamps is None:
            return None, paired
        bins = np.floor(np.asarray(stamps, dtype=np.float64) / self.bin_s)
        first = np.empty(bins.size, dtype=bool)
        first[0] = self._last_bin is None or bins[0] > self._last_bin
        np.greater(bins[1:], bins[:-1], out=first[1:])
        rows = np.flatnonzero(first)
        breaks = np.cumsum(~np.asarray(paired, dtype=bool))
        if rows.size == 0:
            self._gap_ok = self._gap_ok and bool(breaks[-1] == 0)
            self.thinned += bins.size
            return rows, np.zeros(0, dtype=bool)
        flags = np.empty(rows.size, dtype=bool)
        flags[0] = self._gap_ok and bool(breaks[rows[0]] == 0)
        np.equal(breaks[rows[1:]], breaks[rows[:-1]], out=flags[1:])
        self._gap_ok = bool(breaks[-1] == breaks[rows[-1]])
        self._last_bin = float(bins[rows[-1]])
        self.thinned += bins.size - rows.size
        return rows, flags
