"""The per-frame jump of the outlier gate (:meth:`ShapeTrack.jump`) equals its block twin (:func:`frame_jumps`).

:meth:`~jointfit_core.gate.ShapeTrack.jump` has two shortcuts on the per-frame path: a frame of the
markers of the latest write of the references (all fresh, all of one fit: no masks), and the
alignment of references from another fit without the block's masks. Both must give the very
numbers of :func:`~jointfit_core.gate.frame_jumps` of that one frame, whatever the history of
passes, provisional references and occlusions.
"""

from __future__ import annotations

import numpy as np
import pytest

from jointfit_core.gate import GATE_JUMP_GAP_CAP, ShapeTrack, frame_jumps, marker_code


def _twin(track: ShapeTrack, index: np.ndarray, local: np.ndarray, frame_no: int, last: bool) -> tuple[float, bool]:
    """:func:`frame_jumps` of one frame against the track's references (or its previous frame seen)."""
    p = track.ref.shape[0]
    full = np.zeros((1, p, 3))
    full[0, index] = local
    vis = np.zeros((1, p), dtype=bool)
    vis[0, index] = True
    ref, at, code = (track.last, track.last_at, track.last_code) if last else (track.ref, track.at, track.code)
    jump, stale = frame_jumps(full, vis, ref[None], at[None], code[None], np.array([frame_no]))
    return float(jump[0]), bool(stale[0])


@pytest.mark.parametrize("seed", range(6))
def test_jump_equals_frame_jumps(seed: int) -> None:
    rng = np.random.default_rng(seed)
    p = int(rng.integers(3, 6))
    template = rng.normal(scale=0.05, size=(p, 3))
    track = ShapeTrack(p)
    frame_no = 0
    checked = {"shortcut": 0, "aligned": 0, "other": 0}
    for _ in range(400):
        frame_no += int(rng.choice([1, 1, 1, 2, GATE_JUMP_GAP_CAP + 1], p=[0.7, 0.1, 0.1, 0.05, 0.05]))
        vis = rng.random(p) > 0.15
        if vis.sum() < 3 and rng.random() < 0.7:
            vis[:] = True
        index = np.flatnonzero(vis)
        if not index.size:
            continue
        code = marker_code(index)
        # a slightly rotated, deformed cluster: references from other fits then need aligning
        angle = 0.02 * rng.normal()
        c, s = np.cos(angle), np.sin(angle)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        local = template[index] @ R.T + 1e-3 * rng.normal(size=(index.size, 3))
        for last in (False, True):
            written = track._last_write if last else track._ref_write
            got = track.jump(index, local, frame_no, code, last=last)
            want = _twin(track, index, local, frame_no, last)
            assert got[1] == want[1]
            assert got[0] == want[0] or (np.isinf(got[0]) and np.isinf(want[0]))
            if code == written[1]:
                checked["shortcut"] += 1
            elif np.isfinite(got[0]) and (track.code[index] != code).any():
                checked["aligned"] += 1
            else:
                checked["other"] += 1
        track.seen(index, local, frame_no, code)
        action = rng.random()
        if action < 0.8:
            track.passed(index, local, frame_no, 0.0, code)
        else:
            track.failed(index, local, frame_no, code)
    assert min(checked.values()) > 0, checked  # every path was taken


def test_passed_block_leaves_no_shortcut() -> None:
    """After a block passed, the references come from different frames: the general path judges the next frame."""
    rng = np.random.default_rng(1)
    track = ShapeTrack(4)
    local = rng.normal(size=(3, 4, 3))
    vis = np.array([[True, True, True, True], [True, True, True, False], [True, True, True, False]])
    track.passed_block(local, vis, np.array([1, 2, 3]), np.zeros(3), np.full(3, np.nan))
    index = np.arange(4)
    y = local[0] + 1e-3
    assert track.jump(index, y, 4, marker_code(index)) == _twin(track, index, y, 4, False)
