"""TimesyncEstimator: NTP-style offset, minimum-RTT filter, clock steps, mapping."""

from __future__ import annotations

import random

import pytest

from firmware_bridge.mavlink.messages import Timesync
from firmware_bridge.mavlink.timesync import NotSyncedError, TimesyncEstimator


def simulate(est, offset_ns, n, rng, t0=10**9, base_delay=200_000, jitter=3_000_000):
    """Round trips with asymmetric random queueing delays; returns the last request time."""
    t = t0
    for _ in range(n):
        up = base_delay + int(rng.expovariate(1 / jitter))
        down = base_delay + int(rng.expovariate(1 / jitter))
        est.add(t, t + up + offset_ns, t + up + down)
        t += 100_000_000
    return t


def test_symmetric_round_trip_is_exact():
    est = TimesyncEstimator()
    assert est.add(1_000, 5_000_500, 2_000)  # vehicle stamped the midpoint
    assert est.offset_ns == 5_000_500 - 1_500 and est.rtt_ns == 1_000
    assert est.to_station_ns(5_000_500) == 1_500


def test_min_rtt_filter_beats_the_mean_under_asymmetric_jitter():
    rng = random.Random(3)
    est = TimesyncEstimator(window=32)
    true_offset = 7_123_456_789
    simulate(est, true_offset, 200, rng)
    # a single sample's error is bounded by rtt/2; the filter picks the tightest one
    assert abs(est.offset_ns - true_offset) <= est.rtt_ns // 2 + 1
    assert abs(est.offset_ns - true_offset) < 1_000_000


def test_negative_or_huge_rtt_is_rejected():
    est = TimesyncEstimator(max_rtt_ns=10_000_000)
    assert not est.add(2_000, 0, 1_000)
    assert not est.add(0, 0, 20_000_000)
    assert est.rejected == 2 and not est.synced


def test_vehicle_reboot_is_followed_after_confirmation():
    rng = random.Random(4)
    est = TimesyncEstimator(window=16, jump_confirm=3)
    t = simulate(est, 5_000_000_000, 30, rng)
    simulate(est, -2_000_000_000, 2, rng, t0=t)
    assert abs(est.offset_ns - 5_000_000_000) < 5_000_000  # two outliers: not yet
    simulate(est, -2_000_000_000, 5, rng, t0=t + 10**9)
    assert abs(est.offset_ns + 2_000_000_000) < 5_000_000
    assert est.clock_steps == 1


def test_observe_uses_replies_only_and_unsynced_mapping_raises():
    est = TimesyncEstimator()
    with pytest.raises(NotSyncedError):
        est.to_station_ns(123)
    assert not est.observe(Timesync(0, 55, time_recv_ns=60))  # a request, not a reply
    assert est.observe(Timesync(1_000_055, 50, time_recv_ns=60))
    assert est.offset_ns == 1_000_000 and est.rtt_ns == 10
