"""jointfit sets one BLAS thread before numpy loads, unless the user chose otherwise (bench/blas_threads.py)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from jointfit_core import BLAS_THREAD_VARIABLES

ROOT = Path(__file__).resolve().parent.parent
VARS = BLAS_THREAD_VARIABLES


def _after_import(module: str, preset: dict[str, str]) -> list[str]:
    env = {k: v for k, v in os.environ.items() if k not in VARS}
    env.update(preset, PYTHONPATH=str(ROOT))
    code = f"import os, {module}; print(' '.join(os.environ.get(v, '-') for v in {VARS!r}))"
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True, cwd=ROOT)
    return done.stdout.split()


@pytest.mark.parametrize("module", ["jointfit_core", "jointfit_ros"])
def test_one_blas_thread_by_default(module: str) -> None:
    assert _after_import(module, {}) == ["1", "1", "1"]


def test_a_users_setting_is_kept() -> None:
    assert _after_import("jointfit_core", {"OPENBLAS_NUM_THREADS": "2"}) == ["2", "1", "1"]
