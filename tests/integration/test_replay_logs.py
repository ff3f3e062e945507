"""The bundled ``replay_logs/``: each opens, is small, carries its ground truth, replays in process
and over the bus with zero gaps, and its TIMESYNC mapping agrees with the simulation's clock;
regenerating one gives identical decoded samples."""

from __future__ import annotations

import os
import subprocess
import time
from collections import Counter, defaultdict
from pathlib import Path

import pytest

from groundstation.acquisition.decoders import content_key
from groundstation.acquisition.reader import open_recording
from groundstation.acquisition.replay import FINISHED, iter_replay
from groundstation.bus.pubsub import Subscriber
from groundstation.runtime.session import REPLAY_PUBLISHER, Session, new_session_id
from groundstation.runtime.sources import source_worker
from groundstation.runtime.supervisor import Supervisor

ROOT = Path(__file__).resolve().parents[2]
LOGS = ROOT / "replay_logs"
NAMES = ("wall_survey", "pillar_survey", "wall_slow_touch_gusts")
SAMPLES = ("samples.imu", "samples.attitude", "samples.pose")

pytestmark = pytest.mark.timeout(300)


def _samples(path: Path) -> dict[str, list]:
    out: dict[str, list] = defaultdict(list)
    for e in iter_replay(str(path)):
        out[e.topic].append(content_key(e))
    return out


def _bus(path: Path, zctx) -> tuple[dict[str, int], dict[str, int]]:
    session = Session(new_session_id(), (REPLAY_PUBLISHER,))
    sub = Subscriber(
        session.subscribe_endpoints(),
        [*SAMPLES, "log"],
        flow_endpoint=session.flow_endpoint(REPLAY_PUBLISHER),
        context=zctx,
    )
    sup = Supervisor([source_worker(f"replay://{path}?speed=max", session, REPLAY_PUBLISHER)])
    counts: Counter = Counter()
    done = False
    try:
        sup.start()
        end = time.monotonic() + 240
        while not done and time.monotonic() < end:
            env = sub.recv(1000)
            if env is None:
                assert sup.alive()[REPLAY_PUBLISHER], "replay process died"
            elif env.topic == "log":
                done = env.payload["message"].startswith(FINISHED)
            else:
                counts[env.topic] += 1
        gaps = {t: s.gaps for t, s in sub.stats.items()}
    finally:
        sub.close()
        sup.stop(timeout_s=10)
    assert done
    return dict(counts), gaps


@pytest.mark.parametrize("name", NAMES)
def test_bundled_log_opens_has_truth_and_replays_in_process(name):
    path = LOGS / f"{name}.mcap"
    assert path.stat().st_size < 5_000_000
    with open_recording(path) as rec:
        assert not rec.truncated
        truth = rec.truth()
        raw = rec.summary.topic_counts
        duration = rec.summary.duration_s
        assert f"--record {name}.mcap" in rec.metadata()["created_by"]
    assert truth["schema"] == "sitl-truth/1" and truth["scene"]["objects"]
    assert truth["vehicle"]["radius"] > 0 and truth["vehicle"]["height"] > 0
    kinds = Counter(c["kind"] for c in truth["contacts"])
    assert kinds["touch"] >= 1 and kinds["gust"] >= 1, kinds
    assert 15 < duration <= 90
    samples = _samples(path)
    assert len(samples["samples.pose"]) == raw["raw.natnet"]  # every datagram decodes
    for topic in ("samples.imu", "samples.attitude"):
        assert len(samples[topic]) > 195 * duration, topic
    # TIMESYNC from the recorded replies: firmware time maps onto the log clock within the
    # link's latency (firmware time = sim time; log time = sim time + station_offset_ns)
    offset = truth["clock"]["station_offset_ns"]
    err = [int(k[3].split(":")[1][:-1]) - (k[1] + offset) for k in samples["samples.imu"][1:]]
    assert max(abs(e) for e in err) < 3_000_000


def test_smallest_bundled_log_replays_over_the_bus_with_zero_gaps(zctx):
    path = LOGS / "wall_slow_touch_gusts.mcap"
    counts, gaps = _bus(path, zctx)
    local = _samples(path)
    for topic in SAMPLES:
        assert counts[topic] == len(local[topic]) > 0 and gaps[topic] == 0, topic


@pytest.mark.soak
@pytest.mark.parametrize("name", NAMES[:2])
def test_larger_bundled_logs_replay_over_the_bus_with_zero_gaps(name, zctx):
    counts, gaps = _bus(LOGS / f"{name}.mcap", zctx)
    with open_recording(LOGS / f"{name}.mcap") as rec:
        natnet = rec.summary.topic_counts["raw.natnet"]
    assert counts["samples.pose"] == natnet and all(gaps[t] == 0 for t in SAMPLES)


def test_regenerating_a_log_gives_identical_decoded_samples(tmp_path):
    name = "wall_slow_touch_gusts"
    env = dict(os.environ, OUT_DIR=str(tmp_path))
    subprocess.run(
        [str(LOGS / "regenerate.sh"), name], env=env, check=True, capture_output=True, timeout=120
    )
    assert _samples(tmp_path / f"{name}.mcap") == _samples(LOGS / f"{name}.mcap")
    with open_recording(tmp_path / f"{name}.mcap") as a, open_recording(LOGS / f"{name}.mcap") as b:
        _same_or_added(b.truth(), a.truth())


def _same_or_added(old, new, where="truth"):
    """``new`` holds every key of ``old`` with the same value; it may add keys (the truth's
    schema grows by additions, so a log made before an addition still regenerates)."""
    if isinstance(old, dict):
        assert isinstance(new, dict), where
        for key, value in old.items():
            assert key in new, f"{where}.{key} missing"
            _same_or_added(value, new[key], f"{where}.{key}")
    elif isinstance(old, list):
        assert isinstance(new, list) and len(new) == len(old), where
        for i, (a, b) in enumerate(zip(old, new, strict=True)):
            _same_or_added(a, b, f"{where}[{i}]")
    else:
        assert old == new or (old != old and new != new), f"{where}: {old!r} != {new!r}"
