"""``jointfit``: the offline command line (``fit``) and the bag player (``replay``).

Usage::

    jointfit fit INPUT --config FILE [--out DIR] [--node-name NAME] [--window {all,config}]
                 [--html] [--no-report] [--write-calibration] [--single-process]
                 [--progress | --quiet]
    jointfit markers FILE        (labels, rate, units, frames and gaps of a C3D/TRC; a bag's topics)
    jointfit replay BAG [--rate R] [--loop] [--topics T ...] ...   (see jointfit_ros.replay)
    python -m jointfit_ros.cli fit ...

``jointfit fit`` runs the node's estimators (:mod:`jointfit_ros.offline`) over
a whole recording, a rosbag2 bag (sqlite3 or mcap), a C3D or a TRC file,
with the node's own parameter file, and writes to ``DIR`` (default
``<input name>_jointfit`` next to the current directory):

* ``<joint>.calibration.yaml``: the calibration the node loads (copy it to the
  joint's ``calibration_file``, or pass ``--write-calibration`` to write it
  there, keeping the previous file as ``.bak``); written only for joints with
  an identifiable estimate;
* ``summary.json``: estimates in the parent and child segment frames, their
  covariances and standard deviations, residuals, verdicts and counters;
* ``<joint>.png``: the report figure (:mod:`jointfit_ros.report`), unless
  ``--no-report``; ``report.html`` with ``--html``.

Everything is computed before anything is written, and every file is written
to a temporary name and renamed: a failed run leaves ``DIR`` as it was.

Exit status: 0 every joint identified; 3 the outputs were written but some
joint has no identifiable estimate, or the outlier gate rejected more than
10 % of a segment's frames (the one-line summary, the summary and the figure
say why);
1 bad input or configuration (one line on stderr, nothing written); 2 bad
arguments; 130 interrupted.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn

from jointfit_core import __version__
from jointfit_core.atomic import write_all_or_nothing
from jointfit_core.calibration import calibration_text, save_calibration
from jointfit_core.errors import JointfitError

from .offline import READER_PROCESS_MIN_BYTES, FitRun, run_fit
from .params import calibration_path, node_config, params_from_file
from .report import fit_summary, html_page, joint_reports

__all__ = ["main", "fit_main"]

PROG = "jointfit"


class _UsageError(Exception):
    """Bad command-line arguments (one line)."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        raise _UsageError(message)


def _fit_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog=f"{PROG} fit",
        description="Fit the configured joints over a whole recording and write calibrations, a summary and a report.",
    )
    p.add_argument("input", help="rosbag2 bag (directory, .db3 or .mcap), .c3d or .trc file")
    p.add_argument("--config", required=True, help="the node's parameter file (config/*.yaml)")
    p.add_argument("--out", help="output directory (default: <input name>_jointfit)")
    p.add_argument("--node-name", default="jointfit", help="entry of the parameter file to read (default jointfit)")
    p.add_argument(
        "--window",
        choices=("all", "config"),
        default="all",
        help="all: every joint's window is the whole recording (default); config: the configured windows, "
        "i.e. what the node holds at the end of the recording",
    )
    p.add_argument("--html", action="store_true", help="also write report.html")
    p.add_argument("--no-report", action="store_true", help="no figures (faster; summary and calibrations only)")
    p.add_argument(
        "--write-calibration",
        action="store_true",
        help="also write each identified joint's calibration to its configured calibration_file (old one kept as .bak)",
    )
    p.add_argument(
        "--single-process",
        action="store_true",
        help="read and parse a bag in this process (default: in a second process while the estimators run, "
        f"for bags of {READER_PROCESS_MIN_BYTES / 1e6:g} MB or more; the results are the same)",
    )
    shown = p.add_mutually_exclusive_group()
    shown.add_argument("--progress", action="store_true", help="show progress even when stderr is not a terminal")
    shown.add_argument("--quiet", action="store_true", help="print only errors")
    return p


def _progress_printer(label: str) -> Any:
    start = time.perf_counter()
    last = [-1.0]

    def show(done: int, total: int) -> None:
        now = time.perf_counter()
        if done < total and now - last[0] < 0.5:
            return  # at most two updates a second
        if done >= total and last[0] == math.inf:
            return
        last[0] = math.inf if done >= total else now
        pct = 100.0 * done / total if total else 100.0
        rate = done / max(now - start, 1e-9)
        end = "\n" if done >= total else ""
        print(f"\r{label}: {pct:5.1f} % ({done}/{total} inputs, {rate:,.0f}/s)", end=end, file=sys.stderr, flush=True)

    return show


