"""Which marker counts can identify a joint (Pham, Ayusawa, Kubota & Nakamura).

Structural identifiability of the joint parameters from ``p`` markers on one
link and ``q`` on the other, for rigid links and noise-free markers
(sections II-IV of the paper). Rigid-body reasoning: with ``p >= 3`` markers a
link has a full frame; with ``p = 2`` only a line (the rotation about the two
markers' axis is lost); with ``p = 1`` only a point.

========= ============== ==================================================
joint     (p, q)         verdict (the paper's section)
========= ============== ==================================================
spherical (3, 1)         identifiable from 4 frames (IV-A): the single
                         marker moves on a sphere in the 3-marker frame
spherical (2, 2)         identifiable from 9 frames (IV-C, S22 in V-A)
spherical (2, 1)         not identifiable (IV-B): one degree of freedom lost
spherical (1, 1)         not identifiable (follows from (2, 1), Remark 1)
revolute  (2, 1)         identifiable from 5 frames (III-A), see the note
revolute  (1, 1)         not identifiable (III-B): one degree of freedom lost
any       (>= 3, >= 3)   the ordinary case (two-segment pose methods)
========= ============== ==================================================

``(p, q)`` and ``(q, p)`` are alike, and adding markers never hurts (Remark 1).

Note on the revolute ``(2, 1)`` case: the linear system of eq. (7)-(10)
determines the five coefficients ``Y`` uniquely, but the map from the hinge
constants to ``Y`` is not one-to-one. Re-deriving eq. (12)-(13) and solving
them numerically for random hinges, the cubic (13) has *two* admissible roots
in every case tried (2000 random hinges), each giving a different real hinge
that passes through every sample exactly, and each hinge has a mirror image
(reflection in the plane of the three markers) with the opposite twist sign
that fits equally. The case is therefore identifiable only up to a discrete
choice among (generically) four hinges; :func:`jointfit_core.fit_axis_minimal`
finds all of them and needs an ``axis_hint`` (or a fourth marker) to pick one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError, NotIdentifiableError

__all__ = [
    "Identifiability",
    "marker_count_identifiability",
    "check_marker_counts",
    "JOINT_KINDS",
]

#: Accepted joint kinds and their aliases.
JOINT_KINDS = {"spherical": "spherical", "ball": "spherical", "revolute": "revolute", "hinge": "revolute"}


@dataclass(frozen=True)
class Identifiability:
    """Verdict on whether a marker count can identify a joint.

    Attributes
    ----------
    kind : str
        ``"spherical"`` or ``"revolute"``.
    n_parent, n_child : int
        Markers on the parent and the child link.
    identifiable : bool
        Whether the joint parameters are structurally identifiable (rigid
        links, no noise, a motion that excites the joint).
    method : str
        The paper's name of the applicable minimal method (``"S31"``,
        ``"S22"``, ``"R21"``), ``"two-segment"`` for the ordinary case of at
        least 3 markers on both links, ``""`` when not identifiable.
    function : str
        The jointfit function that implements it, ``""`` when none.
    min_frames : int
        Frames needed in the noise-free case (4 for S31, 9 for S22, 5 for
        R21, 3 for the two-segment methods); 0 when not identifiable. Noisy
        data need many more.
    reason : str
        Why the joint is not identifiable, what is lost and what to do;
        empty when identifiable.
    note : str
        Caveats of an identifiable case (degenerate motions, discrete
        ambiguities); empty when none.
    """

    kind: str
    n_parent: int
    n_child: int
    identifiable: bool
    method: str
    function: str
    min_frames: int
    reason: str
    note: str


def _check_kind(kind: str) -> str:
    if not isinstance(kind, str) or kind.lower() not in JOINT_KINDS:
        raise InputError(
            f"kind: expected one of {sorted(JOINT_KINDS)} ('ball' = 'spherical', 'hinge' = 'revolute'), got {kind!r}"
        )
    return JOINT_KINDS[kind.lower()]


def _check_count(count: int, name: str) -> int:
    if isinstance(count, bool) or not isinstance(count, int | np.integer) or count < 0:
        raise InputError(f"{name}: expected a marker count (integer >= 0), got {count!r}")
    return int(count)


def _verdict(kind: str, p: int, q: int) -> Identifiability:
    lo, hi = min(p, q), max(p, q)
    pair = f"({p}, {q})"

    def no(reason: str) -> Identifiability:
        return Identifiability(kind, p, q, False, "", "", 0, reason, "")

    def yes(method: str, function: str, min_frames: int, note: str = "") -> Identifiability:
        return Identifiability(kind, p, q, True, method, function, min_frames, "", note)

    if lo == 0:
        side = "parent" if p == 0 else "child"
        return no(
            f"{kind} joint with {pair} markers: the {side} link carries no marker, so nothing about the joint "
            "is observed; put at least 2 markers on each link (spherical) or 2 + 1 (revolute)"
        )
    if hi >= 3 and lo >= 3:
        return yes(
            "two-segment",
            "fit_centre_two_segments" if kind == "spherical" else "fit_axis_two_segments",
            3,
            "the ordinary case: both links have full frames; the minimal-marker methods also work",
        )
    if kind == "spherical":
        if hi >= 3:  # (>=3, 1 or 2)
            return yes(
                "S31",
                "fit_centre_minimal",
                4,
                f"section IV-A: the link with {hi} markers has a full frame, in which each marker of the other "
                "link moves on a sphere about the centre; 4 non-coplanar samples fix it. Degenerate when the "
                "samples are coplanar (rotation about a single axis)",
            )
        if lo == 2:  # (2, 2)
            return yes(
                "S22",
                "fit_centre_minimal",
                9,
                "section IV-C / V-A (S22): the centre keeps constant distances (d, r) from the parent pair's axis "
                "and rho1, rho2 from the two child markers; degenerate when the child only rotates about one "
                "axis relative to the parent",
            )
        lost = (
            "section IV-B: the link with 2 markers fixes the centre only on a circle of radius r about their "
            "axis (its rotation about that axis is not observed), and the single marker only its distance rho "
            "from the centre; shrinking the circle by delta and growing rho by delta (r' = r - delta, "
            "rho' = rho + delta) explains exactly the same data, so one degree of freedom is lost"
            if hi == 2
            else "with one marker per link only the distance between the two markers is observed; even (2, 1) "
            "is not identifiable (section IV-B, Remark 1)"
        )
        return no(
            f"spherical joint with {pair} markers is not identifiable: {lost}. Add a marker: 2 + 2 (S22, "
            "fit_centre_minimal) or 3 + 1 (S31, fit_centre_minimal) is the minimum"
        )
    # revolute
    if hi >= 3:  # (>=3, 1 or 2)
        return yes(
            "R31",
            "fit_axis_two_segments" if lo >= 3 else "fit_axis",
            3,
            f"the link with {hi} markers has a full frame, in which the other link's markers move on coaxial "
            "circles (express them in that frame and use fit_axis)",
        )
    if hi == 2:  # (2, 1) or (2, 2)
        note = (
            "section III-A (R21): the hinge is fixed by the constants (d, r, alpha) of its line relative to the "
            "pair's axis and (l, rho) of the single marker's circle. The data fix these only up to a discrete "
            "ambiguity: generically two different hinges and their mirror images fit exactly, so give "
            "fit_axis_minimal an axis_hint (or add a fourth marker: (2, 2) resolves it)"
            if lo == 1
            else "follows from (2, 1) (Remark 1); the fourth marker also removes the discrete ambiguity of (2, 1)"
        )
        return yes("R21", "fit_axis_minimal", 5, note)
    return no(
        f"revolute joint with {pair} markers is not identifiable: section III-B: only the distance r of the "
        "parent marker and rho of the child marker from the axis are constant, and r' = r - delta, "
        "rho' = rho + delta explain exactly the same data, so one degree of freedom is lost. Add a marker: "
        "2 + 1 (R21, fit_axis_minimal) is the minimum"
    )


def marker_count_identifiability(kind: str, n_parent: int, n_child: int) -> Identifiability:
    """Whether ``n_parent`` + ``n_child`` markers can identify a joint, and how.

    Parameters
    ----------
    kind : {"spherical", "revolute"}
        Joint type (``"ball"`` and ``"hinge"`` are accepted aliases).
    n_parent, n_child : int
        Number of markers on each link (>= 0). The verdict is symmetric:
        ``(p, q)`` and ``(q, p)`` are alike.

    Returns
    -------
    Identifiability
        The verdict, the applicable method and function, the frames needed
        without noise, and the reason (if not identifiable) or caveats.

    Raises
    ------
    InputError
        Unknown ``kind`` or a count that is not an integer >= 0.

    Notes
    -----
    Pham, Ayusawa, Kubota & Nakamura, "On the structural identifiability of
    joint parameters from motion capture data": revolute (2, 1) is
    5-identifiable (section III-A) and (1, 1) is not (III-B); spherical
    (3, 1) is 4-identifiable (IV-A), (2, 1) is not (IV-B) and (2, 2) is
    9-identifiable (IV-C). Remark 1 gives the symmetry and the monotonicity
    in the counts. See the module docstring for the discrete ambiguity of
    revolute (2, 1) that the paper's uniqueness argument misses.
    """
    return _verdict(_check_kind(kind), _check_count(n_parent, "n_parent"), _check_count(n_child, "n_child"))


def check_marker_counts(kind: str, n_parent: int, n_child: int) -> Identifiability:
    """Raise :class:`NotIdentifiableError` unless the marker counts can identify the joint.

    Parameters
    ----------
    kind : {"spherical", "revolute"}
        Joint type (``"ball"``, ``"hinge"`` accepted).
    n_parent, n_child : int
        Number of markers on each link.

    Returns
    -------
    Identifiability
        The verdict (always identifiable) with the method to use.

    Raises
    ------
    NotIdentifiableError
        The counts cannot identify the joint; the message says which degree
        of freedom is lost and how many markers to add.
    InputError
        Unknown ``kind`` or a bad count.
    """
    verdict = marker_count_identifiability(kind, n_parent, n_child)
    if not verdict.identifiable:
        raise NotIdentifiableError(verdict.reason)
    return verdict
