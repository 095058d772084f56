"""Marker-count identifiability rules (jointfit_core.identifiability; Pham et al. sections II-IV)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from jointfit_core import check_marker_counts, marker_count_identifiability
from jointfit_core.errors import InputError, NotIdentifiableError

IDENTIFIABLE = [
    ("spherical", 3, 1, "S31", 4),
    ("spherical", 1, 3, "S31", 4),
    ("spherical", 2, 2, "S22", 9),
    ("spherical", 3, 2, "S31", 4),
    ("spherical", 2, 3, "S31", 4),
    ("spherical", 3, 3, "two-segment", 3),
    ("spherical", 5, 4, "two-segment", 3),
    ("revolute", 2, 1, "R21", 5),
    ("revolute", 1, 2, "R21", 5),
    ("revolute", 2, 2, "R21", 5),
    ("revolute", 3, 1, "R31", 3),
    ("revolute", 4, 4, "two-segment", 3),
]

# (kind, p, q, phrases the message must contain)
NOT_IDENTIFIABLE = [
    ("spherical", 2, 1, ("IV-B", "r' = r - delta", "one degree of freedom is lost", "2 + 2", "3 + 1")),
    ("spherical", 1, 2, ("IV-B", "one degree of freedom is lost", "2 + 2", "3 + 1")),
    ("spherical", 1, 1, ("even (2, 1)", "2 + 2", "3 + 1")),
    ("revolute", 1, 1, ("III-B", "r' = r - delta", "one degree of freedom is lost", "2 + 1")),
    ("spherical", 0, 3, ("no marker", "parent")),
    ("spherical", 3, 0, ("no marker", "child")),
    ("revolute", 0, 2, ("no marker",)),
]


@pytest.mark.parametrize(("kind", "p", "q", "method", "min_frames"), IDENTIFIABLE)
def test_identifiable_counts(kind: str, p: int, q: int, method: str, min_frames: int) -> None:
    verdict = check_marker_counts(kind, p, q)
    assert verdict.identifiable
    assert verdict.reason == ""
    assert verdict.method == method
    assert verdict.min_frames == min_frames
    assert verdict.function
    assert (verdict.kind, verdict.n_parent, verdict.n_child) == (kind, p, q)


@pytest.mark.parametrize(("kind", "p", "q", "phrases"), NOT_IDENTIFIABLE)
def test_not_identifiable_counts_raise_with_explanation(kind: str, p: int, q: int, phrases: tuple[str, ...]) -> None:
    verdict = marker_count_identifiability(kind, p, q)
    assert not verdict.identifiable
    assert verdict.method == "" and verdict.function == "" and verdict.min_frames == 0
    for phrase in phrases:
        assert phrase in verdict.reason
    with pytest.raises(NotIdentifiableError) as info:
        check_marker_counts(kind, p, q)
    assert str(info.value) == verdict.reason
    assert isinstance(info.value, ValueError)  # callers catching ValueError see it too


@pytest.mark.parametrize("kind", ["spherical", "revolute"])
def test_symmetric_in_the_two_links(kind: str) -> None:
    for p, q in itertools.product(range(6), repeat=2):
        a, b = marker_count_identifiability(kind, p, q), marker_count_identifiability(kind, q, p)
        assert a.identifiable == b.identifiable
        assert a.method == b.method
        assert a.min_frames == b.min_frames


@pytest.mark.parametrize("kind", ["spherical", "revolute"])
def test_more_markers_never_hurt(kind: str) -> None:
    """Remark 1: identifiable (p, q) implies identifiable (p + 1, q)."""
    for p, q in itertools.product(range(6), repeat=2):
        if marker_count_identifiability(kind, p, q).identifiable:
            assert marker_count_identifiability(kind, p + 1, q).identifiable


def test_minimal_sets_are_minimal() -> None:
    """Removing any marker from a minimal identifiable set makes it non-identifiable (section V)."""
    for kind, p, q in (("spherical", 2, 2), ("spherical", 3, 1), ("revolute", 2, 1)):
        assert marker_count_identifiability(kind, p, q).identifiable
        assert not marker_count_identifiability(kind, p - 1, q).identifiable
        assert not marker_count_identifiability(kind, p, q - 1).identifiable


def test_revolute_21_notes_the_discrete_ambiguity() -> None:
    note = marker_count_identifiability("revolute", 2, 1).note
    assert "axis_hint" in note and "mirror" in note
    assert "removes the discrete ambiguity" in marker_count_identifiability("revolute", 2, 2).note


def test_aliases_and_numpy_counts() -> None:
    assert marker_count_identifiability("ball", np.int64(2), 2).kind == "spherical"
    assert marker_count_identifiability("Hinge", 2, np.int32(1)).kind == "revolute"


@pytest.mark.parametrize(
    ("kind", "p", "q"),
    [("prismatic", 2, 2), (3, 2, 2), ("spherical", -1, 2), ("spherical", 2, 1.5), ("revolute", True, 1), ("revolute", "2", 1)],
)
def test_bad_arguments_raise_input_error(kind: object, p: object, q: object) -> None:
    with pytest.raises(InputError):
        marker_count_identifiability(kind, p, q)  # type: ignore[arg-type]


def test_two_segment_fits_refuse_non_identifiable_counts_and_point_to_the_minimal_methods() -> None:
    """fit_centre_two_segments / fit_axis_two_segments apply the marker-count rules before anything else."""
    import numpy as np

    from jointfit_core import InputError, fit_axis_two_segments, fit_centre_two_segments

    rng = np.random.default_rng(0)
    markers = rng.normal(0.0, 100.0, (50, 4, 3))
    with pytest.raises(NotIdentifiableError, match=r"\(2, 1\) markers is not identifiable"):
        fit_centre_two_segments(markers[:, :2], markers[:, 2:3])
    with pytest.raises(NotIdentifiableError, match=r"\(1, 1\) markers is not identifiable"):
        fit_axis_two_segments(markers[:, :1], markers[:, 1:2])
    with pytest.raises(InputError, match="use fit_centre_minimal"):
        fit_centre_two_segments(markers[:, :2], markers[:, 2:4])
    with pytest.raises(InputError, match="use fit_axis_minimal"):
        fit_axis_two_segments(markers[:, :2], markers[:, 2:3])
