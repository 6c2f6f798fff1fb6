"""Error types shared by every layer.

The CLI maps :class:`InputError` to exit code 2 (bad usage or bad input) and
:class:`WorkError` to exit code 1 (the input is fine but the work failed).
Messages are one line and name the file and, where known, the key.
"""

from __future__ import annotations


class CurvimeshError(Exception):
    """Base class of every error curvimesh reports to a user."""

    exit_code = 1


class InputError(CurvimeshError):
    """Bad input: an invalid metric file, an unreadable mesh, a bad option value."""

    exit_code = 2


class ExpressionError(InputError):
    """An expression in a metric file was rejected by the whitelist parser."""


class MetricError(InputError):
    """A metric file is invalid, or its field is not SPD / finite where evaluated."""


class MeshReadError(InputError):
    """A mesh file could not be read or is not a mesh curvimesh can use."""


class WorkError(CurvimeshError):
    """The input was fine but the work failed (for instance no valid mesh)."""
