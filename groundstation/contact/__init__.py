"""Contact detection: filter, threshold, localise, build observations (pure core)."""

from groundstation.contact.detector import (
    ContactDetector,
    ContactEvent,
    Observation,
    contact_point,
    earth_acceleration,
)
from groundstation.contact.settings import ContactSettings, G

__all__ = [
    "G",
    "ContactDetector",
    "ContactEvent",
    "ContactSettings",
    "Observation",
    "contact_point",
    "earth_acceleration",
]
