"""Endpoint exposure policy (pure parts)."""

from __future__ import annotations

import pytest

from groundstation.bus.errors import BusSecurityError
from groundstation.bus.security import CurveKeys, check_bind, is_loopback_endpoint


@pytest.mark.parametrize(
    "ep",
    [
        "tcp://127.0.0.1:5555",
        "tcp://127.0.0.1:*",
        "tcp://127.3.2.1:1",
        "tcp://localhost:9",
        "tcp://[::1]:5555",
        "ipc:///tmp/gs/x",
        "inproc://x",
    ],
)
def test_loopback_endpoints_bind_without_keys(ep):
    assert is_loopback_endpoint(ep)
    check_bind(ep, None)


@pytest.mark.parametrize(
    "ep",
    ["tcp://0.0.0.0:5555", "tcp://*:5555", "tcp://192.168.1.4:1", "tcp://eth0:5", "tcp://[::]:5"],
)
def test_other_interfaces_need_keys(ep):
    assert not is_loopback_endpoint(ep)
    with pytest.raises(BusSecurityError, match="CURVE"):
        check_bind(ep, None)
    with pytest.raises(BusSecurityError):
        check_bind(ep, CurveKeys(b"x" * 40))  # a public key alone is not server keys
    check_bind(ep, CurveKeys.generate())


@pytest.mark.parametrize("ep", ["udp://127.0.0.1:5", "127.0.0.1:5", "ipc:///" + "x" * 120])
def test_malformed_endpoints_are_refused(ep):
    with pytest.raises(BusSecurityError):
        check_bind(ep, None)


def test_key_files_round_trip(tmp_path):
    from groundstation.bus.security import create_key_files

    public_path, secret_path = create_key_files(tmp_path, "srv")
    full = CurveKeys.load(secret_path)
    pub = CurveKeys.load(public_path)
    assert full.secret is not None and pub.secret is None and pub.public == full.public
    with pytest.raises(BusSecurityError, match="not found"):
        CurveKeys.load(tmp_path / "missing.key")
