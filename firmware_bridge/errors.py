"""One exception root for the drone side of the wire.

Errors name the offending value and suggest a fix. Read loops never raise these for bad bytes on
the wire (those are skipped and counted); they are for bad settings, URIs and devices.
"""

from __future__ import annotations


class BridgeError(Exception):
    """Root of all deliberate firmware-bridge errors."""

    def __init__(self, message: str, hint: str | None = None):
        super().__init__(message)
        self.message = message
        self.hint = hint

    def __str__(self) -> str:
        return self.message if not self.hint else f"{self.message} (hint: {self.hint})"


class LinkError(BridgeError, OSError):
    """A link (serial port, UDP socket) cannot be opened or has failed."""


class UriError(BridgeError, ValueError):
    """A link URI is malformed or names an unknown scheme."""


class ProtocolError(BridgeError, ValueError):
    """A message cannot be encoded, or a value is out of the protocol's range."""
