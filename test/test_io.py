"""Tests of the marker readers and writer (jointfit_core.io)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from jointfit_core.errors import InputError, MissingDependencyError
from jointfit_core.io import MarkerData, read_c3d, read_trc, write_trc

DATA = Path(__file__).parent / "data"
HIP = DATA / "biobuddy" / "right_hip.c3d"
KNEE = DATA / "biobuddy" / "right_knee.c3d"
RACING = DATA / "kineticstoolkit" / "kinematics_racing_full.c3d"

HIP_LABELS = (
    "RASIS", "LASIS", "RPSIS", "LPSIS", "RTHI1", "RTHI2", "RTHI3",
    "RGT", "RLFE", "RMFE", "RLEG1", "RLEG2", "RLEG3",
)  # fmt: skip


def _need_ezc3d() -> None:
    pytest.importorskip("ezc3d")


def _random_data(rng: np.random.Generator, n_frames: int = 20, n_markers: int = 4) -> MarkerData:
    markers = rng.normal(scale=300.0, size=(n_frames, n_markers, 3))
    markers[rng.random((n_frames, n_markers)) < 0.2] = np.nan
    labels = tuple(f"M{i}" for i in range(n_markers))
    return MarkerData(
        markers=markers, labels=labels, rate=float(rng.uniform(30, 250)), units="mm", first_frame=7
    )


# --- real fixtures ----------------------------------------------------------------------------------------


def test_read_right_hip() -> None:
    _need_ezc3d()
    data = read_c3d(HIP)
    assert data.markers.shape == (1690, 13, 3)
    assert data.markers.dtype == np.float64
    assert data.labels == HIP_LABELS
    assert data.rate == 100.0
    assert data.units == "mm"
    assert data.first_frame == 0
    assert not np.isnan(data.markers).any()
    np.testing.assert_allclose(data.times[[0, -1]], [0.0, 16.89])
    asis = data.select(["RASIS", "LASIS"])
    width = np.linalg.norm(asis[:, 0] - asis[:, 1], axis=1)
    assert 200.0 < np.median(width) < 240.0  # inter-ASIS distance in mm, ~217


def test_read_right_knee() -> None:
    _need_ezc3d()
    data = read_c3d(str(KNEE))
    assert data.markers.shape == (922, 16, 3)
    assert data.labels == (*HIP_LABELS, "RATT", "RLM", "RSPH")
    assert data.rate == 100.0
    assert data.units == "mm"
    assert not np.isnan(data.markers).any()


def test_read_racing_in_metres_with_gaps() -> None:
    _need_ezc3d()
    data = read_c3d(RACING)
    assert data.markers.shape == (700, 46, 3)
    assert data.rate == pytest.approx(69.9926, abs=1e-3)
    assert data.units == "m"
    for name in ("ArmR1", "ArmR2", "ArmR3", "ForearmR1", "ForearmR2", "ForearmR3", "LateralEpicondyleR"):
        assert name in data.labels
    present = np.asarray(~np.isnan(data.markers).any(axis=2))
    assert not present[:, data.labels.index("Probe1")].any()  # never recorded
    arm = data.select(["ArmR1", "ArmR2", "ArmR3"])
    assert not np.isnan(arm).any()
    spacing = np.linalg.norm(arm[:, 0] - arm[:, 1], axis=1)
    np.testing.assert_allclose(spacing, 0.043, atol=0.002)  # a rigid plate, metres
    # a marker is either fully present or fully NaN
    partial = np.isnan(data.markers).any(axis=2) & ~np.isnan(data.markers).all(axis=2)
    assert not partial.any()


# --- MarkerData -------------------------------------------------------------------------------------------


def test_select_order_shape_and_copy() -> None:
    data = _random_data(np.random.default_rng(1))
    out = data.select(["M2", "M0"])
    assert out.shape == (data.n_frames, 2, 3)
    np.testing.assert_array_equal(out[:, 0], data.markers[:, 2])
    np.testing.assert_array_equal(out[:, 1], data.markers[:, 0])
    out[:] = 0.0  # a copy: the data is unchanged
    assert not (data.markers[:, 2] == 0.0).all()


def test_select_missing_labels_are_named() -> None:
    data = _random_data(np.random.default_rng(2))
    with pytest.raises(InputError, match=r"not found: \['RASIS', 'XX'\].*available labels: \['M0', 'M1'"):
        data.select(["M1", "RASIS", "XX"])
    with pytest.raises(InputError, match="single str"):
        data.select("M1")


def test_select_duplicate_label_is_refused() -> None:
    data = MarkerData(np.zeros((2, 2, 3)), ("A", "A"), 100.0, "mm")
    with pytest.raises(InputError, match="more than once"):
        data.select(["A"])


def test_markers_are_read_only_and_nan_spreads_over_xyz() -> None:
    markers = np.ones((3, 2, 3))
    markers[1, 0, 2] = np.nan
    data = MarkerData(markers, ("A", "B"), 50.0, "mm")
    assert np.isnan(data.markers[1, 0]).all()
    assert not np.isnan(markers[1, 0, :2]).any()  # the input is not modified
    with pytest.raises(ValueError):
        data.markers[0, 0, 0] = 5.0


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"markers": np.zeros((3, 2))}, r"shape \(N, P, 3\)"),
        ({"markers": np.full((3, 2, 3), np.inf)}, "inf"),
        ({"labels": ("A",)}, "expected 2 labels"),
        ({"labels": "AB"}, "single str"),
        ({"rate": 0.0}, "rate"),
        ({"rate": float("nan")}, "rate"),
        ({"units": 1}, "units"),
        ({"first_frame": 1.5}, "first_frame"),
    ],
)
def test_markerdata_checks(kwargs: dict[str, object], message: str) -> None:
    args: dict[str, object] = {
        "markers": np.zeros((3, 2, 3)),
        "labels": ("A", "B"),
        "rate": 100.0,
        "units": "mm",
    }
    args.update(kwargs)
    with pytest.raises(InputError, match=message):
        MarkerData(**args)  # type: ignore[arg-type]


def test_times_start_at_zero() -> None:
    data = MarkerData(np.zeros((5, 1, 3)), ("A",), 50.0, "m", first_frame=100)
    np.testing.assert_allclose(data.times, [0.0, 0.02, 0.04, 0.06, 0.08])


def test_unit_conversion() -> None:
    data = _random_data(np.random.default_rng(3))
    metres = data.to_units("m")
    assert metres.units == "m"
    assert (metres.labels, metres.rate, metres.first_frame) == (data.labels, data.rate, data.first_frame)
    np.testing.assert_allclose(metres.markers, data.markers / 1000.0)
    assert np.array_equal(np.isnan(metres.markers), np.isnan(data.markers))
    np.testing.assert_allclose(metres.to_units("mm").markers, data.markers, rtol=1e-15)
    np.testing.assert_allclose(data.to_units("cm").markers, data.markers / 10.0)
    assert data.to_units("mm") is data
    with pytest.raises(InputError, match="expected one of"):
        data.to_units("inch")
    odd = MarkerData(np.zeros((1, 1, 3)), ("A",), 10.0, "")
    with pytest.raises(InputError, match="data's units ''"):
        odd.to_units("m")


def test_unit_conversion_of_real_file() -> None:
    _need_ezc3d()
    millimetres = read_c3d(RACING).to_units("mm")
    arm = millimetres.select(["ArmR1", "ArmR2"])
    np.testing.assert_allclose(np.linalg.norm(arm[:, 0] - arm[:, 1], axis=1), 43.0, atol=2.0)


# --- C3D specifics ----------------------------------------------------------------------------------------


def _write_synthetic_c3d(path: Path, points: np.ndarray, residuals: np.ndarray | None = None) -> None:
    import ezc3d

    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = [200.0]
    c3d["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = ("A ", " B", "C")
    c3d["header"]["points"]["first_frame"] = 9
    c3d["data"]["points"] = points
    if residuals is not None:
        n_points, n_frames = points.shape[1:]
        c3d["data"]["meta_points"] = {
            "residuals": residuals,
            "camera_masks": np.zeros((7, n_points, n_frames), dtype=bool),
        }
    c3d.write(str(path))


def test_c3d_zero_and_negative_residual_are_missing(tmp_path: Path) -> None:
    _need_ezc3d()
    rng = np.random.default_rng(4)
    points = np.ones((4, 3, 6))
    points[:3] = rng.normal(scale=100.0, size=(3, 3, 6))
    points[:3, 0, 1] = 0.0  # exactly (0, 0, 0): a gap written as zeros
    points[:3, 1, 2] = [0.0, 5.0, 0.0]  # a genuine position with zero coordinates: kept
    points[:3, 2, 4] = np.nan
    residuals = np.zeros((1, 3, 6))
    residuals[0, 2, 3] = -1.0
    path = tmp_path / "synthetic.c3d"
    _write_synthetic_c3d(path, points, residuals)

    data = read_c3d(path)
    assert data.labels == ("A", "B", "C")  # whitespace stripped
    assert (data.rate, data.units, data.first_frame) == (200.0, "mm", 9)
    assert data.markers.shape == (6, 3, 3)
    missing = np.isnan(data.markers).all(axis=2)
    expected = np.zeros((6, 3), dtype=bool)
    expected[1, 0] = expected[4, 2] = expected[3, 2] = True
    np.testing.assert_array_equal(missing, expected)
    np.testing.assert_allclose(data.markers[2, 1], [0.0, 5.0, 0.0])
    np.testing.assert_allclose(data.markers[~expected], points[:3].transpose(2, 1, 0)[~expected], rtol=1e-6)


def test_missing_file_gives_input_error(tmp_path: Path) -> None:
    path = tmp_path / "nothing_here.c3d"
    with pytest.raises(InputError, match=r"no such file: .*nothing_here\.c3d"):
        read_c3d(path)
    with pytest.raises(InputError, match=r"no such file: .*nothing_here\.trc"):
        read_trc(tmp_path / "nothing_here.trc")
    with pytest.raises(InputError, match="not a regular file"):
        read_c3d(tmp_path)


@pytest.mark.parametrize(
    "content", [b"", b"hello\n", bytes(np.random.default_rng(5).integers(0, 256, 3000, np.uint8))]
)
def test_garbage_file_gives_input_error(tmp_path: Path, content: bytes) -> None:
    _need_ezc3d()
    path = tmp_path / "garbage.c3d"
    path.write_bytes(content)
    with pytest.raises(InputError, match=r"garbage\.c3d"):
        read_c3d(path)
    with pytest.raises(InputError, match=r"garbage\.c3d"):
        read_trc(path)


def test_missing_ezc3d_raises_missing_dependency(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "ezc3d", None)  # makes `import ezc3d` raise ImportError
    with pytest.raises(MissingDependencyError, match=r"pip install 'jointfit\[c3d\]'"):
        read_c3d(HIP)


# --- TRC --------------------------------------------------------------------------------------------------


def test_trc_round_trip_with_nan(tmp_path: Path) -> None:
    rng = np.random.default_rng(6)
    for trial in range(5):
        data = _random_data(rng, n_frames=int(rng.integers(1, 40)), n_markers=int(rng.integers(1, 6)))
        path = tmp_path / f"trial{trial}.trc"
        write_trc(path, data)
        back = read_trc(path)
        np.testing.assert_array_equal(back.markers, data.markers)  # exact, NaN where NaN
        assert (back.labels, back.rate, back.units, back.first_frame) == (
            data.labels,
            data.rate,
            data.units,
            data.first_frame,
        )


def test_trc_with_a_byte_order_mark_reads_as_without(tmp_path: Path) -> None:
    """A TRC saved by a Windows editor starts with a UTF-8 byte-order mark: the same data, not a refusal.

    It was refused as not starting with 'PathFileType' (the mark shown as '\\ufeff').
    """
    data = _random_data(np.random.default_rng(7), n_frames=12, n_markers=3)
    plain, marked = tmp_path / "plain.trc", tmp_path / "marked.trc"
    write_trc(plain, data)
    marked.write_bytes(b"\xef\xbb\xbf" + plain.read_bytes())
    back = read_trc(marked)
    np.testing.assert_array_equal(back.markers, data.markers)
    assert (back.labels, back.rate, back.units, back.first_frame) == (data.labels, data.rate, data.units, data.first_frame)


def test_trc_whose_frame_numbers_skip_is_refused(tmp_path: Path) -> None:
    """Rows left out of a TRC (Frame# 1..100, then 151..) are refused, naming the line, not read as contiguous.

    The frames after the gap were taken 50 frames early: every later frame at the wrong time, and
    the fit's joints.csv / joints.trc numbered them 50 too low.
    """
    data = _random_data(np.random.default_rng(8), n_frames=200, n_markers=2)
    path = tmp_path / "full.trc"
    write_trc(path, data)
    lines = path.read_text().splitlines()
    header, rows = lines[:6], lines[6:]
    kept = rows[:100] + rows[150:]
    header[2] = header[2].replace("\t200\t2\t", f"\t{len(kept)}\t2\t", 1)
    gap = tmp_path / "gap.trc"
    gap.write_text("\n".join(header + kept) + "\n")
    first = data.first_frame + 1
    with pytest.raises(InputError, match=rf"gap\.trc, line 107: Frame# {first + 150} where the rows before it make it {first + 100}:"):
        read_trc(gap)
    assert read_trc(path).n_frames == 200  # contiguous frame numbers, from any first frame, read as before


def test_trc_round_trip_of_real_file(tmp_path: Path) -> None:
    _need_ezc3d()
    data = read_c3d(RACING)
    path = tmp_path / "racing.trc"
    write_trc(path, data)
    back = read_trc(path)
    np.testing.assert_array_equal(back.markers, data.markers)
    assert back.labels == data.labels
    assert back.rate == data.rate
    assert back.units == "m"


OPENSIM_TRC = (
    "PathFileType\t4\t(X/Y/Z)\twalk.trc\n"
    "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames\n"
    "60.00\t60.00\t3\t2\tmm\t60.00\t5\t3\n"
    "Frame#\tTime\tR.ASIS\t\t\tL.ASIS\t\t\t\n"
    "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\t\n"
    "\n"
    "5\t0.000\t1.5\t2\t3\t4\t5\t6\n"
    "6\t0.017\t\t\t\t4.5\t5\t6\n"
    "7\t0.033\t1\t2\t3\n"
)


def test_trc_written_by_another_tool(tmp_path: Path) -> None:
    path = tmp_path / "walk.trc"
    path.write_text(OPENSIM_TRC)
    data = read_trc(path)
    assert data.labels == ("R.ASIS", "L.ASIS")
    assert (data.rate, data.units, data.first_frame) == (60.0, "mm", 4)
    expected = np.array(
        [[[1.5, 2, 3], [4, 5, 6]], [[np.nan] * 3, [4.5, 5, 6]], [[1, 2, 3], [np.nan] * 3]], dtype=np.float64
    )
    np.testing.assert_array_equal(data.markers, expected)


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ("60.00\t60.00\t3\t2", "60.00\t60.00\t4\t2", "expected 4 data rows"),
        ("60.00\t60.00\t3\t2", "60.00\t60.00\t3\t3", "expected 3 marker names"),
        ("4.5\t5", "4.5\tfive", r"line 8: expected a number for marker 'L.ASIS', got 'five'"),
        ("Units\t", "Unit\t", "'Units'"),
        ("PathFileType", "Something", "PathFileType"),
        ("Frame#", "Frame", "names row"),
        ("7\t0.033\t1\t2\t3", "7\t0.033\t1\t2\t3\t4\t5\t6\t7", "at most 8 cells"),
    ],
)
def test_trc_bad_content(tmp_path: Path, old: str, new: str, message: str) -> None:
    path = tmp_path / "bad.trc"
    path.write_text(OPENSIM_TRC.replace(old, new, 1))
    with pytest.raises(InputError, match=message):
        read_trc(path)


def test_write_trc_checks(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="MarkerData"):
        write_trc(tmp_path / "x.trc", np.zeros((2, 1, 3)))  # type: ignore[arg-type]
    with pytest.raises(InputError, match="tab"):
        write_trc(tmp_path / "x.trc", MarkerData(np.zeros((2, 1, 3)), ("A\tB",), 10.0, "mm"))
    with pytest.raises(InputError, match="units"):
        write_trc(tmp_path / "x.trc", MarkerData(np.zeros((2, 1, 3)), ("A",), 10.0, ""))
