"""Importers on hostile files: declared errors only, no partial output, no endless waits.

Reproducers (issue 14): the CSV importer raised UnicodeDecodeError on one non-UTF-8 byte and, on
1e308 values, a traceback that left a partial recording behind; a 36 KB corrupted ULog kept
``import ulog`` busy for more than 60 s inside pyulog.
"""

from __future__ import annotations

import os
import random
import struct
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from groundstation.acquisition.importers import FlightStreams, ImportDataError, write_flight
from groundstation.acquisition.importers import ulog as ulog_mod
from groundstation.acquisition.importers.csv_imu import (
    IMU_COLUMNS,
    import_csv,
    parse_numeric_csv,
)
from groundstation.acquisition.importers.tlog import import_tlog, read_tlog
from groundstation.acquisition.reader import open_recording
from groundstation.errors import GroundstationError

sys.path.insert(0, str(Path(__file__).parent))
from ulog_builder import make_endless_ulog, make_ulog  # noqa: E402

HEADER = ",".join(IMU_COLUMNS)


def csv_rows(n: int = 50) -> list[str]:
    return [f"{i / 120:.6f},1.0,-2.0,{i * 0.1:.3f},0.1,0.2,9.81,0.5,-0.5,1.0" for i in range(n)]


def _write(path: Path, lines: list[str], raw: bytes = b"") -> Path:
    path.write_bytes(("\n".join([HEADER, *lines]) + "\n").encode() + raw)
    return path


def _no_output(out: Path) -> None:
    assert not out.exists()
    assert not list(out.parent.glob(f".{out.name}.partial-*"))


def test_csv_with_one_non_utf8_byte_skips_that_row(tmp_path):
    rows = csv_rows()
    rows[10] = rows[10].replace("0.1,0.2", "0.1,0.\xff2")
    src = tmp_path / "IMU_1.csv"
    src.write_bytes(("\n".join([HEADER, *rows]) + "\n").encode("latin-1"))
    report = import_csv(src, tmp_path / "out.mcap")
    assert report.skipped == {"IMU_1.csv: not a number": 1}
    assert report.counts["imu (HIGHRES_IMU)"] == 49


def test_csv_with_1e308_values_skips_them_and_fails_cleanly_when_nothing_is_left(tmp_path):
    rows = csv_rows()
    rows[5] = rows[5].replace("9.81", "1e308")
    rows[6] = "1e308" + rows[6][rows[6].index(",") :]  # time
    report = import_csv(_write(tmp_path / "IMU_1.csv", rows), tmp_path / "a.mcap")
    assert report.skipped == {"IMU_1.csv: value out of range": 2}
    out = tmp_path / "b.mcap"
    bad = [r.replace("9.81", "1e308") for r in csv_rows()]
    with pytest.raises(ImportDataError, match="no usable rows"):
        import_csv(_write(tmp_path / "IMU_2.csv", bad), out)
    _no_output(out)


def test_csv_nul_bytes_and_giant_fields_are_counted(tmp_path):
    rows = csv_rows()
    rows[3] = rows[3] + "\0"
    rows[4] = rows[4] + "," + "9" * 200_000  # beyond csv.field_size_limit()
    report = import_csv(_write(tmp_path / "IMU_1.csv", rows), tmp_path / "out.mcap")
    assert report.skipped["IMU_1.csv: malformed CSV line"] == 1  # the giant field
    assert report.skipped["IMU_1.csv: not a number"] == 1  # "1.0\0" (Python 3.11 reads NULs)
    assert report.counts["imu (HIGHRES_IMU)"] == 48


def test_a_failed_import_keeps_an_existing_output(tmp_path):
    out = tmp_path / "keep.mcap"
    out.write_bytes(b"an earlier recording")
    with pytest.raises(ImportDataError):
        import_csv(_write(tmp_path / "IMU_1.csv", ["x,y"] * 3), out)
    assert out.read_bytes() == b"an earlier recording"


def test_a_value_the_wire_cannot_carry_is_an_import_error_without_output(tmp_path):
    n = 5
    t = np.arange(n, dtype=np.int64) * 5_000_000_000_000_000  # time_boot_ms beyond uint32
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    streams = FlightStreams(t, np.zeros((n, 3)), np.zeros((n, 3)), t, q, np.zeros((n, 3)))
    out = tmp_path / "w.mcap"
    with pytest.raises(ImportDataError, match="cannot import"):
        write_flight(streams, out, source="x", created_by="t", link_uri="a", mocap_uri="b")
    _no_output(out)


def test_endless_ulog_is_stopped_and_reported(tmp_path):
    src = tmp_path / "endless.ulg"
    src.write_bytes(make_endless_ulog())
    assert 35_000 < src.stat().st_size < 37_000
    out = tmp_path / "e.mcap"
    with pytest.raises(ImportDataError, match="did not finish within 2 s"):
        ulog_mod.import_ulog(src, out, time_limit_s=2.0)
    _no_output(out)


