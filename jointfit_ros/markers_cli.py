"""``jointfit markers FILE``: what a recording holds, before writing a parameter file for it.

C3D and TRC: the labels (in file order, ready to paste into ``marker_names``),
the rate, the units, the frame count and each marker's gaps (frames missing,
longest run). A rosbag2 bag: its topics with their types and message counts.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from jointfit_core.errors import JointfitError
from jointfit_core.io import MarkerData, read_c3d, read_trc

__all__ = ["markers_main", "marker_gaps", "describe_markers", "marker_names_line"]

PROG = "jointfit markers"


def marker_gaps(markers: NDArray[np.float64]) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Per marker, the frames missing and the longest run of missing frames.

    Parameters
    ----------
    markers : ndarray, shape (N, P, 3)
        NaN = missing.

    Returns
    -------
    missing, longest : ndarray of int, shape (P,)
    """
    gone = np.isnan(markers).any(axis=2)  # (N, P)
    n, p = gone.shape
    longest = np.zeros(p, dtype=np.intp)
    if n:
        # run lengths of True per column: positions of the edges of each run
        padded = np.concatenate([np.zeros((1, p), bool), gone, np.zeros((1, p), bool)]).astype(np.int8)
        edges = np.diff(padded, axis=0)
        for k in range(p):  # one pass per marker of a file, not per frame
            starts, stops = np.flatnonzero(edges[:, k] == 1), np.flatnonzero(edges[:, k] == -1)
            if starts.size:
                longest[k] = int((stops - starts).max())
    return gone.sum(axis=0).astype(np.intp), longest


def marker_names_line(labels: Sequence[str]) -> str:
    """``marker_names: [...]`` as YAML that reads back as ``labels`` (a label such as ``#C7``, ``a, b`` or ``yes`` quoted)."""
    import yaml

    flow: str = yaml.safe_dump(list(labels), default_flow_style=True, width=1 << 20, allow_unicode=True)
    return f"marker_names: {flow.strip()}"


def describe_markers(data: MarkerData, path: Path) -> str:
    """The text of :func:`markers_main` for a C3D or TRC file."""
    missing, longest = marker_gaps(data.markers)
    seconds = data.n_frames / data.rate if data.rate > 0 else float("nan")
    lines = [
        f"{path}: {data.n_frames} frames at {data.rate:g} Hz ({seconds:.1f} s), units {data.units or '(none)'}, "
        f"{len(data.labels)} markers",
        marker_names_line(data.labels),
        "",
        f"{'marker':<24} {'missing frames':>14} {'%':>6} {'longest gap':>12}",
    ]
    for k, label in enumerate(data.labels):
        share = 100.0 * missing[k] / max(data.n_frames, 1)
        lines.append(f"{label:<24} {missing[k]:>14d} {share:>6.1f} {longest[k]:>12d}")
    return "\n".join(lines) + "\n"


def _describe_bag(path: Path) -> str:
    from .bag import bag_topics

    topics = bag_topics(path)
    lines = [f"{path}: {len(topics)} topic(s)", f"{'topic':<40} {'type':<36} {'messages':>9}"]
    for name, info in sorted(topics.items()):
        lines.append(f"{name:<40} {info.msgtype:<36} {info.count:>9d}")
    return "\n".join(lines) + "\n"


def markers_main(argv: Sequence[str]) -> int:
    """Run ``jointfit markers``; returns the exit status (0, 1 bad input, 2 bad arguments)."""
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("input", help="a .c3d or .trc file, or a rosbag2 bag (directory, .db3, .mcap)")
    try:
        opts = parser.parse_args(list(argv))
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else 2
    path = Path(opts.input)
    try:
        suffix = path.suffix.lower()
        if suffix == ".c3d":
            text = describe_markers(read_c3d(path), path)
        elif suffix == ".trc":
            text = describe_markers(read_trc(path), path)
        else:
            text = _describe_bag(path)
    except (JointfitError, OSError, ValueError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 1
    sys.stdout.write(text)
    return 0
