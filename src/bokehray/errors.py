"""Exceptions raised by bokehray.

Every check happens once, at the public boundary (API, CLI, readers), and the
message reads ``<what>: expected <what>, got <what>`` followed by how to fix it.
"""

from __future__ import annotations

__all__ = ["BokehrayError", "InputError", "NumericalError", "OutputError", "ResourceError"]


class BokehrayError(Exception):
    """Base of all bokehray errors."""


class InputError(BokehrayError, ValueError):
    """An argument or input file has the wrong shape, dtype, range or format."""


class NumericalError(BokehrayError, FloatingPointError):
    """A kernel produced NaN or Inf (a bug: report it with the inputs)."""


class ResourceError(BokehrayError, MemoryError):
    """A request cannot fit in the memory or device available."""


class OutputError(BokehrayError, OSError):
    """An output file could not be written (disk full, permission, folder gone); the message names the file.

    Nothing partial is left behind: the writer's temporary file is removed and an existing
    file at that path is untouched.
    """
