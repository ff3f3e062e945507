"""``groundstation replay`` of a damaged recording says what it dropped and exits non-zero.

Reproducer (issue 14): two flipped payload bytes in one chunk made replay drop a chunk's worth of
messages silently, exit 0.
"""

from __future__ import annotations

import os
import struct
import subprocess
import sys

import pytest

os.environ["MAVLINK20"] = "1"

from firmware_bridge.mavlink import MavlinkCodec
from firmware_bridge.mavlink.messages import AttitudeSample, ImuSample
from groundstation.acquisition import layout
from groundstation.acquisition.recorder import Recorder
from groundstation.cli.replay import EXIT_DAMAGED

pytestmark = pytest.mark.timeout(300)


def _chunks(data: bytes) -> list[int]:
    """File offsets of the chunk records (MCAP: opcode 0x06; stop at the footer 0x02)."""
    pos, out = 8, []
    while pos + 9 <= len(data):
        op, length = struct.unpack_from("<BQ", data, pos)
        if op == 0x02:
            break
        if op == 0x06:
            out.append(pos + 9 + length)  # end of the chunk record
        pos += 9 + length
    return out


def _recording(path):
    tx = MavlinkCodec(1, 1)
    with Recorder(path, max_chunk_span_ns=200_000_000) as rec:
        for i in range(600):  # 3 s of 200 Hz IMU + attitude, ~15 chunks
            t = 10**9 + i * 5_000_000
            frame = tx.encode(ImuSample((0.0, 0.0, -9.8), (0.0, 0.0, 0.0), time_source_ns=t))
            frame += tx.encode(AttitudeSample((1.0, 0.0, 0.0, 0.0), (0, 0, 0), time_source_ns=t))
            rec.write(frame, layout.RAW_MAVLINK_TOPIC, t, t, source="test")
    data = bytearray(path.read_bytes())
    end = _chunks(data)[len(_chunks(data)) // 2]
    for k in (40, 80):  # two flipped bytes inside the chunk's compressed records
        data[end - k] ^= 0xFF
    path.write_bytes(bytes(data))
    return path


def _replay(*args):
    return subprocess.run(
        [sys.executable, "-m", "groundstation.cli", "replay", *args, "--quiet"],
        capture_output=True,
        text=True,
        timeout=240,
    )


def test_replay_of_a_damaged_recording_reports_what_it_dropped(tmp_path):
    log = _recording(tmp_path / "damaged.mcap")
    r = _replay(str(log))
    assert r.returncode == EXIT_DAMAGED, r.stderr
    assert "damaged" in r.stderr and "1 corrupt chunk(s) skipped" in r.stderr
    assert "message(s) lost (raw.mavlink" in r.stderr
    assert "--allow-damaged" in r.stderr and "Traceback" not in r.stderr
    ok = _replay(str(log), "--allow-damaged")
    assert ok.returncode == 0, ok.stderr
    assert "warning: recording damaged.mcap is damaged" in ok.stderr
