"""BLAS threads: the two-segment fits' wall clock and CPU with one OpenBLAS thread against one per core.

Run with ``python bench/blas_threads.py`` (repository root, ``PYTHONPATH=.:test``); prints Markdown and
writes ``bench/results/blas_threads.md``. Why: ``jointfit_core`` sets ``OPENBLAS_NUM_THREADS`` (and the
OpenMP / MKL twins) to 1 unless the user set them, before numpy loads; this measures what that changes.

What is measured
----------------
Each configuration runs in its own Python process (OpenBLAS reads the variable once, when numpy loads):
``fit_axis_two_segments`` and ``fit_centre_two_segments`` on the synthetic rigs of ``bench/peers.py``
(3 + 3 markers, 1 mm noise plus 3 mm of smooth artefact, 20 s at 60 Hz, skin attachment), one warm-up
fit, then the median over ``REPEATS`` fits of the wall clock (``time.perf_counter``) and of the process
CPU (``time.process_time``, all threads). Threads: ``1`` against ``os.cpu_count()``. Machine: as found
(its load average is in the header: shared machines are rarely idle), and with one more process spinning
on one core (as the node's marker stream or a second fit would), in the same run, so that the ratios
compare like with like.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine, markdown_table, save_results

from jointfit_core import BLAS_THREAD_VARIABLES

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results" / "blas_threads.md"
REPEATS = 5

CHILD = """
import json, sys, time
sys.path.insert(0, "bench")
import numpy as np
import peers
from jointfit_core.segments import fit_axis_two_segments, fit_centre_two_segments
out = {}
for kind, fit in (("hinge", fit_axis_two_segments), ("ball", fit_centre_two_segments)):
    _, p, c = peers._rig(np.random.default_rng(3), kind, 20.0, True)
    fit(p, c)
    wall, cpu = [], []
    for _ in range(REPEATS):
        w0, c0 = time.perf_counter(), time.process_time()
        fit(p, c)
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    out[kind] = (float(np.median(wall)), float(np.median(cpu)))
print(json.dumps(out))
"""


def _spin(stop: float) -> None:
    while time.time() < stop:
        pass


def _run(threads: int) -> dict[str, tuple[float, float]]:
    env = dict(os.environ, PYTHONPATH=f"{ROOT}:{ROOT / 'test'}")
    for name in BLAS_THREAD_VARIABLES:
        env[name] = str(threads)
    code = CHILD.replace("REPEATS", str(REPEATS))
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, check=True)
    result: dict[str, tuple[float, float]] = {k: tuple(v) for k, v in json.loads(done.stdout.splitlines()[-1]).items()}
    return result


def main() -> int:
    cores = os.cpu_count() or 1
    started = time.time()
    rows = []
    for load in ("as found", "+1 busy core"):
        runs: dict[int, dict[str, tuple[float, float]]] = {}
        spinner = None
        if load != "as found":
            spinner = mp.Process(target=_spin, args=(time.time() + 3600.0,), daemon=True)
            spinner.start()
        try:
            for threads in (1, cores):
                runs[threads] = _run(threads)
        finally:
            if spinner is not None:
                spinner.terminate()
                spinner.join()
        for kind in ("hinge", "ball"):
            (w1, c1), (wn, cn) = runs[1][kind], runs[cores][kind]
            rows.append([f"{kind}, 20 s skin", load, f"{1e3 * w1:.0f}", f"{1e3 * c1:.0f}", f"{1e3 * wn:.0f}",
                         f"{1e3 * cn:.0f}", f"{wn / w1:.2f}", f"{cn / c1:.2f}"])  # fmt: skip
    table = markdown_table(
        ["fit", "machine", "1 thread wall (ms)", "1 thread CPU (ms)", f"{cores} threads wall (ms)",
         f"{cores} threads CPU (ms)", "wall ratio", "CPU ratio"],
        rows,
    )  # fmt: skip
    text = "\n".join([
        "# BLAS threads: one OpenBLAS thread against one per core",
        "",
        f"Command: `python bench/blas_threads.py`; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime(started))}.",
        f"Machine: {machine()}.",
        "",
        f"Median of {REPEATS} fits per cell, each configuration in its own process (see the script's docstring); "
        "ratio: threads per core over one thread (above 1: the threads cost more).",
        "",
        table,
        "",
    ])  # fmt: skip
    print(text)
    save_results(RESULTS, text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
