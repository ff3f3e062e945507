"""Start-up: the ready handshake against the PUB/SUB slow-joiner problem, across processes."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest

from groundstation.bus.errors import BusTimeoutError
from groundstation.bus.pubsub import Publisher, Subscriber

pytestmark = pytest.mark.timeout(60)
IMU = {"accel_mps2": np.zeros(3), "gyro_radps": np.zeros(3)}


def test_late_subscriber_process_gets_seq_0(zctx):
    """The subscriber process starts after the publisher is up and publishing is about to
    begin; thanks to wait_for_subscribers it still receives every message from seq 0."""
    topics = ["samples.imu", "status"]
    with Publisher(topics=topics, context=zctx) as pub:
        proc = subprocess.Popen(
            [sys.executable, "-m", "groundstation.bus.probe", *pub.endpoints]
            + ["--topics", ",".join(topics), "--count", "51", "--timeout-s", "10"],
            stdout=subprocess.PIPE,
            text=True,
        )
        counts = pub.wait_for_subscribers(1, topics, timeout_s=30)
        assert counts == {"samples.imu": 1, "status": 1}
        pub.publish("status", {"process": "test", "state": "up", "topics": {}})
        for _ in range(50):  # immediately, no sleep
            pub.publish("samples.imu", arrays=IMU)
        out, _ = proc.communicate(timeout=30)
    summary = json.loads(out.strip().splitlines()[-1])
    imu, status = summary["topics"]["samples.imu"], summary["topics"]["status"]
    assert (imu["first_seq"], imu["last_seq"], imu["received"], imu["gaps"]) == (0, 49, 50, 0)
    assert (status["first_seq"], status["received"]) == (0, 1)


def test_handshake_times_out_naming_the_missing_topics(zctx):
    with (
        Publisher(topics=["samples.imu", "observations"], context=zctx) as pub,
        Subscriber(pub.endpoints, ["samples.imu"], context=zctx),
    ):
        assert pub.wait_for_subscribers(1, ["samples.imu"], timeout_s=10)["samples.imu"] == 1
        with pytest.raises(BusTimeoutError, match="observations"):
            pub.wait_for_subscribers(1, timeout_s=0.3)


def test_subscriber_counts_follow_joins_and_leaves(zctx):
    with Publisher(topics=["status"], context=zctx) as pub:
        subs = [Subscriber(pub.endpoints, ["status"], context=zctx) for _ in range(3)]
        try:
            assert pub.wait_for_subscribers(3, timeout_s=10) == {"status": 3}
            subs[-1].close()
            for _ in range(250):  # the unsubscribe arrives asynchronously
                if pub.subscriber_counts()["status"] == 2:
                    break
                time.sleep(0.02)
            assert pub.subscriber_counts() == {"status": 2}
        finally:
            for s in subs:
                s.close()