def _one_line(run: FitRun, joint: dict[str, Any]) -> str:
    unit = run.units or "units"
    name = f"{joint['name']} ({joint['type']})"
    if joint["status"] == "no estimate":
        return f"{name}: no estimate: {joint['message']}"
    if "centre_parent" in joint:
        est = "centre_parent (" + ", ".join(f"{v:.4g}" for v in joint["centre_parent"]) + ")"
        est += f" sd <= {max(joint['sd_parent']):.2g} {unit}"
        if "sd_parent_statistical" in joint:
            est += f" (statistical {max(joint['sd_parent_statistical']):.2g}, the rest soft-tissue artefact)"
    else:
        est = "direction_parent (" + ", ".join(f"{v:.3f}" for v in joint["direction_parent"]) + ")"
        est += f" sd {joint['direction_sd_deg_parent']:.2g} deg"
        if "direction_sd_deg_parent_statistical" in joint:
            est += f" (statistical {joint['direction_sd_deg_parent_statistical']:.2g})"
        est += f", pointing {joint['axis_points']}"
    verdict = "" if joint["identifiable"] else f"; NOT identifiable: {joint['reason']}"
    if joint.get("gate_warning"):
        verdict += f"; WARNING: {joint['gate_warning']}"
    gated = joint["gated"]
    share = f"gated {gated['parent']['percent']:.2g} % parent, {gated['child']['percent']:.2g} % child"
    return f"{name}: {est}, rms {joint['rms_residual']:.3g} {unit}, {joint['frames_in_window']} frames, {share}{verdict}"


def fit_main(argv: Sequence[str]) -> int:
    """Run ``jointfit fit`` (see the module docstring); returns the exit status."""
    try:
        opts = _fit_parser().parse_args(list(argv))
    except _UsageError as exc:
        print(f"{PROG} fit: error: {exc}", file=sys.stderr)
        return 2
    except SystemExit as exc:  # --help
        return exc.code if isinstance(exc.code, int) else 0
    out_dir = Path(opts.out) if opts.out else Path(Path(opts.input).name.split(".")[0] + "_jointfit")
    show = opts.progress or (not opts.quiet and sys.stderr.isatty())
    started = time.perf_counter()
    try:
        cfg = node_config(params_from_file(opts.config, opts.node_name))
        run = run_fit(
            opts.input,
            cfg,
            whole_recording=opts.window == "all",
            keep_frames=not opts.no_report,
            reader_process=False if opts.single_process else None,
            progress=_progress_printer(f"fitting {Path(opts.input).name}") if show else None,
        )
        geos, figures = ({}, {}) if opts.no_report else joint_reports(run)
        summary = fit_summary(run, elapsed_s=time.perf_counter() - started, version=__version__, geos=geos)
        # Everything is computed before anything is written.
        calibrations: dict[str, dict[str, Any]] = {}
        configured = {j.name: j for j in cfg.joints}
        for trace, joint in zip(run.traces, summary["joints"], strict=True):
            if trace.final is not None and trace.final.identifiable:
                data = trace.runner.estimator.to_dict()
                # The estimate is the recording's; the window a node resumes with (after ~/freeze false)
                # is the configured one, not the fit's no-forgetting sums.
                data.update(dict.fromkeys(("window", "window_s", "half_life", "half_life_s")))
                data.update(configured[joint["name"]].window_kwargs())
                calibrations[joint["name"]] = data
        for joint in summary["joints"]:
            name = joint["name"]
            joint["calibration_file"] = str(out_dir / f"{name}.calibration.yaml") if name in calibrations else None
            joint["figure"] = str(out_dir / f"{name}.png") if name in figures else None
        summary["config"] = str(opts.config)
        summary["window"] = opts.window

        files: dict[str, bytes | str] = {f"{n}.calibration.yaml": calibration_text(d) for n, d in calibrations.items()}
        files.update({f"{n}.png": png for n, png in figures.items()})
        if opts.html:
            files["report.html"] = html_page(summary, {n: f"{n}.png" for n in figures})
        files["summary.json"] = json.dumps(summary, indent=2, allow_nan=False, default=str) + "\n"
        write_all_or_nothing(out_dir, files)
        installed = []
        if opts.write_calibration:
            for j in cfg.joints:
                if j.name in calibrations and j.calibration_file:
                    installed.append(str(save_calibration(calibration_path(j.calibration_file), calibrations[j.name])))
    except (JointfitError, OSError, ValueError) as exc:
        print(f"{PROG} fit: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{PROG} fit: interrupted", file=sys.stderr)
        return 130
    if not opts.quiet:
        for joint in summary["joints"]:
            print(_one_line(run, joint))
        print(f"wrote {out_dir}/ ({len(calibrations)} calibration(s), summary.json"
              + (f", {len(figures)} figure(s)" if figures else "") + (", report.html" if opts.html else "") + ")")
        for path in installed:
            print(f"installed calibration {path}")
    warned = any(j.get("gate_warning") for j in summary["joints"])
    return 0 if len(calibrations) == len(run.traces) and not warned else 3


def main(argv: Sequence[str] | None = None) -> None:
    """Console entry point ``jointfit``."""
    args = list(sys.argv[1:] if argv is None else argv)
    usage = f"usage: {PROG} {{fit,markers,replay}} ... (see '{PROG} fit --help', '{PROG} replay --help')"
    if not args or args[0] in ("-h", "--help"):
        print(usage)
        sys.exit(0 if args else 2)
    command, rest = args[0], args[1:]
    if command == "fit":
        sys.exit(fit_main(rest))
    if command == "markers":
        from .markers_cli import markers_main

        sys.exit(markers_main(rest))
    if command == "replay":
        from .replay import replay_main

        sys.exit(replay_main(rest))
    print(f"{PROG}: error: unknown command {command!r}; {usage}", file=sys.stderr)
    sys.exit(2)


if __name__ == "__main__":
    main()
