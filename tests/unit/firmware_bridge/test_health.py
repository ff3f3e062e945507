"""LinkHealth: rates over a sliding window, bytes/s, latency and inter-arrival percentiles."""

from __future__ import annotations

from firmware_bridge.mavlink import MavlinkCodec
from firmware_bridge.mavlink.health import LinkHealth, percentile
from firmware_bridge.mavlink.messages import AttitudeSample, Heartbeat, ImuSample

MS = 1_000_000


def feed(health, t_end_ms=3000, offset=0, delay_ms=2):
    for k in range(0, t_end_ms, 5):  # 200 Hz IMU, 100 Hz attitude, 1 Hz heartbeat
        src = k * MS + offset
        recv = k * MS + delay_ms * MS
        health.on_bytes(100, recv)
        health.on_record(
            ImuSample((0, 0, -9.8), (0, 0, 0), time_source_ns=src, time_recv_ns=recv), offset
        )
        if k % 10 == 0:
            health.on_record(
                AttitudeSample((1, 0, 0, 0), (0, 0, 0), time_source_ns=src, time_recv_ns=recv),
                offset,
            )
        if k % 1000 == 0:
            health.on_record(Heartbeat(2, 12, 0, 0, 4, time_recv_ns=recv))


def test_rates_bytes_and_latency():
    h = LinkHealth(window_s=2.0)
    feed(h, offset=5_000 * MS, delay_ms=2)
    rates = h.rates()
    assert rates["HIGHRES_IMU"] == 200.0
    assert rates["ATTITUDE_QUATERNION"] == 100.0
    assert rates["HEARTBEAT"] == 1.0
    assert h.bytes_per_s() == 200 * 100
    assert h.latency_ns() == (2 * MS, 2 * MS)
    assert h.interarrival_ns("HIGHRES_IMU") == (5 * MS, 5 * MS)
    line = h.summary()
    assert "HIGHRES_IMU 200.0Hz" in line and "20.0kB/s" in line and "p50 2.00ms" in line


def test_a_stream_that_stops_decays_to_zero():
    h = LinkHealth(window_s=1.0)
    feed(h, t_end_ms=1000)
    for k in range(1000, 3000, 100):
        h.on_record(Heartbeat(2, 12, 0, 0, 4, time_recv_ns=k * MS))
    assert h.rates()["HIGHRES_IMU"] == 0.0
    assert h.rates()["HEARTBEAT"] == 10.0


def test_no_latency_without_timesync_and_stats_are_reported():
    h = LinkHealth()
    h.on_record(ImuSample((0, 0, 0), (0, 0, 0), time_source_ns=5, time_recv_ns=10))
    assert h.latency_ns() is None
    codec = MavlinkCodec()
    codec.decode(b"\x00" * 17, 1)
    h.on_stats(codec.stats)
    assert "garbage 17B" in h.summary() and "latency" not in h.summary()


def test_percentile_nearest_rank():
    assert percentile(list(range(1, 101)), 50) == 50
    assert percentile(list(range(1, 101)), 99) == 99
    assert percentile([7], 99) == 7
