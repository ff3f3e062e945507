"""One exception root for the ground station.

Every error raised on purpose derives from :class:`GroundstationError`; it names the offending
value and, where one exists, suggests the fix. The command line prints ``message`` and ``hint``
and exits with status 2 instead of a traceback.
"""

from __future__ import annotations


class GroundstationError(Exception):
    """Root of all deliberate ground-station errors.

    Parameters
    ----------
    message : str
        What is wrong, naming the offending value.
    hint : str, optional
        How to fix it.
    """

    def __init__(self, message: str, hint: str | None = None):
        super().__init__(message)
        self.message = message
        self.hint = hint

    def __str__(self) -> str:
        return self.message if not self.hint else f"{self.message} (hint: {self.hint})"


class ConfigError(GroundstationError, ValueError):
    """A setting has a bad value or an unknown name."""


class InputDataError(GroundstationError, ValueError):
    """Data handed to a pure core function is malformed (shape, NaN/inf, units, labels)."""


class NotFittedError(GroundstationError, RuntimeError):
    """An estimator was used before ``fit``."""


class ConvergenceWarning(UserWarning):
    """An iterative fit stopped at its iteration limit before meeting its tolerance."""
