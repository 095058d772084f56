"""Fixtures shared by the test modules."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest


@pytest.fixture
def client() -> Iterator[Any]:
    """The live-node tests' client (:class:`test_node._Client`: a marker publisher, output subscribers,
    service clients) on the default test domain; closed after the test. Needs rclpy (those modules skip
    without it)."""
    from test_node import _Client

    c = _Client()
    yield c
    c.close()
