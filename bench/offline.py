"""Throughput of ``jointfit fit`` on a long recording against reading the same file alone.

Run with ``python bench/offline.py`` (repository root, ``PYTHONPATH=.:test``); ``--frames N``
changes the length (default 100 000). Prints Markdown and writes ``bench/results/offline.md``.

The recording: the fake mocap stream (:mod:`jointfit_ros.fake_mocap`: a hip ball joint and a knee
hinge, 4 + 4 markers each, plus 24 static markers, so 40 markers per frame; 0.5 mm noise, 2 %
occlusions) at 100 Hz, written as rosbag2 ``PoseArray`` messages in both storages (sqlite3 and
mcap) with ``rosbags``. For each bag, in the same run:

* **read**: iterate over the messages (:func:`jointfit_ros.bag.iter_bag_messages`): what any
  tool pays to get the bytes out of the file;
* **read + parse**: also parse every message into a ``(40, 3)`` frame, in blocks of 4096
  messages as ``jointfit fit`` does (:meth:`jointfit_ros.inputs.MarkerParser.frames_many`);
* **fit, one process**: ``jointfit fit BAG --config ... --no-report --single-process``
  (:func:`jointfit_ros.cli.fit_main`, called here): read, parse, both joints' estimators over
  the whole recording (windows covering it), final solve, calibrations and summary written, all
  in this process;
* **fit**: the same as ``jointfit fit`` runs by default: the bag read and parsed in a second
  process while the estimators run (:mod:`jointfit_ros.bag_blocks`);
* **fit + report**: ``fit`` with the report figures.

Each is timed three times after one untimed warm-up read of the bag (file cache); the table
gives the fastest wall time, and the CPU time (this process and its reader process) of that
run. The headline is **fit / read**: how much the estimation adds to reading the file.
"""

from __future__ import annotations

import argparse
import datetime as dt
import math
import resource
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine, markdown_table, save_results
from bagtools import write_marker_bag

from jointfit_ros.bag import iter_bag_messages
from jointfit_ros.cli import fit_main
from jointfit_ros.fake_mocap import extra_marker_positions, frame_at, make_rigs, marker_names
from jointfit_ros.inputs import MessageRouter
from jointfit_ros.params import node_config, params_from_file

RESULTS = Path(__file__).resolve().parent / "results" / "offline.md"
EXTRA = 24
RATE = 100.0


def _config(path: Path) -> Path:
    path.write_text(
        f"""jointfit:
  ros__parameters:
    joints: [hip, knee]
    marker_topic: /markers
    marker_names: [{", ".join(marker_names(EXTRA))}]
    hip:
      type: ball
      parent_markers: [PELV1, PELV2, PELV3, PELV4]
      child_markers: [THIGH1, THIGH2, THIGH3, THIGH4]
    knee:
      type: hinge
      parent_markers: [FEMUR1, FEMUR2, FEMUR3, FEMUR4]
      child_markers: [SHANK1, SHANK2, SHANK3, SHANK4]
"""
    )
    return path


def _frames(n: int) -> tuple[np.ndarray, np.ndarray]:
    rigs = make_rigs(0)
    rng = np.random.default_rng(0)
    extra = extra_marker_positions(EXTRA, 0)
    t = np.arange(n) / RATE
    frames = np.stack([frame_at(rigs, float(tk), rng, 0.5, 0.02, extra=extra) for tk in t]) / 1000.0
    return frames, (1_700_000_000_000_000_000 + np.rint(t * 1e9)).astype(np.int64)


def _cpu() -> float:
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def _timed(fn: Callable[[], object], repeat: int = 3) -> tuple[float, float]:
    """The fastest of ``repeat`` runs: (wall s, CPU s of this process and its finished children)."""
    best = (math.inf, math.inf)
    for _ in range(repeat):
        cpu, start = _cpu(), time.perf_counter()
        fn()
        best = min(best, (time.perf_counter() - start, _cpu() - cpu))
    return best


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100_000, help="frames in the recording (default 100000)")
    opts = parser.parse_args(argv)
    n = opts.frames
    command = "python bench/offline.py" + (f" --frames {n}" if n != 100_000 else "")
    print(f"generating {n} frames of 40 markers ...", file=sys.stderr)
    frames, stamps = _frames(n)
    rows = []
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        config = _config(tmp / "params.yaml")
        cfg = node_config(params_from_file(config))
        for storage in ("sqlite3", "mcap"):
            start = time.perf_counter()
            bag = write_marker_bag(tmp / f"rec_{storage}", frames, stamps, storage=storage, topic="/markers")
            write_s = time.perf_counter() - start
            size_mb = sum(p.stat().st_size for p in bag.iterdir()) / 1e6
            print(f"{storage}: wrote {size_mb:.0f} MB in {write_s:.1f} s", file=sys.stderr)

            def read(bag: Path = bag) -> None:
                for _ in iter_bag_messages(bag, ["/markers"]):
                    pass

            def read_parse(bag: Path = bag) -> None:
                router = MessageRouter(cfg, [])
                block: list[bytes] = []
                for msg in iter_bag_messages(bag, ["/markers"]):
                    block.append(msg.raw)
                    if len(block) == 4096:
                        router.parser.frames_many(block)
                        block = []
                router.parser.frames_many(block)

            def fit(*extra: str, bag: Path = bag) -> None:
                args = [str(bag), "--config", str(config), "--out", str(tmp / "out"), "--quiet", *extra]
                code = fit_main(args)
                if code != 0:
                    raise SystemExit(f"jointfit fit failed with status {code}")

            read()  # warm the file cache
            t_read = _timed(read)
            steps = [
                ("read", t_read),
                ("read + parse", _timed(read_parse)),
                ("fit, one process", _timed(lambda: fit("--no-report", "--single-process"))),
                ("fit", _timed(lambda: fit("--no-report"))),
                ("fit + report", _timed(fit)),
            ]
            for what, (secs, cpu) in steps:
                rows.append(
                    [
                        storage,
                        what,
                        f"{secs:.2f}",
                        f"{cpu:.2f}",
                        f"{n / secs:,.0f}",
                        f"{secs / t_read[0]:.2f}",
                        f"{1e6 * secs / n:.1f}",
                    ]
                )
            print(f"{storage}: read {t_read[0]:.2f} s, fit {steps[3][1][0]:.2f} s", file=sys.stderr)
    table = markdown_table(["storage", "what", "wall s", "CPU s", "frames/s", "x read", "us/frame"], rows)
    fit_ratio = [float(r[5]) for r in rows if r[1] == "fit"]
    one_ratio = [float(r[5]) for r in rows if r[1] == "fit, one process"]
    text = "\n".join(
        [
            f"# jointfit fit throughput ({n} frames, 40 markers, two joints)",
            "",
            f"Command: `{command}` ({dt.date.today().isoformat()})",
            "",
            f"Machine: {machine()}",
            "",
            table,
            "",
            f"fit / read: {', '.join(f'{x:.2f}' for x in fit_ratio)} (sqlite3, mcap); "
            f"in one process {', '.join(f'{x:.2f}' for x in one_ratio)}. "
            "`x read` is each step's wall time over reading the file alone in the same run. "
            "The reader process (`fit`) shortens the wall time, not the CPU time.",
            "",
        ]
    )
    print(text)
    save_results(RESULTS, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
