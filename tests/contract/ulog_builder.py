"""Build small ULog files in memory (ULog spec: header, definitions, add-logged, data messages).

Used by the importer tests to make valid logs and the reproducer of pyulog's endless loop on a
corrupted definitions section, without copying outside recordings into the repository.
"""

from __future__ import annotations

import math
import struct

HEADER = b"ULog\x01\x12\x35" + b"\x01"
SENSOR_COMBINED = "sensor_combined:uint64_t timestamp;float[3] gyro_rad;float[3] accelerometer_m_s2"
VEHICLE_ATTITUDE = "vehicle_attitude:uint64_t timestamp;float[4] q"


def _msg(kind: str, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), ord(kind)) + payload


def _info(key: str, value: bytes) -> bytes:
    k = key.encode()
    return _msg("I", bytes([len(k)]) + k + value)


def make_ulog(n: int = 200, rate_hz: float = 250.0) -> bytes:
    """A ULog with ``n`` sensor_combined and n/2 vehicle_attitude samples (level, at rest)."""
    out = bytearray(HEADER + struct.pack("<Q", 1_000_000))
    out += _msg("B", bytes(40))  # flag bits: no compat/incompat flags, no appended data
    out += _info("char[6] sys_name", b"PX4gs!")
    out += _msg("F", SENSOR_COMBINED.encode())
    out += _msg("F", VEHICLE_ATTITUDE.encode())
    out += _msg("A", struct.pack("<BH", 0, 1) + b"sensor_combined")
    out += _msg("A", struct.pack("<BH", 0, 2) + b"vehicle_attitude")
    dt_us = int(1e6 / rate_hz)
    for i in range(n):
        t = 2_000_000 + i * dt_us
        gyro = (0.01 * math.sin(i / 10), 0.0, 0.0)
        out += _msg("D", struct.pack("<HQ6f", 1, t, *gyro, 0.1, 0.0, -9.81))
        if i % 2 == 0:
            out += _msg("D", struct.pack("<HQ4f", 2, t, 1.0, 0.0, 0.0, 0.0))
    return bytes(out)


def make_endless_ulog(size: int = 36_000) -> bytes:
    """A ~36 KB ULog whose definitions section makes pyulog loop for ever.

    Every INFO message is 82 bytes; at the end, a message header of type 0 and size
    ``82 * 200 + 6`` with only 5 bytes after it. pyulog reads what it can, flags the packet as
    corrupt and seeks back ``2 + size`` bytes "to advance by one byte": that lands exactly on
    an INFO message boundary 200 messages earlier, so it parses its way back to the same
    header, and again, for ever (``ULog._read_file_definitions``).
    """
    out = bytearray(HEADER + struct.pack("<Q", 0))
    out += _msg("B", bytes(40))
    i = 0
    while len(out) < size - 100:
        out += _info(f"char[64] k{i:04d}", b"x" * 64)  # 3 + 1 + 14 + 64 = 82 bytes
        i += 1
    out += struct.pack("<HB", 82 * 200 + 1 + 5, 0) + bytes(5)
    return bytes(out)
