"""Record (or compare with a recording) every output of the 12-joint per-message path of ``bench/skeleton.py``.

A regression check for work on the per-frame path that must not change results (issue 16):
run it once on the code before the change (``--save``) and once after (``--compare``).

Run from the repository root with ``PYTHONPATH=.:test``::

    python bench/_path_reference.py --save /tmp/ref_skin.npy
    python bench/_path_reference.py --compare /tmp/ref_skin.npy
    python bench/_path_reference.py --attachment rigid --save /tmp/ref_rigid.npy

What is recorded: the stream of ``bench/skeleton.py`` (the full skeleton, seed 0, 0.5 mm noise, 2 %
occluded markers, 100 Hz), :data:`FRAMES` frames; the 12 joints' :class:`~skeleton._Path` warmed up
on the first ``WARM`` frames and solved (as the bench does), then fed the rest with a solve of one
joint in turn every ``SOLVE_EVERY`` frames. Per frame and joint: the output's position (3,), cov
(3, 3), direction (3,), cov_direction (3, 3) and residual (NaN where there is no output or no
direction), the encoded output message bytes, the ``~/segments`` poses and bytes; at the end, every
runner's counters, every estimator's ``dropped``, ``gated_frames``, ``joint_gated_frames``,
``n_frames_seen`` and its window sums and solution's position/cov.

``--compare``: arrays must be equal (``np.array_equal``, NaN equal to NaN) and bytes identical;
with ``--rtol`` > 0, float arrays may differ by that relative amount (reported); counters must be
equal in any case. Exit status 1 on a difference.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from skeleton import SOLVE_EVERY, T0, WARM, _Path  # type: ignore[attr-defined]

from jointfit_core.skeleton_truth import make_skeleton, skeleton_frames
from jointfit_ros.conversions import axis_pose_bytes, pose_with_covariance_bytes
from jointfit_ros.params import node_config
from jointfit_ros.raw import pose_array_bytes
from jointfit_ros.skeleton_params import skeleton_parameters

#: Frames in all (warm-up included).
FRAMES = 1500
RATE = 100.0
JOINTS = 12


def _record(attachment: str, frames: int) -> dict[str, Any]:
    """Run the path and collect its outputs (see the module docstring)."""
    sk = make_skeleton("full", seed=0)
    t = np.arange(frames) / RATE
    data = skeleton_frames(sk, t, np.random.default_rng(0), 0.0005, 0.02)
    messages = [pose_array_bytes(T0 + round(tk * 1e9), "world", f) for tk, f in zip(t, data, strict=True)]
    params = skeleton_parameters(sk, sk.joints[:JOINTS])
    for j in sk.joints[:JOINTS]:
        params[f"{j}.attachment"] = attachment
    cfg = node_config(params)
    path = _Path(cfg, messages[:WARM])
    names = [r.cfg.name for r in path.runners]
    index = {n: i for i, n in enumerate(names)}
    timed = messages[WARM:]
    k, n = len(timed), len(names)
    pos = np.full((k, n, 3), np.nan)
    cov = np.full((k, n, 3, 3), np.nan)
    direction = np.full((k, n, 3), np.nan)
    cov_direction = np.full((k, n, 3, 3), np.nan)
    residual = np.full((k, n), np.nan)
    rotation = np.full((k, n, 3, 3), np.nan)
    rotation_cov = np.full((k, n, 3, 3), np.nan)
    encoded: list[bytes] = []
    seg_R: list[np.ndarray] = []
    seg_t: list[np.ndarray] = []
    seg_bytes: list[bytes] = []
    for f, raw in enumerate(timed):
        for routed in path.router.markers(raw):
            out, j = routed.output, index[routed.runner.cfg.name]
            pos[f, j], cov[f, j], residual[f, j] = out.position, out.cov, out.residual
            if out.rotation is not None and out.rotation_cov is not None:
                rotation[f, j], rotation_cov[f, j] = out.rotation, out.rotation_cov
            if out.direction is None:
                encoded.append(pose_with_covariance_bytes(routed.stamp_ns, routed.frame_id, out.position, out.cov))
            else:
                assert out.cov_direction is not None
                direction[f, j], cov_direction[f, j] = out.direction, out.cov_direction
                encoded.append(axis_pose_bytes(routed.stamp_ns, routed.frame_id, out.position, out.direction, out.cov,
                                               out.cov_direction))  # fmt: skip
        R, tt = path.segments.poses()
        seg_R.append(R)
        seg_t.append(tt)
        seg_bytes.append(path.segments.pose_array(T0, "world", R, tt))
        path.router.after_outputs()
        if (f + 1) % SOLVE_EVERY == 0:
            path.runners[path.turn].estimate(force=True)
            path.turn = (path.turn + 1) % len(path.runners)
    counters: dict[str, int] = {}
    sums: dict[str, np.ndarray] = {}
    for r in path.runners:
        est = r.estimator
        for key, value in r.counters.items():
            counters[f"{r.cfg.name}.runner.{key}"] = value
        for key, value in est.dropped.items():
            counters[f"{r.cfg.name}.dropped.{key}"] = value
        counters[f"{r.cfg.name}.gated_parent"], counters[f"{r.cfg.name}.gated_child"] = est.gated_frames
        counters[f"{r.cfg.name}.joint_gated_frames"] = est.joint_gated_frames
        counters[f"{r.cfg.name}.n_frames_seen"] = est.n_frames_seen
        vec = est.sums_vector()
        sums[f"{r.cfg.name}.sums"] = np.zeros(0) if vec is None else vec
        sol = est.solution
        if sol is not None:
            sums[f"{r.cfg.name}.solution_cov_parent"] = np.asarray(
                sol.cov_parent if hasattr(sol, "cov_parent") else sol.cov_point_parent
            )
    return {
        "position": pos, "cov": cov, "direction": direction, "cov_direction": cov_direction, "residual": residual,
        "rotation": rotation, "rotation_cov": rotation_cov, "segments_R": np.stack(seg_R),
        "segments_t": np.stack(seg_t), "encoded": np.array(encoded, dtype=object),
        "segments_bytes": np.array(seg_bytes, dtype=object), "counters": counters, **sums,
    }  # fmt: skip


def _compare(ref: dict[str, Any], new: dict[str, Any], rtol: float) -> list[str]:
    """The differences between two recordings, in words (empty when none beyond ``rtol``)."""
    problems: list[str] = []
    if ref["counters"] != new["counters"]:
        keys = sorted(set(ref["counters"]) | set(new["counters"]))
        diff = [(k, ref["counters"].get(k), new["counters"].get(k)) for k in keys
                if ref["counters"].get(k) != new["counters"].get(k)]  # fmt: skip
        problems.append(f"counters differ: {diff}")
    for key in sorted(set(ref) | set(new)):
        if key == "counters":
            continue
        if key not in ref or key not in new:
            problems.append(f"{key}: only in one recording")
            continue
        a, b = ref[key], new[key]
        if a.dtype == object:
            same = len(a) == len(b) and all(x == y for x, y in zip(a, b, strict=True))
            if not same:
                bad = sum(x != y for x, y in zip(a, b, strict=False))
                problems.append(f"{key}: {bad} of {len(a)} messages differ" + (" (bytes)" if rtol == 0 else ""))
            continue
        if a.shape != b.shape:
            problems.append(f"{key}: shapes {a.shape} and {b.shape}")
        elif not np.array_equal(a, b, equal_nan=True):
            nan_same = np.array_equal(np.isnan(a), np.isnan(b))
            scale = np.nanmax(np.abs(a)) if np.isfinite(a).any() else 1.0
            rel = float(np.nanmax(np.abs(a - b)) / scale) if nan_same else np.inf
            where = int(np.sum(~((a == b) | (np.isnan(a) & np.isnan(b)))))
            text = f"{key}: {where} values differ, largest by {rel:.3g} of the largest value"
            if rel > rtol:
                problems.append(text)
            else:
                print(f"within rtol: {text}")
    return problems


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--attachment", choices=("skin", "rigid"), default="skin")
    p.add_argument("--frames", type=int, default=FRAMES)
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--save", type=Path)
    g.add_argument("--compare", type=Path)
    p.add_argument("--rtol", type=float, default=0.0, help="relative tolerance of float arrays (default 0: equal)")
    opts = p.parse_args(argv)
    rec = _record(opts.attachment, opts.frames)
    if opts.save is not None:
        np.save(opts.save, np.array(rec, dtype=object), allow_pickle=True)
        print(f"saved {opts.save}: {len(rec['encoded'])} outputs, {len(rec['counters'])} counters")
        return 0
    ref = np.load(opts.compare, allow_pickle=True).item()
    problems = _compare(ref, rec, opts.rtol)
    for text in problems:
        print("DIFFERENT:", text)
    print("identical" if not problems else f"{len(problems)} difference(s)")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
