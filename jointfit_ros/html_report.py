"""``report.html`` of ``jointfit fit``: the summary as tables, the verdicts in words, and the figures.

ROS-free and dependency-free (the figures are the PNG files written beside
the page). Every number is formatted here; nothing is printed as a Python
repr.
"""

from __future__ import annotations

import html
from collections.abc import Mapping, Sequence
from typing import Any

__all__ = ["html_page"]

_STYLE = (
    "body{font-family:sans-serif;margin:2em;max-width:1600px} table{border-collapse:collapse;margin:0.5em 0 1em}"
    " td,th{border:1px solid #ccc;padding:3px 8px;text-align:right} th{background:#f3f3f3}"
    " td.l,th.l{text-align:left} .ok{color:#060} .warn{color:#a40} img{max-width:100%}"
)


def _e(value: Any) -> str:
    return html.escape(str(value))


def _num(value: Any, digits: int = 4) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, (int, float)):
        return f"{value:.{digits}g}"
    return _e(value)


def _vec(values: Sequence[float] | None, digits: int = 4) -> str:
    return "-" if values is None else "(" + ", ".join(_num(v, digits) for v in values) + ")"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    head = "".join(f"<th class='l'>{_e(h)}</th>" if k == 0 else f"<th>{_e(h)}</th>" for k, h in enumerate(header))
    body = "".join(
        "<tr>" + "".join(f"<td class='l'>{c}</td>" if k == 0 else f"<td>{c}</td>" for k, c in enumerate(r)) + "</tr>"
        for r in rows
    )
    return f"<table><tr>{head}</tr>{body}</table>"


def _verdict(joint: Mapping[str, Any]) -> str:
    """The verdict in words, e.g. 'Identified: the estimate can be used.'."""
    status = joint["status"]
    if status == "ok" and joint.get("consistency_warning"):
        return (f"<p class='warn'>Identified and a calibration was written, but "
                f"{_e(joint['consistency_warning'])}</p>")
    if status == "ok":
        return "<p class='ok'>Identified: the motion makes this joint identifiable; a calibration was written.</p>"
    if status == "outlier gate":
        return f"<p class='warn'>Estimated, but {_e(joint.get('gate_warning', ''))}</p>"
    if status == "not identifiable":
        return f"<p class='warn'>Not identifiable: {_e(joint.get('reason', ''))}. No calibration was written.</p>"
    return f"<p class='warn'>No estimate: {_e(joint.get('message', ''))}</p>"


def _estimate_rows(joint: Mapping[str, Any], unit: str) -> list[list[str]]:
    rows = []
    if "centre_parent" in joint:
        rows.append(["centre, parent frame", _vec(joint["centre_parent"]), _vec(joint["sd_parent"], 2), unit])
        rows.append(["centre, child frame", _vec(joint["centre_child"]), _vec(joint["sd_child"], 2), unit])
    if "direction_parent" in joint:
        rows.append(["axis direction, parent frame", _vec(joint["direction_parent"]),
                     _num(joint["direction_sd_deg_parent"], 2), "deg"])
        rows.append(["axis point, parent frame", _vec(joint["point_parent"]), _vec(joint["point_sd_parent"], 2), unit])
        rows.append(["axis direction, child frame", _vec(joint["direction_child"]),
                     _num(joint["direction_sd_deg_child"], 2), "deg"])
        rows.append(["axis point, child frame", _vec(joint["point_child"]), _vec(joint["point_sd_child"], 2), unit])
    return rows


def _counter_rows(joint: Mapping[str, Any], unit: str) -> list[list[str]]:
    rows = [
        ["frames received", _num(joint["frames_received"], 9)],
        ["frames in the estimate", _num(joint["frames_in_window"], 9)],
        ["malformed frames", _num(joint["malformed_frames"], 9)],
        ["absurd markers (treated as missing)", _num(joint["absurd_markers"], 9)],
    ]
    for side in ("parent", "child"):
        g = joint["gated"][side]
        rows.append([f"{side} frames rejected by the outlier gate", f"{g['frames']} ({g['percent']:.2f} %)"])
    for reason, n in joint.get("dropped", {}).items():
        rows.append([f"dropped: {_e(reason)}", _num(n, 9)])
    if "rms_residual" in joint:
        rows.append([f"rms constraint residual ({_e(unit)})", _num(joint["rms_residual"], 3)])
        noise = joint["noise_sd"]
        rows.append([f"marker noise sd parent / child ({_e(unit)})", f"{_num(noise['parent'], 3)} / {_num(noise['child'], 3)}"])
    if joint.get("axis_points"):
        rows.append(["axis points", _e(joint["axis_points"])])
    return rows


