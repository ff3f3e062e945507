"""Linux joystick js_event codec and ioctl numbers (pure: bytes in, records out).

``struct js_event { __u32 time; /* ms */ __s16 value; __u8 type; __u8 number; }`` (8 bytes,
little-endian on the machines we run on; linux/joystick.h). Type bits: JS_EVENT_BUTTON 0x01,
JS_EVENT_AXIS 0x02, JS_EVENT_INIT 0x80 (on open the kernel replays the current state of every
button, then every axis, with INIT set).
"""

from __future__ import annotations

import dataclasses
import struct
from collections.abc import Iterable

JS_EVENT_BUTTON = 0x01
JS_EVENT_AXIS = 0x02
JS_EVENT_INIT = 0x80
EVENT_SIZE = 8
_EVENT = struct.Struct("<IhBB")


def _ioc_read(nr: int, size: int) -> int:
    """_IOC(_IOC_READ, 'j', nr, size) (asm-generic/ioctl.h: dir<<30 | size<<16 | type<<8 | nr)."""
    return (2 << 30) | (size << 16) | (ord("j") << 8) | nr


JSIOCGVERSION = _ioc_read(0x01, 4)
JSIOCGAXES = _ioc_read(0x11, 1)
JSIOCGBUTTONS = _ioc_read(0x12, 1)


def JSIOCGNAME(length: int) -> int:  # noqa: N802 - the kernel's macro name
    return _ioc_read(0x13, length)


@dataclasses.dataclass(frozen=True)
class JsEvent:
    """One js_event: ``time_ms`` (device clock, ms, u32), ``value`` (s16), ``type``, ``number``."""

    time_ms: int
    value: int
    type: int
    number: int

    @property
    def is_init(self) -> bool:
        return bool(self.type & JS_EVENT_INIT)

    @property
    def kind(self) -> int:
        """JS_EVENT_AXIS, JS_EVENT_BUTTON, or another (unknown) value."""
        return self.type & ~JS_EVENT_INIT

    def encode(self) -> bytes:
        return _EVENT.pack(self.time_ms & 0xFFFFFFFF, self.value, self.type, self.number)

    @classmethod
    def decode(cls, data: bytes) -> JsEvent:
        if len(data) != EVENT_SIZE:
            raise ValueError(f"a js_event is {EVENT_SIZE} bytes, got {len(data)}")
        return cls(*_EVENT.unpack(data))


def decode_events(buffer: bytes) -> tuple[list[JsEvent], bytes]:
    """Split a byte chunk into whole events and the leftover partial event (< 8 bytes)."""
    n = len(buffer) // EVENT_SIZE * EVENT_SIZE
    events = [JsEvent(*t) for t in _EVENT.iter_unpack(buffer[:n])]
    return events, buffer[n:]


def encode_events(events: Iterable[JsEvent]) -> bytes:
    return b"".join(e.encode() for e in events)


def init_burst(
    axes: dict[int, int] | list[int], buttons: dict[int, bool] | list[bool], time_ms: int = 0
) -> bytes:
    """The bytes the kernel sends on open: every button then every axis, with JS_EVENT_INIT."""
    ax = dict(enumerate(axes)) if isinstance(axes, list) else axes
    bt = dict(enumerate(buttons)) if isinstance(buttons, list) else buttons
    evs = [
        JsEvent(time_ms, int(v), JS_EVENT_BUTTON | JS_EVENT_INIT, n) for n, v in sorted(bt.items())
    ]
    evs += [
        JsEvent(time_ms, int(v), JS_EVENT_AXIS | JS_EVENT_INIT, n) for n, v in sorted(ax.items())
    ]
    return encode_events(evs)
