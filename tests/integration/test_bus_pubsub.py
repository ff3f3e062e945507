"""Publisher/Subscriber over real ZeroMQ sockets: gaps, drop policies, rates, bad input, replay.

Measurements (printed, never asserted; run with ``-s`` to see them): p50/p99 publish->receive
latency at 200 Hz over tcp loopback and ipc, and the throughput of 5 MB mesh messages.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest
import zmq

from groundstation.bus.envelope import Envelope, Header, encode, pack_frames, unpack_frames
from groundstation.bus.pubsub import LATEST_HWM, Publisher, Subscriber

pytestmark = pytest.mark.timeout(60)
IMU = {"accel_mps2": np.zeros(3), "gyro_radps": np.zeros(3)}


def _drain(sub: Subscriber, idle_ms: int = 300) -> list[Envelope]:
    out = []
    while (env := sub.recv(idle_ms)) is not None:
        out.append(env)
    return out


def test_gap_counter_sees_a_dropped_sequence_number(zctx):
    with (
        Publisher(topics=["samples.imu"], context=zctx) as pub,
        Subscriber(pub.endpoints, ["samples.imu"], context=zctx) as sub,
    ):
        pub.wait_for_subscribers(1, timeout_s=10)
        for seq in (0, 1, 2, 4, 5, 9):  # 3, 6, 7, 8 dropped on purpose
            env = Envelope("samples.imu", Header("imu_sample", 1, seq, seq, 0, 77), {}, IMU)
            pub.republish(encode(env))
        got = _drain(sub)
        assert [e.header.seq for e in got] == [0, 1, 2, 4, 5, 9]
        assert sub.gaps == {"samples.imu": 4}
        assert sub.received == {"samples.imu": 6} and sub.last_seq == {"samples.imu": 9}
        assert all(e.header.recv_ns > 0 for e in got)  # stamped on receipt


def test_bad_messages_are_skipped_and_counted(zctx):
    raw = zctx.socket(zmq.PUB)
    raw.linger = 0
    port = raw.bind_to_random_port("tcp://127.0.0.1")
    pub = Publisher(topics=["samples.imu"], context=zctx)
    sub = Subscriber([f"tcp://127.0.0.1:{port}", *pub.endpoints], ["samples.imu"], context=zctx)
    try:
        pub.wait_for_subscribers(1, timeout_s=10)
        time.sleep(0.3)  # plain PUB has no handshake: let the subscription reach it
        raw.send_multipart([b"samples.imu", b"garbage", b"{}"])
        raw.send_multipart([b"samples.imu"])
        good = pub.publish("samples.imu", arrays=IMU)
        got = _drain(sub)
        assert [e.header.seq for e in got] == [good.header.seq]
        assert sub.bad_messages == 2 and sub.stats["samples.imu"].bad == 2
        assert "bad magic" in sub.last_error or "frame count" in sub.last_error
    finally:
        sub.close()
        pub.close()
        raw.close()


def test_hostile_messages_are_counted_and_the_subscriber_lives_on(zctx, monkeypatch):
    """The fuzz crash kinds (5,000-digit integer, deep JSON nesting, zero-size array with huge
    dimensions) over a real socket, plus an unexpected exception inside decode: each is skipped
    and counted; the good message after them still arrives."""
    import groundstation.bus.pubsub as pubsub

    huge_int = [b"samples.imu", encode(Envelope("samples.imu", Header("imu_sample", 1, 0, 0)))[1]]
    header = bytes(huge_int[1])
    hostile = [
        [b"samples.imu", header, b'{"a":[],"p":{"t_station_ns":' + b"9" * 5000 + b"}}"],
        [b"samples.imu", header, b'{"a":[],"p":{"x":' + b"[" * 50_000 + b"]" * 50_000 + b"}}"],
        [b"samples.imu", header, b'{"a":[["accel_mps2","<f8",[0,1180591620717411303424]]],'
         b'"p":{}}', b""],
    ]  # fmt: skip
    raw = zctx.socket(zmq.PUB)
    raw.linger = 0
    port = raw.bind_to_random_port("tcp://127.0.0.1")
    pub = Publisher(topics=["samples.imu"], context=zctx)
    sub = Subscriber([f"tcp://127.0.0.1:{port}", *pub.endpoints], ["samples.imu"], context=zctx)
    real_decode = pubsub.decode

    def flaky_decode(frames, table=None):
        if bytes(frames[-1]) == b"boom":
            raise RuntimeError("unexpected")
        return real_decode(frames, table)

    monkeypatch.setattr(pubsub, "decode", flaky_decode)
    try:
        pub.wait_for_subscribers(1, timeout_s=10)
        time.sleep(0.3)  # plain PUB has no handshake: let the subscription reach it
        for frames in hostile:
            raw.send_multipart(frames)
        raw.send_multipart([b"samples.imu", header, b"boom"])
        good = pub.publish("samples.imu", arrays=IMU)
        got = _drain(sub)
        assert [e.header.seq for e in got] == [good.header.seq]
        assert sub.bad_messages == 4 and sub.stats["samples.imu"].bad == 4
        assert "RuntimeError: unexpected" in sub.last_error
    finally:
        sub.close()
        pub.close()
        raw.close()


def test_latest_value_topics_drop_while_lossless_topics_keep_everything(zctx):
    n = 40
    mesh = {
        "vertices": np.zeros((2**17, 3), np.float32),  # 1.5 MB
        "triangles": np.zeros((2**16, 3), np.int32),
        "vertex_std": np.zeros(2**17, np.float32),
    }
    obs = {"x_m": np.zeros(3), "normal": np.zeros(3)}
    with (
        Publisher(topics=["mesh", "observations"], context=zctx) as pub,
        Subscriber(pub.endpoints, ["mesh", "observations"], context=zctx) as sub,
    ):
        assert len(pub.endpoints) == 2  # one socket per drop policy
        pub.wait_for_subscribers(1, timeout_s=10)
        for i in range(n):  # the subscriber is not reading meanwhile
            pub.publish("mesh", {"fit_index": i}, mesh)
            pub.publish("observations", {"id": i, "label": 0}, obs)
        time.sleep(0.5)
        got = _drain(sub, 500)
        meshes = [e.header.seq for e in got if e.topic == "mesh"]
        assert [e.header.seq for e in got if e.topic == "observations"] == list(range(n))
        assert sub.gaps.get("observations", 0) == 0
        # bounded queue: HWM on both sides plus what the kernel socket buffers hold
        assert 1 <= len(meshes) < n
        assert sub.stats["mesh"].gaps == meshes[-1] - meshes[0] + 1 - len(meshes)
        # once caught up, the newest value gets through
        last = pub.publish("mesh", {"fit_index": n}, mesh)
        again = _drain(sub, 500)
        assert [e.header.seq for e in again] == [last.header.seq]
        print(f"\nBUS-MEASURE latest: {len(meshes)}/{n} meshes kept (HWM {LATEST_HWM})")


def test_recorded_frames_republish_byte_for_byte(zctx):
    with (
        Publisher(topics=["mesh", "samples.pose"], context=zctx) as pub,
        Subscriber(pub.endpoints, ["samples.pose", "mesh"], context=zctx) as sub,
    ):
        pub.wait_for_subscribers(1, timeout_s=10)
        pub.publish(
            "samples.pose",
            {"body_id": 3, "valid": True},
            {"position_m": np.array([1.0, 2, 3]), "q_wxyz": np.array([1.0, 0, 0, 0])},
        )
        pub.publish(
            "mesh",
            {"fit_index": 0},
            {
                "vertices": np.ones((3, 3)),
                "triangles": np.array([[0, 1, 2]], np.int32),
                "vertex_std": np.ones(3),
            },
        )
        blobs = []
        while (got := sub.recv_with_frames(500)) is not None:
            blobs.append(pack_frames(got[1]))  # what a recorder writes to MCAP
        assert len(blobs) == 2
    with (
        Publisher(topics=["mesh", "samples.pose"], context=zctx) as replay,
        Subscriber(replay.endpoints, ["samples.pose", "mesh"], context=zctx) as sub2,
    ):
        replay.wait_for_subscribers(1, timeout_s=10)
        for b in blobs:
            replay.republish(unpack_frames(b))
        again = []
        while (got := sub2.recv_with_frames(500)) is not None:
            again.append(pack_frames(got[1]))
        assert sorted(again) == sorted(blobs)


def _run_probe(endpoints, topics, count, extra=()):
    cmd = [sys.executable, "-m", "groundstation.bus.probe", *endpoints]
    cmd += ["--topics", ",".join(topics), "--count", str(count), "--timeout-s", "10", *extra]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)


def _finish(proc) -> dict:
    out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0
    return json.loads(out.strip().splitlines()[-1])


@pytest.mark.parametrize("transport", ["tcp", "ipc"])
def test_200_hz_for_3_s_to_another_process_without_gaps(zctx, transport, tmp_path):
    endpoint = "tcp://127.0.0.1:*" if transport == "tcp" else f"ipc://{tmp_path}/imu"
    n, period = 600, 5_000_000
    with Publisher(endpoint, ["samples.imu"], context=zctx) as pub:
        proc = _run_probe(pub.endpoints, ["samples.imu"], n)
        pub.wait_for_subscribers(1, timeout_s=20)
        t0 = time.monotonic_ns()
        for i in range(n):  # absolute deadlines: late wake-ups do not accumulate
            delay = t0 + i * period - time.monotonic_ns()
            if delay > 0:
                time.sleep(delay / 1e9)
            pub.publish("samples.imu", arrays=IMU)  # source_ns = monotonic now
        summary = _finish(proc)
    st = summary["topics"]["samples.imu"]
    assert summary["received"] == n and st["gaps"] == 0 and st["first_seq"] == 0
    assert st["last_seq"] == n - 1 and summary["bad_messages"] == 0
    lat = summary["latency_us"]
    print(f"\nBUS-MEASURE 200 Hz {transport}: p50 {lat['p50']:.0f} us, p99 {lat['p99']:.0f} us")


def test_5_mb_mesh_throughput(zctx):
    v, t = 200_000, 150_000
    mesh = {
        "vertices": np.random.default_rng(0).random((v, 3), np.float32),
        "triangles": np.zeros((t, 3), np.int32),
        "vertex_std": np.zeros(v, np.float32),
    }
    size = sum(a.nbytes for a in mesh.values())
    reps = 10
    with (
        Publisher(topics=["mesh"], context=zctx) as pub,
        Subscriber(pub.endpoints, ["mesh"], context=zctx) as sub,
    ):
        pub.wait_for_subscribers(1, timeout_s=10)
        t0 = time.perf_counter()
        for i in range(reps):  # one in flight at a time: latest-value HWM drops nothing
            pub.publish("mesh", {"fit_index": i}, mesh)
            env = sub.recv(10_000)
            assert env is not None and env.header.seq == i
        dt = time.perf_counter() - t0
        np.testing.assert_array_equal(env.arrays["vertices"], mesh["vertices"])
    print(f"\nBUS-MEASURE mesh {size / 1e6:.1f} MB over tcp: {reps * size / dt / 1e9:.2f} GB/s")