def test_endless_ulog_on_the_command_line(tmp_path):
    src = tmp_path / "endless.ulg"
    src.write_bytes(make_endless_ulog())
    r = subprocess.run(
        [sys.executable, "-m", "groundstation.cli", "import", "ulog", str(src), "--out",
         str(tmp_path / "e.mcap"), "--time-limit", "2"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert r.returncode == 2
    assert r.stderr.startswith("error: cannot read ULog") and "hint:" in r.stderr
    assert "Traceback" not in r.stderr


def test_a_crashing_pyulog_child_is_reported(tmp_path, monkeypatch):
    src = tmp_path / "ok.ulg"
    src.write_bytes(make_ulog())
    monkeypatch.setattr(ulog_mod, "_child", lambda path, conn: os._exit(7))
    with pytest.raises(ImportDataError, match="crashed"):
        ulog_mod.read_ulog(src, 10.0)


def test_a_good_synthetic_ulog_imports(tmp_path):
    src = tmp_path / "ok.ulg"
    src.write_bytes(make_ulog())
    report = ulog_mod.import_ulog(src, tmp_path / "ok.mcap")
    assert report.counts == {"imu (HIGHRES_IMU)": 200, "attitude (ATTITUDE_QUATERNION)": 100}


def _tlog(n: int = 20, time_us: int = 1_700_000_000_000_000) -> bytes:
    from firmware_bridge.mavlink import MavlinkCodec
    from firmware_bridge.mavlink.messages import Heartbeat

    tx = MavlinkCodec(1, 1)
    return b"".join(
        struct.pack(">Q", time_us + i * 1000) + tx.encode(Heartbeat(2, 12, 0, 0, 4))
        for i in range(n)
    )


def test_tlog_timestamps_beyond_int64_ns_are_dropped(tmp_path):
    src = tmp_path / "x.tlog"
    src.write_bytes(_tlog(5) + _tlog(3, time_us=2**63))
    report = import_tlog(src, tmp_path / "x.mcap")
    assert report.counts == {"HEARTBEAT": 5}
    assert report.skipped == {"timestamp beyond 2**63 ns (dropped)": 3}


def test_tlog_without_frames_fails_without_output(tmp_path):
    src = tmp_path / "junk.tlog"
    src.write_bytes(bytes(range(256)) * 8)
    out = tmp_path / "junk.mcap"
    with pytest.raises(ImportDataError, match="no valid MAVLink frames"):
        import_tlog(src, out)
    _no_output(out)


def _mutate(data: bytes, rng: random.Random) -> bytes:
    b = bytearray(data)
    for _ in range(rng.randint(1, 8)):
        at = rng.randrange(len(b) + 1)
        op = rng.randrange(5)
        if op == 0 and at < len(b):
            b[at] ^= 1 << rng.randrange(8)
        elif op == 1:
            b[at:at] = rng.choice(
                [b"\xff", b"\0", b"1e308", b"nan", b",", b"\n", b'"', b"-", b"9" * 400]
            )
        elif op == 2:
            del b[at : at + rng.randint(1, 40)]
        elif op == 3 and at + 8 <= len(b):
            b[at : at + 8] = struct.pack("<Q", rng.choice([0, 2**63, 2**64 - 1, 2**31]))
        else:
            b[at:at] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 12)))
    return bytes(b)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1))
def test_mutated_csv_text_raises_only_import_errors(seed):
    rng = random.Random(seed)
    data = _mutate(("\n".join([HEADER, *csv_rows(20)]) + "\n").encode(), rng)
    text = data.decode("utf-8", "surrogateescape")
    skipped: Counter = Counter()
    try:
        cols = parse_numeric_csv(text, IMU_COLUMNS, skipped)
    except ImportDataError:
        return
    t = cols["time"]
    assert np.all(np.diff(t) > 0) and t[0] >= 0 and np.all(np.isfinite(t))
    from groundstation.acquisition.importers.csv_imu import convert_xsens

    convert_xsens(cols).validate()  # the conversion of accepted rows is always writable


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_mutated_tlog_bytes_never_raise(seed):
    skipped: Counter = Counter()
    for rec in read_tlog(_mutate(_tlog(), random.Random(seed)), skipped):
        assert rec.time_us >= 0 and rec.frame[0] in (0xFD, 0xFE)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1))
def test_mutated_ulogs_give_a_parse_or_an_import_error(seed, tmp_path_factory):
    src = tmp_path_factory.mktemp("ulog") / "m.ulg"
    src.write_bytes(_mutate(make_ulog(60), random.Random(seed)))
    try:
        parsed = ulog_mod.read_ulog(src, 5.0)
        streams = ulog_mod.convert_ulog(parsed)
        streams.validate()
    except GroundstationError:
        pass


def test_import_of_mutated_csv_files_leaves_output_only_on_success(tmp_path):
    rng = random.Random(5)
    good = ("\n".join([HEADER, *csv_rows(30)]) + "\n").encode()
    for i in range(40):
        src = tmp_path / f"IMU_{i}.csv"
        src.write_bytes(_mutate(good, rng))
        out = tmp_path / f"out_{i}.mcap"
        try:
            import_csv(src, out)
        except ImportDataError:
            _no_output(out)
        else:
            with open_recording(out) as rec:
                assert rec.summary.message_count > 0 and not rec.damaged
