"""MAVLink 2 for the firmware link: typed records, pure codec, signing, time sync, link health.

``MavlinkCodec`` (pure) turns records into frames and byte chunks into records;
``MavlinkEndpoint`` (``firmware_bridge.mavlink.endpoint``) is the thin threaded shell over a link.
"""

from __future__ import annotations

import os

os.environ["MAVLINK20"] = "1"  # must precede any pymavlink import (pymavlink.mavutil reads it)

from firmware_bridge.mavlink.codec import DecodeStats, MavlinkCodec  # noqa: E402

__all__ = ["DecodeStats", "MavlinkCodec"]
