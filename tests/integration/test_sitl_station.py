"""The SITL waits for its station, and its pty link cannot lead a station to another vehicle.

- ``sitl --link pty:PATH`` (waiting for the station, the default): reading the link shows only
  standby HEARTBEATs until the station speaks; after the station's first HEARTBEAT the IMU
  stream starts. ``--no-wait-for-station`` streams at once.
- ``PATH`` is a symlink to the SITL's pseudo-terminal held by a lock: a second SITL cannot take
  it, and once the SITL is gone (even SIGKILLed, leaving a stale link behind) the station's
  link worker refuses the path instead of opening whatever ``/dev/pts/N`` now is.
"""

from __future__ import annotations

import os
import signal
import time

import pytest

from firmware_bridge.errors import LinkError
from firmware_bridge.link import open_link
from firmware_bridge.mavlink import MavlinkCodec
from firmware_bridge.mavlink.messages import Heartbeat, ImuSample
from groundstation.runtime.workers.link import check_sitl_link
from tests.integration.test_pilot_sitl import start, stop, wait_for

pytestmark = pytest.mark.timeout(120)


def _read(link, codec, seconds: float) -> list:
    out, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        data = link.read(0.05)
        if data:
            out += codec.decode(data, time.monotonic_ns())
    return out


def test_the_sitl_holds_until_the_station_speaks_and_guards_its_link(tmp_path):
    path = tmp_path / "vehicle"
    sitl = start(["sitl", "--link", f"pty:{path}", "--pilot", "script:hover"],
                 tmp_path / "sitl.out", tmp_path / "sitl.err")  # fmt: skip
    try:
        wait_for(lambda: path.is_symlink(), 60, "the SITL link")
        assert os.readlink(path).startswith("/dev/pts/")
        check_sitl_link(f"serial://{path}")  # the SITL holds the lock: accepted
        second = start(["sitl", "--link", f"pty:{path}"], tmp_path / "s2.out",
                       tmp_path / "s2.err")  # fmt: skip
        assert second.wait(60) == 2
        assert "another running SITL" in (tmp_path / "s2.err").read_text()

        link, codec = open_link(f"serial://{path}?baud=921600"), MavlinkCodec(255, 190)
        try:
            held = _read(link, codec, 2.5)
            assert any(isinstance(r, Heartbeat) for r in held), held
            assert not any(isinstance(r, ImuSample) for r in held), "flew before the station"
            link.write(codec.encode(Heartbeat(6, 8, 0, 0, 4)))
            flying = _read(link, codec, 1.5)
            assert sum(isinstance(r, ImuSample) for r in flying) > 100
        finally:
            link.close()
        os.kill(sitl.pid, signal.SIGKILL)  # leaves its link behind, stale
        sitl.wait(10)
        assert path.is_symlink()
        with pytest.raises(LinkError, match="no longer running"):
            check_sitl_link(f"serial://{path}")
    finally:
        stop(sitl)
    argv = ["sitl", "--link", f"pty:{path}", "--duration", "1", "--no-wait-for-station",
            "--pilot", "script:hover"]  # fmt: skip
    clean = start(argv, tmp_path / "s3.out", tmp_path / "s3.err")
    assert clean.wait(60) == 0, (tmp_path / "s3.err").read_text()[-2000:]
    assert not path.exists() and not path.is_symlink()  # replaced the stale link, then removed
