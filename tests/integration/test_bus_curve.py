"""CURVE: keyed publishers talk only to clients holding the server key; no keys, no exposure."""

from __future__ import annotations

import numpy as np
import pytest

from groundstation.bus.errors import BusSecurityError
from groundstation.bus.pubsub import Publisher, Subscriber
from groundstation.bus.security import CurveKeys, create_key_files

pytestmark = pytest.mark.timeout(60)
IMU = {"accel_mps2": np.zeros(3), "gyro_radps": np.zeros(3)}


@pytest.mark.parametrize("endpoint", ["tcp://0.0.0.0:*", "tcp://*:*"])
def test_binding_beyond_loopback_without_keys_is_refused(zctx, endpoint):
    with pytest.raises(BusSecurityError, match="CURVE"):
        Publisher(endpoint, ["samples.imu"], context=zctx)
    with pytest.raises(BusSecurityError, match="CURVE"):
        Publisher(topics=["samples.imu"], flow_window=4, flow_endpoint=endpoint, context=zctx)


def test_unkeyed_and_wrong_key_clients_cannot_read_a_keyed_publisher(zctx, tmp_path):
    _, secret_path = create_key_files(tmp_path, "bus")
    keys = CurveKeys.load(secret_path)
    with Publisher(topics=["samples.imu"], server_keys=keys, context=zctx) as pub:
        good = Subscriber(
            pub.endpoints, ["samples.imu"], server_public_key=keys.public, context=zctx
        )
        plain = Subscriber(pub.endpoints, ["samples.imu"], context=zctx)
        wrong = Subscriber(
            pub.endpoints,
            ["samples.imu"],
            server_public_key=CurveKeys.generate().public,
            context=zctx,
        )
        try:
            assert pub.wait_for_subscribers(1, timeout_s=10) == {"samples.imu": 1}
            for _ in range(20):
                pub.publish("samples.imu", arrays=IMU)
            got = []
            while (env := good.recv(500)) is not None:
                got.append(env.header.seq)
            assert got == list(range(20))
            assert plain.recv(300) is None and wrong.recv(300) is None
            assert pub.subscriber_counts() == {"samples.imu": 1}  # never completed a handshake
        finally:
            for s in (good, plain, wrong):
                s.close()
