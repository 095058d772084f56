"""One joint's state for ``/diagnostics``: the level, the one-line message and the key/values.

Pure Python (no rclpy). :func:`joint_status` is :meth:`JointRunner.status
<jointfit_ros.runner.JointRunner.status>`: it reads what the runner and its
estimator hold (the counters, the drops and gated shares, the loaded
calibration, the estimate with its noise, serial correlation, spread,
coverage and soft-tissue part, the consistency across movement blocks and
the live anatomy) and says, in order of precedence, what is wrong (a gate
that held out much, an estimate not identifiable, a stream in the wrong unit,
a sign convention not honoured, an inconsistent window) or how far the
estimate is from done. :func:`live_status` is :meth:`JointRunner.live_status
<jointfit_ros.runner.JointRunner.live_status>`: that status as of the wall
clock (:class:`~jointfit_ros.activity.InputActivity`: stale input, every input
dropped). It stands off a frame's path: the node calls it at each
diagnostics tick.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from jointfit_core.axis_sign import direction_sd_deg
from jointfit_core.cluster_turn import TURN_SD_MAX_DEG, weakest_turn_sd_deg
from jointfit_core.errors import InputError
from jointfit_core.estimator import OnlineJoint
from jointfit_core.gate import gated_verdict
from jointfit_core.hinge_from_sums import PoseSumsAxis
from jointfit_core.segments import PoseSumsCentre

from .absurd_values import unit_problem
from .activity import InputActivity
from .progress import coverage_values, done_check, estimate_sd

if TYPE_CHECKING:
    from .runner import JointRunner

__all__ = ["OK", "WARN", "ERROR", "STALE", "Status", "joint_status", "live_status", "weak_cluster"]

FloatArray = NDArray[np.float64]

#: diagnostic_msgs/DiagnosticStatus levels.
OK, WARN, ERROR, STALE = 0, 1, 2, 3


@dataclass(frozen=True)
class Status:
    """A joint's state for ``/diagnostics``: level, one-line message and key/values."""

    level: int
    message: str
    values: dict[str, Any]


#: Said while a joint whose window restarted after it broke (:attr:`OnlineJoint.joint_breaks
#: <jointfit_core.estimator.OnlineJoint.joint_breaks>`) has no estimate again.
BROKE_TEXT = (
    "estimating afresh: the two segments' relative pose changed for good (labels swapped between segments, a "
    "cluster moved on its bone, another subject), so the frames before were forgotten"
)
#: Said while a joint whose window restarted after its recent frames disagreed with its estimate
#: (:attr:`OnlineJoint.joint_drifts <jointfit_core.estimator.OnlineJoint.joint_drifts>`) has no estimate again.
DRIFT_TEXT = (
    "estimating afresh: the joint's recent frames disagreed with its estimate (a cluster moved on its bone: "
    "bumped, or slipped on its strap), so the frames before were forgotten"
)


def _largest_sd(cov: FloatArray) -> float:
    return float(np.sqrt(max(float(np.linalg.eigvalsh(cov)[-1]), 0.0)))


def _artefact_values(est: OnlineJoint, sol: PoseSumsCentre | PoseSumsAxis, u: str) -> dict[str, Any]:
    """The statistical and with-artefact parts of the estimate's sd, for /diagnostics (keys with units ``u``)."""
    values: dict[str, Any] = {"attachment": "/".join(est.attachment)}
    if "skin" in est.attachment:
        values["movement in the window (s)"] = round(est.movement_seconds, 2)
    stat = est.statistical_solution
    if stat is None:
        return values
    values[f"artefact scale ({u}/rad)"] = est.artefact_scale
    if isinstance(sol, PoseSumsCentre) and isinstance(stat, PoseSumsCentre):
        values[f"statistical sd ({u})"] = _largest_sd(stat.cov_parent)
        values[f"with-artefact sd ({u})"] = _largest_sd(sol.cov_parent)
    elif isinstance(sol, PoseSumsAxis) and isinstance(stat, PoseSumsAxis):
        values["statistical direction sd (deg)"] = round(direction_sd_deg(stat.cov_direction_parent), 3)
        values["with-artefact direction sd (deg)"] = round(direction_sd_deg(sol.cov_direction_parent), 3)
        values[f"statistical point sd ({u})"] = _largest_sd(stat.cov_point_parent)
        values[f"with-artefact point sd ({u})"] = _largest_sd(sol.cov_point_parent)
    return values


