"""``jointfit``: the offline command line (``fit``) and the bag player (``replay``).

Usage::

    jointfit fit INPUT --config FILE [--out DIR] [--node-name NAME] [--window {all,config}]
                 [--html] [--no-report] [--export csv,trc,c3d] [--write-calibration]
                 [--single-process] [--progress | --quiet]
    jointfit markers FILE        (labels, rate, units, frames and gaps of a C3D/TRC; a bag's topics)
    jointfit convert FILE --to BAG [--type posearray|pointcloud2] [--topic T] [--frame-id F]
                     [--storage mcap|sqlite3] [--start S] [--units U] [--force]
                                 (a C3D/TRC as a rosbag2 bag; see jointfit_ros.convert)
    jointfit replay BAG [--rate R] [--loop] [--topics T ...] ...   (see jointfit_ros.replay)
    jointfit status [--node NAME] [--once] [--timeout S]           (a running node's /diagnostics)
    jointfit call {reset,freeze,save} [true|false] [--node NAME] [--timeout S]   (its services)
    python -m jointfit_ros.cli fit ...

``jointfit fit`` runs the node's estimators (:mod:`jointfit_ros.offline`) over
a whole recording, a rosbag2 bag (sqlite3 or mcap), a C3D or a TRC file,
with the node's own parameter file (for a C3D or TRC without ``marker_names``
the file's labels are the marker names), and writes to ``DIR`` (default
``<input name>_jointfit`` next to the current directory):

* ``<joint>.calibration.yaml``: the calibration the node loads (copy it to the
  joint's ``calibration_file``, or pass ``--write-calibration`` to write it
  there, keeping the previous file as ``.bak``; with the node's
  ``calibration_file`` the identified joints all go to that one file,
  :mod:`jointfit_core.node_calibration`, where a joint not identified keeps
  its previous entry); written only for joints with an identifiable estimate;
* ``summary.json``: estimates in the parent and child segment frames, their
  covariances and standard deviations, residuals, verdicts and counters;
* ``<joint>.png``: the report figure (:mod:`jointfit_ros.report`), unless
  ``--no-report``; ``report.html`` with ``--html``;
* ``joint_angles.csv``: each joint's angles per frame (rad) and their rates, as
  ``~/joint_states`` gives them live (:mod:`jointfit_ros.angles_export`), unless
  ``--no-report`` without ``--export`` (the frames are not kept then);
* ``subject.urdf``: the identified joints as a URDF in metres
  (:func:`jointfit_core.urdf.urdf_from_calibrations`), when they form one tree
  (otherwise ``summary.json`` says why under ``urdf``);
* with ``--export``: ``joints.csv`` (the joints frame by frame in the world
  frame, with their sd), ``joints.trc`` / ``joints.c3d`` (the markers plus
  ``<joint>_JC``, ``<joint>_AX1``, ``<joint>_AX2``), see :mod:`jointfit_ros.export`.

Everything is computed before anything is written, and every file is written
to a temporary name and renamed: a failed run leaves ``DIR`` as it was.

Exit status: 0 every joint identified; 3 the outputs were written but some
joint has no identifiable estimate, or the outlier gate rejected more than
10 % of a segment's frames (the one-line summary, the summary and the figure
say why);
1 bad input or configuration (one line on stderr, nothing written); 2 bad
arguments; 130 interrupted. A failed consistency check across movement
blocks ("skin artefact dominates", in the one-line summary and
``summary.json``) leaves the status as it is: the estimate is still the best
the recording gives, only its covariance understates how far it can be off.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NoReturn

from jointfit_core import __version__
from jointfit_core.atomic import write_all_or_nothing
from jointfit_core.calibration import calibration_text, save_calibration
from jointfit_core.errors import InputError, JointfitError
from jointfit_core.io import METRES_PER_UNIT
from jointfit_core.node_calibration import (
    load_node_calibration,
    node_calibration,
    save_node_calibration,
    segment_key,
)
from jointfit_core.urdf import urdf_from_calibrations
from jointfit_core.window_entries import check_window_max_frames

from .angles_export import joint_angles_csv
from .export import EXPORT_FORMATS, check_exportable, export_files
from .html_report import html_page
from .naming import node_path
from .offline import READER_PROCESS_MIN_BYTES, FitRun, read_marker_file, run_fit, with_file_marker_names
from .params import NodeConfig, calibration_path, node_config, params_from_file
from .report import fit_summary, joint_reports, length_unit
from .runner import JointRunner

__all__ = ["main", "fit_main"]

PROG = "jointfit"


class _UsageError(Exception):
    """Bad command-line arguments (one line)."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        raise _UsageError(message)


