"""A recorder process killed with SIGKILL, or hitting a file-size limit mid-session, leaves a file
that the reader recovers up to its last complete chunk, with the loss reported."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap

import pytest

from groundstation.acquisition.reader import TruncatedRecordingWarning, open_recording

pytestmark = pytest.mark.timeout(120)

# The child writes message i = "<i as 8 bytes>" + padding on three topics as fast as it can and
# prints the number of messages that are durable (inside chunks handed to the OS).
CHILD = textwrap.dedent(
    """
    import sys, resource, signal
    from groundstation.acquisition.recorder import Recorder, RecordingError
    path, limit = sys.argv[1], int(sys.argv[2])
    if limit:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # get EFBIG from write() instead
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    topics = ["raw.mavlink", "raw.natnet", "samples.imu"]
    rec = Recorder(path, chunk_bytes=16 * 1024)
    last = -1
    i = 0
    try:
        while True:
            rec.write(i.to_bytes(8, "little") + bytes(40 + i % 50), topics[i % 3], 5_000_000 * i)
            i += 1
            if rec.stats.durable_messages != last:
                last = rec.stats.durable_messages
                print("durable", last, flush=True)
    except RecordingError as exc:
        print("error", exc, flush=True)
        print("errno", exc.errno, flush=True)
        rec.close()
        print("done", rec.stats.durable_messages, flush=True)
    """
)


def _check_prefix(path, at_least: int) -> int:
    with pytest.warns(TruncatedRecordingWarning):
        rec = open_recording(path)
    with rec:
        assert rec.truncated
        got = list(rec.messages())
        report = rec.recovery
    ids = [int.from_bytes(m.data[:8], "little") for m in got]
    assert ids == list(range(len(ids))), "recovered messages must be a gap-free prefix"
    assert len(ids) >= at_least
    assert report.recovered_messages == len(ids)
    assert f"recovered {len(ids)} messages" in report.describe()
    return len(ids)


def test_sigkill_mid_session_recovers_up_to_last_complete_chunk(tmp_path):
    path = tmp_path / "killed.mcap"
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(path), "0"],
        stdout=subprocess.PIPE,
        text=True,
    )
    durable = 0
    try:
        for line in proc.stdout:
            if line.startswith("durable"):
                durable = int(line.split()[1])
                if durable >= 3000:
                    break
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL
    assert durable >= 3000
    recovered = _check_prefix(path, durable)
    # the child may have closed more chunks between its last report and the kill; loss is
    # bounded by what was still in memory (one chunk), never by what was on disk.
    assert recovered >= durable


def test_write_error_mid_session_is_reported_and_file_stays_readable(tmp_path):
    path = tmp_path / "limited.mcap"
    out = subprocess.run(
        [sys.executable, "-c", CHILD, str(path), str(200_000)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    lines = dict(line.split(" ", 1) for line in out.stdout.splitlines() if " " in line)
    assert str(path) in lines["error"] and "cannot write recording" in lines["error"]
    assert int(lines["errno"]) == 27  # EFBIG: the OS error is kept on the exception
    durable = int(lines["done"])
    assert durable > 1000
    assert path.stat().st_size <= 200_000
    assert _check_prefix(path, durable) >= durable