def _spread_deg(deficit: float) -> float:
    return float(np.rad2deg(np.sqrt(2.0 * max(deficit, 0.0))))


def joint_status(runner: JointRunner) -> tuple[Status, bool]:
    """The joint's level, message and values for ``/diagnostics``, and whether it is done.

    Parameters
    ----------
    runner : JointRunner
        The joint (read only).

    Returns
    -------
    status : Status
        Values in the runner's input units ``u``; ``STALE`` before any frame,
        ``WARN`` before an estimate or with a warning, else ``OK``.
    done : bool
        Identifiable, no warning, every sd at most ``target_sd`` and the hinge
        sign chosen (:func:`~jointfit_ros.progress.done_check`).
    """
    est = runner.estimator
    values = _input_values(runner)
    sol = est.solution
    if sol is None:
        msg = runner.odd_markers() or runner.waiting() or runner.last_error or "collecting frames"
        if (est.joint_breaks or est.joint_drifts) and not runner.waiting():
            drifted = est.joint_drifts and (not est.joint_breaks or est.joint_drifts[-1] > est.joint_breaks[-1])
            msg = f"{DRIFT_TEXT if drifted else BROKE_TEXT}; {msg}"
        return Status(WARN if est.n_frames_seen else STALE, msg, values), False
    u = runner.node.units
    units = unit_problem(est.length_scale, u)
    values.update(_estimate_values(est, sol, u, units))
    for side, ratio in runner.lever_ratios().items():  # the invisible soft-tissue bias grows with it
        values[f"lever / cluster radius {side}"] = ratio
    cfg = runner.cfg
    if sol.identifiable:
        values.update(runner.consistency.values(est, u))
        if runner.live_geometry is not None:
            values.update(runner.live_geometry.values(sol, u))
    if cfg.target_sd > 0.0:
        values[f"target sd ({u if isinstance(sol, PoseSumsCentre) else 'deg'})"] = cfg.target_sd
    warning = _warning(runner, sol, units)
    if warning:
        return Status(WARN, warning, values), False
    done, progress = done_check(sol, cfg.target_sd, u)
    done = done and not runner.sign_pending
    if cfg.target_sd > 0.0:
        values["done"] = done
    message = "frozen" if est.frozen else "estimating"
    if progress:
        message += f"; {progress}"
    if runner.auto_note:
        message += f"; {runner.auto_note}"
    if runner.last_error and (runner.counters["malformed"] or runner.counters["estimate_failures"]):
        return Status(OK, f"{message}; last problem: {runner.last_error}", values), done
    return Status(OK, message, values), done


