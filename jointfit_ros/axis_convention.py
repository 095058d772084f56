"""Which way a hinge joint's axis points: the marker convention of ``axis_toward_marker``, chosen once.

Pure Python and numpy (no rclpy). :class:`AxisConvention` is the part of a
:class:`~jointfit_ros.runner.JointRunner` that holds whether the hinge sign
is chosen, why a configured convention cannot be honoured, and says which
way the axis points in words. :meth:`AxisConvention.choose` reads the sign
from one frame's markers (:func:`~jointfit_core.axis_sign.hinge_sign`) once
the estimate is identified well enough; the runner calls it on a frame's path
only until the sign is chosen.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from jointfit_core.axis_sign import SIGN_SD_MAX_DEG, direction_sd_deg, hinge_sign
from jointfit_core.estimator import JointOutput, OnlineJoint
from jointfit_core.hinge_from_sums import PoseSumsAxis

from .params import JointConfig, NodeConfig

__all__ = ["AxisConvention"]

FloatArray = NDArray[np.float64]


class AxisConvention:
    """The hinge axis sign of one joint: by the configured marker convention, or the default.

    Parameters
    ----------
    cfg : JointConfig
        The joint's parameters (``axis_toward_marker``, ``axis_from_marker``).
    node : NodeConfig
        The node's marker names (the convention's markers' rows in a frame).
    cluster_rows : ndarray of intp, shape (M,)
        The rows of both segments' markers in a frame (the one-marker convention is read beyond them).

    Attributes
    ----------
    fixed : bool
        The sign is chosen, or no convention is configured: axis outputs go out.
    text : str
        Which way the hinge axis points, in words (set when the sign is chosen; empty before).
    problem : str
        Why the configured convention cannot be honoured (empty when it can, or before it is tried).
    """

    def __init__(self, cfg: JointConfig, node: NodeConfig, cluster_rows: NDArray[np.intp]) -> None:
        self.cfg = cfg
        self.fixed = not cfg.axis_toward_marker
        self.text = ""
        self.problem = ""
        self._toward_row = node.marker_index(cfg.axis_toward_marker) if cfg.axis_toward_marker else -1
        self._from_row = node.marker_index(cfg.axis_from_marker) if cfg.axis_from_marker else -1
        self._cluster_rows = cluster_rows

    @property
    def pending(self) -> bool:
        """A hinge sign convention is configured and not chosen yet (its axis outputs are withheld until it is)."""
        return not self.fixed

    def convention(self) -> str:
        """The configured convention, in words (``from A toward B``, or ``toward B (beyond the clusters ...)``)."""
        if self.cfg.axis_from_marker:
            return f"from {self.cfg.axis_from_marker} toward {self.cfg.axis_toward_marker}"
        return f"toward {self.cfg.axis_toward_marker} (beyond the clusters along the axis)"

    def words(self) -> str:
        """Which way the hinge axis points, in words (or that the sign is not chosen yet)."""
        if self.text:
            return self.text
        if self.cfg.axis_toward_marker:
            return (
                f"not chosen yet ({self.convention()} once identifiable, statistical direction sd < "
                f"{SIGN_SD_MAX_DEG:g} deg; no axis output until then)"
            )
        return "default: largest parent-frame component positive at the first identifiable estimate, kept after"

    def restored(self, source: str) -> None:
        """A saved calibration was restored: it carries its sign (``source``: where it was loaded from)."""
        self.fixed = True
        if self.cfg.axis_toward_marker:
            self.text = f"{self.convention()} (as saved in {source})"

    def unchoose(self) -> None:
        """Forget the chosen sign (a restored calibration was discarded): it is chosen anew from the frames to come."""
        self.fixed = not self.cfg.axis_toward_marker
        self.text = ""

    def reset(self) -> None:
        """:meth:`unchoose`, and forget :attr:`problem` (the joint was reset)."""
        self.unchoose()
        self.problem = ""

    def choose(self, out: JointOutput, frame: FloatArray, est: OnlineJoint) -> tuple[JointOutput, bool]:
        """Point the hinge axis by the marker convention once, from an identified estimate; then keep that sign.

        Until the estimate is identifiable with a statistical direction sd below
        :data:`~jointfit_core.axis_sign.SIGN_SD_MAX_DEG`, nothing is chosen
        (an unconverged direction can be anything); a convention that
        cannot be honoured (:func:`~jointfit_core.axis_sign.hinge_sign`) is
        reported in :attr:`problem` and the default sign stays. The
        statistical part (skin markers: without the soft-tissue prior) is what
        more movement reduces; the artefact part is a bias of a few degrees
        that cannot flip a sign read from markers whose line runs at least
        :data:`~jointfit_core.axis_sign.MIN_ALONG_RATIO` along the axis (the
        real knee fixture: total 5.2 deg, statistical 0.9 deg).

        Parameters
        ----------
        out : JointOutput
            The frame's world output (input units).
        frame : ndarray, shape (P, 3)
            The frame's markers (input units; NaN: missing).
        est : OnlineJoint
            The joint's estimator: its reference direction is set when the sign is chosen.

        Returns
        -------
        out : JointOutput
            ``out`` with the chosen sign.
        resolve : bool
            The estimator's reference direction was set: the window is to be solved again now.
        """
        sol = est.solution
        if not isinstance(sol, PoseSumsAxis) or out.direction is None or out.cov_direction is None:
            return out, False
        stat = est.statistical_solution
        cov = stat.cov_direction_parent if isinstance(stat, PoseSumsAxis) else sol.cov_direction_parent
        if not sol.identifiable or not direction_sd_deg(cov) < SIGN_SD_MAX_DEG:
            return out, False
        names = (self.cfg.axis_toward_marker, self.cfg.axis_from_marker)
        choice = hinge_sign(
            out.position,
            out.direction,
            frame[self._toward_row],
            frame[self._from_row] if self._from_row >= 0 else None,
            None if self._from_row >= 0 else frame[self._cluster_rows],
            names,
        )
        if not choice.final:
            return out, False
        self.fixed = True
        if choice.sign == 0.0:
            self.problem = choice.reason
            self.text = "default (largest parent-frame component positive): " + choice.reason
            return out, False
        self.text = self.convention()
        est.set_reference_direction(choice.sign * sol.direction_parent)
        if choice.sign < 0.0:
            out = replace(out, direction=-out.direction)
        return out, True
