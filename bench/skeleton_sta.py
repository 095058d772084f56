"""Skin artefact on every segment of the lower body: are the node's published covariances honest?

Run with ``python bench/skeleton_sta.py`` (repository root; ``--trials N``, default 16;
``--quick`` 4); prints Markdown and writes ``bench/results/skeleton_sta.md``. Issues 16 + 17.

Data: the ``lower`` skeleton of :mod:`jointfit_core.skeleton_truth` (motion phases drawn per
trial; every joint through its range within its 10 s cycle), ``SECONDS`` of it, with the skin
artefact of :func:`jointfit_core.skeleton_sta.skeleton_skin_frames` on every segment: each
cluster's displacement on its bone linear plus quadratic in the angles of the joints adjacent to
it (the thigh's in the hip's and the knee's, the pelvis's in both hips'), 75 % rigid cluster
motion, rms thigh 10 mm, shank 5 mm, pelvis and foot 3 mm; 0.5 mm white noise, 2 % of the markers
occluded (``--occlusion``); at 100 Hz and at 25 Hz, the same trials (skeleton seed, artefact field)
at both rates.

The path: the node's per-message path without ROS (``config/lower_body.yaml`` through
``MessageRouter`` -> ``JointRunner`` -> ``OnlineJoint``, as ``test/test_skeleton_configs.py``),
every joint solved every 0.1 s of the stream as the node does (``ESTIMATE_PERIOD``), once with the
default ``attachment: skin`` and once, on the same frames, with ``attachment: rigid`` for every
joint; scored on the solve at the end.

Measures, per joint: the error against the truth in the joint's parent template frame
(``Skeleton.joint_in_template``); e/k = err^T cov^+ err / rank (1 on average when the published
covariance is honest; > 3 in one trial happens with probability 0.03 for a Gaussian k = 3 and
0.05 for k = 2): the ball centre (k = 3), the hinge direction (k = 2) and the hinge point's
off-axis part in the plane normal to the estimated axis (k = 2, as bench/sta.py).
``--drivers proximal`` moves each segment's skin with its proximal joint only, ``--drivers distal``
with its distal joint(s) only (the pelvis's with both hips, the foot's with the ankle, either way),
to separate the artefact a joint's own angles explain from the other joint's: with ``distal`` the
hip's thigh cluster follows the knee (not the hip), the knee's thigh cluster its own knee and its
shank the ankle; with ``proximal`` the hip's thigh follows the hip, the knee's thigh the hip and
its shank the knee.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _paper_helpers import elapsed_line, fmt, markdown_table, print_and_write, run_header
from skeleton_runs import JointScore, run_stream, score

from jointfit_core.skeleton_sta import adjacent_joints, skeleton_skin_frames, sta_amplitudes
from jointfit_core.skeleton_truth import Skeleton, make_skeleton
from jointfit_ros.params import node_config, params_from_file

SCRIPT = "skeleton_sta.py"
SEED = 20261202
SECONDS = 20.0
RATES = (100.0, 25.0)
NOISE_M = 0.0005
OCCLUSION = 0.02  # default share of occluded markers
CONFIG = Path(__file__).resolve().parents[1] / "config" / "lower_body.yaml"
ATTACHMENTS = ("skin", "rigid")
#: Stream seconds between solves, as the node's ``estimate_period`` (its default): the outlier gate's limits
#: follow the latest estimate (without solves during the stream an occlusion can lock a skin marker out).
ESTIMATE_PERIOD = 0.1


def _drivers(sk: Skeleton, which: str) -> dict[str, tuple[str, ...]] | None:
    """Which joints move each segment's skin: all adjacent (None), the proximal one, or the distal ones.

    A segment without a joint on that side (the pelvis, the foot) keeps its adjacent joints.
    """
    if which == "adjacent":
        return None
    out = {}
    for s in sk.segments:
        adjacent = adjacent_joints(sk)[s.name]
        if s.parent is None or len(adjacent) == 1:
            out[s.name] = adjacent
        else:
            out[s.name] = adjacent[:1] if which == "proximal" else adjacent[1:]
    return out


def trial(rng: np.random.Generator, rate: float, drivers: str, occlusion: float) -> dict[str, list[JointScore]]:
    """One trial: the same skin frames through the node's path with each attachment."""
    sk = make_skeleton("lower", seed=int(rng.integers(2**31)))
    t = np.arange(round(SECONDS * rate)) / rate
    frames = skeleton_skin_frames(sk, t, rng, sta_amplitudes(sk), noise=NOISE_M, occlusion=occlusion,
                                  drivers=_drivers(sk, drivers))
    out = {}
    for attachment in ATTACHMENTS:
        values = params_from_file(CONFIG)
        for j in sk.joints:
            values[f"{j}.attachment"] = attachment
        out[attachment] = [
            score(sk, r) for r in run_stream(node_config(values), t, frames, estimate_period=ESTIMATE_PERIOD)
        ]
    return out


Results = dict[float, dict[str, list[list[JointScore]]]]