def _input_values(runner: JointRunner) -> dict[str, Any]:
    """What the joint received, dropped, gated and loaded (the values of every status)."""
    est, c = runner.estimator, runner.counters
    values: dict[str, Any] = {
        "type": runner.cfg.type,
        "frozen": est.frozen,
        "frames in window": est.n_window,
        "frames received": c["frames"],
        "input rate (Hz)": round(runner.input_rate(), 1),
        "outputs": c["outputs"],
        "malformed frames": c["malformed"],
        "unmatched inputs": c["unmatched"],
        "estimate failures": c["estimate_failures"],
        "outputs withheld (not identifiable)": c["withheld_unidentified"],
        "outputs withheld (hinge sign not chosen yet)": c["withheld_unsigned"],
        "absurd markers (treated as missing)": c["absurd_markers"],
        "outputs withheld (non-finite or beyond the workspace)": c["absurd_outputs"],
    }
    if runner.cfg.type == "hinge":
        values["axis points"] = runner.axis_words()
    if est.window_thinned:
        cap = est.statistics.entries.rate_cap
        values["frames left out of the window (input faster than window_max_frames / window_s)"] = est.window_thinned
        values["frames entering the window (Hz, at most)"] = round(cap, 1)
    for reason, count in sorted(est.dropped.items()):
        values[f"dropped: {reason}"] = count
    for side, n in zip(("parent", "child", "joint"), (*est.gated_frames, est.joint_gated_frames), strict=True):
        values[f"{side} gated (%)"] = round(100.0 * n / est.n_frames_seen, 2) if est.n_frames_seen else 0.0
    for side, n in zip(("parent", "child"), est.relabelled_frames, strict=True):
        values[f"{side} swapped labels put right (frames)"] = n
    values["joint broke for good (times)"] = len(est.joint_breaks)
    values["cluster moved on its bone (times)"] = len(est.joint_drifts)
    if runner.loaded_from:
        values["calibration loaded from"] = runner.loaded_from
    if runner.calib.load_problem:
        values["calibration not loaded"] = runner.calib.load_problem
    return values


def _estimate_values(est: OnlineJoint, sol: PoseSumsCentre | PoseSumsAxis, u: str, units: str) -> dict[str, Any]:
    """The estimate's values: noise, serial correlation, fit, spread, the estimate and its sd, coverage, artefact.

    ``u``: the input units; ``units``: :func:`~jointfit_ros.absurd_values.unit_problem`'s verdict (a value when any).
    """
    values: dict[str, Any] = {}
    sigma_p, sigma_c = est.noise_std
    serial = est.serial_inflation
    if serial is not None:
        values["residual lag-1 autocorrelation"] = round(serial.rho_raw, 4)
        values["covariance inflation (correlation)"] = round(serial.factor, 3)
    if units:
        values["unit check"] = units
    values[f"noise sd parent ({u})"] = sigma_p
    values[f"noise sd child ({u})"] = sigma_c
    white = est.white_noise_std
    if white is not None:  # skin: the pooled noise above holds the clusters' deformation; this is the markers'
        values[f"white noise sd parent ({u})"] = white[0]
        values[f"white noise sd child ({u})"] = white[1]
    values[f"rms residual ({u})"] = sol.rms
    values["identifiable"] = sol.identifiable
    if not est.frozen and est.n_window >= 3:
        try:
            sums = est.pose_sums()[0]
            s = np.linalg.svd(np.asarray(sums.S) / sums.n, compute_uv=False)
            values["relative rotation spread (deg)"] = [round(_spread_deg(1.0 - v), 1) for v in s]
        except InputError:
            pass
    if isinstance(sol, PoseSumsCentre):
        values[f"centre_parent ({u})"] = np.round(sol.centre_parent, 6).tolist()
        values[f"centre sd ({u})"] = estimate_sd(sol)[0]
    else:
        values["direction_parent (unit vector)"] = np.round(sol.direction_parent, 6).tolist()
        values[f"point_parent ({u})"] = np.round(sol.point_parent, 6).tolist()
        values["direction sd (deg)"] = round(direction_sd_deg(sol.cov_direction_parent), 3)
        values[f"point sd ({u})"] = float(np.sqrt(max(np.linalg.eigvalsh(sol.cov_point_parent)[-1], 0.0)))
    values.update(coverage_values(est, sol)[1])
    values.update(_artefact_values(est, sol, u))
    return values


#: Unlabelled clouds: the marker identities come from the first complete cloud; one in another order
#: makes every segment a mix of markers that do not move together, which reads as noise or swaps.
_UNLABELLED_HINT = (
    "; unlabelled clouds: the marker identities were learnt from the first complete cloud, which must list "
    "the markers in marker_names order (if it did not, no segment is rigid: call ~/reset while the source "
    "sends an ordered cloud to learn them again)"
)


