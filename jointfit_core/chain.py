"""Skeleton chains from minimal marker sets (Pham et al., section V-B).

Joints are fitted in order; each fitted joint adds *virtual markers* that the
next joints can use as markers of either link, so that a whole limb can be
identified from very few real markers: 3 trunk markers give the hip
(spherical, 3 + 1: the thigh marker); the hip centre and the thigh marker are
two "markers" on the thigh, which with one shank marker give the knee
(revolute, 2 + 1); the knee axis and the shank marker fix the shank, which
with one foot marker gives the ankle (spherical, 3 + 1).

Virtual markers (world frame, per frame, NaN where the joint could not be
computed):

* a spherical joint ``"name"`` adds ``"name"``: its centre;
* a revolute joint ``"name"`` adds ``"name"``: the point of the axis nearest
  the single-marker link's first marker (the centre of its circle), and
  ``"name:axis"``: the point one lever arm (that marker's distance from the
  axis) further along the axis. Both lie on the axis, so both are rigid on
  both links.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import InputError
from .identifiability import JOINT_KINDS, check_marker_counts
from .minimal import fit_axis_minimal, fit_centre_minimal
from .results import MinimalAxisFit, MinimalCentreFit

__all__ = ["ChainJoint", "fit_chain", "virtual_markers", "leg_chain_spec"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class ChainJoint:
    """One joint of a chain.

    Attributes
    ----------
    name : str
        Joint name; also the name of the virtual marker(s) it adds.
    kind : {"spherical", "revolute"}
        Joint type (``"ball"``, ``"hinge"`` accepted).
    parent, child : tuple of str
        Names of the (real or virtual) markers on each link.
    axis_hint : array_like, shape (3,) or (N, 3), optional
        Revolute joints only: a world direction the axis roughly points along
        (or one per frame), passed to :func:`jointfit_core.fit_axis_minimal`
        to pick among the hinges that fit a 2 + 1 marker set equally well.
    """

    name: str
    kind: str
    parent: tuple[str, ...]
    child: tuple[str, ...]
    axis_hint: ArrayLike | None = None


def leg_chain_spec(
    trunk: Sequence[str] = ("trunk1", "trunk2", "trunk3"),
    thigh: str = "thigh",
    shank: str = "shank",
    foot: str = "foot",
    *,
    knee_axis_hint: ArrayLike | None = None,
) -> tuple[ChainJoint, ...]:
    """The paper's leg: hip (spherical 3 + 1), knee (revolute 2 + 1), ankle (spherical 3 + 1).

    Parameters
    ----------
    trunk : sequence of 3 str
        Names of the trunk (pelvis) markers.
    thigh, shank, foot : str
        Names of the single thigh, shank and foot markers.
    knee_axis_hint : array_like, shape (3,) or (N, 3), optional
        World direction the knee axis roughly points along (medio-lateral).

    Returns
    -------
    tuple of ChainJoint
        ``hip``, ``knee`` and ``ankle``, in fitting order.
    """
    return (
        ChainJoint("hip", "spherical", tuple(trunk), (thigh,)),
        ChainJoint("knee", "revolute", ("hip", thigh), (shank,), knee_axis_hint),
        ChainJoint("ankle", "spherical", ("knee", "knee:axis", shank), (foot,)),
    )


def _check_markers_by_name(markers: Mapping[str, ArrayLike]) -> tuple[dict[str, FloatArray], int]:
    if not isinstance(markers, Mapping) or not markers:
        raise InputError("markers: expected a non-empty mapping from marker name to an (N, 3) array")
    out: dict[str, FloatArray] = {}
    n_frames: int | None = None
    for name, value in markers.items():
        try:
            arr = np.array(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(f"markers[{name!r}]: expected a numeric array of shape (N, 3)") from None
        if arr.ndim != 2 or arr.shape[1] != 3:
            raise InputError(f"markers[{name!r}]: expected shape (N, 3), got {arr.shape}")
        if np.isinf(arr).any():
            raise InputError(f"markers[{name!r}]: contains inf; use NaN for missing samples")
        if n_frames is None:
            n_frames = arr.shape[0]
        elif arr.shape[0] != n_frames:
            raise InputError(f"markers[{name!r}]: expected {n_frames} frames like the others, got {arr.shape[0]}")
        arr[np.isnan(arr).any(axis=1)] = np.nan
        out[str(name)] = arr
    assert n_frames is not None
    return out, n_frames


def _check_joints(joints: Sequence[ChainJoint]) -> None:
    if not joints:
        raise InputError("joints: expected at least one ChainJoint")
    seen: set[str] = set()
    for joint in joints:
        if not isinstance(joint, ChainJoint):
            raise InputError(f"joints: expected ChainJoint items, got {type(joint).__name__}")
        if joint.name in seen:
            raise InputError(f"joints: joint name {joint.name!r} used twice")
        seen.add(joint.name)
        if not isinstance(joint.kind, str) or joint.kind.lower() not in JOINT_KINDS:
            raise InputError(f"joint {joint.name!r}: kind must be one of {sorted(JOINT_KINDS)}, got {joint.kind!r}")


def virtual_markers(name: str, fit: MinimalCentreFit | MinimalAxisFit) -> dict[str, FloatArray]:
    """The virtual markers a fitted joint adds to a chain (see the module docstring).

    Parameters
    ----------
    name : str
        The joint's name.
    fit : MinimalCentreFit or MinimalAxisFit
        Its fit.

    Returns
    -------
    dict of str to ndarray, shape (N, 3)
        ``{name: centre}`` for a ball joint, ``{name: point, name + ":axis":
        point + lever * direction}`` for a hinge.
    """
    if isinstance(fit, MinimalCentreFit):
        return {name: np.array(fit.centre_world)}
    lever = float(np.max(fit.radii))
    return {
        name: np.array(fit.point_world),
        f"{name}:axis": np.array(fit.point_world + lever * fit.direction_world),
    }


def fit_chain(
    markers: Mapping[str, ArrayLike], joints: Sequence[ChainJoint]
) -> dict[str, MinimalCentreFit | MinimalAxisFit]:
    """Fit a chain of joints whose estimates become virtual markers for the next ones.

    Parameters
    ----------
    markers : mapping of str to array_like, shape (N, 3)
        Real marker trajectories by name, world frame, same frames, any
        length unit; NaN marks a missing sample.
    joints : sequence of ChainJoint
        The joints in fitting order; each may use the real markers and the
        virtual markers of the joints before it (see :func:`virtual_markers`).

    Returns
    -------
    dict of str to MinimalCentreFit or MinimalAxisFit
        The fit of every joint, by name, in order.

    Raises
    ------
    InputError
        Bad marker arrays, unknown marker names, a marker used on both links,
        unsupported counts.
    NotIdentifiableError
        A joint's marker counts cannot identify it (with the reason), or its
        motion does not determine it at all.

    Notes
    -----
    Section V-B of Pham et al.: a spherical joint with 3 (real or virtual)
    markers on one link and 1 on the other is the (3, 1) case of section
    IV-A, with 2 + 2 the S22 case; a revolute joint with 2 + 1 is the R21
    case of section III-A (:func:`jointfit_core.fit_centre_minimal`,
    :func:`jointfit_core.fit_axis_minimal`). The virtual markers carry the
    errors of the joints they come from, which each later fit treats as
    marker noise (its residual-based noise estimate absorbs them), so the
    covariances of later joints are approximate: they ignore that a virtual
    marker's error is correlated across frames. A joint that uses virtual
    markers of a non-identifiable joint is returned with ``identifiable``
    False and a reason naming that joint.
    """
    available, _ = _check_markers_by_name(markers)
    _check_joints(joints)
    results: dict[str, MinimalCentreFit | MinimalAxisFit] = {}
    unreliable: dict[str, str] = {}  # virtual marker -> the non-identifiable joint it comes from
    for joint in joints:
        for side, names in (("parent", joint.parent), ("child", joint.child)):
            missing = [name for name in names if name not in available]
            if missing:
                raise InputError(
                    f"joint {joint.name!r}: {side} marker(s) {missing} are neither markers nor virtual markers of "
                    f"earlier joints; available: {sorted(available)}"
                )
        both = set(joint.parent) & set(joint.child)
        if both:
            raise InputError(f"joint {joint.name!r}: marker(s) {sorted(both)} on both links")
        kind = JOINT_KINDS[joint.kind.lower()]
        check_marker_counts(kind, len(joint.parent), len(joint.child))
        parent = np.stack([available[name] for name in joint.parent], axis=1)
        child = np.stack([available[name] for name in joint.child], axis=1)
        fit: MinimalCentreFit | MinimalAxisFit
        if kind == "spherical":
            fit = fit_centre_minimal(parent, child)
        else:
            fit = fit_axis_minimal(parent, child, axis_hint=joint.axis_hint)
        upstream = sorted({unreliable[name] for name in (*joint.parent, *joint.child) if name in unreliable})
        if upstream and fit.identifiable:
            fit = replace(
                fit,
                identifiable=False,
                reason=f"uses the virtual markers of joint(s) {upstream}, which are not identifiable",
            )
        results[joint.name] = fit
        added = virtual_markers(joint.name, fit)
        available.update(added)
        if not fit.identifiable:
            unreliable.update({name: joint.name for name in added})
    return results
