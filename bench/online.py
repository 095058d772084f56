"""Per-frame cost of the online estimators against re-fitting the window with the batch functions.

Run with ``python bench/online.py`` (from the repository root, ``PYTHONPATH=.``); prints Markdown
and writes ``bench/results/online.md``. Every number comes from this run on this machine (seeded
``np.random.default_rng``); the header names the machine. Times are wall-clock
(``time.perf_counter_ns`` around each call), in microseconds (us).

What is measured
----------------
1. **OnlineCentre** and **OnlineAxis** (:mod:`jointfit_core.online`), windows of 100, 1 000 and
   10 000 frames, 4, 10 and 40 markers. Markers rotate about a fixed centre (random-walk
   rotations, 1 deg/frame, :func:`jointfit_core.synthetic.random_walk_rotations`) or about a fixed
   axis (1 deg/frame, as :func:`jointfit_core.synthetic.gl_axis_setup`), 1 mm Gaussian noise per
   coordinate, a lab offset of a few metres, and 5 % of the marker positions missing (NaN).
   The window is filled first (``update`` only, ``window`` times); then, for each of
   ``TIMED_FRAMES`` frames, ``update(frame)`` and ``estimate()`` are timed separately. The batch
   baseline is :func:`~jointfit_core.sphere.fit_centre` / :func:`~jointfit_core.axis.fit_axis` on the
   same window's frames (the window ending at each timed frame), with as many repetitions as fit
   in ``BATCH_BUDGET_S`` (at least ``BATCH_MIN_REPS``, so only a handful at 10 000 x 40; the
   repetition count is printed). Columns are medians over the timed frames (repetitions);
   **batch / online** (batch re-fit over update + estimate) is the headline. ``|online - batch|``
   checks that both computed the same thing (the online estimate and the batch fit of the final
   window, which should agree to rounding). Target: cost flat in the window length, update +
   estimate at 10 000 frames within 1.5x of that at 100 frames, printed per marker count.
2. **OnlineJoint** (:mod:`jointfit_core.estimator`), ball and hinge, 4 + 4 markers
   (:func:`jointfit_core.synthetic.two_segment_motion`, 100 Hz, same noise, offset and
   occlusions), windows of 100, 1 000 and 10 000 frames. After the templates are built and the
   window is full, ``JOINT_FRAMES`` frames are streamed three times: with ``estimate()`` after
   every frame, after every 10th and after every 100th. ``update`` (which returns the world
   output of the frame from the latest estimate) is timed on its own: p50, p99, max and mean per
   call; ``estimate()`` on its own, mean per call; **per frame** = mean update + estimate cost
   amortised over the frames. Target: one joint under 50 us per frame including the world
   output; the verdict is printed per row. The batch baseline (table 2b) is
   ``fit_centre_two_segments(parent, child, weighted=False, model_error=False)`` (ball) and
   ``fit_axis_two_segments(parent, child, weighted=False)`` (hinge) on the window, against the
   online per-frame cost with ``estimate()`` every frame. After the timed frames, one more frame's
   world output (from the estimate of the window just before it) is compared with the batch fit of
   the window ending at that frame and with the true joint: ball, distance between world centres;
   hinge, distance of the axis point from the other axis line and the angle between the axes.
   This is a plausibility check only: the batch builds its templates from the window, the online
   estimator from its first frames, so they agree to noise level, not to rounding. The errors are
   those of one frame's world output, which carries that frame's parent pose noise over the
   ~500 mm lever arm; the output's own ``sqrt(tr cov)`` is printed next to them.

Reading the numbers: this machine is a small shared VM (the header prints the load average at
the start), so single calls vary; medians and p50 are robust, p99/max show the spikes, the
scheduler's and the garbage collector's included (the estimators themselves do the same work
every frame, no O(window) rebuilds).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import gc
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from _common import machine, markdown_table, save_results
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from jointfit_core.axis import fit_axis
from jointfit_core.errors import InputError, NotIdentifiableError
from jointfit_core.estimator import JointOutput, OnlineJoint
from jointfit_core.online import OnlineAxis, OnlineCentre
from jointfit_core.segments import fit_axis_two_segments, fit_centre_two_segments
from jointfit_core.sphere import fit_centre
from jointfit_core.synthetic import TwoSegmentMotion, random_walk_rotations, two_segment_motion

FloatArray = NDArray[np.float64]

SEED = 20240612
RESULTS = Path(__file__).resolve().parent / "results" / "online.md"

WINDOWS = (100, 1_000, 10_000)
MARKERS = (4, 10, 40)
NOISE_MM = 1.0
OCCLUDED = 0.05
OFFSET_MM = (2500.0, -1800.0, 1000.0)
STEP_DEG = 1.0
TIMED_FRAMES = 500
BATCH_BUDGET_S = 1.0
BATCH_MIN_REPS = 5
BATCH_MAX_REPS = 200
FLAT_TARGET = 1.5

JOINT_MARKERS = (4, 4)
JOINT_RATE_HZ = 100.0
JOINT_TEMPLATE_FRAMES = 50
JOINT_FRAMES = 2_000
ESTIMATE_EVERY = (1, 10, 100)
JOINT_BATCH_BUDGET_S = 2.0
JOINT_TARGET_US = 50.0

_ESTIMATE_ERRORS = (InputError, NotIdentifiableError)


# ----------------------------------------------------------------------------- helpers


def _us(ns: float) -> float:
    return ns / 1e3


def _p(ns: Sequence[int] | NDArray[np.int64], q: float) -> float:
    """Percentile ``q`` of call durations, in us."""
    return _us(float(np.percentile(np.asarray(ns, dtype=np.float64), q)))


def _occlude(rng: np.random.Generator, markers: FloatArray, fraction: float) -> FloatArray:
    """NaN for ``fraction`` of the marker positions, never a whole frame."""
    out = markers.copy()
    gone = rng.random(markers.shape[:2]) < fraction
    gone[gone.all(axis=1)] = False
    out[gone] = np.nan
    return out


def _time_batch(fit: Callable[[int], Any], ends: Sequence[int], budget_s: float) -> tuple[list[int], int]:
    """Durations (ns) of ``fit(end)`` for the windows ending at ``ends``, as many as fit in ``budget_s``.

    One untimed call first (imports, caches); then at least ``BATCH_MIN_REPS`` and at most
    ``BATCH_MAX_REPS`` timed calls. Returns the durations and the number of calls that raised.
    """
    with contextlib.suppress(*_ESTIMATE_ERRORS):
        fit(ends[0])
    raised = 0
    times: list[int] = []
    spent = 0
    for k, end in enumerate(ends):
        if k >= BATCH_MAX_REPS or (k >= BATCH_MIN_REPS and spent > budget_s * 1e9):
            break
        t0 = time.perf_counter_ns()
        try:
            fit(end)
        except _ESTIMATE_ERRORS:
            raised += 1
        dt_ns = time.perf_counter_ns() - t0
        times.append(dt_ns)
        spent += dt_ns
    return times, raised


# ----------------------------------------------------------------------------- data


def _centre_markers(rng: np.random.Generator, n_markers: int, n_frames: int) -> FloatArray:
    """(n_frames, P, 3) mm: markers 100-350 mm from a centre in the lab, random-walk rotations, noise, NaNs."""
    direction = rng.normal(size=(n_markers, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    local = direction * rng.uniform(100.0, 350.0, (n_markers, 1))
    rots = random_walk_rotations(rng, n_frames, step_deg=STEP_DEG).as_matrix()
    clean = np.einsum("nij,pj->npi", rots, local) + np.asarray(OFFSET_MM)
    return _occlude(rng, clean + rng.normal(0.0, NOISE_MM, clean.shape), OCCLUDED)


def _axis_markers(rng: np.random.Generator, n_markers: int, n_frames: int) -> tuple[FloatArray, FloatArray]:
    """(n_frames, P, 3) mm rotating STEP_DEG per frame about a fixed lab axis; and the axis direction."""
    direction = Rotation.random(random_state=rng).apply([0.0, 1.0, 0.0])
    basis = np.linalg.svd(direction[None, :])[2][1:]  # two unit vectors orthogonal to the axis
    radius = rng.uniform(50.0, 300.0, n_markers)
    phi = rng.uniform(0.0, 2.0 * np.pi, n_markers)
    along = rng.uniform(-150.0, 150.0, n_markers)
    local = (
        radius[:, None] * (np.cos(phi)[:, None] * basis[0] + np.sin(phi)[:, None] * basis[1])
        + along[:, None] * direction
    )
    angles = np.deg2rad(STEP_DEG) * np.arange(n_frames)
    rots = Rotation.from_rotvec(angles[:, None] * direction[None, :]).as_matrix()
    clean = np.einsum("nij,pj->npi", rots, local) + np.asarray(OFFSET_MM)
    return _occlude(rng, clean + rng.normal(0.0, NOISE_MM, clean.shape), OCCLUDED), direction


# ----------------------------------------------------------------------------- table 1


@dataclass
class _Cell:
    """Timings of one (window, markers) cell of table 1."""

    window: int
    n_markers: int
    update_ns: list[int]
    total_ns: list[int]
    estimate_ns: list[int]
    batch_ns: list[int]
    raised_online: int
    raised_batch: int
    agreement: str

    @property
    def online_us(self) -> float:
        return _p(self.total_ns, 50)

    @property
    def batch_us(self) -> float:
        return _p(self.batch_ns, 50)


def _agreement_centre(est: OnlineCentre) -> str:
    try:
        a = est.estimate().centre
        b = fit_centre(est.window_markers()).centre
    except _ESTIMATE_ERRORS as exc:
        return f"raised {type(exc).__name__}"
    return f"{np.max(np.abs(a - b)):.1e} mm"


def _agreement_axis(est: OnlineAxis) -> str:
    try:
        a = est.estimate()
        b = fit_axis(est.window_markers(), reference_direction=est.reference_direction)
    except _ESTIMATE_ERRORS as exc:
        return f"raised {type(exc).__name__}"
    return f"{np.max(np.abs(a.point - b.point)):.1e} mm, {np.max(np.abs(a.direction - b.direction)):.1e} dir"


def _online_cell(kind: str, window: int, markers: FloatArray, direction: FloatArray | None) -> _Cell:
    """Fill the window, then time update and estimate per frame, then the batch re-fit."""
    est: OnlineCentre | OnlineAxis
    est = (
        OnlineCentre(window=window)
        if kind == "centre"
        else OnlineAxis(window=window, reference_direction=direction)
    )
    for k in range(window):
        est.update(markers[k])
    upd: list[int] = []
    tot: list[int] = []
    estn: list[int] = []
    raised = 0
    gc.collect()
    for k in range(window, window + TIMED_FRAMES):
        t0 = time.perf_counter_ns()
        est.update(markers[k])
        t1 = time.perf_counter_ns()
        try:
            est.estimate()
        except _ESTIMATE_ERRORS:
            raised += 1
        t2 = time.perf_counter_ns()
        upd.append(t1 - t0)
        estn.append(t2 - t1)
        tot.append(t2 - t0)
    agreement = _agreement_centre(est) if isinstance(est, OnlineCentre) else _agreement_axis(est)

    def batch(end: int) -> Any:
        frames = markers[end - window + 1 : end + 1]
        if kind == "centre":
            return fit_centre(frames)
        return fit_axis(frames, reference_direction=direction)

    gc.collect()
    batch_ns, raised_batch = _time_batch(batch, range(window, window + TIMED_FRAMES), BATCH_BUDGET_S)
    return _Cell(window, markers.shape[1], upd, tot, estn, batch_ns, raised, raised_batch, agreement)


def moments_table(kind: str, rng: np.random.Generator) -> tuple[str, str]:
    """Table 1 (``kind`` "centre") or 1b ("axis") and its flatness lines."""
    n_frames = max(WINDOWS) + TIMED_FRAMES
    cells: dict[tuple[int, int], _Cell] = {}
    for p in MARKERS:
        direction: FloatArray | None
        if kind == "centre":
            markers, direction = _centre_markers(rng, p, n_frames), None
        else:
            markers, direction = _axis_markers(rng, p, n_frames)
        for w in WINDOWS:
            cells[(w, p)] = _online_cell(kind, w, markers, direction)
    rows = []
    for w in WINDOWS:
        for p in MARKERS:
            c = cells[(w, p)]
            raised = c.raised_online + c.raised_batch
            rows.append(
                [
                    f"{w:,}".replace(",", " "),
                    f"{p}",
                    f"{_p(c.update_ns, 50):.0f}",
                    f"{_p(c.estimate_ns, 50):.0f}",
                    f"{c.online_us:.0f}",
                    f"{c.batch_us:,.0f}".replace(",", " "),
                    f"{len(c.batch_ns)}",
                    f"**{c.batch_us / c.online_us:.1f}**",
                    c.agreement,
                    f"{raised}",
                ]
            )
    header = [
        "window",
        "markers",
        "update (us)",
        "estimate (us)",
        "update + estimate (us)",
        "batch re-fit (us)",
        "batch reps",
        "batch / online",
        "|online - batch|",
        "raised",
    ]
    lines = []
    lo, hi = min(WINDOWS), max(WINDOWS)
    for p in MARKERS:
        r_tot = cells[(hi, p)].online_us / cells[(lo, p)].online_us
        r_upd = _p(cells[(hi, p)].update_ns, 50) / _p(cells[(lo, p)].update_ns, 50)
        verdict = "meets" if r_tot <= FLAT_TARGET else "misses"
        lines.append(
            f"- {p} markers: update + estimate at {hi} / at {lo} frames = **{r_tot:.2f}** ({verdict} the "
            f"target <= {FLAT_TARGET}); update only {r_upd:.2f}."
        )
    return markdown_table(header, rows), "\n".join(lines)


# ----------------------------------------------------------------------------- table 2


@dataclass
class _JointRow:
    """One (kind, window, estimate policy) row of table 2."""

    kind: str
    window: int
    every: int
    update_ns: NDArray[np.int64]
    estimate_ns: list[int]
    no_output: int
    raised: int

    @property
    def per_frame_us(self) -> float:
        return _us(float(self.update_ns.mean()) + sum(self.estimate_ns) / self.update_ns.size)


def _joint_stream(
    rng: np.random.Generator, kind: str, n_frames: int
) -> tuple[FloatArray, FloatArray, TwoSegmentMotion]:
    motion = two_segment_motion(rng, kind=kind, n_markers=JOINT_MARKERS, offset=OFFSET_MM)
    parent, child = motion.markers_at(np.arange(n_frames) / JOINT_RATE_HZ)
    parent = _occlude(rng, parent + rng.normal(0.0, NOISE_MM, parent.shape), OCCLUDED)
    child = _occlude(rng, child + rng.normal(0.0, NOISE_MM, child.shape), OCCLUDED)
    return parent, child, motion


def _line_gap(point: FloatArray, direction: FloatArray, line_point: FloatArray, line_dir: FloatArray) -> str:
    """Distance (mm) of ``point`` from a line and the angle (deg) between the directions, as text."""
    diff = point - line_point
    dist = float(np.linalg.norm(diff - line_dir * (diff @ line_dir)))
    angle = float(np.degrees(np.arccos(min(abs(float(direction @ line_dir)), 1.0))))
    return f"{dist:.2f} mm, {angle:.3f} deg"


def _joint_gaps(
    kind: str, out: JointOutput | None, fit: Any, motion: TwoSegmentMotion, frame: int
) -> list[str]:
    """Online vs batch, online vs truth, batch vs truth at ``frame`` (world, carried by the parent pose)."""
    t = frame / JOINT_RATE_HZ
    truth = motion.centre_world_at(t)[0]
    if kind == "ball":
        b = fit.centre_world[-1]
        if out is None:
            return ["no output", "no output", "", f"{np.linalg.norm(b - truth):.2f} mm"]
        return [
            f"{np.linalg.norm(out.position - b):.2f} mm",
            f"{np.linalg.norm(out.position - truth):.2f} mm",
            f"{np.sqrt(np.trace(out.cov)):.2f} mm",
            f"{np.linalg.norm(b - truth):.2f} mm",
        ]
    d_true = motion.poses_at(t)[0][0] @ motion.axis
    b_point, b_dir = fit.point_world[-1], fit.direction_world[-1]
    batch_gap = _line_gap(b_point, b_dir, truth, d_true)
    if out is None or out.direction is None:
        return ["no output", "no output", "", batch_gap]
    return [
        _line_gap(out.position, out.direction, b_point, b_dir),
        _line_gap(out.position, out.direction, truth, d_true),
        f"{np.sqrt(np.trace(out.cov)):.2f} mm",
        batch_gap,
    ]


def _joint_batch(kind: str, parent: FloatArray, child: FloatArray, window: int) -> Callable[[int], Any]:
    """The batch fit of the window ending at frame ``end``, as a function of ``end``."""

    def batch(end: int) -> Any:
        p, c = parent[end - window + 1 : end + 1], child[end - window + 1 : end + 1]
        if kind == "ball":
            return fit_centre_two_segments(p, c, weighted=False, model_error=False)
        return fit_axis_two_segments(p, c, weighted=False)

    return batch


def joint_tables(rng: np.random.Generator) -> tuple[str, str, str]:
    """Table 2 (per-frame cost by estimate policy), table 2b (batch baseline) and the verdict lines."""
    # Occluded frames count towards neither the templates nor the window: 10 % spare frames.
    n_stream = int(1.1 * (2 * JOINT_TEMPLATE_FRAMES + max(WINDOWS))) + len(ESTIMATE_EVERY) * JOINT_FRAMES
    rows: list[_JointRow] = []
    base_rows: list[list[str]] = []
    for kind in ("ball", "hinge"):
        parent, child, motion = _joint_stream(rng, kind, n_stream)
        for w in WINDOWS:
            est = OnlineJoint(kind, window=w, template_frames=JOINT_TEMPLATE_FRAMES)
            k = 0
            while not (est.templates_ready and est.n_window >= w):
                est.update(parent[k], child[k])
                k += 1
            est.estimate()
            first_timed = k
            out: JointOutput | None = None
            for every in ESTIMATE_EVERY:
                upd = np.empty(JOINT_FRAMES, dtype=np.int64)
                estn: list[int] = []
                no_output = raised = 0
                gc.collect()
                for i in range(JOINT_FRAMES):
                    t0 = time.perf_counter_ns()
                    out = est.update(parent[k], child[k])
                    t1 = time.perf_counter_ns()
                    upd[i] = t1 - t0
                    no_output += out is None
                    k += 1
                    if i % every == every - 1:
                        t1 = time.perf_counter_ns()
                        try:
                            est.estimate()
                        except _ESTIMATE_ERRORS:
                            raised += 1
                        estn.append(time.perf_counter_ns() - t1)
                rows.append(_JointRow(kind, w, every, upd, estn, no_output, raised))
            # Agreement: estimate the window ending at k - 1, then frame k's world output (untimed),
            # against the batch fit of the window ending at k (one frame apart) and the truth.
            est.estimate()
            out = est.update(parent[k], child[k])
            batch = _joint_batch(kind, parent, child, w)
            try:
                gaps = _joint_gaps(kind, out, batch(k), motion, k)
            except _ESTIMATE_ERRORS as exc:
                gaps = [f"batch raised {type(exc).__name__}"] * 4
            gc.collect()
            batch_ns, raised_batch = _time_batch(
                batch, range(first_timed, first_timed + JOINT_FRAMES), JOINT_BATCH_BUDGET_S
            )
            online = next(r for r in rows if r.kind == kind and r.window == w and r.every == 1)
            b_us = _p(batch_ns, 50)
            base_rows.append(
                [
                    kind,
                    f"{w:,}".replace(",", " "),
                    f"{b_us:,.0f}".replace(",", " "),
                    f"{len(batch_ns)}",
                    f"{online.per_frame_us:.0f}",
                    f"**{b_us / online.per_frame_us:.0f}**",
                    *gaps,
                    f"{raised_batch}",
                ]
            )
    table = []
    for r in rows:
        est_mean = _us(float(np.mean(r.estimate_ns))) if r.estimate_ns else float("nan")
        met = "yes" if r.per_frame_us < JOINT_TARGET_US else "no"
        table.append(
            [
                r.kind,
                f"{r.window:,}".replace(",", " "),
                f"{r.every}",
                f"{_p(r.update_ns, 50):.0f}",
                f"{_p(r.update_ns, 99):.0f}",
                f"{_us(float(r.update_ns.max())):.0f}",
                f"{_us(float(r.update_ns.mean())):.0f}",
                f"{est_mean:.0f}",
                f"**{r.per_frame_us:.0f}**",
                met,
                f"{r.no_output}",
                f"{r.raised}",
            ]
        )
    header = [
        "kind",
        "window",
        "estimate every",
        "update p50 (us)",
        "update p99 (us)",
        "update max (us)",
        "update mean (us)",
        "estimate() (us/call)",
        "per frame (us)",
        f"< {JOINT_TARGET_US:g} us",
        "no output",
        "raised",
    ]
    base_header = [
        "kind",
        "window",
        "batch re-fit (us)",
        "batch reps",
        "online per frame, estimate every frame (us)",
        "batch / online",
        "|online - batch|",
        "online error",
        "online √tr cov",
        "batch error",
        "batch raised",
    ]
    verdict = _joint_verdict(rows)
    return markdown_table(header, table), markdown_table(base_header, base_rows), verdict


def _joint_verdict(rows: Sequence[_JointRow]) -> str:
    """The 50 us target, said plainly, from the rows."""
    upd_p50 = [_p(r.update_ns, 50) for r in rows if r.every == max(ESTIMATE_EVERY)]
    est = [float(np.mean(r.estimate_ns)) / 1e3 for r in rows if r.every == 1]
    best = min(r.per_frame_us for r in rows)
    met = [r for r in rows if r.per_frame_us < JOINT_TARGET_US]
    lo, hi = min(WINDOWS), max(WINDOWS)
    flat = []
    for kind in ("ball", "hinge"):
        by_w = {r.window: r for r in rows if r.kind == kind and r.every == max(ESTIMATE_EVERY)}
        flat.append(f"{kind} {_p(by_w[hi].update_ns, 50) / _p(by_w[lo].update_ns, 50):.2f}")
    ratios = [_p(r.update_ns, 99) / _p(r.update_ns, 50) for r in rows]
    all_ns = np.concatenate([r.update_ns for r in rows])
    slow = int(np.count_nonzero(all_ns > 1_000_000))
    every_lo = [_p(r.update_ns, 50) for r in rows if r.every == min(ESTIMATE_EVERY)]
    amortised = [r.per_frame_us for r in rows if r.every == max(ESTIMATE_EVERY)]
    verdict = (
        "met" if len(met) == len(rows) else f"met in {len(met)} of {len(rows)} rows" if met else "not met"
    )
    lines = [
        f"- **Target (< {JOINT_TARGET_US:g} us per frame for one joint, world output included): {verdict}.** "
        f"The fastest row costs {best:.0f} us per frame. With `estimate()` every {max(ESTIMATE_EVERY)} frames "
        f"the per-frame cost is {min(amortised):.0f}-{max(amortised):.0f} us and `update` alone (world output "
        f"included) has p50 {min(upd_p50):.0f}-{max(upd_p50):.0f} us. `estimate()` costs "
        f"{min(est):.0f}-{max(est):.0f} us per call, so solving every frame dominates; `update` p50 is also "
        f"higher then ({min(every_lo):.0f}-{max(every_lo):.0f} us).",
        f"- Flat in the window: update p50 at {hi} / at {lo} frames (estimate every {max(ESTIMATE_EVERY)}): "
        + ", ".join(flat)
        + ".",
        f"- Latency spikes: p99 / p50 of `update` is {np.median(ratios):.1f} in the median row, at most "
        f"{max(ratios):.1f}; {slow} of {all_ns.size} `update` calls took over 1 ms (max "
        f"{_us(float(all_ns.max())):.0f} us).",
    ]
    return "\n".join(lines)


# ----------------------------------------------------------------------------- main


def main() -> int:
    t_start = time.perf_counter()
    rng_c, rng_a, rng_j = (np.random.default_rng(s) for s in np.random.SeedSequence(SEED).spawn(3))
    host = machine()
    print(f"Machine: {host}", flush=True)
    centre_md, centre_flat = moments_table("centre", rng_c)
    axis_md, axis_flat = moments_table("axis", rng_a)
    joint_md, base_md, joint_verdict = joint_tables(rng_j)
    parts = [
        "# jointfit online estimators: cost per frame",
        "",
        f"Made by `python bench/online.py` on {dt.date.today().isoformat()}, seed {SEED}.",
        "",
        f"Machine: {host}.",
        "",
        f"Synthetic markers (mm): {NOISE_MM:g} mm noise per coordinate, lab offset {OFFSET_MM} mm, "
        f"{100 * OCCLUDED:g} % of marker positions missing (NaN). All times in microseconds (us), "
        "wall clock per call (`time.perf_counter_ns`).",
        "",
        f"## 1. OnlineCentre (random-walk rotations about a centre, {STEP_DEG:g} deg/frame)",
        "",
        f"Window filled first, then {TIMED_FRAMES} frames timed: `update` then `estimate()` per frame "
        f"(medians). Batch = `fit_centre` on the same window's frames, repetitions as fit in "
        f"{BATCH_BUDGET_S:g} s (min {BATCH_MIN_REPS}, max {BATCH_MAX_REPS}; median). "
        "|online - batch| = largest coordinate difference of the final window's centre.",
        "",
        centre_md,
        "",
        centre_flat,
        "",
        f"## 1b. OnlineAxis (rotation about a fixed axis, {STEP_DEG:g} deg/frame)",
        "",
        "As table 1, batch = `fit_axis` on the window (same `reference_direction`). "
        "|online - batch| = largest coordinate difference of the point (mm) and of the unit direction.",
        "",
        axis_md,
        "",
        axis_flat,
        "",
        f"## 2. OnlineJoint, {JOINT_MARKERS[0]} + {JOINT_MARKERS[1]} markers, per-frame cost",
        "",
        f"Two-segment rig at {JOINT_RATE_HZ:g} Hz; templates from {JOINT_TEMPLATE_FRAMES} frames, window "
        f"filled, then {JOINT_FRAMES} frames per row. `update` includes the frame's world output (from "
        "the latest estimate); per frame = mean update + estimate() cost / frames. 'no output' counts "
        "frames whose `update` returned None (parent not posed); 'raised' counts estimate() calls that "
        "raised.",
        "",
        joint_md,
        "",
        joint_verdict,
        "",
        "## 2b. OnlineJoint against re-fitting the window in batch",
        "",
        "Batch = `fit_centre_two_segments(parent, child, weighted=False, model_error=False)` (ball), "
        "`fit_axis_two_segments(parent, child, weighted=False)` (hinge) on the window ending at each "
        f"timed frame, repetitions as fit in {JOINT_BATCH_BUDGET_S:g} s (min {BATCH_MIN_REPS}; median). "
        "The last columns compare one frame after the timed ones (world output of the online "
        "estimate of the window just before it; batch fit of the window ending at it; true joint): "
        "ball, distance between world centres; hinge, distance of the axis point from the other axis "
        "line and the angle between the axes. A plausibility check: the templates differ (online: "
        "first frames; batch: the window), so agreement is to noise level, not to rounding. The errors "
        "are of one frame's world output, so they include that frame's parent pose noise carried over "
        "the ~500 mm lever arm; online √tr cov is the spread the output reports for it (position).",
        "",
        base_md,
        "",
    ]
    parts.append(f"Total runtime {time.perf_counter() - t_start:.0f} s.")
    text = "\n".join(parts) + "\n"
    print(text, end="")
    save_results(RESULTS, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
