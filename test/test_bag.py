"""jointfit_ros.bag: rosbag2 bags (sqlite3 and mcap) read back as raw CDR, without ROS.

Bags are written with rosbags' Writer (test/bagtools.py) from a synthetic
marker stream with occlusions; every variant (storage, compression, message
type, path form) must give back the same stamps, log times and numbers,
NaN included. Error messages are checked for what they must tell the user.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

pytest.importorskip("rosbags.rosbag2")

from bagtools import pose_stamped_bytes, write_marker_bag, write_raw_bag
from scipy.spatial.transform import Rotation

from jointfit_core.errors import InputError, MissingDependencyError
from jointfit_ros.bag import (
    SUPPORTED_MSGTYPES,
    BagMessage,
    BagTopic,
    bag_topics,
    iter_bag_messages,
    supported_topics,
)
from jointfit_ros.raw import (
    parse_pointcloud2,
    parse_pose_array,
    parse_pose_stamped,
    pose_array_bytes,
    rotation_matrix_from_quaternion,
)

N, P = 40, 6
T0 = 1_700_000_000_123_456_789
PA, PC, PS = SUPPORTED_MSGTYPES


def _stream(seed: int = 0) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """(N, P, 3) metres with ~15 % NaN rows, and irregular increasing stamps (ns)."""
    rng = np.random.default_rng(seed)
    frames = rng.normal(0.0, 1.0, (N, P, 3)) + np.array([2.5, 3.0, 0.9])
    frames[rng.random((N, P)) < 0.15] = np.nan
    frames[3] = np.nan  # a fully occluded frame
    stamps = T0 + np.cumsum(rng.integers(4_000_000, 6_000_000, N))
    return frames, stamps


def _poses(seed: int = 1) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    rng = np.random.default_rng(seed)
    R = Rotation.random(N, random_state=rng).as_matrix()
    d = rng.normal(0.0, 2.0, (N, 3))
    d[5] = np.nan
    return R, d


def _same(a: NDArray[np.float64], b: NDArray[np.float64]) -> bool:
    return a.shape == b.shape and bool(np.array_equal(a, b, equal_nan=True))


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
@pytest.mark.parametrize("msgtype", ["pose_array", "pointcloud2"])
def test_round_trip(tmp_path: Path, storage: str, msgtype: str) -> None:
    frames, stamps = _stream()
    R, d = _poses()
    bag = write_marker_bag(
        tmp_path / "bag", frames, stamps, storage=storage, msgtype=msgtype, pose_topics={"body/pose": (R, d)}
    )
    marker_type = PA if msgtype == "pose_array" else PC
    assert bag_topics(bag) == {
        "/body/pose": BagTopic("/body/pose", PS, N),
        "/markers": BagTopic("/markers", marker_type, N),
    }
    msgs = list(iter_bag_messages(bag, ["markers", "/body/pose"]))
    assert len(msgs) == 2 * N
    assert all(isinstance(m, BagMessage) and type(m.raw) is bytes for m in msgs)
    assert all(m.raw[:2] == b"\x00\x01" for m in msgs)  # encapsulation header kept (CDR little-endian)
    times = [m.log_time_ns for m in msgs]
    assert times == sorted(times)
    markers = [m for m in msgs if m.topic == "/markers"]
    poses = [m for m in msgs if m.topic == "/body/pose"]
    assert {m.msgtype for m in markers} == {marker_type} and {m.msgtype for m in poses} == {PS}
    assert [m.log_time_ns for m in markers] == stamps.tolist() == [m.log_time_ns for m in poses]
    for k, m in enumerate(markers):
        if msgtype == "pose_array":
            got = parse_pose_array(m.raw)
        else:
            got = parse_pointcloud2(m.raw, label_field="label")
            assert got.labels is not None and got.labels.tolist() == list(range(P))
        assert got.stamp_ns == stamps[k] and got.frame_id == "world"
        assert _same(got.points, frames[k]), k
    for k, m in enumerate(poses):
        pose = parse_pose_stamped(m.raw)
        assert pose.stamp_ns == stamps[k]
        assert _same(pose.position, d[k])
        np.testing.assert_allclose(rotation_matrix_from_quaternion(pose.quaternion), R[k], atol=1e-12)


def test_topics_select_and_order(tmp_path: Path) -> None:
    frames, stamps = _stream()
    R, d = _poses()
    bag = write_marker_bag(tmp_path / "bag", frames, stamps, pose_topics={"a": (R, d), "b": (R, d)})
    only_b = list(iter_bag_messages(bag, ["b"]))
    assert [m.topic for m in only_b] == ["/b"] * N
    assert [m.log_time_ns for m in only_b] == stamps.tolist()
    both = list(iter_bag_messages(bag, ["/a", "a", "markers"]))  # duplicates are read once
    assert len(both) == 2 * N
    assert supported_topics(bag) == ["/a", "/b", "/markers"]


@pytest.mark.parametrize(
    ("storage", "compression"),
    [("mcap", "storage"), ("mcap", "message"), ("mcap", "file"), ("sqlite3", "message"), ("sqlite3", "file")],
)
def test_compressed_bags(tmp_path: Path, storage: str, compression: str) -> None:
    frames, stamps = _stream(3)
    bag = write_marker_bag(tmp_path / "bag", frames, stamps, storage=storage, compression=compression)
    msgs = list(iter_bag_messages(bag, ["markers"]))
    assert [m.log_time_ns for m in msgs] == stamps.tolist()
    assert all(_same(parse_pose_array(m.raw).points, frames[k]) for k, m in enumerate(msgs))


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_path_forms(tmp_path: Path, storage: str) -> None:
    """Directory, metadata.yaml, the storage file itself, a directory that lost its metadata.yaml."""
    frames, stamps = _stream(2)
    bag = write_marker_bag(tmp_path / "bag", frames, stamps, storage=storage)
    (storage_file,) = [p for p in bag.iterdir() if p.suffix in (".db3", ".mcap")]
    expected = {"/markers": BagTopic("/markers", PA, N)}
    for path in (bag, str(bag), bag / "metadata.yaml", storage_file):
        assert bag_topics(path) == expected, path
        assert [m.log_time_ns for m in iter_bag_messages(path, ["markers"])] == stamps.tolist()
    (bag / "metadata.yaml").unlink()
    assert bag_topics(bag) == expected


def test_empty_topic_and_mixed_names(tmp_path: Path) -> None:
    raw = pose_array_bytes(5, "world", [[1.0, 2.0, np.nan]])
    bag = write_raw_bag(
        tmp_path / "bag",
        [("markers", PA, 5, raw), ("markers", PA, 6, raw)],  # relative name, as some writers store it
        empty_topics={"/idle": PC},
    )
    assert bag_topics(bag) == {"/idle": BagTopic("/idle", PC, 0), "markers": BagTopic("markers", PA, 2)}
    assert supported_topics(bag) == ["markers"]
    assert [m.topic for m in iter_bag_messages(bag, ["/markers"])] == ["markers", "markers"]
    assert list(iter_bag_messages(bag, ["idle"])) == []


# --------------------------------------------------------------------------- errors


def _error(call: object, *args: object) -> str:
    with pytest.raises(InputError) as info:
        result = call(*args)  # type: ignore[operator]
        if not isinstance(result, dict):
            list(result)
    text = str(info.value)
    assert "\n" not in text
    return text


def test_error_missing_path(tmp_path: Path) -> None:
    missing = tmp_path / "nope"
    assert _error(bag_topics, missing) == f"no such bag: {missing}"
    assert _error(iter_bag_messages, missing, ["markers"]) == f"no such bag: {missing}"


def test_error_not_a_bag(tmp_path: Path) -> None:
    text_file = tmp_path / "notes.txt"
    text_file.write_text("hello")
    assert "not a rosbag2 bag" in _error(bag_topics, text_file)
    assert "expected a bag directory with metadata.yaml, a .db3 or a .mcap file" in _error(
        bag_topics, text_file
    )
    empty_dir = tmp_path / "empty"
    empty_dir.mkdir()
    assert "has no metadata.yaml and no .db3 or .mcap file" in _error(bag_topics, empty_dir)
    for name in ("junk.db3", "junk.mcap"):
        junk = tmp_path / name
        junk.write_bytes(bytes(range(256)) * 4)
        assert _error(bag_topics, junk).startswith(f"not a readable rosbag2 bag: {junk} (ReaderError: ")
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "metadata.yaml").write_text("rosbag2_bagfile_information: {version: 9}\n")
    assert _error(bag_topics, broken).startswith(f"not a readable rosbag2 bag: {broken}")
    frames, stamps = _stream()
    compressed = write_marker_bag(tmp_path / "zbag", frames, stamps, compression="file")
    (zfile,) = compressed.glob("*.zstd")
    assert _error(bag_topics, zfile) == (
        f"not a rosbag2 bag: {zfile} is a zstd-compressed storage file; pass its bag directory (with metadata.yaml)"
    )
    two = tmp_path / "two"
    two.mkdir()
    (two / "a.db3").write_bytes(b"")
    (two / "b.mcap").write_bytes(b"")
    assert "2 storage files (a.db3, b.mcap); pass one of them" in _error(bag_topics, two)


def test_error_topics_absent(tmp_path: Path) -> None:
    frames, stamps = _stream()
    R, d = _poses()
    bag = write_marker_bag(
        tmp_path / "bag", frames, stamps, msgtype="pointcloud2", pose_topics={"tool": (R, d)}
    )
    text = _error(iter_bag_messages, bag, ["markers", "mocap/markers", "/rigid"])
    assert text == (
        f"{bag}: topics not in the bag: mocap/markers, /rigid; the bag has "
        f"/markers ({PC}, {N} messages), /tool ({PS}, {N} messages)"
    )
    assert "expected at least one topic name; the bag has /markers" in _error(iter_bag_messages, bag, [])
    assert "expected a sequence of topic names, got 'markers'" in _error(iter_bag_messages, bag, "markers")


def test_error_unsupported_type(tmp_path: Path) -> None:
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    String = ts.types["std_msgs/msg/String"]
    chatter = bytes(ts.serialize_cdr(String(data="hi"), "std_msgs/msg/String"))
    pose = pose_stamped_bytes(7, "world", np.eye(3), [1.0, 2.0, 3.0])
    bag = write_raw_bag(
        tmp_path / "bag",
        [("/chatter", "std_msgs/msg/String", 7, chatter), ("/pose", PS, 7, pose)],
        storage="mcap",
    )
    assert bag_topics(bag)["/chatter"] == BagTopic("/chatter", "std_msgs/msg/String", 1)
    assert supported_topics(bag) == ["/pose"]
    text = _error(iter_bag_messages, bag, ["pose", "chatter"])
    assert (
        text == f"{bag}: topic /chatter has message type std_msgs/msg/String; "
        f"supported: {', '.join(SUPPORTED_MSGTYPES)}"
    )


def test_errors_are_raised_before_iteration(tmp_path: Path) -> None:
    frames, stamps = _stream()
    bag = write_marker_bag(tmp_path / "bag", frames, stamps)
    with pytest.raises(InputError, match="topics not in the bag: nothing"):
        iter_bag_messages(bag, ["nothing"])  # not iterated
    it = iter_bag_messages(bag, ["markers"])
    first = next(it)
    assert first.log_time_ns == stamps[0]
    it.close()  # type: ignore[attr-defined]  # a generator: closes the reader


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_truncated_bag(tmp_path: Path, storage: str) -> None:
    """A storage file cut short (recorder killed): one clear error, never wrong messages."""
    frames, _ = _stream()
    n = 20 * N
    bag = write_marker_bag(
        tmp_path / "bag", np.repeat(frames, 20, axis=0), T0 + np.arange(n) * 5_000_000, storage=storage
    )
    (storage_file,) = [p for p in bag.iterdir() if p.suffix in (".db3", ".mcap")]
    data = storage_file.read_bytes()
    cut = tmp_path / f"cut{storage_file.suffix}"
    cut.write_bytes(data[: len(data) // 2])
    try:
        msgs = list(iter_bag_messages(cut, ["markers"]))
    except InputError as exc:
        text = str(exc)
        assert "\n" not in text and str(cut) in text
        if storage == "mcap":
            assert text.endswith("the MCAP file looks truncated: repair it with `mcap recover` (mcap CLI)")
    else:  # a reader that recovers the complete part must give it right
        assert 0 < len(msgs) < n
        assert [m.log_time_ns for m in msgs] == (T0 + np.arange(len(msgs)) * 5_000_000).tolist()


def test_missing_rosbags(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("x: 1\n")
    monkeypatch.setitem(sys.modules, "rosbags.rosbag2", None)  # import now raises ImportError
    with pytest.raises(MissingDependencyError, match=r"pip install 'jointfit\[bag\]'"):
        bag_topics(bag)


def test_modules_import_neither_ros_nor_rosbags() -> None:
    """jointfit_ros.bag and .replay import without ROS; rosbags is imported when a bag is opened."""
    import subprocess

    code = (
        "import sys, jointfit_ros.bag, jointfit_ros.replay; "
        "roots = ('rclpy', 'rosbags', 'geometry_msgs', 'sensor_msgs'); "
        "bad = [m for m in sys.modules if m.split('.')[0] in roots]; "
        "print(bad)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
