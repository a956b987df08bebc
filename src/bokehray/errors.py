"""Exceptions raised by bokehray.

Every check happens once, at the public boundary (API, CLI, readers), and the
message reads ``<what>: expected <what>, got <what>`` followed by how to fix it.
"""

from __future__ import annotations

import signal

__all__ = [
    "EXIT_INTERRUPTED",
    "EXIT_TERMINATED",
    "BokehrayError",
    "InputError",
    "NumericalError",
    "OutputError",
    "OutputExistsError",
    "ResourceError",
    "Terminated",
]


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


class OutputExistsError(OutputError):
    """An exclusive write found its file there already (made meanwhile by another writer); nothing was written."""


EXIT_INTERRUPTED = 130  # 128 + SIGINT: the CLI's exit status after Ctrl-C
EXIT_TERMINATED = 143  # 128 + SIGTERM


class Terminated(KeyboardInterrupt):
    """SIGTERM (or SIGHUP: the terminal closed), raised in the main thread like Ctrl-C (``bokehray.app.cli`` installs
    the handler) so that every cleanup path runs (atomic writes remove their temporary file); the CLI then exits with
    128 + the signal's number (143 for SIGTERM, 129 for SIGHUP), not Ctrl-C's 130."""

    def __init__(self, signum: int = signal.SIGTERM) -> None:
        super().__init__()
        self.signum = int(signum)

    @property
    def exit_code(self) -> int:
        return 128 + self.signum

    @property
    def said(self) -> str:
        """How the CLI names it: ``terminated (SIGTERM)``, ``terminated (SIGHUP)``."""
        return f"terminated ({signal.Signals(self.signum).name})"
