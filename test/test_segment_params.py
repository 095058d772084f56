"""Segments as the unit of the configuration (issue 16, item 1).

``segments`` names every body segment once with its markers (or a pose topic);
joints name their ``parent`` and ``child`` segment. The segment form must give
exactly the joints that the per-joint marker lists give (so every existing config
keeps working and the two forms mix), name the segments in ``~/segments``, the TF
tree and the URDF, and refuse every inconsistent layout with one line naming the
parameter.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from jointfit_core.segment_frames import SegmentFrames, SegmentJoint
from jointfit_core.skeleton_truth import make_skeleton
from jointfit_core.urdf import segment_names
from jointfit_ros.offline import with_file_marker_names
from jointfit_ros.params import ConfigError, node_config, params_from_file
from jointfit_ros.skeleton_params import skeleton_parameters

CONFIG = Path(__file__).resolve().parents[1] / "config"
NAMES = ["P1", "P2", "P3", "P4", "T1", "T2", "T3", "T4", "S1", "S2", "S3"]


def _segment_form(**extra: Any) -> dict[str, Any]:
    values: dict[str, Any] = {
        "joints": ["hip", "knee"],
        "marker_names": NAMES,
        "segments": ["pelvis", "thigh", "shank"],
        "pelvis.markers": NAMES[:4],
        "thigh.markers": NAMES[4:8],
        "shank.markers": NAMES[8:],
        "hip.parent": "pelvis",
        "hip.child": "thigh",
        "knee.type": "hinge",
        "knee.parent": "thigh",
        "knee.child": "shank",
    }
    values.update(extra)
    return {k: v for k, v in values.items() if v is not None}


def _marker_form() -> dict[str, Any]:
    return {
        "joints": ["hip", "knee"],
        "marker_names": NAMES,
        "hip.parent_markers": NAMES[:4],
        "hip.child_markers": NAMES[4:8],
        "knee.type": "hinge",
        "knee.parent_markers": NAMES[4:8],
        "knee.child_markers": NAMES[8:],
    }


def test_the_segment_form_gives_the_joints_of_the_marker_form() -> None:
    by_segment = node_config(_segment_form())
    by_markers = node_config(_marker_form())
    for a, b in zip(by_segment.joints, by_markers.joints, strict=True):
        assert dataclasses.replace(a, parent_segment="", child_segment="") == b
    hip, knee = by_segment.joints
    assert (hip.parent_segment, hip.child_segment, knee.parent_segment) == ("pelvis", "thigh", "thigh")
    assert hip.child_markers == knee.parent_markers == tuple(NAMES[4:8])  # one shared segment
    assert knee.segment_names() == ("parent thigh", "child shank")
    assert by_segment.segment_labels() == {
        tuple(NAMES[:4]): "pelvis", tuple(NAMES[4:8]): "thigh", tuple(NAMES[8:]): "shank"
    }
    assert by_markers.segments == () and by_markers.segment_labels() == {}


def test_the_two_forms_mix_and_segments_may_go_unused() -> None:
    values = _segment_form(**{"knee.parent": None, "knee.parent_markers": NAMES[4:8]})
    values["segments"] = ["pelvis", "thigh", "shank", "spare"]
    values["spare.markers"] = []
    with pytest.raises(ConfigError, match=r"spare: give spare\.markers .* or spare\.pose_topic, got neither"):
        node_config(values)
    values["spare.pose_topic"] = "/spare/pose"
    cfg = node_config(values)
    knee = cfg.joints[1]
    assert knee.parent_markers == tuple(NAMES[4:8]) and knee.parent_segment == "" and knee.child_segment == "shank"
    assert [s.name for s in cfg.segments] == ["pelvis", "thigh", "shank", "spare"]


def test_a_pose_topic_segment_is_the_joints_pose_topic() -> None:
    values = _segment_form(**{"thigh.markers": None, "thigh.pose_topic": "/thigh/pose"})
    values["joints"] = ["hip"]
    values = {k: v for k, v in values.items() if not k.startswith("knee.")}
    hip = node_config(values).joints[0]
    assert hip.child_pose_topic == "/thigh/pose" and hip.child_markers == () and hip.child_segment == "thigh"


@pytest.mark.parametrize(
    ("pose_topics", "given", "expected"),
    [
        ((), "auto", "skin"),  # marker clusters: skin
        (("thigh",), "auto", "skin"),  # one side on the skin is enough for its artefact
        (("pelvis", "thigh"), "auto", "rigid"),  # two rigid-body pose inputs (issue 17 item 3)
        (("pelvis", "thigh"), "skin", "skin"),  # a rigid body on a skin-mounted plate: as set
        ((), "rigid", "rigid"),
    ],
)
def test_attachment_auto_is_rigid_for_two_pose_topics_only(pose_topics: tuple[str, ...], given: str, expected: str) -> None:
    change: dict[str, Any] = {}
    for seg in pose_topics:
        change |= {f"{seg}.markers": None, f"{seg}.pose_topic": f"/{seg}/pose"}
    values = _segment_form(**change)
    values["joints"] = ["hip"]
    values = {k: v for k, v in values.items() if not k.startswith("knee.")}
    if given != "auto":
        values["hip.attachment"] = given
    assert node_config(values).joints[0].attachment == expected


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"hip.parent": "pelvic"}, r"hip\.parent: 'pelvic' is not in segments \['pelvis', 'thigh', 'shank'\]"),
        ({"hip.parent_markers": NAMES[:4]}, r"hip\.parent: give the segment \(hip\.parent\) or hip\.parent_markers"),
        ({"hip.child_pose_topic": "/t"}, r"hip\.child: give the segment \(hip\.child\) or"),
        ({"shank.markers": ["S1", "S2", "T4"]}, r"shank\.markers: 'T4' is also on segment 'thigh'"),
        ({"shank.markers": ["S1", "S2"]}, r"knee\.child: segment 'shank' has 2 marker\(s\)"),
        ({"shank.markers": ["S1", "S2", "X9"]}, r"shank\.markers: \['X9'\] are not in marker_names"),
        ({"shank.markers": ["S1", "S1", "S2"]}, r"shank\.markers: a marker is listed twice"),
        ({"shank.pose_topic": "/shank"}, r"shank: give shank\.markers .* not both"),
        ({"knee.child": "thigh"}, r"knee: parent and child are the same segment 'thigh'"),
        ({"segments": ["pelvis", "thigh", "shank", "hip"], "hip.markers": ["S1"]}, r"'hip' is also a joint's name"),
        ({"segments": ["pelvis", "thigh", "thigh"]}, r"segments: a name is listed twice"),
        ({"segments": ["pelvis", "thigh", "shank", "units"], "units.markers": ["S1"]}, r"'units' is the name of a node"),
        ({"segments": ["pelvis", "thigh", "2shank"]}, r"'2shank' is not a valid name"),
        ({"thigh.marker": NAMES[4:8]}, r"thigh\.marker: unknown parameter; did you mean 'thigh\.markers'\?"),
        ({"segments": ["pelvis", "thigh"]}, r"shank\.markers: unknown parameter; 'shank' is not in joints"),
        ({"hip.parent": 3}, r"hip\.parent: expected a string"),
    ],
)
def test_inconsistent_segments_are_refused_with_the_parameter_named(change: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        node_config(_segment_form(**change))


def test_segment_names_come_from_the_configuration() -> None:
    cfg = node_config(_segment_form())
    joints = [SegmentJoint(j.name, j.parent_markers, j.child_markers) for j in cfg.joints]
    assert SegmentFrames(joints, cfg.segment_labels()).names == ["pelvis", "thigh", "shank"]
    assert SegmentFrames(joints).names == ["P", "T", "S"]  # without: the markers' common prefixes
    # a configured name is never given twice: a prefix that clashes with one becomes segment_<k>
    lists = [("A1", "A2", "A3"), ("B1", "B2", "B3")]
    assert segment_names(lists, {lists[1]: "A"}) == {lists[0]: "segment_0", lists[1]: "A"}


@pytest.mark.parametrize("name", ["lower", "full"])
def test_skeleton_configs_name_every_segment_once(name: str) -> None:
    sk = make_skeleton(name)
    cfg = node_config(params_from_file(CONFIG / f"{name}_body.yaml"))
    assert [s.name for s in cfg.segments] == [s.name for s in sk.segments]
    for j in cfg.joints:
        child = sk.joint_segment(j.name)
        assert (j.parent_segment, j.child_segment) == (child.parent, child.name)
        assert list(j.child_markers) == child.marker_names
    # the parameters of a subset name only the segments its joints use
    values = skeleton_parameters(sk, ["r_knee"])
    assert values["segments"] == ["r_thigh", "r_shank"] and "pelvis.markers" not in values


def test_segment_markers_are_checked_against_a_files_labels() -> None:
    values = _segment_form(marker_names=None)
    values = {k: v for k, v in values.items() if k != "marker_names"}
    out = with_file_marker_names(values, NAMES, "trial.c3d")
    assert out["marker_names"] == NAMES
    values["thigh.markers"] = ["T1", "T2", "T3", "T5"]
    with pytest.raises(ConfigError, match=r"thigh\.markers: 'T5' is not a marker label of trial\.c3d"):
        with_file_marker_names(values, NAMES, "trial.c3d")


def test_urdf_links_take_the_segment_names() -> None:
    from jointfit_core.urdf import urdf_from_calibrations

    rng = np.random.default_rng(3)
    tp, tc = rng.normal(size=(4, 3)) * 0.05, rng.normal(size=(4, 3)) * 0.05
    ts = rng.normal(size=(3, 3)) * 0.05
    hip = {"kind": "ball", "joint": "hip", "parent_markers": NAMES[:4], "child_markers": NAMES[4:8],
           "template_parent": tp.tolist(), "template_child": tc.tolist(),
           "estimate": {"centre_parent": [0.0, 0.0, -0.1], "centre_child": [0.0, 0.0, 0.2]}}
    knee = {"kind": "hinge", "joint": "knee", "parent_markers": NAMES[4:8], "child_markers": NAMES[8:],
            "template_parent": tc.tolist(), "template_child": ts.tolist(),
            "estimate": {"point_parent": [0.0, 0.0, -0.2], "point_child": [0.0, 0.0, 0.2],
                         "direction_parent": [1.0, 0.0, 0.0]}}
    labels = node_config(_segment_form()).segment_labels()
    named = urdf_from_calibrations([hip, knee], segment_labels=labels)
    assert all(f'<link name="{n}">' in named for n in ("pelvis", "thigh", "shank"))
    assert '<parent link="thigh"/><child link="knee_axis"/>' in named and '<child link="shank"/>' in named
    unnamed = urdf_from_calibrations([hip, knee])
    assert '<link name="T">' in unnamed and "thigh" not in unnamed
