"""An online joint's calibration file: its settings, templates, noise and estimate as plain types, and back.

:func:`to_dict` and :func:`from_dict` are :meth:`OnlineJoint.to_dict
<jointfit_core.estimator.OnlineJoint.to_dict>` and :meth:`OnlineJoint.from_dict
<jointfit_core.estimator.OnlineJoint.from_dict>`: a joint's calibration
(format :data:`CALIBRATION_FORMAT`, version :data:`CALIBRATION_VERSION`) as
YAML-able types (the files of ``jointfit fit`` and of the node's
``~/save_calibration``, :mod:`jointfit_core.node_calibration`), and the frozen
joint that a saved calibration restores, its per-frame outputs starting with
the first frame. They stand off a frame's path: a file is written from the
latest estimate (solving the window first when it is stale) and read before
any frame. Reading refuses what no fit could have written
(:func:`_check_saved_solution`). The fits' own fields are
:mod:`jointfit_core.calibration`'s.

The functions take the joint and read (to_dict) or set (from_dict) its state.
"""

from __future__ import annotations

import math
from dataclasses import asdict
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from .calibration import fit_from_dict, fit_to_dict
from .checks import check_vector3
from .errors import InputError
from .hinge_from_sums import PoseSumsAxis
from .joint_sums import _Z
from .segments import PoseSumsCentre
from .serial import SerialInflation
from .window_entries import WINDOW_MAX_FRAMES

if TYPE_CHECKING:
    from .estimator import OnlineJoint

__all__ = ["CALIBRATION_FORMAT", "CALIBRATION_VERSION", "to_dict", "from_dict", "matched_child_point"]

FloatArray = NDArray[np.float64]

#: ``format`` and ``version`` keys of a saved calibration (:func:`to_dict`).
CALIBRATION_FORMAT = "jointfit-calibration"
CALIBRATION_VERSION = 1

#: A saved joint farther from its segment than this many template sizes is refused as absurd.
_SAVED_REACH = 1000.0


def to_dict(joint: OnlineJoint) -> dict[str, Any]:
    """The calibration as plain YAML-able types: settings, templates, noise and estimate.

    Solves the window first when the estimate is stale (``joint.estimate()``)
    and keeps the hinge's matched child point on the joint (a calibration
    loaded later writes the same one).

    Parameters
    ----------
    joint : OnlineJoint
        The joint whose calibration is written.

    Returns
    -------
    dict
        Format :data:`CALIBRATION_FORMAT`, version :data:`CALIBRATION_VERSION`;
        lengths in input units, the estimate as :func:`~jointfit_core.calibration.fit_to_dict`.

    Raises
    ------
    InputError, NotIdentifiableError
        No estimate can be made yet.
    """
    sol = joint.estimate()
    p_tpl, c_tpl = joint.templates
    assert p_tpl is not None and c_tpl is not None
    fit = fit_to_dict(sol)
    joint._matched = matched_child_point(joint, sol)
    spec = joint.spec
    return {
        "format": CALIBRATION_FORMAT,
        "version": CALIBRATION_VERSION,
        "kind": joint.kind,
        "window": spec.frames,
        "window_s": spec.seconds,
        "half_life": spec.half_life,
        "half_life_s": spec.half_life_s,
        "window_max_frames": joint.window_max_frames,
        "template_frames": joint.template_frames,
        "reference_direction": None if joint.reference_direction is None else joint.reference_direction.tolist(),
        "n_markers": list(joint.n_markers) if joint.n_markers is not None else None,
        "template_parent": p_tpl.tolist(),
        "template_child": c_tpl.tolist(),
        "noise_std_parent": joint._sigma[0],
        "noise_std_child": joint._sigma[1],
        "noise_std_fixed": [v is not None for v in joint._noise_arg],
        "templates_fixed": [v is not None for v in joint._templates_arg],
        "serial_correlation": joint.serial_correlation,
        "gate": joint.gate,
        "serial_inflation": None if joint._serial is None else _serial_to_dict(joint._serial),
        "attachment": list(joint.attachment),
        "artefact_scale": joint._artefact_scale,
        "cluster_motion": None if joint._cluster_motion is None else joint._cluster_motion.tolist(),
        "estimate": fit,
        "point_child_matched": None if joint._matched is None else joint._matched.tolist(),
    }


