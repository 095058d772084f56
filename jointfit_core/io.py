"""Read and write marker trajectories: C3D (through ``ezc3d``) and OpenSim TRC.

Every reader returns a :class:`MarkerData`: markers as a ``(N, P, 3)`` float64
array (time first, NaN for a missing marker), their labels, the frame rate and
the length unit the file declares. Nothing is converted on reading; call
:meth:`MarkerData.to_units` to change units.
"""

from __future__ import annotations

import math
import os
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import InputError, MissingDependencyError

__all__ = ["MarkerData", "marker_name", "read_c3d", "read_trc", "trc_text", "write_trc"]

#: Metres per unit, for :meth:`MarkerData.to_units`.
_METRES_PER_UNIT: dict[str, float] = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}
#: The length units of marker files, in metres.
METRES_PER_UNIT = _METRES_PER_UNIT

_TRC_KEYS = (
    "DataRate",
    "CameraRate",
    "NumFrames",
    "NumMarkers",
    "Units",
    "OrigDataRate",
    "OrigDataStartFrame",
    "OrigNumFrames",
)


def marker_name(label: str) -> str:
    """A label's marker name: without its subject prefix (``RTHI1`` for Vicon Nexus's ``Subject01:RTHI1``)."""
    return label.rpartition(":")[2]


@dataclass(frozen=True)
class MarkerData:
    """Marker trajectories of one recording.

    Parameters
    ----------
    markers : array_like, shape (N, P, 3)
        Marker positions in ``units``, time first, then marker, then xyz.
        NaN marks a missing marker; a marker with any NaN coordinate is stored
        with all three NaN. Stored as a read-only float64 copy.
    labels : sequence of str, length P
        Marker names, in the order of axis 1 of ``markers``.
    rate : float
        Frame rate, Hz (finite, > 0).
    units : str
        Length unit of ``markers`` as the file declares it (e.g. ``'mm'``, ``'m'``).
    first_frame : int
        Index of the first frame in the original recording, 0-based
        (a C3D or TRC file that starts at its frame 1 gives 0).

    Raises
    ------
    InputError
        Wrong shape, infinite values, a label count that does not match P,
        or a rate that is not a finite positive number.
    """

    markers: NDArray[np.float64]
    labels: tuple[str, ...]
    rate: float
    units: str
    first_frame: int = 0

    def __post_init__(self) -> None:
        try:
            arr = np.array(self.markers, dtype=np.float64, copy=True)
        except (TypeError, ValueError) as exc:
            raise InputError(
                f"markers: expected a numeric array of shape (N, P, 3), "
                f"got {type(self.markers).__name__}: {exc}"
            ) from None
        if arr.ndim != 3 or arr.shape[2] != 3:
            raise InputError(
                f"markers: expected shape (N, P, 3) (frames, markers, xyz), got shape {arr.shape}"
            )
        if np.isinf(arr).any():
            raise InputError("markers: contains inf; use NaN for missing markers")
        arr[np.isnan(arr).any(axis=2)] = np.nan
        arr.setflags(write=False)
        if isinstance(self.labels, str):
            raise InputError(f"labels: expected a sequence of str, got the single str {self.labels!r}")
        labels = tuple(self.labels)
        if not all(isinstance(label, str) for label in labels):
            raise InputError(f"labels: expected str labels, got {[type(lab).__name__ for lab in labels]}")
        if len(labels) != arr.shape[1]:
            raise InputError(
                f"labels: expected {arr.shape[1]} labels (one per marker, axis 1 of markers), "
                f"got {len(labels)}"
            )
        try:
            rate = float(self.rate)
        except (TypeError, ValueError):
            raise InputError(
                f"rate: expected a positive number of frames per second, got {self.rate!r}"
            ) from None
        if not math.isfinite(rate) or rate <= 0.0:
            raise InputError(f"rate: expected a finite frame rate > 0 Hz, got {rate!r}")
        if not isinstance(self.units, str):
            raise InputError(f"units: expected a str such as 'mm' or 'm', got {self.units!r}")
        if isinstance(self.first_frame, bool) or not isinstance(self.first_frame, (int, np.integer)):
            raise InputError(f"first_frame: expected an int, got {self.first_frame!r}")
        object.__setattr__(self, "markers", arr)
        object.__setattr__(self, "labels", labels)
        object.__setattr__(self, "rate", rate)
        object.__setattr__(self, "first_frame", int(self.first_frame))

    @property
    def n_frames(self) -> int:
        """Number of frames N."""
        return int(self.markers.shape[0])

    @property
    def times(self) -> NDArray[np.float64]:
        """Time of each frame, s, shape (N,), starting at 0 for the first frame read."""
        return np.arange(self.n_frames, dtype=np.float64) / self.rate

    def select(self, names: Sequence[str]) -> NDArray[np.float64]:
        """Return the trajectories of the named markers.

        Parameters
        ----------
        names : sequence of str, length K
            Labels to take, in the wanted order; a name without the subject prefix of a label
            (``RTHI1`` for ``Subject:RTHI1``) takes that label when only one has it.

        Returns
        -------
        ndarray, shape (N, K, 3), float64
            A writable copy, in ``units``; NaN where a marker is missing.

        Raises
        ------
        InputError
            ``names`` is a single str, a label is not in the data (the message
            lists the missing and the available labels), or a label appears
            more than once in the data.
        """
        if isinstance(names, str):
            raise InputError(
                f"names: expected a sequence of labels, got the single str {names!r}; use [{names!r}]"
            )
        wanted = [self._label_of(name) for name in names]
        missing = [name for name, label in zip(names, wanted, strict=True) if label not in self.labels]
        if missing:
            raise InputError(f"markers not found: {missing}; available labels: {list(self.labels)}")
        ambiguous = sorted({name for name in wanted if self.labels.count(name) > 1})
        if ambiguous:
            raise InputError(f"labels appear more than once in the data, cannot select: {ambiguous}")
        index = [self.labels.index(name) for name in wanted]
        return np.array(self.markers[:, index, :], dtype=np.float64, copy=True)

    def _label_of(self, name: str) -> str:
        """The file's label for ``name``: itself, or the one label that is ``name`` with a subject prefix.

        Vicon Nexus writes ``Subject:RTHI1`` when the trial holds a labelled subject; a configuration
        names ``RTHI1``. Two subjects (``Ann:RTHI1``, ``Bob:RTHI1``) are ambiguous: the name is left as
        it is (not found), and the error lists the labels.
        """
        if name in self.labels:
            return name
        prefixed = [label for label in self.labels if ":" in label and marker_name(label) == name]
        return prefixed[0] if len(prefixed) == 1 else name

    def to_units(self, units: str) -> MarkerData:
        """Return the same data expressed in another length unit.

        Parameters
        ----------
        units : {'mm', 'cm', 'm'}
            Target unit.

        Returns
        -------
        MarkerData
            A new object with the markers scaled; ``self`` when the units are already ``units``.

        Raises
        ------
        InputError
            ``units`` or the data's own units are not one of 'mm', 'cm', 'm'.
        """
        if units not in _METRES_PER_UNIT:
            raise InputError(f"units: expected one of {sorted(_METRES_PER_UNIT)}, got {units!r}")
        if self.units == units:
            return self
        if self.units not in _METRES_PER_UNIT:
            raise InputError(
                f"cannot convert from the data's units {self.units!r}: "
                f"expected one of {sorted(_METRES_PER_UNIT)}"
            )
        scale = _METRES_PER_UNIT[self.units] / _METRES_PER_UNIT[units]
        return MarkerData(
            markers=self.markers * scale,
            labels=self.labels,
            rate=self.rate,
            units=units,
            first_frame=self.first_frame,
        )


