"""The recorder process over real ZeroMQ ipc sockets: SIGKILL mid-session leaves a file readable up
to its last complete chunk; an unwritable path is reported on ``log`` while the process keeps
running and counts drops; raw topics are stored as wire bytes, the others as received frames."""

from __future__ import annotations

import signal
import subprocess
import time

import numpy as np
import pytest

from groundstation.acquisition.reader import TruncatedRecordingWarning, open_recording
from groundstation.bus.envelope import from_bytes
from groundstation.bus.pubsub import Publisher, Subscriber
from groundstation.runtime.session import Session, new_session_id
from groundstation.runtime.supervisor import python_module

pytestmark = pytest.mark.timeout(90)


IMU = {"accel_mps2": np.zeros(3), "gyro_radps": np.zeros(3)}


def _start_recorder(session: Session, out) -> subprocess.Popen:
    argv = python_module(
        "groundstation.runtime.workers.recorder", *session.as_args(), "--out", str(out)
    )
    return subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _publish(pub: Publisher, i: int) -> None:
    now = time.monotonic_ns()
    pub.publish("raw.mavlink", {"link": "serial:///dev/x"},
                {"data": np.frombuffer(i.to_bytes(8, "little") * 4, np.uint8)},
                source_ns=now, recv_ns=now)  # fmt: skip
    pub.publish("samples.imu", {"t_station_ns": i}, IMU, source_ns=i, recv_ns=now)


def test_sigkill_mid_session_leaves_a_gap_free_prefix(tmp_path, zctx):
    session = Session(new_session_id(), ("link", "recorder"))
    out = tmp_path / "killed.mcap"
    proc = _start_recorder(session, out)
    pub = Publisher(topics=["raw.mavlink", "samples.imu"], context=zctx,
                    **session.publisher_kwargs("link"))  # fmt: skip
    status = Subscriber(session.subscribe_endpoints(), ["status"], context=zctx)
    written, i = 0, 0
    try:
        pub.wait_for_subscribers(1, ["samples.imu"], timeout_s=30)
        deadline = time.monotonic() + 60
        while written < 20_000 and time.monotonic() < deadline:  # > 1 closed chunk on disk
            for _ in range(20):
                _publish(pub, i)
                i += 1
            time.sleep(0.01)
            while (env := status.recv(0)) is not None:
                if env.payload["process"] == "recorder":
                    written = env.payload["topics"]["recording"]["bytes_written"]
        proc.send_signal(signal.SIGKILL)
        assert proc.wait(10) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        status.close()
        pub.close(linger_ms=0)
    assert written >= 20_000
    with pytest.warns(TruncatedRecordingWarning):
        rec = open_recording(out)
    with rec:
        assert rec.truncated and rec.metadata() is not None
        imu = [from_bytes(m.data).payload["t_station_ns"] for m in rec.messages("samples.imu")]
        raw = [int.from_bytes(m.data[:8], "little") for m in rec.messages("raw.mavlink")]
    assert 0 < len(imu) < i
    assert imu == list(range(len(imu))), "recovered messages must be a gap-free prefix"
    assert raw[: len(imu)] == imu[: len(raw)]


def test_unwritable_path_is_reported_and_the_process_keeps_running(tmp_path, zctx):
    session = Session(new_session_id(), ("link", "recorder"))
    out = tmp_path / "no" / "such" / "dir" / "x.mcap"
    proc = _start_recorder(session, out)
    pub = Publisher(topics=["raw.mavlink", "samples.imu"], context=zctx,
                    **session.publisher_kwargs("link"))  # fmt: skip
    sub = Subscriber(session.subscribe_endpoints(), ["status", "log"], context=zctx)
    errors, dropped, counts = [], 0, {}
    try:
        pub.wait_for_subscribers(1, ["samples.imu"], timeout_s=30)
        time.sleep(0.5)  # let this test's SUB finish connecting to the recorder's sockets
        for i in range(50):
            _publish(pub, i)
        # the error is logged at the first dropped message and repeated every 5 s while
        # dropping (a subscriber that joined after start-up still hears it)
        deadline = time.monotonic() + 30
        while not (errors and dropped >= 100) and time.monotonic() < deadline:
            env = sub.recv(200)
            if env is None or env.payload.get("process") != "recorder":
                continue
            if env.topic == "log" and env.payload["level"] == "error":
                errors.append(env.payload)
            elif env.topic == "status" and env.payload["state"] == "failed":
                dropped = env.payload["topics"]["recording"]["dropped"]
                counts = {k: v.get("count") for k, v in env.payload["topics"].items()}
        assert proc.poll() is None, "the recorder must keep running"
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(15) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        sub.close()
        pub.close(linger_ms=0)
    # 50 raw + 50 samples (+ the recorder's own log/status), counted instead of written
    assert dropped >= 100 and counts["samples.imu"] == counts["raw.mavlink"] == 50
    assert errors, "RecordingError not reported on log"
    err = errors[-1]
    assert "cannot create recording" in err["message"] and str(out) in err["message"]
    assert "dropped" in err["message"] and err["hint"]
    assert not out.exists()


def test_recorded_layout_raw_as_wire_bytes_envelopes_as_frames(tmp_path, zctx):
    session = Session(new_session_id(), ("link", "recorder"))
    out = tmp_path / "ok.mcap"
    proc = _start_recorder(session, out)
    pub = Publisher(topics=["raw.mavlink", "samples.imu"], context=zctx,
                    **session.publisher_kwargs("link"))  # fmt: skip
    try:
        pub.wait_for_subscribers(1, ["samples.imu"], timeout_s=30)
        for i in range(30):
            _publish(pub, i)
        time.sleep(0.3)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(15) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        pub.close(linger_ms=0)
    with open_recording(out) as rec:
        assert not rec.truncated
        enc = {c.topic: c.message_encoding for c in rec.summary.channels}
        assert enc["raw.mavlink"] == "mavlink2" and enc["samples.imu"] == "gs-envelope/1"
        raw = list(rec.messages("raw.mavlink"))
        imu = [from_bytes(m.data) for m in rec.messages("samples.imu")]
    assert [int.from_bytes(m.data[:8], "little") for m in raw] == list(range(30))
    assert raw[0].channel.metadata["source"] == "serial:///dev/x"
    assert [e.header.seq for e in imu] == list(range(30))
    assert [e.header.source_ns for e in imu] == list(range(30))
