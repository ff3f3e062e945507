"""js_event codec and ioctl numbers (linux/joystick.h), pure."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from groundstation.pilot import jsevent as jsdev
from groundstation.pilot.jsevent import JsEvent, decode_events, encode_events, init_burst


def test_golden_bytes_little_endian_time_value_type_number():
    ev = JsEvent(time_ms=0x01020304, value=-2, type=0x82, number=5)
    assert ev.encode().hex() == "04030201feff8205"
    assert JsEvent.decode(bytes.fromhex("04030201feff8205")) == ev
    assert ev.is_init and ev.kind == jsdev.JS_EVENT_AXIS


def test_ioctl_request_numbers_match_the_kernel_macros():
    # _IOR('j', 0x11, __u8), _IOR('j', 0x12, __u8), _IOR('j', 0x01, __u32), _IOC(READ,'j',0x13,len)
    assert jsdev.JSIOCGAXES == 0x80016A11
    assert jsdev.JSIOCGBUTTONS == 0x80016A12
    assert jsdev.JSIOCGVERSION == 0x80046A01
    assert jsdev.JSIOCGNAME(128) == 0x80806A13


@given(
    st.lists(
        st.builds(
            JsEvent,
            st.integers(0, 2**32 - 1),
            st.integers(-32768, 32767),
            st.integers(0, 255),
            st.integers(0, 255),
        ),
        max_size=20,
    ),
    st.integers(0, 7),
)
def test_round_trip_with_partial_tail(events, cut):
    data = encode_events(events)
    got, rest = decode_events(data + b"\x00" * cut)
    assert got == events and rest == b"\x00" * cut


def test_split_stream_reassembles():
    evs = [JsEvent(i, i * 100, jsdev.JS_EVENT_AXIS, i) for i in range(5)]
    data = encode_events(evs)
    pending, out = b"", []
    for i in range(0, len(data), 3):
        got, pending = decode_events(pending + data[i : i + 3])
        out += got
    assert out == evs and pending == b""


def test_init_burst_is_buttons_then_axes_with_init_bit():
    evs, rest = decode_events(init_burst([10, -20], [True, False, True], time_ms=7))
    assert rest == b""
    assert [(e.type, e.number, e.value) for e in evs] == [
        (0x81, 0, 1), (0x81, 1, 0), (0x81, 2, 1), (0x82, 0, 10), (0x82, 1, -20),
    ]  # fmt: skip
    assert all(e.time_ms == 7 for e in evs)


def test_decode_rejects_wrong_length():
    with pytest.raises(ValueError, match="8 bytes"):
        JsEvent.decode(b"\x00" * 7)
