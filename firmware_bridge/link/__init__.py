"""Byte links opened by URI: ``serial://``, ``udp://`` (and ``natnet://``, another package).

Link classes are imported lazily by scheme (see ``firmware_bridge.link.base.LINK_CLASSES``).
"""

from __future__ import annotations

from firmware_bridge.link.base import (
    LINK_CLASSES,
    Link,
    LinkEvent,
    LinkOptions,
    ParsedUri,
    open_link,
    parse_uri,
)

__all__ = [
    "LINK_CLASSES",
    "Link",
    "LinkEvent",
    "LinkOptions",
    "ParsedUri",
    "open_link",
    "parse_uri",
]
