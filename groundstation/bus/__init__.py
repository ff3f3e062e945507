"""The ZeroMQ bus: one versioned envelope, one topic table, thin PUB/SUB shells.

- :mod:`~groundstation.bus.envelope` (pure): ``Envelope``, ``Header``, ``encode``/``decode``,
  ``to_bytes``/``from_bytes``.
- :mod:`~groundstation.bus.topics`: ``TOPICS``, every topic with its schema and drop policy.
- :mod:`~groundstation.bus.sequence` (pure): per-topic gap counting.
- :mod:`~groundstation.bus.pubsub`: ``Publisher`` (XPUB, ready handshake), ``Subscriber``.
- :mod:`~groundstation.bus.flow`: credit flow control for lossless replay at max speed.
- :mod:`~groundstation.bus.security`: loopback-only binding unless CURVE keys are given.

Names are imported lazily so that the pure modules load without ZeroMQ.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "Envelope": "groundstation.bus.envelope",
    "Header": "groundstation.bus.envelope",
    "encode": "groundstation.bus.envelope",
    "decode": "groundstation.bus.envelope",
    "to_bytes": "groundstation.bus.envelope",
    "from_bytes": "groundstation.bus.envelope",
    "TOPICS": "groundstation.bus.topics",
    "Topic": "groundstation.bus.topics",
    "TopicStats": "groundstation.bus.sequence",
    "SequenceTracker": "groundstation.bus.sequence",
    "Publisher": "groundstation.bus.pubsub",
    "Subscriber": "groundstation.bus.pubsub",
    "CurveKeys": "groundstation.bus.security",
    "BusError": "groundstation.bus.errors",
    "EnvelopeError": "groundstation.bus.errors",
    "SchemaError": "groundstation.bus.errors",
    "BusSecurityError": "groundstation.bus.errors",
    "BusTimeoutError": "groundstation.bus.errors",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'groundstation.bus' has no attribute {name!r}")
    return getattr(importlib.import_module(_EXPORTS[name]), name)