def run(trials: int, drivers: str, occlusion: float, seed: int = SEED) -> Results:
    results: Results = {}
    for rate in RATES:
        acc: dict[str, list[list[JointScore]]] = {a: [] for a in ATTACHMENTS}
        for trial_seq in np.random.SeedSequence(seed).spawn(trials):
            # the same trial seeds (skeleton, artefact field) at every rate, for every --drivers and
            # --occlusion: only the rate, the drivers or the occlusions change
            row = trial(np.random.default_rng(trial_seq), rate, drivers, occlusion)
            for a in ATTACHMENTS:
                acc[a].append(row[a])
        results[rate] = acc
    return results


def _quantities(kind: str) -> list[tuple[str, str, str, str, str]]:
    """(label, error attribute, sd attribute, e attribute, unit) per estimated quantity."""
    if kind == "ball":
        return [("centre", "error", "sd", "e", "mm")]
    return [("direction", "error", "sd", "e", "deg"), ("point", "point_error", "point_sd", "point_e", "mm")]


def tables(results: Results) -> list[str]:
    parts = []
    for rate, acc in results.items():
        rows = []
        names = [s.name for s in acc["skin"][0]]
        for k, name in enumerate(names):
            for label, err_a, sd_a, e_a, unit in _quantities(acc["skin"][0][k].kind):
                cells = [f"{name} {label} ({unit})"]
                for a in ATTACHMENTS:
                    e = np.array([getattr(tr[k], e_a) for tr in acc[a]])
                    cells += [fmt(float(e.mean())), fmt(float(np.median(e))), fmt(float((e > 3.0).mean()), 2)]
                    if a == "skin":
                        cells.append(fmt(float(e.max())))
                err = np.array([getattr(tr[k], err_a) for tr in acc["skin"]])
                sd = {a: np.array([getattr(tr[k], sd_a) for tr in acc[a]]) for a in ATTACHMENTS}
                flagged = np.mean([not tr[k].identifiable for tr in acc["skin"]])
                gated = np.array([tr[k].gated for tr in acc["skin"]])
                cells += [fmt(float(err.mean())), fmt(float(err.std(ddof=1)) if err.size > 1 else float("nan")),
                          fmt(float(np.sqrt(np.mean(sd["skin"] ** 2)))), fmt(float(np.sqrt(np.mean(sd["rigid"] ** 2)))),
                          fmt(float(flagged), 2), fmt(float(gated.mean()), 2), fmt(float((gated > 0.2).mean()), 2)]
                rows.append(cells)
        n = len(acc["skin"])
        parts += [
            f"## {rate:g} Hz, {SECONDS:g} s ({round(SECONDS * rate)} frames), {n} trials",
            "",
            markdown_table(
                ["joint", "skin mean e/k", "skin median e/k", "skin share e/k > 3", "skin max e/k", "rigid mean e/k",
                 "rigid median e/k", "rigid share e/k > 3", "error mean", "error sd", "skin sd (rms)",
                 "rigid sd (rms)", "flagged (skin)", "gated frames", "trials gated > 20 %"],
                rows,
                align="lrrrrrrrrrrrrrr",
            ),
            "",
        ]
    same = all(
        np.isclose(s.error, r.error, rtol=1e-9, atol=1e-12)
        for acc in results.values()
        for ts, tr in zip(acc["skin"], acc["rigid"], strict=True)
        for s, r in zip(ts, tr, strict=True)
    )
    parts += [
        "e/k: err^T cov^+ err / rank of the published covariance (centre k = 3; hinge direction k = 2; hinge "
        "point: its off-axis part in the plane normal to the estimated axis, k = 2); an honest covariance gives "
        "a mean near 1 and e/k > 3 in ~3-5 % of the trials. error: the skin estimate's distance from the truth "
        "(centre, point: mm; direction: deg), its mean and sd over the trials; sd (rms): root mean square over "
        "the trials of sqrt(tr cov) as published. flagged: the share the node called not identifiable (still "
        "scored). gated frames: the mean share of the frames in which the outlier gate left out a marker or a "
        "segment of the joint; trials gated > 20 %: the share of trials where it did so in more than a fifth of "
        f"the frames. The rigid-attachment estimates are {'the same' if same else 'not the same'} as the skin ones "
        "(the attachment changes the covariance only).",
    ]
    return parts


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="4 trials per rate instead of 16")
    parser.add_argument("--trials", type=int, default=None, help="trials per rate (overrides --quick)")
    parser.add_argument("--drivers", choices=("adjacent", "proximal", "distal"), default="adjacent",
                        help="which joints' angles move each segment's skin (default: all adjacent joints)")
    parser.add_argument("--occlusion", type=float, default=OCCLUSION,
                        help=f"share of the markers missing in a frame (default {OCCLUSION})")
    parser.add_argument("--out", default="skeleton_sta.md", help="result file name in bench/results")
    args_list = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(args_list)
    trials = args.trials or (4 if args.quick else 16)
    t0 = time.perf_counter()
    results = run(trials, args.drivers, args.occlusion)
    parts = run_header(
        "Skin artefact on every segment of the lower body: the node's covariances, skin against rigid",
        SCRIPT,
        args_list,
        SEED,
        f"{trials} trials per rate; skin artefact driven by the {args.drivers} joints' angles; "
        f"{100 * args.occlusion:g} % of the markers occluded; the data and "
        "the measures are described in the script's docstring.",
    )
    parts += tables(results)
    parts += ["", elapsed_line(t0)]
    print_and_write(args.out, parts)
    return 0


if __name__ == "__main__":
    sys.exit(main())
