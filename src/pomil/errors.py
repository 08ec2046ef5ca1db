"""User-facing errors: the CLI prints them as one line and exits non-zero."""

from __future__ import annotations


class PomilError(Exception):
    """A problem with the user's input (file, field, option), not a bug in pomil."""

    exit_status = 2  # what the CLI exits with


class ConfigError(PomilError, ValueError):
    """A config value of the wrong type or outside its field's interval (a ValueError too,
    so that building a config in Python fails as a bad argument does)."""


class InvalidArgument(PomilError, ValueError):
    """A bad argument to the Python API (``TrainedPolicy.reset``, ``act``), named in the message."""


class DivergenceError(PomilError):
    """A run produced NaN or inf (a loss, gradient, parameter or reward) and stopped before
    writing it to a checkpoint; the message names the iteration, the quantity and a hint."""

    exit_status = 3


class RunBusyError(PomilError):
    """Another live run holds the run directory's lock."""


class DataError(PomilError):
    """Demonstrations that are missing, malformed or inconsistent.

    ``field`` names the offending array or metadata key, ``source`` the file
    (filled in by the loader), so the message reads
    ``demos.npz: field 'actions': expected ..., got ...``.
    """

    def __init__(self, field: str, message: str, source: str | None = None) -> None:
        self.field = field
        self.message = message
        self.source = source
        super().__init__(str(self))

    def __str__(self) -> str:
        where = f"{self.source}: " if self.source else ""
        return f"{where}field '{self.field}': {self.message}"

    def with_source(self, source: str) -> DataError:
        return DataError(self.field, self.message, source)