def _formats(text: str) -> tuple[str, ...]:
    formats = tuple(f.strip().lower() for f in text.split(",") if f.strip())
    bad = [f for f in formats if f not in EXPORT_FORMATS]
    if bad or not formats:
        raise argparse.ArgumentTypeError(f"expected formats from {', '.join(EXPORT_FORMATS)}, got {text!r}")
    return formats


def _fit_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog=f"{PROG} fit",
        description="Fit the configured joints over a whole recording and write calibrations, a summary and a report.",
    )
    p.add_argument("input", help="rosbag2 bag (directory, .db3 or .mcap), .c3d or .trc file")
    p.add_argument("--config", required=True, help="the node's parameter file (config/*.yaml)")
    p.add_argument("--out", help="output directory (default: <input name>_jointfit)")
    p.add_argument(
        "--node-name",
        default=None,
        help="the node whose entries of the parameter file to read, with its namespace (e.g. /subject_a/jointfit; "
        "default: the file's only node entry, else /jointfit)",
    )
    p.add_argument(
        "--window",
        choices=("all", "config"),
        default="all",
        help="all: every joint's window is the whole recording (default); config: the configured windows, "
        "i.e. what the node holds at the end of the recording",
    )
    p.add_argument("--html", action="store_true", help="also write report.html")
    p.add_argument(
        "--export",
        type=_formats,
        default=(),
        metavar="FORMATS",
        help="also write the joints frame by frame (world frame): csv (joints.csv), trc, c3d (joints.trc, "
        "joints.c3d: the markers plus <joint>_JC, <joint>_AX1, <joint>_AX2); comma separated, e.g. csv,trc",
    )
    p.add_argument("--no-report", action="store_true", help="no figures (faster; summary and calibrations only)")
    p.add_argument(
        "--write-calibration",
        action="store_true",
        help="also write each identified joint's calibration to its configured calibration_file, or all of them "
        "to the node's calibration_file (old one kept as .bak)",
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
    unit = length_unit(run)
    name = f"{joint['name']} ({joint['type']})"
    if joint["status"] == "no estimate":
        dropped = ", ".join(f"{n} {why.replace('_', ' ')}" for why, n in joint["dropped"].items() if n)
        why = f" ({dropped}; {joint['frames_received']} frames received)" if dropped else ""
        return f"{name}: no estimate: {joint['message']}{why}"
    if "centre_parent" in joint:
        est = "centre_parent (" + ", ".join(f"{v:.4g}" for v in joint["centre_parent"]) + ")"
        est += f" sd <= {max(joint['sd_parent']):.2g} {unit}"
        if "sd_parent_statistical" in joint:
            est += f" (statistical {max(joint['sd_parent_statistical']):.2g})"
    else:
        est = "direction_parent (" + ", ".join(f"{v:.3f}" for v in joint["direction_parent"]) + ")"
        est += f" sd {joint['direction_sd_deg_parent']:.2g} deg"
        if "direction_sd_deg_parent_statistical" in joint:
            est += f" (statistical {joint['direction_sd_deg_parent_statistical']:.2g})"
        est += f", pointing {joint['axis_points']}"
    verdict = "" if joint["identifiable"] else f"; NOT identifiable: {joint['reason']}"
    if joint.get("not_saved"):
        verdict += f"; NO calibration: {joint['not_saved']}"
    if joint.get("gate_warning"):
        verdict += f"; WARNING: {joint['gate_warning']}"
    if joint.get("units_warning"):
        verdict += f"; WARNING: {joint['units_warning']}"
    if joint.get("label_warning"):
        verdict += f"; WARNING: {joint['label_warning']}"
    if joint.get("cluster_warning"):
        verdict += f"; WARNING: {joint['cluster_warning']}"
    if joint.get("consistency_warning"):
        verdict += f"; WARNING: {joint['consistency_warning']}"
    gated = joint["gated"]
    share = f"gated {gated['parent']['percent']:.2g} % parent, {gated['child']['percent']:.2g} % child"
    if gated.get("joint", {}).get("frames"):
        share += f", {gated['joint']['percent']:.2g} % by the joint test"
    line = f"{name}: {est}, rms {joint['rms_residual']:.3g} {unit}, {joint['frames_in_window']} frames, {share}{verdict}"
    return line + _anatomy_text(joint)


def _anatomy_text(joint: dict[str, Any]) -> str:
    """The range of motion and the anatomical results of a joint's summary, for its one-line summary."""
    out = ""
    rom = joint.get("range_of_motion") or {}
    if "flexion_range_deg" in rom:
        out += f"; flexion range {rom['flexion_range_deg']:.0f} deg"
    elif rom:
        out += "; rotation ranges " + "/".join(f"{v:.0f}" for v in rom["principal_ranges_deg"]) + " deg"
    anatomy = joint.get("anatomical") or {}
    pelvis, epi = anatomy.get("pelvis") or {}, anatomy.get("epicondyles") or {}
    if "centre" in pelvis:
        u = pelvis["unit"]
        out += ("; ISB pelvis frame (" + ", ".join(f"{v:.0f}" for v in pelvis["centre"]) + f") {u} = ("
                + ", ".join(f"{v:.0f}" for v in pelvis["percent_width"]) + ") % of the ASIS width, "
                + ", ".join(f"{k.replace('_', ' ')} {r['distance']:.0f} {u} away" for k, r in pelvis["regressions"].items()))
    if "angle_to_epicondyle_line_deg" in epi:
        out += (f"; {epi['angle_to_epicondyle_line_deg']:.1f} deg from the epicondyle line, "
                f"{epi['distance_to_epicondyle_midpoint']:.1f} {epi['unit']} from their midpoint")
    for part in (anatomy, pelvis, epi):
        if "error" in part:
            out += f"; anatomical: {part['error']}"
        if "warning" in part:
            out += f"; anatomical WARNING: {part['warning']}"
    return out


def _previous_entries(
    path: Path, cfg: NodeConfig, units: str, fresh: Mapping[str, Any]
) -> dict[str, dict[str, Any]]:
    """The node calibration file's entries of the configured joints the fit did not identify, that a node would load.

    As the node's ``~/save`` keeps a joint's previous entry when it cannot save it
    (:class:`~jointfit_ros.calibration_store.NodeCalibrationFile`): without this, a fit of a
    recording that identifies the knee only dropped the hip's entry from the file.

    Parameters
    ----------
    path : Path
        The node's ``calibration_file``.
    cfg : NodeConfig
    units : str
        The fit's length unit: a file in another unit keeps nothing.
    fresh : mapping
        The joints identified by the fit (their entries are replaced).

    Returns
    -------
    dict
        Joint name to its previous calibration; empty when the file is absent or not loadable as a whole.
    """
    if not path.is_file():
        return {}
    try:
        doc = load_node_calibration(path)
    except (JointfitError, OSError, UnicodeDecodeError):
        return {}
    if doc["units"] != units:
        return {}
    kept: dict[str, dict[str, Any]] = {}
    for joint in cfg.joints:
        entry = doc["joints"].get(joint.name)
        if joint.name in fresh or entry is None:
            continue
        problem = ""
        try:
            segment_key(entry["calibration"], "parent"), segment_key(entry["calibration"], "child")
        except InputError as exc:
            problem = str(exc)
        check = JointRunner(joint, cfg)  # every check of the node's load (record, kind, version, identifiable)
        if check.restore(entry["calibration"], f"file {path} (joint {joint.name})", str(path), problem):
            kept[joint.name] = entry["calibration"]
    return kept


#: Files ``jointfit fit`` writes whatever the joints (besides ``summary.json``, always written).
_RUN_FILES = ("subject.urdf", "report.html", "joints.csv", "joints.trc", "joints.c3d", "joint_angles.csv")


def _stale_outputs(out_dir: Path, cfg: NodeConfig, written: Sequence[str]) -> list[str]:
    """The fit's own file names in an existing ``out_dir`` that this run does not write (an earlier run's).

    Parameters
    ----------
    out_dir : Path
    cfg : NodeConfig
        Its joints name the per-joint files (``<joint>.calibration.yaml``, ``<joint>.png``).
    written : sequence of str
        The names this run writes.

    Returns
    -------
    list of str
        E.g. ``right_knee.calibration.yaml`` of a run that identified the knee, beside a
        summary that now says it is not identifiable. They are left in place (they may be
        the user's), and named.
    """
    if not out_dir.is_dir():
        return []
    names = [f"{j.name}{suffix}" for j in cfg.joints for suffix in (".calibration.yaml", ".png")] + list(_RUN_FILES)
    return [name for name in names if name not in written and (out_dir / name).exists()]


def _holds(given: Path, target: Path) -> bool:
    """Whether an existing ``target`` is the file ``given``, or a file in the directory ``given`` (a bag)."""
    if not given.exists():
        return False
    a, b = given.resolve(), target.resolve()
    return a == b or (a.is_dir() and b.is_relative_to(a))


def _check_install_targets(cfg: NodeConfig, calibrations: Mapping[str, Any], inputs: Sequence[Path]) -> None:
    """Refuse ``--write-calibration`` targets that are not calibration files, before anything is written.

    Parameters
    ----------
    cfg : NodeConfig
    calibrations : mapping
        The identified joints (the per-joint files written are theirs).
    inputs : sequence of Path
        The recording and the parameter file: a calibration written over one of them would
        replace it (kept only as ``.bak``, until the next fit).

    Raises
    ------
    InputError
        A target that is an input of the fit, or exists and is not a regular file (a directory).
    """
    targets = [calibration_path(cfg.calibration_file)] if cfg.calibration_file and calibrations else []
    targets += [calibration_path(j.calibration_file) for j in cfg.joints if j.name in calibrations and j.calibration_file]
    for target in targets:
        if target.exists() and any(_holds(p, target) for p in inputs):
            raise InputError(f"calibration_file {target} is an input of this fit; writing the calibration would replace it")
        if target.exists() and not target.is_file():
            raise InputError(f"calibration_file {target} exists and is not a regular file")


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
    stale: list[str] = []
    try:
        values = params_from_file(opts.config, opts.node_name)
        recording = read_marker_file(opts.input)  # C3D/TRC (None for a bag): marker_names default to its labels
        if recording is not None:
            values = with_file_marker_names(values, recording.labels, Path(opts.input).name)
        cfg = node_config(values)
        if opts.export:
            check_exportable(cfg)
        run = run_fit(
            opts.input,
            cfg,
            whole_recording=opts.window == "all",
            keep_frames=not opts.no_report or bool(opts.export),
            reader_process=False if opts.single_process else None,
            progress=_progress_printer(f"fitting {Path(opts.input).name}") if show else None,
            data=recording,
        )
        geos, figures = ({}, {}) if opts.no_report else joint_reports(run)
        summary = fit_summary(run, elapsed_s=time.perf_counter() - started, version=__version__, geos=geos)
        # Everything is computed before anything is written.
        calibrations: dict[str, dict[str, Any]] = {}
        configured = {j.name: j for j in cfg.joints}
        for trace, joint in zip(run.traces, summary["joints"], strict=True):
            if trace.final is not None and trace.final.identifiable:
                try:  # the estimate and the joint's record, as ~/save writes them (jointfit urdf reads it)
                    data = trace.runner.calibration()
                except JointfitError as exc:  # a hinge whose configured sign could not be chosen: ~/save refuses it too
                    joint["not_saved"] = str(exc)
                    continue
                # The estimate is the recording's; the window a node resumes with (after ~/freeze false)
                # is the configured one, not the fit's no-forgetting sums.
                data.update(dict.fromkeys(("window", "window_s", "half_life", "half_life_s")))
                data.update(configured[joint["name"]].window_kwargs())
                data["window_max_frames"] = check_window_max_frames(configured[joint["name"]].window_max_frames)
                calibrations[joint["name"]] = data
        for joint in summary["joints"]:
            name = joint["name"]
            joint["calibration_file"] = str(out_dir / f"{name}.calibration.yaml") if name in calibrations else None
            joint["figure"] = str(out_dir / f"{name}.png") if name in figures else None
        summary["config"] = str(opts.config)
        summary["window"] = opts.window
        exported = export_files(run, opts.export) if opts.export else {}
        if run.frames is not None and run.frames.shape[0]:
            exported["joint_angles.csv"] = joint_angles_csv(run)
        if calibrations:
            try:
                unit = length_unit(run)
                metres = METRES_PER_UNIT.get(unit)
                if metres is None:
                    raise JointfitError(f"the length unit {unit!r} is not m, cm or mm (URDF lengths are metres)")
                exported["subject.urdf"] = urdf_from_calibrations(
                    list(calibrations.values()), metres_per_unit=metres, segment_labels=cfg.segment_labels()
                )
            except JointfitError as exc:  # e.g. joints that do not form one tree: the fit stands without it
                summary["urdf"] = f"not written: {exc}"
        summary["exports"] = [str(out_dir / name) for name in exported]

        files: dict[str, bytes | str] = {f"{n}.calibration.yaml": calibration_text(d) for n, d in calibrations.items()}
        files.update({f"{n}.png": png for n, png in figures.items()})
        files.update(exported)
        stale = _stale_outputs(out_dir, cfg, [*files, "report.html" if opts.html else ""])
        if stale:
            summary["stale_files"] = [str(out_dir / name) for name in stale]
        if opts.html:
            files["report.html"] = html_page(summary, {n: f"{n}.png" for n in figures})
        files["summary.json"] = json.dumps(summary, indent=2, allow_nan=False, default=str) + "\n"
        if opts.write_calibration:
            _check_install_targets(cfg, calibrations, [Path(opts.input), Path(opts.config)])
        write_all_or_nothing(out_dir, files)
        installed = []
        if opts.write_calibration:
            if cfg.calibration_file and calibrations:  # the node's one file: every identified joint
                node_file = calibration_path(cfg.calibration_file)
                previous = _previous_entries(node_file, cfg, length_unit(run), calibrations)
                doc = node_calibration(
                    [calibrations.get(j.name) or previous[j.name] for j in cfg.joints if j.name in {**calibrations, **previous}],
                    node=node_path(opts.node_name) if opts.node_name else "",
                    units=length_unit(run),  # the numbers' unit: a C3D's or TRC's own, not the units parameter
                    segment_labels=cfg.segment_labels(),
                )
                installed.append(str(save_node_calibration(node_file, doc)))
                installed += [f"{name}: not identified here, its entry is kept ({node_file})" for name in previous]
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
              + (f", {len(figures)} figure(s)" if figures else "") + (", report.html" if opts.html else "")
              + "".join(f", {name}" for name in exported) + ")")
        for path in installed:
            print(path if ": not identified here" in path else f"installed calibration {path}")
    if stale:  # also with --quiet: a calibration there is not this fit's
        print(f"WARNING: {out_dir}/ still holds {', '.join(stale)} of an earlier fit, not of this one "
              "(summary.json lists what this fit wrote)", file=sys.stderr)
    warned = any(j.get("gate_warning") or j.get("label_warning") or j.get("cluster_warning") for j in summary["joints"])
    return 0 if len(calibrations) == len(run.traces) and not warned else 3


