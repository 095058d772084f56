"""Two publishers on one input: frames from both interleave, and the joints must not take them.

A mocap driver started twice, or a replay beside the live driver, sends a
second stream on the same topic. The node cannot tell whose message is whose
(rclpy's ``EventsExecutor`` gives no message info), so without this every
joint mixes two subjects' or two sessions' frames. Measured before this
module: the hip's per-frame outputs were 30+ sd off (errors up to 0.5 m) on
two interleaved fake mocaps, while the joint said only that its test
rejected a third of the frames.

The count of matched publishers comes from the subscription's *matched*
event (:meth:`InterleaveGuard.set_publishers`). A count above one is not
proof by itself: a publisher killed without a goodbye (SIGKILL) stays
matched until DDS's lease runs out (~20 s), and an idle publisher never
sends. So while the count is above one, each frame is also checked against
the frames before it (:meth:`InterleaveGuard.admit`):

* **a step out of line**: a frame far from the one before it but close to
  one two or three back (the stream went A, B, A): the median marker
  distance to the previous frame more than :data:`OUT_OF_LINE_RATIO` times
  the smaller median distance to the two frames before that. Smooth motion
  gives about 1/2 and 1/3 of that ratio, noise alone about 1; or a frame
  whose step from the previous one is more than :data:`OUT_OF_LINE_RATIO`
  times the median of the last :data:`STEP_MEMORY` steps (the jump into B);
* **a copy**: a frame whose markers equal, bit for bit, one of the last
  few frames' (the same driver twice, each stamping its own copy).

Frames are held back while the count is above one until
:data:`SETTLE_FRAMES` frames in a row came without a step out of line (a
single stream: the other publisher is a ghost or idle), and again for
:data:`SETTLE_FRAMES` frames after any step out of line. Copies are always
dropped while the count is above one. When the count falls to one, frames go
through again at once.
"""

from __future__ import annotations

from collections import deque

import numpy as np
from numpy.typing import NDArray

__all__ = ["COPY_MEMORY", "OUT_OF_LINE_RATIO", "SETTLE_FRAMES", "STEP_MEMORY", "InterleaveGuard"]

FloatArray = NDArray[np.float64]

#: A frame is out of line when its median marker distance to the previous frame is more than this many
#: times its smaller median distance to the two frames before that. A single stream gives ~1 when still
#: (noise) and ~1/2 when moving; two interleaved streams give the distance between them over one step of
#: motion, tens to thousands.
OUT_OF_LINE_RATIO = 4.0

#: Frames in a row without a step out of line before frames go to the joints again while more than one
#: publisher is matched (0.5 s at 100 Hz): the other publisher sends nothing, or the same frames.
SETTLE_FRAMES = 50

#: Frames a copy is looked for among.
COPY_MEMORY = 3

#: Steps (median marker distances between consecutive frames) whose median a jump is measured against.
STEP_MEMORY = 8


class InterleaveGuard:
    """One input topic's publisher count and the recent frames that tell whether two of them send.

    Attributes
    ----------
    publishers : int
        Publishers matched on the topic (the subscription's matched event; 1 until one arrives).
    held : int
        Frames held back since the start because two publishers seemed to interleave.
    copies : int
        Frames dropped since the start as a copy of a recent frame while more than one publisher was matched.
    steps_out_of_line : int
        Steps out of line seen since the start.
    """

    def __init__(self) -> None:
        self.publishers = 1
        self.held = 0
        self.copies = 0
        self.steps_out_of_line = 0
        self._recent: deque[FloatArray] = deque(maxlen=COPY_MEMORY)
        self._steps: deque[float] = deque(maxlen=STEP_MEMORY)
        self._clean = 0  # frames in a row without a step out of line, since the count rose above one

    def set_publishers(self, n: int) -> None:
        """The matched-publisher count changed to ``n``."""
        if n > 1 and self.publishers <= 1:
            self._clean = 0
        self.publishers = int(n)
        if n <= 1:
            self._recent.clear()
            self._steps.clear()

    @property
    def interleaving(self) -> bool:
        """More than one publisher is matched and frames are being held back."""
        return self.publishers > 1 and self._clean < SETTLE_FRAMES

    def admit(self, frame: FloatArray) -> str:
        """Whether a frame goes to the joints: ``""`` yes, else why not (``"copy"`` or ``"interleaved"``).

        Parameters
        ----------
        frame : ndarray, shape (P, 3)
            The frame's markers (NaN for missing), or a pose's position as ``(1, 3)``.
        """
        if self.publishers <= 1:
            return ""
        recent = self._recent
        for old in recent:
            if np.array_equal(old, frame, equal_nan=True):
                self.copies += 1
                return "copy"
        out_of_line = False
        if recent:
            step = _median_step(frame, recent[-1])
            steps = self._steps
            if len(steps) >= 3:
                typical = float(np.median(steps))
                out_of_line = step > OUT_OF_LINE_RATIO * typical and typical > 0.0
            if np.isfinite(step):
                steps.append(step)
            if len(recent) >= 3:
                out_of_line = out_of_line or _out_of_line(frame, recent[-1], recent[-2], recent[-3])
        recent.append(frame.copy())
        if out_of_line:
            self.steps_out_of_line += 1
            self._clean = 0
        else:
            self._clean += 1
        if self._clean <= SETTLE_FRAMES:
            self.held += 1
            return "interleaved"
        return ""


def _median_step(a: FloatArray, b: FloatArray) -> float:
    """Median distance between the markers seen in both frames (inf when none is)."""
    d = np.sqrt(((a - b) ** 2).sum(axis=1))
    d = d[np.isfinite(d)]
    return float(np.median(d)) if d.size else np.inf


def _out_of_line(f0: FloatArray, f1: FloatArray, f2: FloatArray, f3: FloatArray) -> bool:
    """``f0`` far from ``f1`` but close to ``f2`` or ``f3`` (the stream went back to where it was)."""
    d01 = _median_step(f0, f1)
    back = min(_median_step(f0, f2), _median_step(f0, f3))
    return bool(np.isfinite(d01) and np.isfinite(back) and d01 > OUT_OF_LINE_RATIO * back and d01 > 0.0)