def _check_existing_file(path: str | os.PathLike[str]) -> Path:
    """Return ``path`` as a Path after checking it names an existing regular file."""
    try:
        file = Path(path)
    except TypeError:
        raise InputError(f"path: expected a str or os.PathLike, got {type(path).__name__}") from None
    if not file.exists():
        raise InputError(f"no such file: {file}")
    if not file.is_file():
        raise InputError(f"not a regular file: {file}")
    return file


def _c3d_labels(point_group: dict[str, Any], n_points: int, file: Path) -> tuple[str, ...]:
    """Labels of the C3D POINT group, following LABELS2, LABELS3, ... for more than 255 points."""
    labels: list[str] = []
    key_index = 1
    while len(labels) < n_points:
        key = "LABELS" if key_index == 1 else f"LABELS{key_index}"
        if key not in point_group:
            break
        labels.extend(str(label).strip() for label in point_group[key]["value"])
        key_index += 1
    if len(labels) < n_points:
        raise InputError(f"{file}: expected {n_points} POINT labels (one per point), got {len(labels)}")
    return tuple(labels[:n_points])


def _c3d_header_frames(file: Path) -> int:
    """Frames the C3D header block declares (words 4-5: first and last frame), 0 when unknown.

    ezc3d reads what a cut file holds and adjusts its parsed header (and
    POINT:FRAMES) to that, so a truncated file is only recognised from the
    raw header. Both byte orders are tried (Intel/DEC files are
    little-endian, MIPS big-endian); the 16-bit last frame of files with more
    than 65535 frames is not trusted.
    """
    try:
        with open(file, "rb") as fh:
            head = fh.read(10)
    except OSError:
        return 0
    if len(head) < 10 or head[1] != 0x50:
        return 0
    for order in ("<", ">"):
        first, last = struct.unpack(f"{order}2H", head[6:10])
        if 1 <= first <= last < 65535:
            return last - first + 1
    return 0