def main(argv: Sequence[str] | None = None) -> None:
    """Console entry point ``jointfit``."""
    args = list(sys.argv[1:] if argv is None else argv)
    usage = (
        f"usage: {PROG} {{fit,markers,convert,replay,urdf,status,call}} ... (see '{PROG} fit --help', "
        f"'{PROG} convert --help', '{PROG} status --help', '{PROG} call --help', ...)"
    )
    if not args or args[0] in ("-h", "--help"):
        print(usage)
        sys.exit(0 if args else 2)
    command, rest = args[0], args[1:]
    if command == "fit":
        sys.exit(fit_main(rest))
    if command == "markers":
        from .markers_cli import markers_main

        sys.exit(markers_main(rest))
    if command == "convert":
        from .convert import convert_main

        sys.exit(convert_main(rest))
    if command == "replay":
        from .replay import replay_main

        sys.exit(replay_main(rest))
    if command == "urdf":
        from .urdf_cli import urdf_main

        sys.exit(urdf_main(rest))
    if command in ("status", "call"):
        from .shell import call_main, status_main

        sys.exit(status_main(rest) if command == "status" else call_main(rest))
    print(f"{PROG}: error: unknown command {command!r}; {usage}", file=sys.stderr)
    sys.exit(2)


if __name__ == "__main__":
    main()
