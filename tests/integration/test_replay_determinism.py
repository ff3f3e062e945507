"""Replay source: speed=max over the bus (credit flow control) twice gives identical samples, equal
to the in-process iterator; a paced replay gives the same; start=/end= seek by log time."""

from __future__ import annotations

import time
from collections import defaultdict
from pathlib import Path

import pytest

from groundstation.acquisition.decoders import content_key
from groundstation.acquisition.reader import open_recording
from groundstation.acquisition.replay import FINISHED, iter_replay
from groundstation.bus.pubsub import Subscriber
from groundstation.runtime.session import REPLAY_PUBLISHER, Session, new_session_id
from groundstation.runtime.sources import parse_replay_uri, source_worker
from groundstation.runtime.supervisor import Supervisor

LOG = Path(__file__).resolve().parents[2] / "replay_logs" / "pillar_survey.mcap"
SAMPLES = ("samples.imu", "samples.attitude", "samples.pose")
RAW = ("raw.mavlink", "raw.natnet")

pytestmark = pytest.mark.timeout(120)


def bus_replay(uri: str, zctx, topics=SAMPLES) -> tuple[dict[str, list], dict[str, int]]:
    """Run the replay process on ``uri`` and collect ``topics`` until it says it finished."""
    session = Session(new_session_id(), (REPLAY_PUBLISHER,))
    paced = parse_replay_uri(uri).speed != float("inf")
    sub = Subscriber(
        session.subscribe_endpoints(),
        [*topics, "log"],
        flow_endpoint=None if paced else session.flow_endpoint(REPLAY_PUBLISHER),
        context=zctx,
    )
    sup = Supervisor([source_worker(uri, session, REPLAY_PUBLISHER)])
    got: dict[str, list] = defaultdict(list)
    done = False
    try:
        sup.start()
        end = time.monotonic() + 90
        while not done and time.monotonic() < end:
            env = sub.recv(1000)
            if env is None:
                assert sup.alive()[REPLAY_PUBLISHER], "replay process died"
            elif env.topic == "log":
                done = env.payload["message"].startswith(FINISHED)
            else:
                got[env.topic].append(content_key(env))
        gaps = {t: s.gaps for t, s in sub.stats.items()}
    finally:
        sub.close()
        sup.stop(timeout_s=10)
    assert done, "replay did not finish"
    return got, gaps


def offline(start=None, end=None, topics=SAMPLES) -> dict[str, list]:
    out: dict[str, list] = defaultdict(list)
    for e in iter_replay(str(LOG), start, end, include_raw=True):
        if e.topic in topics:
            out[e.topic].append(content_key(e))
    return out


def test_speed_max_twice_over_the_bus_is_identical_and_equals_in_process(zctx):
    uri = f"replay://{LOG}?speed=max&start=5&end=10"
    first, gaps1 = bus_replay(uri, zctx, SAMPLES + RAW)
    second, gaps2 = bus_replay(uri, zctx, SAMPLES + RAW)
    local = offline(5, 10, SAMPLES + RAW)
    assert offline(5, 10, SAMPLES + RAW) == local  # in process, twice
    for topic in SAMPLES + RAW:
        assert len(first[topic]) > 750, topic
        assert first[topic] == second[topic] == local[topic], topic
        assert gaps1[topic] == gaps2[topic] == 0


def test_paced_replay_gives_the_same_samples_as_max(zctx):
    got, gaps = bus_replay(f"replay://{LOG}?speed=4&start=20&end=22", zctx)
    local = offline(20, 22)
    for topic in SAMPLES:
        assert len(local[topic]) > 350 and got[topic] == local[topic], topic
        assert gaps[topic] == 0


def test_start_end_seek_by_log_time():
    with open_recording(LOG) as rec:
        t0 = rec.summary.start_ns
    start, end = t0 + 10_000_000_000, t0 + 12_000_000_000
    full = offline()
    win = offline(10, 12, SAMPLES + RAW)
    for topic in SAMPLES + RAW:
        assert win[topic] and all(start <= k[2] < end for k in win[topic]), topic
    # NatNet datagrams are self-contained: exactly the poses of the full replay in the window
    assert win["samples.pose"] == [k for k in full["samples.pose"] if start <= k[2] < end]
    # MAVLink restarts cold (a frame cut at the window start is lost, TIMESYNC re-converges):
    # the same samples by both clocks and values, at most one fewer
    strip = [(k[1], k[2], k[4]) for k in win["samples.imu"]]
    ref = [(k[1], k[2], k[4]) for k in full["samples.imu"] if start <= k[2] < end]
    assert strip == ref[len(ref) - len(strip) :] and len(ref) - len(strip) <= 1
