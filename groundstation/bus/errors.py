"""Exceptions of the bus, all rooted at :class:`groundstation.errors.GroundstationError`."""

from __future__ import annotations

from groundstation.errors import GroundstationError


class BusError(GroundstationError):
    """Root of bus errors (sockets, handshakes, flow control)."""


class EnvelopeError(BusError, ValueError):
    """A message cannot be encoded or decoded; the message names the bad part."""


class SchemaError(EnvelopeError):
    """A payload or array does not match its topic's declared schema."""


class BusSecurityError(BusError):
    """An endpoint would be exposed beyond loopback without CURVE keys, or keys are unusable."""


class BusTimeoutError(BusError, TimeoutError):
    """A handshake or flow-control wait did not complete in time."""
