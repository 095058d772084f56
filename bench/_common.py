"""Shared by the bench scripts: the machine line of every results header and Markdown tables."""

from __future__ import annotations

import os
import platform
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import scipy


def cpu_name() -> str:
    """The CPU model from /proc/cpuinfo (Linux), else what platform says."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def machine() -> str:
    """One line: OS, CPU, core count, Python/numpy/scipy versions and the load average now."""
    return (
        f"{platform.platform()}, {cpu_name()}, {os.cpu_count()} CPUs; Python {platform.python_version()}, "
        f"numpy {np.__version__}, scipy {scipy.__version__}; load average at start "
        f"{', '.join(f'{x:.2f}' for x in os.getloadavg())}"
    )


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]], align: str = "") -> str:
    """A Markdown table (no trailing newline); ``align``: one ``l``/``r`` per column (default all right)."""
    spec = align or "r" * len(header)
    sep = ["---:" if a == "r" else ":---" for a in spec]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(sep) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def save_results(path: Path, text: str) -> Path:
    """Write a results file (UTF-8, its folder created) and return its path."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


def selected(label: str, cases: Sequence[str]) -> bool:
    """Whether a case runs under a ``--cases`` filter: its label contains one of ``cases`` (none given: all)."""
    return not cases or any(text in label for text in cases)
