"""Markers that do not move with their segment's cluster: a label on the wrong segment.

Pure numpy. A segment's markers keep their mutual distances whatever the
segment does: exactly on a rigid body, within the cluster's deformation on
skin. A marker that belongs to another segment (a label swapped across
segments in the capture software, a marker listed under the wrong segment)
changes its distances to the others as the joint between the two segments
moves. The pose fit cannot say which marker it is: a four-marker rigid fit
spreads the misfit over all four, the pooled residual only grows, and the
joint's covariance widens with it, so the joint is published with a wide
covariance and nothing names the cause (measured on the lower-body skin
skeleton with PELV1 and RTHI1 swapped: the left hip 27-31 mm off at e/3 0.5-0.65,
status OK; the right hip "not identifiable").

The pairwise distances can say it. For every segment of at least three markers,
the standard deviation over frames of every pair's distance is taken (its
glitches left out: :data:`GLITCH_MADS`); the marker whose removal leaves the
rest most rigid is *odd* when the segment's largest pair sd is at least
:data:`ODD_RATIO` times what is left without it, and at least ``floor`` (a
still stance or a rigid cluster's noise never is).

Measured (``skeleton_skin_frames``, lower body, 30 s, seeds 0-1), as the largest pair
sd with all markers against without the odd candidate:

- no swap, the literature's skin artefact (thigh 10 mm): ratios 1.1-2.0 (largest
  sd 2.2-10.3 mm); twice that artefact: 1.1-2.0 (up to 20.5 mm);
- one marker swapped between pelvis and thigh, thigh and shank, shank and foot,
  or the two thighs: ratios 4.3-9.2 in the segments holding a foreign marker
  (18.5-37.3 mm), but for a shank marker near the knee in the thigh cluster (9 mm,
  ratio 1.7: within the thigh's own deformation, and as small an effect on the
  joints); at twice the artefact 3.1-8.4, but 2.0 in one thigh holding a pelvis
  marker (the pelvis holding the thigh's marker read 5.0 there).
- Every swap of one marker between two segments of the skin skeletons (lower body
  42 and full body 182 per seed, seeds 0-1): both segments named in 36/36 and
  166/169, one of them in 5-10, neither in 0-1 (lower) and 6 (full: pelvis-trunk
  and forearm-hand, whose markers move least relative to each other). Rigid
  clusters at the rigid floor: both named in every swap.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["GLITCH_MADS", "ODD_RATIO", "ClusterPairs", "ClusterRigidity", "OddMarker", "odd_markers"]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: The odd marker's verdict: the segment's largest pair-distance sd over the largest without that marker.
#: Skin clusters read at most 2.0 (deformation alone, see the module notes); a foreign marker 3.1-9.2.
ODD_RATIO = 3.0
#: Fewest frames with both markers of a pair seen for its sd to count.
MIN_PAIR_FRAMES = 100
#: A pair's distance farther than this many robust sds (1.4826 MAD) from its median is a glitch, left out of its
#: sd: a corrupt value (a driver's 1e7 for a lost marker named the marker as not moving with its segment), a
#: ghost or a few frames' swap. A marker's distance that follows the joint angle, or the skin's deformation,
#: stays within ~1.5 of them (a sinusoid's extremes), and a rigid pair's noise within ~5.
GLITCH_MADS = 10.0


@dataclass(frozen=True)
class OddMarker:
    """A segment's marker that does not keep its distances to the others.

    Attributes
    ----------
    segment : int
        The segment's position in the list given to :class:`ClusterPairs`.
    marker : int
        The marker's position in that segment's list.
    spread : float
        The segment's largest pair-distance sd over frames (input units).
    without : float
        The largest pair-distance sd among the segment's other markers (input units).
    """

    segment: int
    marker: int
    spread: float
    without: float


class ClusterPairs:
    """Every pair of markers within each segment, as rows of the marker frame.

    Parameters
    ----------
    segments : sequence of sequence of int
        Each segment's markers, as rows of the marker frame ``(P, 3)``.
        Segments of fewer than three markers take no part (no marker can be
        told from the other).
    """

    def __init__(self, segments: Sequence[Sequence[int]]) -> None:
        self.segments = [tuple(int(m) for m in s) for s in segments]
        first: list[int] = []
        second: list[int] = []
        owner: list[int] = []
        for k, rows in enumerate(self.segments):
            if len(rows) < 3:
                continue
            a, b = np.triu_indices(len(rows), 1)
            first.extend(rows[i] for i in a)
            second.extend(rows[j] for j in b)
            owner.extend([k] * a.size)
        self.first: IntArray = np.asarray(first, dtype=np.intp)
        self.second: IntArray = np.asarray(second, dtype=np.intp)
        self.owner: IntArray = np.asarray(owner, dtype=np.intp)

    @property
    def n_pairs(self) -> int:
        """Number of pairs ``Q`` over all segments."""
        return int(self.first.size)

    def distances(self, frames: FloatArray) -> FloatArray:
        """Every pair's distance in each frame.

        Parameters
        ----------
        frames : ndarray, shape (K, P, 3)
            Marker frames (input units; NaN where a marker is missing).

        Returns
        -------
        ndarray, shape (K, Q)
            Distances (input units; NaN where a marker of the pair is missing).
        """
        diff = frames[:, self.first] - frames[:, self.second]
        return np.sqrt(np.einsum("kqi,kqi->kq", diff, diff))

    def spread(self, distances: FloatArray, min_frames: int = MIN_PAIR_FRAMES) -> FloatArray:
        """Every pair's distance sd over frames, NaN where fewer than ``min_frames`` frames saw both markers.

        Parameters
        ----------
        distances : ndarray, shape (K, Q)
            :meth:`distances` of ``K`` frames.
        min_frames : int

        Returns
        -------
        ndarray, shape (Q,)
            Input units.
        """
        seen = np.isfinite(distances)
        if seen.any():  # glitches (a ghost, a few frames' swap, a corrupt value) are not the pair's spread
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # (all-NaN pairs: NaN, left out below)
                med = np.nanmedian(distances, axis=0)
                off = np.abs(distances - med)
                mad = np.nanmedian(off, axis=0)
            with np.errstate(invalid="ignore"):
                seen &= off <= GLITCH_MADS * 1.4826 * mad
        n = seen.sum(axis=0)
        d = np.where(seen, distances, 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = d.sum(axis=0) / n
            var = np.where(seen, (d - mean) ** 2, 0.0).sum(axis=0) / (n - 1)
        out = np.sqrt(np.maximum(var, 0.0))
        out[n < max(min_frames, 2)] = np.nan
        return out


def odd_markers(
    pairs: ClusterPairs, spread: FloatArray, floor: float | Sequence[float], ratio: float = ODD_RATIO
) -> list[OddMarker]:
    """The segments' odd markers: one per segment at most, in segment order.

    Parameters
    ----------
    pairs : ClusterPairs
    spread : ndarray, shape (Q,)
        :meth:`ClusterPairs.spread` (NaN pairs are left out).
    floor : float or sequence of float
        Smallest largest-pair sd that counts (input units; one for all
        segments or one per segment): below it the segment moved too little,
        or its markers are too rigid, to tell.
    ratio : float
        The largest pair sd over the largest without the marker (:data:`ODD_RATIO`).

    Returns
    -------
    list of OddMarker
        A segment's odd marker is the one whose removal leaves the smallest
        largest-pair sd, reported when the segment's largest is at least
        ``floor`` and ``ratio`` times that.

    Notes
    -----
    Distances between markers do not depend on the frame they are measured in,
    on the segment's pose, or on the order of its markers.
    """
    floors = np.broadcast_to(np.asarray(floor, dtype=np.float64), (len(pairs.segments),))
    out = []
    for k, rows in enumerate(pairs.segments):
        mine = pairs.owner == k
        sd = spread[mine]
        if len(rows) < 3 or not np.isfinite(sd).any():
            continue
        total = float(np.nanmax(sd))
        if total < floors[k]:
            continue
        first, second = pairs.first[mine], pairs.second[mine]
        without = []
        for m in rows:
            keep = (first != m) & (second != m) & np.isfinite(sd)
            without.append(float(sd[keep].max()) if keep.any() else np.inf)
        best = int(np.argmin(without))
        if total >= ratio * without[best]:
            out.append(OddMarker(k, best, total, without[best]))
    return out


class ClusterRigidity:
    """The recent pair distances of a stream's segments, sampled at most every ``every_s`` seconds.

    What a live node keeps to say which marker does not move with its
    segment: a ring of ``samples`` rows of :meth:`ClusterPairs.distances`,
    one per ``every_s`` of stamps (the first frame in each interval), so that
    per-message and block feeding keep the same rows, whatever the frame rate.

    Parameters
    ----------
    segments : sequence of sequence of int
        As for :class:`ClusterPairs`.
    floor : float or sequence of float
        :func:`odd_markers`'s ``floor`` (input units; one per segment or one for all).
    every_s : float
        Seconds of stamps between two samples (default 0.02: 50 per second).
    samples : int
        Rows kept (default 1000: the last 20 s at ``every_s`` 0.02).
    """

    def __init__(
        self, segments: Sequence[Sequence[int]], floor: float | Sequence[float], every_s: float = 0.02,
        samples: int = 1000,
    ) -> None:
        self.pairs = ClusterPairs(segments)
        self.floor = floor
        self._every_ns = max(round(every_s * 1e9), 1)
        self._ring = np.full((samples, self.pairs.n_pairs), np.nan)
        self._rows = 0  # rows written so far (the next goes to _rows % samples)
        self._last_bin: int | None = None
        self._verdict: tuple[int, list[OddMarker]] = (-1, [])

    def add(self, stamps_ns: NDArray[np.int64], frames: FloatArray) -> None:
        """Take the frames that open a new sampling interval.

        Parameters
        ----------
        stamps_ns : ndarray of int, shape (K,)
            The frames' times (ns, increasing).
        frames : ndarray, shape (K, P, 3)
        """
        if not self.pairs.n_pairs or not len(stamps_ns):
            return
        if len(stamps_ns) == 1 and int(stamps_ns[0]) // self._every_ns == self._last_bin:
            return  # a live frame within the interval already sampled (most of them)
        bins = np.asarray(stamps_ns, dtype=np.int64) // self._every_ns
        new = np.empty(bins.size, dtype=bool)
        new[0] = self._last_bin is None or bins[0] != self._last_bin
        new[1:] = bins[1:] != bins[:-1]
        self._last_bin = int(bins[-1])
        if not new.any():
            return
        taken = int(np.count_nonzero(new))
        rows = self.pairs.distances(frames[new])[-self._ring.shape[0]:]  # more than the ring holds: the last
        at = (self._rows + taken - rows.shape[0] + np.arange(rows.shape[0])) % self._ring.shape[0]
        self._ring[at] = rows
        self._rows += taken

    def clear(self) -> None:
        """Forget the samples (after a reset)."""
        self._ring[:] = np.nan
        self._rows = 0
        self._last_bin = None
        self._verdict = (-1, [])

    def odd_markers(self) -> list[OddMarker]:
        """:func:`odd_markers` of the samples kept (taken again only after new samples)."""
        if self._verdict[0] != self._rows:
            spread = self.pairs.spread(self._ring[: min(self._rows, self._ring.shape[0])])
            self._verdict = (self._rows, odd_markers(self.pairs, spread, self.floor))
        return self._verdict[1]
