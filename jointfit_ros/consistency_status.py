"""The consistency check across movement blocks for a joint's ``/diagnostics`` (ROS-free).

:class:`ConsistencyMonitor` runs :func:`~jointfit_core.block_check.window_consistency`
on a joint's window at diagnostics time, not per frame: at most once per new
estimate and every :data:`CONSISTENCY_PERIOD_S` seconds, and the joints of a
process at least :data:`CONSISTENCY_SPACING_S` apart (a check solves
:data:`~jointfit_core.consistency.CONSISTENCY_BLOCKS` blocks: 20-80 ms for a
3000-frame window), and
gives its verdict as diagnostic values whose keys carry their units.
"""

from __future__ import annotations

import math
import time
from typing import Any

from jointfit_core.block_check import window_consistency
from jointfit_core.consistency import BlockConsistency
from jointfit_core.errors import JointfitError
from jointfit_core.estimator import OnlineJoint

__all__ = ["ConsistencyMonitor", "CONSISTENCY_PERIOD_S", "consistency_values"]

#: Seconds (monotonic) between two checks of one joint's window while its estimate keeps changing.
CONSISTENCY_PERIOD_S = 10.0

#: Seconds between two re-checks of any joints of the process: a 12-joint skeleton spreads its checks
#: over the diagnostics ticks instead of solving 48 blocks in one (a joint's first check is not held back).
CONSISTENCY_SPACING_S = 0.5


def consistency_values(check: BlockConsistency | None, frames: int, units: str, why_none: str) -> dict[str, Any]:
    """Diagnostic values of a check (keys with units ``units``); ``why_none`` when there is no check."""
    if check is None:
        return {"consistency": why_none}
    values: dict[str, Any] = {
        "consistency": check.message,
        "consistency blocks (compared, skipped)": [check.n_blocks, check.n_skipped],
        "consistency checked at frames in window": frames,
    }
    if check.consistent is None:
        return values
    values["consistency ratio (x what the covariances allow)"] = round(check.ratio, 3)
    values["consistency p-value"] = float(f"{check.p_value:.3g}")
    values[f"block spread ({units})"] = float(f"{check.spread:.4g}")
    if math.isfinite(check.spread_deg):
        values["block spread (deg)"] = round(check.spread_deg, 4)
    return values


class ConsistencyMonitor:
    """The latest check of one estimator's window, re-run when its estimate changed and the period passed.

    Parameters
    ----------
    period_s : float
        Fewest seconds (``time.monotonic``) between two checks of the same estimator.
    """

    #: Earliest monotonic time of the next re-check of any monitor of the process (see :data:`CONSISTENCY_SPACING_S`).
    _next_any: float = -math.inf

    def __init__(self, period_s: float = CONSISTENCY_PERIOD_S) -> None:
        self.period_s = float(period_s)
        self._key: tuple[int, int] | None = None
        self._at = -math.inf
        self._frames = 0
        self.check: BlockConsistency | None = None

    def values(self, est: OnlineJoint, units: str, now: float | None = None) -> dict[str, Any]:
        """Run the check when due and return its diagnostic values (see :func:`consistency_values`)."""
        if est.frozen:
            return {"consistency": "not checked: frozen"}
        if est.spec.exponential:
            return {"consistency": "not checked: exponential forgetting keeps no frames to cut into movement blocks"}
        now = time.monotonic() if now is None else now
        key = est.solved_version
        new_estimator = self._key is None or key[0] != self._key[0]
        due = now - self._at >= self.period_s and now >= ConsistencyMonitor._next_any
        if est.solution is not None and key != self._key and (new_estimator or due):
            self._key, self._at, self._frames = key, now, est.n_window
            ConsistencyMonitor._next_any = now + CONSISTENCY_SPACING_S
            try:
                self.check = window_consistency(est, units=units)
            except JointfitError:
                self.check = None
        if self._key is None or self._key[0] != key[0]:
            return {"consistency": "not checked yet: no estimate"}
        return consistency_values(self.check, self._frames, units, "not checked: the blocks could not be solved")

    def warning(self, est: OnlineJoint) -> str:
        """The "skin artefact dominates" message of the latest check of ``est`` (empty when none or consistent)."""
        current = self._key is not None and self._key[0] == est.solved_version[0] and not est.frozen
        return self.check.message if current and self.check is not None and self.check.warns else ""
