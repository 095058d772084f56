"""The frames that reach an online joint, numbered as they arrive, and their stamps checked.

:class:`FrameClock` is the clock of :class:`~jointfit_core.estimator.OnlineJoint`'s
frame path (:meth:`~FrameClock.arrive`, once per frame) and of its block path
(:mod:`jointfit_core.joint_blocks`, which numbers and checks a block's frames at
once with the same state): every well-formed frame gets the next number, stamp
or not (the outlier gate's turn test and its limits' refresh count frames so,
:mod:`jointfit_core.joint_outliers`), and a frame is accepted only when its
stamp exceeds the last accepted one.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError
from .stats import WindowSpec

__all__ = ["FrameClock"]


class FrameClock:
    """A joint's frame numbers and its last accepted stamp.

    Parameters
    ----------
    spec : WindowSpec
        The joint's window (whether it needs a stamp with every frame).

    Attributes
    ----------
    arrivals : int
        Frames numbered so far: the latest frame's number (1-based).
    last_stamp : float or None
        The latest accepted stamp (s); None before any.
    """

    def __init__(self, spec: WindowSpec) -> None:
        self.spec = spec
        self.arrivals = 0
        self.last_stamp: float | None = None

    def arrive(self, stamp: float | None) -> tuple[int, float | None, bool]:
        """Number a frame that arrived (well-formed, whatever its stamp) and check its stamp.

        Parameters
        ----------
        stamp : float or None
            The frame's stamp (s).

        Returns
        -------
        number : int
            The frame's number.
        stamp : float or None
            The stamp as a float.
        accepted : bool
            False when the stamp does not exceed the latest accepted one (the
            frame is to be dropped and counted as ``stamp_not_increasing``).

        Raises
        ------
        InputError
            A non-finite stamp, or none where the window needs stamps (the
            frame is numbered all the same).
        """
        self.arrivals += 1
        st = None if stamp is None else float(stamp)
        if st is not None and not np.isfinite(st):
            raise InputError(f"stamp: expected a finite number of seconds, got {stamp!r}")
        if self.spec.needs_stamps and st is None:
            raise InputError(f"stamp: the window ({self.spec.describe()}) needs a stamp with every frame")
        if st is not None and self.last_stamp is not None and st <= self.last_stamp:
            return self.arrivals, st, False
        if st is not None:
            self.last_stamp = st
        return self.arrivals, st, True
