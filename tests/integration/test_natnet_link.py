"""natnet:// link over real loopback UDP sockets (unicast and multicast)."""

from __future__ import annotations

import socket
import threading

import pytest

from firmware_bridge.errors import LinkError, UriError
from firmware_bridge.natnet import (
    FrameOfData,
    RigidBody,
    ServerInfo,
    encode_connect_request,
    encode_frame_of_data,
    encode_server_info,
    parse_packet,
)
from firmware_bridge.natnet.link import NatNetLink

pytestmark = pytest.mark.timeout(30)

GROUP = "239.255.42.99"


def _frame(i: int) -> bytes:
    body = RigidBody(1, (0.1 * i, 1.0, -2.0), (0.0, 0.0, 0.0, 1.0), 0.0005, True)
    return encode_frame_of_data(FrameOfData(i, (body,), i / 200.0), (4, 1))


@pytest.fixture
def sender():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    yield s
    s.close()


def test_unicast_loopback_frames_arrive_in_order_and_decode(sender):
    with NatNetLink("natnet://127.0.0.1:0") as link:
        host, port = link.local_address
        assert host == "127.0.0.1" and port > 0
        n = 400  # two seconds' worth of a 200 Hz stream, sent as fast as possible
        received = []
        for i in range(n):
            sender.sendto(_frame(i), (host, port))
            if i % 50 == 49:  # drain in bursts; the 1 MiB buffer holds far more than 50
                while data := link.read(0.5):
                    received.append(parse_packet(data, (4, 1)))
                    if len(received) == i + 1:
                        break
        assert [f.frame_id for f in received] == list(range(n))
        assert received[-1].rigid_bodies[0].position[0] == pytest.approx(39.9, rel=1e-6)
        assert link.datagrams_read == n
        assert link.last_source == sender.getsockname()
        assert link.read(0.05) == b""  # timeout gives b"", not an exception


def test_read_blocks_until_data_or_timeout(sender):
    """A zero timeout polls once; a datagram already queued is returned at once."""
    with NatNetLink("natnet://127.0.0.1:0") as link:
        assert link.read(0) == b""
        sender.sendto(b"\x07\x00\x00\x00", link.local_address)
        assert link.read(5.0) == b"\x07\x00\x00\x00"


def test_write_goes_to_the_server_command_port_and_reply_is_read():
    """A fake Motive command socket answers a connect request with server info."""
    server = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    server.bind(("127.0.0.1", 0))
    server.settimeout(5.0)
    try:
        cmd_port = server.getsockname()[1]
        with NatNetLink(f"natnet://127.0.0.1:0?cmd_port={cmd_port}") as link:
            assert link.server == "127.0.0.1"
            link.write(encode_connect_request())
            request, client = server.recvfrom(65535)
            assert parse_packet(request).message_id == 0
            info = ServerInfo(
                "Motive", (3, 1, 0, 0), (4, 1, 0, 0), 10_000_000, 1511, False, "0.0.0.0"
            )
            server.sendto(encode_server_info(info), client)
            assert parse_packet(link.read(5.0)) == info
    finally:
        server.close()


def test_opened_through_the_link_factory(sender):
    from firmware_bridge.link.base import open_link, parse_uri

    with open_link("natnet://127.0.0.1:0") as link:
        assert isinstance(link, NatNetLink)
        sender.sendto(b"abcd", link.local_address)
        assert link.read(5.0) == b"abcd"
        assert link.uri == "natnet://127.0.0.1:0"
        assert [e.kind for e in link.events] == ["opened"]
    assert link.events[-1].kind == "closed"
    with NatNetLink(parse_uri("natnet://127.0.0.1:0?rcvbuf=65536")) as link2:
        assert link2.read(0) == b""


def test_bad_uris():
    with pytest.raises(UriError, match="scheme"):
        NatNetLink("udp://127.0.0.1:1511")
    with pytest.raises(UriError, match="missing host"):
        NatNetLink("natnet://:1511")
    with pytest.raises(UriError, match="iface"):
        NatNetLink("natnet://127.0.0.1:1511?iface=not-an-ip")
    with pytest.raises(UriError):
        NatNetLink("natnet://127.0.0.1:99999")
    with pytest.raises(UriError, match="cmd_port"):
        NatNetLink("natnet://127.0.0.1:0?cmd_port=x")


def test_closed_link_reads_empty_and_drops_writes():
    link = NatNetLink("natnet://127.0.0.1:0")
    link.close()
    link.close()
    assert link.read(0.1) == b""
    assert link.write(b"x") is False
    assert link.dropped_writes == 1
    assert [e.kind for e in link.events] == ["opened", "closed", "write_dropped"]


def test_close_wakes_a_blocked_reader():
    link = NatNetLink("natnet://127.0.0.1:0")
    got = []
    reader = threading.Thread(target=lambda: got.append(link.read(60.0)))
    reader.start()
    link.close()
    reader.join(timeout=10.0)
    assert not reader.is_alive() and got == [b""]


def test_multicast_without_server_drops_writes_until_a_frame_arrives():
    try:
        link = NatNetLink(f"natnet://{GROUP}:0?iface=127.0.0.1")
    except LinkError as exc:
        pytest.skip(f"sandbox cannot join multicast groups on loopback: {exc}")
    with link:
        assert link.group == GROUP and link.server is None
        link.write(b"x")
        assert link.dropped_writes == 1
        assert link.events[-1].kind == "write_dropped"
        assert "server address unknown" in link.events[-1].detail


def test_multicast_on_loopback(sender):
    try:
        link = NatNetLink(f"natnet://{GROUP}:0?iface=127.0.0.1")
    except LinkError as exc:
        pytest.skip(f"sandbox cannot join multicast groups on loopback: {exc}")
    with link:
        port = link.local_address[1]
        sender.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
        sender.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
        sender.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)
        try:
            for i in range(20):
                sender.sendto(_frame(i), (GROUP, port))
        except OSError as exc:
            pytest.skip(f"sandbox does not route multicast on loopback: {exc}")
        got = []
        while len(got) < 20 and (data := link.read(2.0)):
            got.append(parse_packet(data, (4, 1)).frame_id)
        if not got:
            pytest.skip("sandbox does not deliver multicast on loopback (nothing received)")
        assert got == list(range(20))
        assert link.server == "127.0.0.1"  # learnt from the sender