#: A chained joint's frames in a row without an output while a chain joint had none, before its status says so.
CHAIN_SILENT_FRAMES = 10


def chain_waiting_text(missing: tuple[str, ...]) -> str:
    """Why a chained joint publishes nothing: the chain joints whose per-frame outputs it lacks."""
    names = ", ".join(missing)
    verb = "has" if len(missing) == 1 else "have"
    return (
        f"no output: its segments hold the per-frame output of {names} as a marker, and {names} {verb} none "
        f"(see {'its' if len(missing) == 1 else 'their'} status)"
    )


def _warning(runner: JointRunner, sol: PoseSumsCentre | PoseSumsAxis, units: str) -> str:
    """The status's warning, the first that applies in order of precedence (empty: none)."""
    est, cfg = runner.estimator, runner.cfg
    if runner.chain_silent >= CHAIN_SILENT_FRAMES:  # first: its chain joints have no output, so it has none
        return chain_waiting_text(runner.chain_missing)  # (nor can its markers be judged against a calibration)
    if est.calibration_problem:  # every output is withheld
        return est.calibration_problem
    odd = runner.odd_markers()
    if odd:  # a label on the wrong segment: what its gate, identifiability and covariance say follows from it
        return odd
    turn = weak_cluster(runner) if sol.identifiable else ""  # its covariance under-states; the gate holds out turns
    if turn:
        return turn
    gated = gated_verdict(est.gated_frames, est.n_frames_seen, cfg.segment_names(), est.joint_gated_frames)
    if gated:  # before the motion's verdict: a gate that deleted real movement must not blame the motion
        return gated + _UNLABELLED_HINT * runner.node.unlabelled
    if est.joint_breaks:  # the estimate is of the frames since: of another joint, when a tracker swapped clusters
        return (
            f"the joint broke for good {len(est.joint_breaks)} time(s), the last at frame {est.joint_breaks[-1]}: "
            "its two segments' relative pose changed at once and stayed so; the estimate is of the frames since. "
            "If a tracker swapped this segment's labels with another cluster's (the two thighs), it is another "
            "joint's; check the labels (~/reset clears this)"
        )
    if est.joint_drifts and _recent_drift(runner):  # a cluster bumped on its bone (rigid markers): the estimate is of the frames since
        return (
            f"the joint's recent frames disagreed with its estimate {len(est.joint_drifts)} time(s), the last at "
            f"frame {est.joint_drifts[-1]}: a cluster moved on its bone (bumped, or slipped on its strap), so the "
            "window restarted there and the estimate is of the frames since; a calibration saved before is of "
            f"the old placement (said for {DRIFT_WARN_S:.0f} s; ~/reset clears this)"
        )
    if not sol.identifiable:
        outputs = (
            "per-frame outputs published with a widened covariance (publish_unidentified)"
            if cfg.publish_unidentified
            else "no per-frame output until it is"
        )
        return f"not identifiable ({outputs}): {sol.reason}{short_window(runner)}" + _UNLABELLED_HINT * runner.node.unlabelled
    if units:
        return units
    if runner.sign.problem:
        return f"hinge sign convention not honoured: {runner.sign.problem}"
    return runner.consistency.warning(est) if sol.identifiable else ""


#: Seconds of input (3000 frames when the rate is not known) after a drift during which the joint warns of it.
#: The new window's estimate is of the same joint (unlike a break's, which may be another's): after that the
#: count stays in the values, the status returns to what the estimate says, and auto_freeze may act.
DRIFT_WARN_S = 30.0


def _recent_drift(runner: JointRunner) -> bool:
    """Whether the joint's last drift (:attr:`OnlineJoint.joint_drifts`) is under DRIFT_WARN_S of input ago."""
    est = runner.estimator
    rate = runner.input_rate()
    span = DRIFT_WARN_S * rate if rate > 0.0 else 3000.0
    return est.n_frames_seen - est.joint_drifts[-1] < span


