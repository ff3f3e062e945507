"""Endpoint exposure policy and CURVE keys.

Binding is allowed without keys only on loopback (``127.0.0.0/8``, ``::1``, ``localhost``) and
on ``ipc://`` / ``inproc://`` endpoints; anything else (``0.0.0.0``, ``*``, a LAN address, an
interface name) raises :class:`BusSecurityError` unless server CURVE keys are given. A keyed
(CURVE server) socket only talks to clients that present its public key; clients use an
ephemeral key pair. There is no client allow-list (no ZAP handler): knowing the server public
key is the credential.

Key files use the ZeroMQ certificate format (``zmq.auth``): ``name.key`` (public) and
``name.key_secret`` (public + secret).
"""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass
from pathlib import Path

import zmq
import zmq.auth

from groundstation.bus.errors import BusSecurityError

IPC_MAX_PATH = 107  # sockaddr_un.sun_path on Linux minus the terminating NUL (STACK.md)


@dataclass(frozen=True)
class CurveKeys:
    """A CURVE key pair (Z85-encoded, 40 bytes each); ``secret`` may be None for a peer's key."""

    public: bytes
    secret: bytes | None = None

    @classmethod
    def generate(cls) -> CurveKeys:
        """New random key pair (``zmq.curve_keypair``)."""
        public, secret = zmq.curve_keypair()
        return cls(public, secret)

    @classmethod
    def load(cls, path: str | Path) -> CurveKeys:
        """Load a ``zmq.auth`` certificate file (``.key`` or ``.key_secret``)."""
        p = Path(path)
        if not p.is_file():
            raise BusSecurityError(f"CURVE key file {p} not found", hint="create_key_files(dir)")
        try:
            public, secret = zmq.auth.load_certificate(p)
        except (ValueError, OSError) as exc:
            raise BusSecurityError(f"cannot read CURVE key file {p}: {exc}") from None
        return cls(public, secret)


def create_key_files(directory: str | Path, name: str = "bus") -> tuple[Path, Path]:
    """Write a new key pair as ``name.key`` / ``name.key_secret``; returns both paths."""
    Path(directory).mkdir(parents=True, exist_ok=True)
    public, secret = zmq.auth.create_certificates(str(directory), name)
    return Path(public), Path(secret)


def is_loopback_endpoint(endpoint: str) -> bool:
    """True for ipc://, inproc:// and tcp:// endpoints on a loopback address (pure)."""
    scheme, sep, rest = endpoint.partition("://")
    if not sep:
        return False
    if scheme in ("ipc", "inproc"):
        return True
    if scheme != "tcp":
        return False
    host = rest.rsplit(":", 1)[0] if ":" in rest else rest
    host = host.rsplit(";", 1)[-1]  # "source;host" form: the bind side is the host
    host = host.strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # "*", interface names, DNS names


def check_endpoint(endpoint: str) -> None:
    """Validate an endpoint's form (scheme, ipc path length); raises :class:`BusSecurityError`."""
    scheme, sep, rest = endpoint.partition("://")
    if not sep or scheme not in ("tcp", "ipc", "inproc"):
        raise BusSecurityError(
            f"endpoint {endpoint!r} is not tcp://, ipc:// or inproc://",
            hint="e.g. tcp://127.0.0.1:* or ipc:///tmp/gs/link",
        )
    if scheme == "ipc" and len(rest.encode()) > IPC_MAX_PATH:
        raise BusSecurityError(
            f"ipc path of {endpoint!r} is {len(rest.encode())} bytes (max {IPC_MAX_PATH})",
            hint="use a shorter directory, e.g. /tmp/gs/",
        )


def check_bind(endpoint: str, server_keys: CurveKeys | None) -> None:
    """Refuse to bind beyond loopback without CURVE server keys."""
    check_endpoint(endpoint)
    if is_loopback_endpoint(endpoint):
        return
    if server_keys is None or server_keys.secret is None:
        raise BusSecurityError(
            f"refusing to bind {endpoint!r} without CURVE keys: it is reachable beyond loopback",
            hint="bind tcp://127.0.0.1:<port> or pass server_keys=CurveKeys.load('bus.key_secret')",
        )


def apply_server_keys(sock: zmq.Socket, keys: CurveKeys) -> None:
    """Make ``sock`` a CURVE server (call before bind)."""
    if keys.secret is None:
        raise BusSecurityError("CURVE server keys need the secret key (load the .key_secret file)")
    sock.curve_secretkey = keys.secret
    sock.curve_publickey = keys.public
    sock.curve_server = True


def apply_client_keys(sock: zmq.Socket, server_public: bytes) -> None:
    """Make ``sock`` a CURVE client of the server with key ``server_public`` (before connect)."""
    client = CurveKeys.generate()
    sock.curve_serverkey = server_public
    sock.curve_publickey = client.public
    sock.curve_secretkey = client.secret
