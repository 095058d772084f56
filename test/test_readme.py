"""The README's Python examples run as written."""

from __future__ import annotations

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_blocks_run() -> None:
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks, "README has no python example"
    for block in blocks:
        exec(compile(block, str(README), "exec"), {"__name__": "readme_example"})


def test_readme_parameter_tables_match_the_declarations() -> None:
    from jointfit_ros.params import parameters_markdown

    assert parameters_markdown() in README.read_text(), "README parameter tables are stale: paste parameters_markdown()"