def matched_child_point(joint: OnlineJoint, sol: PoseSumsCentre | PoseSumsAxis) -> FloatArray | None:
    """Hinge: the child-frame point that is the parent's axis point (``point_parent``), from the window's mean pose.

    ``point_child`` is the axis point nearest the child's own origin, another point
    of the axis; over the window the child's maps to the parent's axis line at
    ``point_parent + s direction_parent`` with ``s = direction_parent . (mean(Q) p_c +
    mean(t) - p_p)`` (linear in the relative pose, so exact from the sums); the
    parent's point is then ``p_c - s direction_child`` in the child frame.

    Parameters
    ----------
    joint : OnlineJoint
        The joint (its window's sums are read).
    sol : PoseSumsCentre or PoseSumsAxis
        Its estimate.

    Returns
    -------
    ndarray, shape (3,), or None
        Child frame, input units. None for a ball; without frames in the
        statistics the joint's earlier one (a loaded calibration keeps its own).
    """
    if not isinstance(sol, PoseSumsAxis):
        return None
    try:
        sums = joint._entered_sums()
    except InputError:
        return joint._matched
    if not sums[0] > 0.0:
        return joint._matched
    Z = (sums[_Z] / sums[0]).reshape(3, 4)
    s = float(sol.direction_parent @ (Z[:, :3] @ sol.point_child + Z[:, 3] - sol.point_parent))
    out: FloatArray = sol.point_child - s * sol.direction_child
    return out


def from_dict(cls: type[OnlineJoint], data: dict[str, Any]) -> OnlineJoint:
    """A frozen joint of class ``cls`` from a saved calibration (:func:`to_dict`).

    The templates and the estimate are restored, so per-frame outputs
    start with the first frame; its ``thaw`` resumes estimation (with
    the saved templates).

    Parameters
    ----------
    cls : type
        :class:`~jointfit_core.estimator.OnlineJoint` (or a subclass).
    data : dict
        The calibration, as :func:`to_dict` wrote it (or an older version).

    Returns
    -------
    OnlineJoint
        Frozen, with the saved settings, templates, noise and estimate.

    Raises
    ------
    InputError
        Not a jointfit calibration, a newer version, or malformed fields.
    """
    if not isinstance(data, dict) or data.get("format") != CALIBRATION_FORMAT:
        raise InputError(f"calibration: expected a dict with format {CALIBRATION_FORMAT!r}")
    version = data.get("version")
    if not isinstance(version, int) or version > CALIBRATION_VERSION or version < 1:
        raise InputError(
            f"calibration: version {version!r} is not supported (this jointfit reads 1..{CALIBRATION_VERSION})"
        )
    try:
        est = _with_settings(cls, data)
        tp, tc = _restore_templates(est, data)
        _restore_estimate(est, data, max(float(np.abs(tp).max()), float(np.abs(tc).max())))
    except InputError:
        raise
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"calibration: a field is missing or malformed: {exc!r}") from None
    est._frozen = True
    return est


def _with_settings(cls: type[OnlineJoint], data: dict[str, Any]) -> OnlineJoint:
    """A new joint with the calibration's settings (kind, window, marker counts, noise, gate, attachment)."""
    return cls(
        str(data["kind"]),
        data.get("window"),
        window_s=data.get("window_s"),
        half_life=data.get("half_life"),
        half_life_s=data.get("half_life_s"),
        template_frames=int(data.get("template_frames", 50)),
        reference_direction=data.get("reference_direction"),
        n_markers=(int(data["n_markers"][0]), int(data["n_markers"][1])),
        noise_std=tuple(  # type: ignore[arg-type]
            float(data[f"noise_std_{side}"]) if fixed else None
            for side, fixed in zip(("parent", "child"), data.get("noise_std_fixed", [False, False]), strict=True)
        ),
        serial_correlation=data.get("serial_correlation", True),  # absent before it existed
        gate=float(data.get("gate", 5.0)),
        attachment=tuple(data.get("attachment", ("rigid", "rigid"))),  # absent before it existed
        window_max_frames=data.get("window_max_frames", WINDOW_MAX_FRAMES),  # absent before it existed
    )


def _restore_templates(est: OnlineJoint, data: dict[str, Any]) -> tuple[FloatArray, FloatArray]:
    """Set the saved templates, parent (Pa, 3) and child (Pc, 3) in input units, and return them."""
    tp = np.array(data["template_parent"], dtype=np.float64)
    tc = np.array(data["template_child"], dtype=np.float64)
    assert est.n_markers is not None
    if tp.shape != (est.n_markers[0], 3) or tc.shape != (est.n_markers[1], 3) or not (
        np.isfinite(tp).all() and np.isfinite(tc).all()
    ):
        raise InputError(
            f"calibration: templates of shapes {tp.shape} and {tc.shape} do not match n_markers {est.n_markers}"
        )
    est._make_segments(*est.n_markers)
    assert est._pose is not None
    est._pose.parent.set_template(tp)
    est._pose.child.set_template(tc)
    tf = data.get("templates_fixed", [False, False])
    est._templates_arg = (tp if tf[0] else None, tc if tf[1] else None)
    return tp, tc