def read_c3d(path: str | os.PathLike[str]) -> MarkerData:
    """Read the marker (POINT) trajectories of a C3D file.

    Parameters
    ----------
    path : str or os.PathLike
        The C3D file.

    Returns
    -------
    MarkerData
        ``markers`` of shape (N, P, 3) in the file's POINT:UNITS (not
        converted), labels from POINT:LABELS (whitespace stripped), rate from
        POINT:RATE in Hz, ``first_frame`` 0-based from the header.

    Raises
    ------
    InputError
        The file does not exist, is not a readable C3D file, or its POINT
        group is inconsistent (label count, rate).
    MissingDependencyError
        ``ezc3d`` is not installed.

    Notes
    -----
    A marker is missing (NaN) in a frame when any of its coordinates is NaN,
    when its residual is negative (the C3D convention for an invalid sample)
    or when it sits exactly at (0, 0, 0), which several exporters write for
    gaps.
    """
    file = _check_existing_file(path)
    try:
        import ezc3d
    except ImportError:
        raise MissingDependencyError("reading C3D needs ezc3d: pip install 'jointfit[c3d]'") from None
    try:
        c3d = ezc3d.c3d(str(file))
    except Exception as exc:  # ezc3d raises OSError, RuntimeError, ... on corrupt files
        raise InputError(f"{file}: not a readable C3D file ({type(exc).__name__}: {exc})") from None

    points = np.asarray(c3d["data"]["points"], dtype=np.float64)
    if points.ndim != 3 or points.shape[0] < 3:
        raise InputError(f"{file}: expected POINT data of shape (4, P, N), got shape {points.shape}")
    declared = _c3d_header_frames(file)
    if declared > points.shape[2]:
        raise InputError(f"{file}: truncated: its header declares {declared} frames, the file holds {points.shape[2]}")
    markers = np.ascontiguousarray(points[:3].transpose(2, 1, 0))  # (N, P, 3)
    missing = np.isnan(markers).any(axis=2) | (markers == 0.0).all(axis=2)
    residuals = c3d["data"].get("meta_points", {}).get("residuals")
    if residuals is not None:
        res = np.asarray(residuals, dtype=np.float64)
        if res.ndim == 3 and res.shape[1:] == points.shape[1:]:
            missing |= res[0].T < 0.0
    markers[missing] = np.nan
    _check_plausible(markers, file)

    group = c3d["parameters"].get("POINT", {})
    labels = _c3d_labels(group, markers.shape[1], file)
    rate_values = list(group.get("RATE", {}).get("value", []))
    rate = float(rate_values[0]) if rate_values else float(c3d["header"]["points"]["frame_rate"])
    if not math.isfinite(rate) or rate <= 0.0:
        raise InputError(f"{file}: expected a POINT:RATE > 0 Hz, got {rate!r}")
    unit_values = list(group.get("UNITS", {}).get("value", []))
    units = str(unit_values[0]).strip() if unit_values else ""
    first_frame = int(c3d["header"]["points"]["first_frame"])
    return MarkerData(markers=markers, labels=labels, rate=rate, units=units, first_frame=first_frame)


#: No marker coordinate of a recording is this large in any unit (1e12 mm is 1e6 km): a broken value.
ABSURD_COORDINATE = 1e12


def _check_plausible(markers: NDArray[np.float64], file: Path, rows: list[tuple[int, str]] | None = None) -> None:
    """Refuse a recording with an absurd coordinate (e.g. 1e300), naming the frame (the TRC line) and the marker."""
    with np.errstate(invalid="ignore"):
        bad = np.abs(markers) > ABSURD_COORDINATE
    if not bad.any():
        return
    frame, marker, axis = (int(v) for v in np.argwhere(bad)[0])
    where = f"line {rows[frame][0]}" if rows is not None else f"frame {frame}"
    raise InputError(
        f"{file}, {where}: marker {marker} has the coordinate {markers[frame, marker, axis]:.3g}, beyond any "
        f"capture volume (|x| > {ABSURD_COORDINATE:g})"
    )