#: A full window by frame count that spans less than this (s of input) is named when the joint is not
#: identifiable: at 500 Hz the default 3000 frames hold 6 s, and "record more movement" cannot help.
SHORT_WINDOW_S = 20.0


def short_window(runner: JointRunner) -> str:
    """Words for a not-identifiable joint whose full frame-count window holds under SHORT_WINDOW_S of input ("" else).

    Measured (lower-body skin skeleton, 20 s at 500 Hz, the default ``window: 3000``): every knee, and
    most hips and ankles, stayed not identifiable with the advice to record more movement cycles, which
    the sliding window then drops as fast as they come.
    """
    est = runner.estimator
    frames = est.spec.frames
    rate = runner.input_rate()
    if est.frozen or frames is None or est.n_window < frames or not rate > 0.0 or frames / rate >= SHORT_WINDOW_S:
        return ""
    return (
        f"; the window holds only the last {frames} frames ({frames / rate:.3g} s at {rate:.3g} Hz), so recording "
        "longer adds no movement to it: lengthen it (window_s, in seconds, at most window_max_frames frames of it "
        "entering; or window, in frames)"
    )


def weak_cluster(runner: JointRunner) -> str:
    """A segment whose markers lie so nearly on a line that each frame turns it by over TURN_SD_MAX_DEG (words)."""
    est = runner.estimator
    noise = est.white_noise_std or est.noise_std  # skin: the markers' own noise (the pooled one holds deformation)
    for side, template, sigma, name in zip(
        ("parent", "child"), est.templates, noise, runner.cfg.segment_names(), strict=True
    ):
        if template is None or not sigma > 0.0:
            continue
        sd = weakest_turn_sd_deg(template, sigma)
        if sd > TURN_SD_MAX_DEG:
            return (
                f"the {name.removeprefix(side + ' ')} markers lie nearly on a line: every frame turns the {side} "
                f"about it by +-{min(sd, 180.0):.0f} deg (sd, at its noise {sigma:.3g}), beyond the "
                f"{TURN_SD_MAX_DEG:.0f} deg to which the covariance holds (it under-states the error): add a marker "
                "off the line, or spread them"
            )
    return ""


def live_status(runner: JointRunner, activity: InputActivity, now: float, stale_after: float) -> Status:
    """:func:`joint_status` as of ``now`` (seconds, monotonic), from the joint's input activity.

    Parameters
    ----------
    runner : JointRunner
        The joint (its ``status()`` is taken: sets its ``done``).
    activity : InputActivity
        The joint's; sampled here with the runner's totals.
    now : float
        Seconds (``time.monotonic()``).
    stale_after : float
        Seconds without input after which the level is STALE.

    Returns
    -------
    Status
        The rate over the recent ticks in the values; STALE after ``stale_after``
        seconds without input; at least WARN when every input since the
        previous call was dropped, with the reasons.
    """
    activity.window_s = stale_after
    est, c = runner.estimator, runner.counters
    upstream = runner._upstream_dropped
    arrived = c["frames"] + c["malformed"] + c["unmatched"] + upstream
    used = est.n_frames_seen - est.dropped.get("parent_not_posed", 0)
    reasons = {
        **est.dropped,
        "malformed": c["malformed"],
        "unmatched": c["unmatched"],
        "dropped before this joint (see jointfit: input)": upstream,
    }
    act = activity.sample(now, arrived, used, reasons)
    st = runner.status()
    values = dict(st.values)
    if act.rate_hz is not None:
        values["input rate (Hz)"] = round(act.rate_hz, 1)
    if act.silent_s is not None and act.silent_s >= stale_after:
        values["seconds without input"] = round(act.silent_s, 1)
        return Status(STALE, f"no input for {act.silent_s:.1f} s (stale_after {stale_after:g} s); {st.message}", values)
    if act.all_dropped and st.level != ERROR:
        return Status(max(st.level, WARN) if st.level != STALE else WARN, f"{act.dropped_text()}; {st.message}", values)
    return st if values == st.values else Status(st.level, st.message, values)
