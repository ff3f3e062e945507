"""MavlinkEndpoint over a real pseudo-terminal against a 200 Hz simulated vehicle.

The vehicle thread owns the pty master: it sends HIGHRES_IMU + ATTITUDE_QUATERNION on absolute
deadlines (select with the time left as timeout, so incoming bytes are served meanwhile), answers
TIMESYNC requests with its own clock and records the commands it receives.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty

import pytest

from firmware_bridge.link import open_link
from firmware_bridge.mavlink import MavlinkCodec
from firmware_bridge.mavlink.endpoint import MavlinkEndpoint
from firmware_bridge.mavlink.health import percentile
from firmware_bridge.mavlink.messages import (
    AttitudeSample,
    Heartbeat,
    ImuSample,
    SetMessageInterval,
    Timesync,
)

VEHICLE_CLOCK_OFFSET_NS = -987_654_321  # vehicle clock = station monotonic clock + this


class Vehicle(threading.Thread):
    def __init__(self, master: int, duration_s: float, rate_hz: float = 200.0) -> None:
        super().__init__(daemon=True)
        self.master, self.n = master, int(round(duration_s * rate_hz))
        self.period_ns = int(1e9 / rate_hz)
        self.tx, self.rx = MavlinkCodec(1, 1), MavlinkCodec()
        self.commands: list = []
        self.timesync_answers = 0
        self.sent = 0
        self.error: BaseException | None = None

    @staticmethod
    def now() -> int:
        return time.monotonic_ns() + VEHICLE_CLOCK_OFFSET_NS

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            view = view[os.write(self.master, view) :]

    def _serve(self, data: bytes) -> None:
        for rec in self.rx.decode(data, 0):
            if isinstance(rec, Timesync) and rec.tc1 == 0:
                self._write(self.tx.encode(Timesync(self.now(), rec.ts1)))
                self.timesync_answers += 1
            elif isinstance(rec, SetMessageInterval):
                self.commands.append(rec)

    def run(self) -> None:
        try:
            t0 = time.monotonic_ns()
            while self.sent < self.n:
                deadline = t0 + self.sent * self.period_ns
                wait = deadline - time.monotonic_ns()
                if wait > 0:
                    ready, _, _ = select.select([self.master], [], [], wait / 1e9)
                    if ready:
                        self._serve(os.read(self.master, 4096))
                    continue
                t = self.now()
                frame = self.tx.encode(
                    ImuSample((0.1, -0.2, -9.81), (0.01, 0.02, -0.03), time_source_ns=t)
                ) + self.tx.encode(
                    AttitudeSample((1.0, 0.0, 0.0, 0.0), (0.01, 0.02, -0.03), time_source_ns=t)
                )
                if self.sent % 200 == 0:
                    frame += self.tx.encode(Heartbeat(2, 12, 81, 0, 4))
                self._write(frame)
                self.sent += 1
            end = time.monotonic_ns() + 300_000_000  # keep answering a little longer
            while time.monotonic_ns() < end:
                ready, _, _ = select.select([self.master], [], [], 0.05)
                if ready:
                    self._serve(os.read(self.master, 4096))
        except BaseException as exc:  # reported by the test
            self.error = exc


def run_session(tmp_path, duration_s: float) -> dict:
    master, slave = os.openpty()
    tty.setraw(slave)
    path = str(tmp_path / "ttyVEHICLE")
    os.symlink(os.ttyname(slave), path)
    link = open_link(f"serial://{path}?baud=921600")
    os.close(slave)
    arrivals: dict[str, list[int]] = {"HIGHRES_IMU": [], "ATTITUDE_QUATERNION": []}
    done = threading.Condition()
    vehicle = Vehicle(master, duration_s)

    def on_record(rec) -> None:
        if isinstance(rec, ImuSample | AttitudeSample):
            arrivals[rec.msg_type].append(rec.time_recv_ns)
            if len(arrivals[rec.msg_type]) >= vehicle.n:
                with done:
                    done.notify_all()

    endpoint = MavlinkEndpoint(link, MavlinkCodec(), timesync_period_s=0.25)
    try:
        endpoint.start(on_record)
        vehicle.start()
        endpoint.request_message_interval(105, 200.0)
        with done:
            done.wait_for(
                lambda: min(len(v) for v in arrivals.values()) >= vehicle.n,
                timeout=duration_s * 3 + 20,
            )
        vehicle.join(10)
        endpoint.stop()
    finally:
        endpoint.stop()
        link.close()
        os.close(master)
    assert vehicle.error is None, vehicle.error
    return {"vehicle": vehicle, "endpoint": endpoint, "arrivals": arrivals}


def check_no_loss(session) -> None:
    vehicle, endpoint, arrivals = session["vehicle"], session["endpoint"], session["arrivals"]
    st = endpoint.codec.stats
    assert len(arrivals["HIGHRES_IMU"]) == vehicle.n
    assert len(arrivals["ATTITUDE_QUATERNION"]) == vehicle.n
    assert st.lost == 0 and st.crc_errors == 0 and st.garbage_bytes == 0
    assert endpoint.callback_errors == 0 and endpoint.read_errors == 0
    assert endpoint.codec.stats.per_type["HEARTBEAT"] == (vehicle.n + 199) // 200


@pytest.mark.timeout(120)
def test_pty_200hz_5s_no_loss_timesync_and_commands(tmp_path):
    session = run_session(tmp_path, 5.0)
    check_no_loss(session)
    vehicle, endpoint = session["vehicle"], session["endpoint"]
    # The vehicle got our rate request and answered our TIMESYNC pings.
    assert vehicle.commands and vehicle.commands[0].message_id == 105
    assert vehicle.commands[0].interval_us == 5000
    assert vehicle.timesync_answers >= 2 and endpoint.timesync.synced
    # Offset error <= rtt/2 by construction; loose bound for a loaded machine.
    assert abs(endpoint.timesync.offset_ns - VEHICLE_CLOCK_OFFSET_NS) < 50_000_000
    assert endpoint.health.latency_ns() is not None
    assert "HIGHRES_IMU" in endpoint.health.summary()


@pytest.mark.soak
@pytest.mark.timeout(400)
def test_soak_pty_200hz_60s_no_loss(tmp_path):
    check_no_loss(run_session(tmp_path, 60.0))


@pytest.mark.soak
@pytest.mark.timeout(200)
def test_measure_pty_200hz_20s(tmp_path):
    """Prints received rates, inter-arrival jitter, reader CPU share, decode throughput (-s)."""
    session = run_session(tmp_path, 20.0)
    check_no_loss(session)
    endpoint, arrivals = session["endpoint"], session["arrivals"]
    lines = []
    for name, times in arrivals.items():
        dt = [b - a for a, b in zip(times, times[1:], strict=False)]
        rate = (len(times) - 1) / ((times[-1] - times[0]) / 1e9)
        jitter = [abs(d - 5_000_000) for d in dt]
        lines.append(
            f"{name}: {rate:.2f} Hz, inter-arrival p50 {percentile(dt, 50) / 1e6:.3f} ms "
            f"p99 {percentile(dt, 99) / 1e6:.3f} ms, |dt-5ms| p50 "
            f"{percentile(jitter, 50) / 1e6:.3f} ms p99 {percentile(jitter, 99) / 1e6:.3f} ms"
        )
    cpu = endpoint.reader_cpu_ns / endpoint.reader_wall_ns
    lat = endpoint.health.latency_ns()
    lines.append(f"reader thread CPU: {100 * cpu:.2f} % of one core")
    lines.append(f"latency p50 {lat[0] / 1e6:.3f} ms p99 {lat[1] / 1e6:.3f} ms")
    # decode throughput: 40k messages in 4 kB chunks
    tx = MavlinkCodec(1, 1)
    data = b"".join(
        tx.encode(ImuSample((0.1, 0.2, -9.8), (0.01, 0.02, 0.03), time_source_ns=i * 5_000))
        + tx.encode(AttitudeSample((1, 0, 0, 0), (0.1, 0.2, 0.3), time_source_ns=i * 5_000_000))
        for i in range(20_000)
    )
    rx, n = MavlinkCodec(), 0
    t = time.perf_counter()
    for i in range(0, len(data), 4096):
        n += len(rx.decode(data[i : i + 4096], i))
    lines.append(f"decode throughput: {n / (time.perf_counter() - t):,.0f} messages/s")
    assert n == 40_000
    print("\n" + "\n".join(lines))


@pytest.mark.timeout(60)
def test_endpoint_survives_callback_errors_and_answers_vehicle_timesync():
    with open_link("udp://127.0.0.1:0?mode=listen") as station:
        vehicle = open_link(f"udp://127.0.0.1:{station.local_address[1]}")
        seen = threading.Condition()
        got: list = []

        def callback(rec) -> None:
            with seen:
                got.append(rec)
                seen.notify_all()
            if len(got) == 1:
                raise ValueError("consumer bug")

        endpoint = MavlinkEndpoint(station, MavlinkCodec(), heartbeat_period_s=None)
        endpoint.start(callback)
        try:
            vtx = MavlinkCodec(1, 1)
            vehicle.write(vtx.encode(Heartbeat(2, 12, 0, 0, 4)))
            vehicle.write(vtx.encode(Timesync(0, 777)))  # the vehicle asks for our clock
            with seen:
                assert seen.wait_for(lambda: len(got) >= 2, 10)
            reply = []
            vrx = MavlinkCodec()
            while not reply:
                data = vehicle.read(5.0)
                assert data, "no TIMESYNC reply"
                reply = [r for r in vrx.decode(data, 0) if isinstance(r, Timesync) and r.tc1]
            assert reply[0].ts1 == 777 and reply[0].system_id == 255
        finally:
            endpoint.stop()
            vehicle.close()
        assert endpoint.callback_errors == 1
        assert [e.kind for e in endpoint.events] == ["callback_error"]
        assert endpoint.target_system == 1 and endpoint.vehicle_heard