def _split_trc_row(line: str) -> list[str]:
    """Split one TRC line into cells (tab separated; whitespace when there is no tab)."""
    line = line.rstrip("\r\n")
    return line.split("\t") if "\t" in line else line.split()


def _trc_number(cell: str, what: str, file: Path, line_no: int) -> float:
    try:
        return float(cell)
    except ValueError:
        raise InputError(f"{file}, line {line_no}: expected a number for {what}, got {cell!r}") from None


def read_trc(path: str | os.PathLike[str]) -> MarkerData:
    """Read an OpenSim TRC marker file.

    Parameters
    ----------
    path : str or os.PathLike
        The TRC file: a ``PathFileType`` line, a line of keys (DataRate,
        CameraRate, NumFrames, NumMarkers, Units, ...), their values, the
        ``Frame#  Time  M1      M2 ...`` names row, the ``X1 Y1 Z1 ...`` row,
        then one row per frame. Cells are tab separated; an empty cell is a
        missing coordinate.

    Returns
    -------
    MarkerData
        ``markers`` of shape (NumFrames, NumMarkers, 3) in the file's Units,
        rate from DataRate in Hz, ``first_frame`` = (Frame# of the first row) - 1.

    Raises
    ------
    InputError
        The file does not exist, is not text, lacks a header key, or its rows
        do not match NumFrames / NumMarkers or hold non-numeric values.
    """
    file = _check_existing_file(path)
    try:
        lines = file.read_text(encoding="utf-8-sig").splitlines()  # a byte-order mark (Windows editors) is no text
    except UnicodeDecodeError:
        raise InputError(f"{file}: expected a UTF-8 text TRC file, got undecodable bytes") from None
    if len(lines) < 5 or not lines[0].startswith("PathFileType"):
        first = lines[0][:40] if lines else ""
        raise InputError(f"{file}: expected a TRC file starting with 'PathFileType', got {first!r}")
    keys = [cell.strip() for cell in _split_trc_row(lines[1])]
    values = [cell.strip() for cell in _split_trc_row(lines[2])]
    header = dict(zip(keys, values, strict=False))  # trailing cells may be missing
    for key in ("DataRate", "NumFrames", "NumMarkers", "Units"):
        if key not in header:
            raise InputError(f"{file}: expected the header key {key!r} on line 2, got keys {keys}")
    rate = _trc_number(header["DataRate"], "DataRate", file, 3)
    n_frames_f = _trc_number(header["NumFrames"], "NumFrames", file, 3)
    n_markers_f = _trc_number(header["NumMarkers"], "NumMarkers", file, 3)
    if n_frames_f != int(n_frames_f) or n_frames_f < 0 or n_markers_f != int(n_markers_f) or n_markers_f < 0:
        raise InputError(
            f"{file}: expected integer NumFrames and NumMarkers, "
            f"got {header['NumFrames']!r}, {header['NumMarkers']!r}"
        )
    n_frames, n_markers = int(n_frames_f), int(n_markers_f)
    names = _split_trc_row(lines[3])
    if len(names) < 2 or names[0].strip() != "Frame#":
        raise InputError(
            f"{file}, line 4: expected the names row 'Frame#<TAB>Time<TAB>...', got {lines[3][:40]!r}"
        )
    labels = tuple(cell.strip() for cell in names[2:] if cell.strip())
    if len(labels) != n_markers:
        raise InputError(f"{file}, line 4: expected {n_markers} marker names (NumMarkers), got {len(labels)}")

    rows = [(line_no, line) for line_no, line in enumerate(lines[5:], start=6) if line.strip()]
    if len(rows) != n_frames:
        raise InputError(f"{file}: expected {n_frames} data rows (NumFrames), got {len(rows)}")
    markers = np.full((n_frames, n_markers, 3), np.nan)
    first_frame = 0
    for frame, (line_no, line) in enumerate(rows):
        cells = _split_trc_row(line)
        if len(cells) > 2 + 3 * n_markers and any(cell.strip() for cell in cells[2 + 3 * n_markers :]):
            raise InputError(
                f"{file}, line {line_no}: expected at most {2 + 3 * n_markers} cells "
                f"(Frame#, Time, 3 x {n_markers} markers), got {len(cells)}"
            )
        if frame == 0:
            first_frame = int(_trc_number(cells[0], "Frame#", file, line_no)) - 1
        coords = cells[2 : 2 + 3 * n_markers]
        if len(cells) < 2 + 3 * n_markers and (len(cells) - 2) % 3 and cells[-1].strip():
            raise InputError(
                f"{file}, line {line_no}: the row is cut short ({len(cells)} cells, {2 + 3 * n_markers} expected, "
                "the last marker incomplete)"
            )
        flat = markers[frame].reshape(-1)
        for k, cell in enumerate(coords):
            if cell.strip():
                flat[k] = _trc_number(cell, f"marker {labels[k // 3]!r}", file, line_no)
    if np.isinf(markers).any():
        raise InputError(f"{file}: contains inf; expected numbers or empty cells for missing markers")
    _check_frame_numbers(rows, first_frame, file)
    _check_plausible(markers, file, rows)
    return MarkerData(
        markers=markers, labels=labels, rate=rate, units=header["Units"], first_frame=first_frame
    )


