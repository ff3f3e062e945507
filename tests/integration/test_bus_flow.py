"""Credit flow control: a fast lossless source never outruns a slow subscriber."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from groundstation.bus.errors import BusTimeoutError
from groundstation.bus.pubsub import Publisher, Subscriber

pytestmark = pytest.mark.timeout(60)
IMU = {"accel_mps2": np.zeros(3), "gyro_radps": np.zeros(3)}


def _slow_consumer(sub: Subscriber, n: int, processed: list[int], delay_s: float) -> None:
    while len(processed) < n:
        env = sub.recv(5000)
        if env is None:
            return
        time.sleep(delay_s)  # "processing"
        processed.append(env.header.seq)  # then the next recv() acknowledges it
    sub.recv(0)  # acknowledge the last one


def _run(zctx, window: int | None, n: int = 300) -> tuple[list[int], int, Subscriber]:
    pub = Publisher(topics=["samples.imu"], flow_window=window, context=zctx)
    flow_ep = pub.flow.endpoint if pub.flow else None
    sub = Subscriber(pub.endpoints, ["samples.imu"], flow_endpoint=flow_ep, context=zctx)
    processed: list[int] = []
    try:
        pub.wait_for_subscribers(1, timeout_s=10)
        worker = threading.Thread(target=_slow_consumer, args=(sub, n, processed, 0.001))
        worker.start()
        max_ahead = 0
        for _ in range(n):  # as fast as the credits allow (replay at speed=max)
            seq = pub.publish("samples.imu", arrays=IMU).header.seq
            max_ahead = max(max_ahead, seq + 1 - len(processed))
        worker.join(30)
        assert not worker.is_alive()
    finally:
        sub.close()
        pub.close()
    return processed, max_ahead, sub


def test_slow_subscriber_gets_everything_and_publisher_stays_within_window(zctx):
    processed, max_ahead, sub = _run(zctx, window=8)
    assert processed == list(range(300)) and sub.gaps == {"samples.imu": 0}
    # sent but not yet processed, counted on the consumer's side
    assert max_ahead <= 8


def test_without_flow_control_the_publisher_runs_ahead(zctx):
    processed, max_ahead, _ = _run(zctx, window=None)
    assert processed == list(range(300))
    assert max_ahead > 8  # the same workload overruns the window: the test above can fail


def test_stuck_consumer_times_out_and_bye_releases(zctx):
    pub = Publisher(topics=["samples.imu"], flow_window=4, flow_timeout_s=0.3, context=zctx)
    sub = Subscriber(pub.endpoints, ["samples.imu"], flow_endpoint=pub.flow.endpoint, context=zctx)
    try:
        pub.wait_for_subscribers(1, timeout_s=10)
        for _ in range(4):
            pub.publish("samples.imu", arrays=IMU)  # seqs 0..3: within the window
        with pytest.raises(BusTimeoutError, match="samples.imu"):
            pub.publish("samples.imu", arrays=IMU)  # nobody processed anything
        sub.close()  # says bye
        pub.flow_timeout_s = 10
        pub.publish("samples.imu", arrays=IMU)  # released
    finally:
        sub.close()
        pub.close()
