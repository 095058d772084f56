"""Calibrations as plain data: fits to and from YAML-able dicts, and atomic files.

A calibration is what an online estimator needs to resume after a restart:
its settings, templates and estimate (see
:meth:`jointfit_core.estimator.OnlineJoint.to_dict`). Here are the pieces
shared by every estimator: turning frozen fit dataclasses into dicts of
lists, floats and strings and back, and writing a file so that a crash
never leaves a half-written or lost calibration.
"""

from __future__ import annotations

import os
from dataclasses import fields
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from .atomic import write_atomic
from .errors import InputError, MissingDependencyError

__all__ = ["fit_to_dict", "fit_from_dict", "save_calibration", "load_calibration", "calibration_text"]

T = TypeVar("T")


def fit_to_dict(fit: Any) -> dict[str, Any]:
    """A frozen fit dataclass as a dict of plain types (arrays to nested lists, NaN to None).

    Parameters
    ----------
    fit : dataclass instance
        E.g. :class:`~jointfit_core.results.CentreFit`.

    Returns
    -------
    dict
        Field name to value; YAML- and JSON-serialisable.
    """
    out: dict[str, Any] = {}
    for f in fields(fit):
        value = getattr(fit, f.name)
        if isinstance(value, np.ndarray):
            if value.dtype.kind == "f":
                out[f.name] = np.where(np.isnan(value), np.array(None), value.astype(object)).tolist()
            else:
                out[f.name] = value.tolist()
        elif isinstance(value, (np.floating, np.integer, np.bool_)):
            out[f.name] = value.item()
        else:
            out[f.name] = value
    return out


def _array(value: Any) -> NDArray[np.float64]:
    obj = np.array(value, dtype=object)
    flat = [np.nan if v is None else float(v) for v in obj.ravel()]
    return np.array(flat, dtype=np.float64).reshape(obj.shape)


def fit_from_dict(cls: type[T], data: dict[str, Any]) -> T:
    """Rebuild a fit dataclass from :func:`fit_to_dict` output.

    Raises
    ------
    InputError
        ``data`` is not a dict, or a field is missing, unknown or malformed.
    """
    if not isinstance(data, dict):
        raise InputError(f"calibration: expected a dict of {cls.__name__} fields, got {type(data).__name__}")
    names = {f.name for f in fields(cls)}  # type: ignore[arg-type]
    missing = names - set(data)
    unknown = set(data) - names
    if missing or unknown:
        raise InputError(
            f"calibration: {cls.__name__} fields do not match (missing {sorted(missing)}, unknown {sorted(unknown)})"
        )
    try:
        return cls(**{k: _array(v) if isinstance(v, list) else v for k, v in data.items()})
    except (TypeError, ValueError) as exc:
        raise InputError(f"calibration: a {cls.__name__} field is malformed: {exc}") from None


def _yaml() -> Any:
    try:
        import yaml
    except ImportError:  # pragma: no cover - PyYAML is in requirements.txt
        raise MissingDependencyError("calibration files need PyYAML: pip install pyyaml") from None
    return yaml


def save_calibration(path: str | os.PathLike[str], data: dict[str, Any]) -> Path:
    """Write a calibration as YAML, atomically.

    The text goes to a temporary file in the same directory, is flushed to
    disk, and then replaces ``path`` in one step (``os.replace``), so that a
    reader sees the old or the new calibration, never a partial one, and a
    crash while writing loses nothing (:func:`~jointfit_core.atomic.write_atomic`).
    A previous file is kept as ``<path>.bak`` (a hard link made before the
    rename: ``path`` itself never disappears).

    Parameters
    ----------
    path : str or path-like
    data : dict
        Plain types only (see :func:`fit_to_dict`).

    Returns
    -------
    Path
        The written path.
    """
    return write_atomic(path, calibration_text(data), keep_backup=True)


def calibration_text(data: dict[str, Any]) -> str:
    """The YAML text :func:`save_calibration` writes for ``data``."""
    text: str = _yaml().safe_dump(data, sort_keys=False, default_flow_style=None)
    return text


def load_calibration(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a calibration written by :func:`save_calibration`.

    Raises
    ------
    FileNotFoundError
        No such file.
    InputError
        Not YAML, or not a mapping.
    """
    yaml = _yaml()
    text = Path(path).read_text(encoding="utf-8")
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise InputError(f"calibration {path}: not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise InputError(f"calibration {path}: expected a mapping, got {type(data).__name__}")
    return data