def _anatomy_section(joint: Mapping[str, Any]) -> str:
    parts = []
    rom = joint.get("range_of_motion") or {}
    if rom:
        rows = [[f"principal axis {k + 1} (parent frame {_vec(a, 3)})", _num(r, 3)]
                for k, (r, a) in enumerate(zip(rom["principal_ranges_deg"], rom["principal_axes_parent"], strict=True))]
        if "flexion_range_deg" in rom:
            rows.insert(0, ["about the hinge axis (flexion)", _num(rom["flexion_range_deg"], 3)])
        parts.append("<h3>Range of motion</h3>" + _table(["rotation", "range (deg)"], rows))
    anatomy = joint.get("anatomical") or {}
    pelvis = anatomy.get("pelvis") or {}
    if "centre" in pelvis:
        u = pelvis["unit"]
        rows = [["estimate (functional)", _vec(pelvis["centre"], 3), _vec(pelvis["sd"], 2), "-"]]
        for name, reg in pelvis["regressions"].items():
            rows.append([_e(name.replace("_", " ").capitalize()), _vec(reg["centre"], 3), "-", _num(reg["distance"], 3)])
        parts.append(
            f"<h3>{_e(pelvis['side'].capitalize())} hip centre in anatomical terms</h3><p>{_e(pelvis['frame'])}; "
            f"inter-ASIS width {_num(pelvis['width'], 4)} {_e(u)}, depth {_num(pelvis['depth'], 4)} {_e(u)}; "
            f"the estimate is {_vec(pelvis['percent_width'], 3)} % of the width (z lateral).</p>"
            + _table(["", f"centre ({u})", f"sd ({u})", f"distance from the estimate ({u})"], rows)
        )
    epi = anatomy.get("epicondyles") or {}
    if "angle_to_epicondyle_line_deg" in epi:
        u = epi["unit"]
        rows = [
            ["angle between the axis and the epicondyle line", f"{_num(epi['angle_to_epicondyle_line_deg'], 3)} deg"],
            ["axis direction sd", f"{_num(epi['direction_sd_deg'], 2)} deg"],
            ["distance of the epicondyle midpoint from the axis", f"{_num(epi['distance_to_epicondyle_midpoint'], 3)} {_e(u)}"],
            ["epicondyle width", f"{_num(epi['epicondyle_width'], 4)} {_e(u)}"],
        ]
        parts.append("<h3>Axis against the epicondyles</h3>" + _table(["", "value"], rows))
    for part in (anatomy, pelvis, epi):
        for key in ("error", "warning"):
            if key in part:
                parts.append(f"<p class='warn'>Anatomical results: {_e(part[key])}</p>")
    return "".join(parts)


def html_page(summary: Mapping[str, Any], images: Mapping[str, str]) -> str:
    """A single HTML page of a fit's summary.

    Parameters
    ----------
    summary : mapping
        :func:`~jointfit_ros.report.fit_summary` (with ``config``, ``window``, per joint ``calibration_file``).
    images : mapping of str to str
        Joint name to the file name of its figure (written beside the page).

    Returns
    -------
    str
        Per joint: the verdict in words, the estimates and their sd, the counters, the range of motion and
        the anatomical results as tables, then the figure.
    """
    unit = summary.get("length_unit") or summary.get("units") or "input units"
    overview = [[_e(j["name"]), _e(j["type"]), _e(j["status"]), _num(j.get("rms_residual"), 3),
                 _num(j.get("frames_in_window"), 9)] for j in summary["joints"]]
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'><title>jointfit report</title>",
        f"<style>{_STYLE}</style></head><body>",
        f"<h1>jointfit report: {_e(summary['input'])}</h1>",
        _table(["input", "value"], [
            ["file", _e(summary["input"])],
            ["kind", _e(summary["input_kind"])],
            ["length unit", _e(unit)],
            ["rate (Hz)", _num(summary.get("rate_hz"), 6) if summary.get("rate_hz") else "-"],
            ["inputs read", _num(summary["inputs_read"], 12)],
            ["fit time (s)", _num(summary["elapsed_s"], 3)],
            ["configuration", _e(summary.get("config", "-"))],
            ["window", _e(summary.get("window", "-"))],
            ["jointfit version", _e(summary["jointfit_version"])],
        ]),
        "<h2>Joints</h2>",
        _table(["joint", "type", "status", f"rms residual ({unit})", "frames"], overview),
    ]
    if summary.get("router"):
        parts.append("<h3>Bag messages</h3>" + _table(["counter", "count"],
                     [[_e(k.replace("_", " ")), _num(v, 12)] for k, v in summary["router"].items()]))
    for joint in summary["joints"]:
        parts.append(f"<h2>{_e(joint['name'])} ({_e(joint['type'])})</h2>")
        parts.append(_verdict(joint))
        rows = _estimate_rows(joint, unit)
        if rows:
            parts.append("<h3>Estimate</h3>" + _table(["quantity", "value", "sd", "unit"], rows))
        parts.append("<h3>Counters and residuals</h3>" + _table(["", "value"], _counter_rows(joint, unit)))
        parts.append(_anatomy_section(joint))
        if joint["name"] in images:
            parts.append(f"<p><img src='{_e(images[joint['name']])}' alt='{_e(joint['name'])} report figure'></p>")
    parts.append("</body></html>")
    return "\n".join(parts)