def _check_frame_numbers(rows: list[tuple[int, str]], first_frame: int, file: Path) -> None:
    """Refuse a TRC whose Frame# column skips or repeats frames (the frames are taken one per row at DataRate).

    Frame# is only checked when every row's is a number: row ``k`` must be frame
    ``first_frame + 1 + k``. A file with rows left out would otherwise put every later frame
    at the wrong time, and the per-frame exports at the wrong frame numbers.
    """
    numbers = []
    for _, line in rows:
        cells = _split_trc_row(line)
        try:
            numbers.append(float(cells[0]))
        except (ValueError, IndexError):
            return
    expected = first_frame + 1 + np.arange(len(numbers))
    bad = np.flatnonzero(np.asarray(numbers) != expected)
    if bad.size:
        k = int(bad[0])
        raise InputError(
            f"{file}, line {rows[k][0]}: Frame# {numbers[k]:g} where the rows before it make it {expected[k]}: "
            "the file skips, repeats or reorders frames; rows are frames at DataRate, so write missing frames as rows "
            "with empty cells"
        )


def _trc_cell(value: float) -> str:
    """Format one coordinate for TRC: shortest round-trip repr, empty for NaN."""
    return "" if math.isnan(value) else repr(float(value))


def trc_text(data: MarkerData, name: str = "markers.trc") -> str:
    """The text of an OpenSim TRC file of ``data`` (what :func:`write_trc` writes).

    Parameters
    ----------
    data : MarkerData
        Markers of shape (N, P, 3) in ``data.units``. Missing markers (NaN)
        are written as empty cells. Coordinates are written with enough digits
        to read back exactly.
    name : str
        File name for the ``PathFileType`` line.

    Returns
    -------
    str

    Raises
    ------
    InputError
        ``data`` is not a MarkerData, or its units or labels are empty or
        contain a tab or a line break.

    Notes
    -----
    Frame# counts from ``data.first_frame + 1`` (TRC frames are 1-based) and
    Time from 0 s, so :func:`read_trc` gives back the same MarkerData.
    """
    if not isinstance(data, MarkerData):
        raise InputError(f"data: expected a MarkerData, got {type(data).__name__}")
    for what, text in [("units", data.units), *[("label", label) for label in data.labels]]:
        if not text or any(ch in text for ch in "\t\r\n") or text != text.strip():
            raise InputError(
                f"{what}: expected a non-empty name without tabs, line breaks or edge spaces, got {text!r}"
            )
    n_frames, n_markers, _ = data.markers.shape
    start = data.first_frame + 1
    values: list[object] = [
        f"{data.rate!r}",
        f"{data.rate!r}",
        n_frames,
        n_markers,
        data.units,
        f"{data.rate!r}",
        start,
        n_frames,
    ]
    out = [
        f"PathFileType\t4\t(X/Y/Z)\t{name}",
        "\t".join(_TRC_KEYS),
        "\t".join(str(value) for value in values),
        "\t".join(["Frame#", "Time", *[f"{label}\t\t" for label in data.labels]]).rstrip("\t"),
        "\t".join(["", "", *[f"X{i}\tY{i}\tZ{i}" for i in range(1, n_markers + 1)]]),
        "",
    ]
    times = data.times
    for frame in range(n_frames):
        cells = [str(start + frame), repr(float(times[frame]))]
        cells.extend(_trc_cell(v) for v in data.markers[frame].reshape(-1))
        out.append("\t".join(cells))
    return "\n".join(out) + "\n"


def write_trc(path: str | os.PathLike[str], data: MarkerData) -> None:
    """Write marker trajectories as an OpenSim TRC file (:func:`trc_text`).

    Parameters
    ----------
    path : str or os.PathLike
        Output file; overwritten if it exists.
    data : MarkerData
        Markers of shape (N, P, 3) in ``data.units``; NaN written as empty cells.

    Raises
    ------
    InputError
        As :func:`trc_text`.
    """
    file = Path(path)
    file.write_text(trc_text(data, file.name), encoding="utf-8")
