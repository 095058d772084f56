"""Exceptions raised by :mod:`jointfit_core`.

Every input check raises :class:`ValueError` or one of its subclasses below, so
``except ValueError`` catches all of them; the subclasses let callers tell bad
input from motion that cannot identify the joint.
"""

from __future__ import annotations

__all__ = ["JointfitError", "InputError", "NotIdentifiableError", "MissingDependencyError"]


class JointfitError(Exception):
    """Base class of every exception raised by jointfit."""


class InputError(JointfitError, ValueError):
    """The input has the wrong shape, type, or too few valid samples.

    The message says what was expected and what came.
    """


class NotIdentifiableError(JointfitError, ValueError):
    """The motion (or marker set) cannot identify the joint parameters.

    The message says why and, where it can, which movement is missing.
    """


class MissingDependencyError(JointfitError, ImportError):
    """An optional dependency (e.g. ``ezc3d``, ``rosbags``) is not installed."""
