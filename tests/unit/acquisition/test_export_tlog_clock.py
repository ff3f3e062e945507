"""``export tlog`` dates its records with a real clock (issue 15: exported tlogs were dated
1970): the recording's ``utc_offset_ns``, else the vehicle's SYSTEM_TIME, else the file's
modification time; ``--utc-start`` overrides."""

from __future__ import annotations

import datetime
import os
import struct

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from groundstation.acquisition import layout  # noqa: E402
from groundstation.acquisition.importers.export_tlog import (  # noqa: E402
    export_tlog,
    system_time_unix_us,
)
from groundstation.acquisition.recorder import Recorder  # noqa: E402

MAV = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
T0 = 5_000_000_000  # log time of the first frame (station monotonic ns)
UNIX_US = 1_777_000_000_000_000  # 2026-04-24


def heartbeat() -> bytes:
    return mavlink2.MAVLink_heartbeat_message(2, 12, 0, 0, 4, 3).pack(MAV)


def system_time(unix_us: int) -> bytes:
    return mavlink2.MAVLink_system_time_message(unix_us, 1234).pack(MAV)


def make(path, frames, extra=None):
    meta = layout.station_metadata(station_version="t", created_by="test", extra=extra)
    with Recorder(path, metadata=meta) as rec:
        for i, f in enumerate(frames):
            rec.write(f, "raw.mavlink", T0 + i * 1_000_000_000, source="serial:///dev/x")
    return path


def first_us(tlog) -> int:
    return struct.unpack(">Q", tlog.read_bytes()[:8])[0]


def test_system_time_frames_are_parsed_and_others_ignored():
    assert system_time_unix_us(system_time(UNIX_US)) == UNIX_US
    assert system_time_unix_us(system_time(0)) == 0
    assert system_time_unix_us(heartbeat()) is None


def test_the_recordings_utc_offset_dates_the_records(tmp_path):
    offset = 1_700_000_000_000_000_000 - T0
    src = make(
        tmp_path / "a.mcap", [heartbeat(), heartbeat()], {layout.KEY_UTC_OFFSET: str(offset)}
    )
    rep = export_tlog(src, tmp_path / "a.tlog")
    assert first_us(tmp_path / "a.tlog") == 1_700_000_000_000_000
    assert "utc_offset_ns" in rep.clock and "2023-11-14" in rep.describe()


def test_the_vehicles_system_time_dates_a_recording_without_metadata(tmp_path):
    src = make(tmp_path / "b.mcap", [heartbeat(), system_time(0), system_time(UNIX_US)])
    rep = export_tlog(src, tmp_path / "b.tlog")
    # the SYSTEM_TIME at log time T0 + 2 s said UNIX_US: the first frame is 2 s earlier
    assert first_us(tmp_path / "b.tlog") == UNIX_US - 2_000_000
    assert rep.clock == "the vehicle's SYSTEM_TIME"


def test_without_a_clock_the_file_time_is_the_end_and_utc_start_overrides(tmp_path):
    src = make(tmp_path / "c.mcap", [heartbeat(), heartbeat(), heartbeat()])
    mtime = 1_750_000_000
    os.utime(src, (mtime, mtime))
    rep = export_tlog(src, tmp_path / "c.tlog")
    assert first_us(tmp_path / "c.tlog") == (mtime - 2) * 1_000_000  # last frame = mtime
    assert "modification time" in rep.clock
    start = datetime.datetime(2026, 5, 1, 10, tzinfo=datetime.UTC).timestamp()
    export_tlog(src, tmp_path / "d.tlog", utc_start=start)
    assert first_us(tmp_path / "d.tlog") == int(start * 1e6)
    assert first_us(tmp_path / "d.tlog") > 1_000_000_000_000_000  # not 1970


def test_cli_utc_start_is_parsed_and_a_bad_one_is_a_clear_error(tmp_path, capsys):
    from groundstation import cli

    src = make(tmp_path / "e.mcap", [heartbeat()])
    out = tmp_path / "e.tlog"
    assert cli.main(["export", "tlog", str(src), "--out", str(out),
                     "--utc-start", "2026-05-01T10:00:00Z"]) == 0  # fmt: skip
    assert first_us(out) == int(
        datetime.datetime(2026, 5, 1, 10, tzinfo=datetime.UTC).timestamp() * 1e6
    )
    assert cli.main(["export", "tlog", str(src), "--out", str(out), "--utc-start", "May 1st"]) == 2
    assert "not an ISO time" in capsys.readouterr().err


@pytest.mark.parametrize("extra", [{layout.KEY_UTC_OFFSET: "x"}, None])
def test_unreadable_offsets_fall_back(tmp_path, extra):
    src = make(tmp_path / "f.mcap", [heartbeat()], extra)
    assert "modification time" in export_tlog(src, tmp_path / "f.tlog").clock
