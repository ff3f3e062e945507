"""``groundstation live`` against ``groundstation sitl`` (pseudo-terminal MAVLink + loopback UDP
NatNet), SIGINT, then the recording: it opens without recovery, holds what the monitor saw with
zero gaps, and (when the detector and mapper are installed) observations.

The SITL flies its scripted survey of the wall at real time; frames are counted, never timed.
"""

from __future__ import annotations

import json
import signal
import subprocess
from pathlib import Path

import pytest

from groundstation.acquisition.segments import open_session as open_recording
from groundstation.cli.live import DETECTOR_MODULE, MAPPER_MODULE, _available
from tests.integration.test_pilot_sitl import free_udp_port, start, stop, wait_for

LIVE_S = 24  # status lines (~seconds) to wait for before SIGINT (start-up included)
STEADY = 8  # lines checked once the streams flow

pytestmark = pytest.mark.timeout(420)


def sitl_device(out: Path, proc: subprocess.Popen, timeout: float = 30) -> str:
    """The pty the SITL printed (``SITL MAVLink on /dev/pts/N``)."""

    def find() -> str | None:
        assert proc.poll() is None, "the SITL exited early"
        for line in out.read_text().splitlines():
            if line.startswith("SITL MAVLink on "):
                return line.rsplit(" ", 1)[1]
        return None

    return wait_for(find, timeout, "the SITL's pty", poll=0.1)


def status_lines(path: Path) -> list[str]:
    return [ln for ln in path.read_text().splitlines() if ln.lstrip("!").lstrip().startswith("t=")]


def run_live_against_sitl(
    tmp_path: Path,
    n_lines: int,
    sitl_args: list[str],
    live_args: list[str],
    during=None,
) -> tuple[int, dict, list[str], str]:
    """Start the SITL (pty + UDP mocap) and ``live``; wait for ``n_lines`` status lines (calling
    ``during()`` once started), SIGINT ``live``; returns (exit code, summary, lines, stderr)."""
    from tests.integration.live_session import private_root

    mport = free_udp_port()
    root = private_root()  # other test runs remove /tmp/gs-* folders that appear meanwhile
    sitl = start(
        ["sitl", "--link", "pty", "--mocap", f"udp://127.0.0.1:{mport}", *sitl_args],
        tmp_path / "sitl.out", tmp_path / "sitl.err",
    )  # fmt: skip
    live = None
    try:
        dev = sitl_device(tmp_path / "sitl.out", sitl)
        live = start(
            ["live", "--link", f"serial://{dev}?baud=921600",
             "--mocap", f"natnet://127.0.0.1:{mport}", "--summary", str(tmp_path / "summary.json"),
             "--session-root", root, *live_args],
            tmp_path / "live.out", tmp_path / "live.err",
        )  # fmt: skip
        if during is not None:
            during()
        wait_for(
            lambda: live.poll() is not None or len(status_lines(tmp_path / "live.out")) >= n_lines,
            n_lines * 3 + 60, f"{n_lines} status lines", poll=0.5,
        )  # fmt: skip
        assert live.poll() is None, (tmp_path / "live.err").read_text()[-3000:]
    finally:
        rc = stop(live) if live is not None else -1
        stop(sitl, signal.SIGTERM)
        import shutil

        shutil.rmtree(root, ignore_errors=True)
    err = (tmp_path / "live.err").read_text()
    summary = json.loads((tmp_path / "summary.json").read_text()) if rc >= 0 else {}
    return rc, summary, status_lines(tmp_path / "live.out"), err


def test_live_session_against_the_sitl_records_everything_with_zero_gaps(tmp_path):
    rec_path = tmp_path / "live.mcap"
    rc, summary, lines, err = run_live_against_sitl(
        tmp_path,
        LIVE_S,
        ["--scene", "wall", "--pilot", "script:survey", "--duration", "120"],
        ["--record", str(rec_path), "--no-viewer"],
    )
    assert rc == 0, err[-3000:]
    assert len(lines) >= LIVE_S
    # after start-up (the SITL waits for the station, workers start): every line shows ~200 Hz
    # streams and no gap
    flowing = [k for k, ln in enumerate(lines) if "rec " in ln and "imu   0.0" not in ln]
    steady = lines[flowing[0] + 1 : flowing[0] + 1 + STEADY]
    assert len(steady) == STEADY, lines
    assert all("gaps 0/0 rec" in ln for ln in steady), steady
    imu = [float(ln.split("imu", 1)[1].split("Hz")[0]) for ln in steady]
    assert sorted(imu)[len(imu) // 2] > 150, imu

    with open_recording(rec_path) as rec:  # no recovery needed: closed cleanly
        assert not rec.truncated
        counts = rec.summary.topic_counts
    assert summary["recording"]["complete"] is True
    assert summary["gaps_monitor"] == 0 and summary["gaps_recorder"] == 0
    for topic in ("samples.imu", "samples.attitude", "samples.pose"):
        assert counts[topic] > 200 * (STEADY - 2), (topic, counts[topic])
        assert counts[topic] == summary["counts"][topic], topic  # the recorder missed nothing
    assert counts["raw.mavlink"] > 0 and counts["raw.natnet"] == counts["samples.pose"]
    if _available(DETECTOR_MODULE) and _available(MAPPER_MODULE):
        assert counts.get("observations", 0) > 0
        assert counts.get("observations", 0) == summary["observations"]
    print(f"\n{lines[-1]}\nrecorded: {counts}")