def _restore_estimate(est: OnlineJoint, data: dict[str, Any], template_size: float) -> None:
    """Set the saved estimate, noise, serial-correlation factor, artefact scale and matched point; arm the joint test.

    ``template_size``: the templates' largest coordinate (input units), the scale of
    :func:`_check_saved_solution`'s reach.
    """
    fit = data["estimate"]
    if est.kind == "ball":
        est._solution = fit_from_dict(PoseSumsCentre, fit)
    else:
        est._solution = fit_from_dict(PoseSumsAxis, fit)
    _check_saved_solution(est._solution, template_size)
    est._sigma = (float(data["noise_std_parent"]), float(data["noise_std_child"]))
    if not all(math.isfinite(v) and v > 0.0 for v in est._sigma):
        raise InputError(f"calibration: the noise sds {est._sigma} are not finite positive numbers")
    serial = data.get("serial_inflation")  # absent from calibrations saved before it existed
    est._serial = None if serial is None else _serial_from_dict(serial)
    scale = float(data.get("artefact_scale", 0.0))  # absent before the soft-tissue part existed
    if not (math.isfinite(scale) and scale >= 0.0):
        raise InputError(f"calibration: the artefact scale {scale!r} is not a finite number >= 0")
    est._artefact_scale = scale  # (saved again as loaded: a save after a restart writes the same file)
    est._cluster_motion = _cluster_motion_from(data.get("cluster_motion"))  # absent before it existed
    matched = data.get("point_child_matched")  # absent before it existed
    est._matched = None if matched is None else check_vector3(matched, name="point_child_matched")
    est._installed()  # as any new estimate: the per-frame outputs' cache cleared, the joint test armed


def _cluster_motion_from(value: Any) -> FloatArray | None:
    """A saved ``cluster_motion`` (2 x 6 variances >= 0) or None; an InputError for anything else."""
    if value is None:
        return None
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        arr = np.full(1, np.nan)
    if arr.shape != (2, 6) or not (np.isfinite(arr).all() and (arr >= 0.0).all()):
        raise InputError(f"calibration: cluster_motion must be 2 rows of 6 finite variances >= 0, got {value!r}")
    return arr


def _serial_to_dict(serial: SerialInflation) -> dict[str, float | None]:
    """The serial-correlation factor's fields, NaN written as None (YAML has no NaN that every reader takes)."""
    return {k: (None if not np.isfinite(v) else float(v)) for k, v in asdict(serial).items()}


def _serial_from_dict(data: Any) -> SerialInflation:
    """:func:`_serial_to_dict` read back (None as NaN; fields absent from older files as NaN)."""
    if not isinstance(data, dict):
        raise InputError(f"calibration: serial_inflation: expected a mapping, got {type(data).__name__}")
    keys = ("rho", "rho_raw", "factor", "n_pairs", "frame_interval_s")  # the last absent before it existed
    vals = {k: float("nan") if data.get(k) is None else float(data[k]) for k in keys}
    return SerialInflation(**vals)


def _check_saved_solution(sol: PoseSumsCentre | PoseSumsAxis, template_size: float) -> None:
    """Refuse a saved estimate that no fit could have made: non-finite, a negative variance, absurdly far.

    Raises
    ------
    InputError
    """
    missing = [f for f in sol.__dataclass_fields__ if getattr(sol, f) is None]
    if missing:
        raise InputError(f"calibration: the estimate has no {', '.join(missing)}")
    arrays = {f: np.asarray(getattr(sol, f)) for f in sol.__dataclass_fields__ if isinstance(getattr(sol, f), np.ndarray)}
    bad = [f for f, a in arrays.items() if not np.isfinite(a).all()]
    if bad or not math.isfinite(sol.rms) or sol.rms < 0.0:
        raise InputError(f"calibration: the estimate is not finite ({', '.join(bad) or 'rms'})")
    for f, a in arrays.items():
        if f.startswith("cov") and (a.ndim != 2 or a.shape[0] != a.shape[1] or (np.diag(a) < 0.0).any()):
            raise InputError(f"calibration: the estimate's {f} is not a covariance (negative variance or shape {a.shape})")
        if f.startswith("direction") and abs(float(np.linalg.norm(a)) - 1.0) > 1e-6:
            raise InputError(f"calibration: the estimate's {f} is not a unit vector (norm {np.linalg.norm(a):.6g})")
    limit = _SAVED_REACH * max(template_size, 1e-300)
    for f in ("centre_parent", "centre_child", "point_parent", "point_child"):
        if f in arrays and float(np.abs(arrays[f]).max()) > limit:
            raise InputError(
                f"calibration: the estimate's {f} is {np.abs(arrays[f]).max():.3g} from its template, more than "
                f"{_SAVED_REACH:g} times the template's size"
            )
