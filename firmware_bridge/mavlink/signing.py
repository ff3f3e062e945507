"""MAVLink 2 message signing: key files and timestamps (MAVLink signing spec).

A signed frame carries link id, a 48-bit timestamp in units of 10 us since 2015-01-01 00:00 UTC,
and the first 6 bytes of SHA-256(secret_key + header + payload + CRC + link id + timestamp). The
generated ``MAVLink`` class computes and checks the signature; this module supplies the key and
the policy of which messages must be signed.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from firmware_bridge.errors import BridgeError

#: Messages of the command uplink (station -> vehicle) that must be signed when signing is
#: required: MANUAL_CONTROL (69), COMMAND_LONG (76), ATT_POS_MOCAP (138).
UPLINK_MESSAGE_IDS: frozenset[int] = frozenset({69, 76, 138})

#: 2015-01-01T00:00:00Z as a UNIX time, s (MAVLink signing epoch).
SIGNING_EPOCH_UNIX_S = 1420070400


class SigningKeyError(BridgeError, ValueError):
    """A signing key (file) is not 32 raw bytes or 64 hexadecimal characters."""


def parse_signing_key(data: bytes, source: str = "<bytes>") -> bytes:
    """Return the 32-byte secret key from 32 raw bytes or 64 hex characters (whitespace ignored).

    Raises
    ------
    SigningKeyError
        Naming ``source`` and the length found.
    """
    if len(data) == 32:
        return bytes(data)
    text = data.strip()
    if len(text) == 64:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    raise SigningKeyError(
        f"signing key {source} must hold 32 raw bytes or 64 hex characters, got {len(data)} bytes",
        hint='create one with: python -c "import os; print(os.urandom(32).hex())" > key.hex',
    )


def load_signing_key(path: str | os.PathLike[str]) -> bytes:
    """Read a signing key file (32 raw bytes or 64 hex characters).

    Raises
    ------
    SigningKeyError
        The file is missing, unreadable or of the wrong form; the message names the file.
    """
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise SigningKeyError(f"cannot read signing key file {p}: {exc.strerror}") from exc
    return parse_signing_key(data, source=f"file {p}")


def signing_timestamp(unix_time_s: float) -> int:
    """MAVLink signing timestamp (10 us units since 2015-01-01 UTC) for a UNIX time in s."""
    return max(0, int((unix_time_s - SIGNING_EPOCH_UNIX_S) * 100_000))


def signing_timestamp_now() -> int:
    """Signing timestamp for the current wall-clock time (the one place signing reads a clock)."""
    return signing_timestamp(time.time())
