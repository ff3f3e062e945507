"""Link URIs: parsing, the lazy scheme table, and errors that name the URI and show a good one."""

from __future__ import annotations

import pytest

from firmware_bridge.errors import LinkError, UriError
from firmware_bridge.link import LINK_CLASSES, open_link, parse_uri


def test_parse_serial_and_udp():
    p = parse_uri("serial:///dev/ttyUSB0?baud=921600")
    assert (p.scheme, p.host, p.port, p.path, p.query) == (
        "serial", "", None, "/dev/ttyUSB0", {"baud": "921600"},
    )  # fmt: skip
    u = parse_uri("udp://0.0.0.0:14550")
    assert (u.scheme, u.host, u.port, u.path) == ("udp", "0.0.0.0", 14550, "")
    n = parse_uri("natnet://239.255.42.99:1511?local=10.0.0.2")
    assert (n.host, n.port, n.query) == ("239.255.42.99", 1511, {"local": "10.0.0.2"})


def test_scheme_table_is_lazy_and_complete():
    assert LINK_CLASSES == {
        "serial": "firmware_bridge.link.serial_link:SerialLink",
        "udp": "firmware_bridge.link.udp_link:UdpLink",
        "natnet": "firmware_bridge.natnet.link:NatNetLink",
    }


@pytest.mark.parametrize(
    ("uri", "problem"),
    [
        ("/dev/ttyUSB0", "scheme://"),
        ("tcp://127.0.0.1:5760", "unknown scheme 'tcp'"),
        ("udp://127.0.0.1:99999", "Port out of range"),
        ("udp://127.0.0.1", "no port"),
        ("udp://0.0.0.0:14550?mode=both", "mode='both'"),
        ("udp://127.0.0.1:14550?colour=red", "unknown parameter"),
        ("serial://dev/ttyUSB0", "three slashes"),
        ("serial:///dev/ttyUSB0?baud=fast", "baud='fast' is not an integer"),
        ("serial:///dev/ttyUSB0?baud=0", "baud=0 must be >= 1"),
    ],
)
def test_bad_uris_raise_uri_error_naming_uri_and_example(uri, problem):
    with pytest.raises(UriError) as info:
        open_link(uri)
    text = str(info.value)
    assert problem in text and repr(uri) in text and "e.g." in text


def test_missing_serial_device_is_a_link_error(tmp_path):
    with pytest.raises(LinkError, match="no-such-tty"):
        open_link(f"serial://{tmp_path}/no-such-tty?baud=921600")
