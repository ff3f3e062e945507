"""ContactStage: output independent of how the three sample streams interleave; bounded wait;
bad input skipped and counted; observation envelopes round-trip."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest

from groundstation.bus.envelope import Envelope, Header
from groundstation.bus.topics import TOPICS
from groundstation.contact.settings import G
from groundstation.contact.stage import (
    AlignmentSettings,
    ContactStage,
    observation_from_envelope,
)
from groundstation.errors import ConfigError
from groundstation.pipeline.offline import event_key

MS = 1_000_000
LEVEL = np.array([1.0, 0.0, 0.0, 0.0])  # FRD == NED


def env(topic, t_ns, payload=None, **arrays):
    spec = TOPICS[topic]
    p = {"t_station_ns": int(t_ns), **(payload or {})}
    return Envelope(topic, Header(spec.type, spec.schema_version, 0, int(t_ns), 0, 0), p, arrays)


def streams(duration_s=6.0, bumps=(2.0, 4.0)):
    """Per-stream lists: 200 Hz IMU + attitude, 200 Hz pose offset by 1.3 ms with dropped
    frames, the drone flying along x and bumping (+x acceleration of 3 G for 40 ms)."""
    imu, att, pose = [], [], []
    n = int(duration_s * 200)
    rng = np.random.default_rng(1)
    for k in range(n):
        t = 1_000 * MS + k * 5 * MS
        ts = t / 1e9 - 1.0
        f = np.array([0.0, 0.0, -G]) + rng.normal(0, 0.05, 3)
        if any(b <= ts < b + 0.04 for b in bumps):
            f[0] -= 3 * G  # wall pushes the drone in -x (FRD x = north)
        imu.append(env("samples.imu", t, accel_mps2=f, gyro_radps=np.zeros(3)))
        att.append(env("samples.attitude", t, q_wxyz=LEVEL))
        if k % 37 != 5:  # dropped mocap frames
            tp = t + 1_300_000
            valid = k % 101 != 7
            pos = np.array([1.0 + 0.3 * ts, 2.0, 1.0]) if valid else np.full(3, np.nan)
            pose.append(
                env(
                    "samples.pose", tp, {"body_id": 1, "valid": valid},
                    position_m=pos, q_wxyz=LEVEL if valid else np.full(4, np.nan),
                )
            )  # fmt: skip
    return imu, att, pose


def interleave(lists, rng: random.Random, max_lag: int = 20):
    """A random merge that keeps each stream's order; one stream may run up to ``max_lag``
    messages ahead of the others (arrival order across sockets/processes)."""
    idx = [0] * len(lists)
    out = []
    while any(i < len(l) for i, l in zip(idx, lists, strict=True)):
        choices = [k for k, l in enumerate(lists) if idx[k] < len(l)]
        lo = min(idx[k] for k in choices)
        choices = [k for k in choices if idx[k] - lo < max_lag] or choices
        k = rng.choice(choices)
        out.append(lists[k][idx[k]])
        idx[k] += 1
    return out


def run(messages, **kw):
    st = ContactStage(alignment=AlignmentSettings(**kw))
    out = st.push_many(messages) + st.flush()
    return out, st


def keys(out):
    ev = [event_key(e) for e in out if e.topic == "contact.event"]
    ob = [
        (e.payload["id"], e.header.source_ns, e.arrays["x_m"].tobytes())
        for e in out
        if e.topic == "observations"
    ]
    return ev, ob


def test_shuffled_interleavings_give_identical_output():
    imu, att, pose = streams()
    ref_out, ref_stage = run(interleave([imu, att, pose], random.Random(0), max_lag=1))
    ref = keys(ref_out)
    assert len([e for e in ref_out if e.topic == "contact.event"]) == 4  # 2 bumps, begin+end
    assert len(ref[1]) > 6
    assert ref_stage.stats.released_by_wait == 0
    for seed in range(1, 6):
        out, _ = run(interleave([imu, att, pose], random.Random(seed), max_lag=40))
        assert keys(out) == ref, seed
    # all poses first, or all IMU first (within the bounded wait: IMU blocks are released late)
    assert keys(run(pose + att + imu)[0]) == ref
    assert keys(run(att + pose + imu)[0]) == ref


def test_a_pose_stream_read_far_ahead_of_the_imu_loses_no_pose():
    # a detector behind live data reads the mocap publisher's backlog faster than the link's:
    # 60 s of poses (12,000, beyond the 4,096 a count-bounded buffer held) before any IMU sample
    imu, att, pose = streams(duration_s=60.0, bumps=(2.0, 55.0))
    ref_out, ref_stage = run(interleave([imu, att, pose], random.Random(0), max_lag=1))
    out, st = run(pose + interleave([imu, att], random.Random(1), max_lag=1))
    assert keys(out) == keys(ref_out)
    assert st.stats.no_pose == ref_stage.stats.no_pose < 0.05 * st.stats.imu
    assert len([e for e in out if e.topic == "contact.event"]) == 4


def test_event_geometry():
    imu, att, pose = streams()
    out, _ = run(interleave([imu, att, pose], random.Random(3)))
    begin = [e for e in out if e.topic == "contact.event" and e.payload["state"] == "begin"]
    t0 = begin[0].header.source_ns / 1e9 - 1.0
    assert 2.0 <= t0 < 2.06
    # FRD -x acceleration = NED south = ENU -y? No: NED x is north = ENU +y; so the normal is -y
    n = begin[0].arrays["normal"]
    assert n[1] < -0.9 and begin[0].payload["peak_g"] > 1.2
    obs = [observation_from_envelope(e) for e in out if e.topic == "observations"]
    contacts = [o for o in obs if o.label == 0]
    assert contacts and all(o.event_id in (0, 1) for o in contacts)
    assert np.allclose(contacts[0].position[1], 2.0 + 0.2, atol=0.05)  # x - r n, r = 0.2 m


def test_silent_pose_stream_releases_after_bounded_wait():
    imu, att, _ = streams(duration_s=2.0, bumps=())
    out, st = run(interleave([imu, att], random.Random(2)), max_wait_s=0.25)
    assert st.pending == 0
    # every sample but the last 0.25 s waits out the bound; none ever finds a position
    assert st.stats.released_by_wait == st.stats.imu - 50 and st.stats.released_at_flush == 50
    assert st.stats.no_attitude == 0 and st.stats.no_pose == st.stats.imu
    assert not [e for e in out if e.topic == "observations"]  # nowhere to place them
    st2 = ContactStage()
    st2.push_many(imu[:40])
    assert st2.pending == 40  # no attitude/pose yet and 0.195 s < 0.25 s of data: all wait
    st2.push_many(imu[40:100])
    assert st2.pending == 50  # the IMU stream is 0.495 s in: the first 0.245 s were released


def test_tracking_loss_waits_for_the_next_valid_pose():
    """An invalid pose right after t must not release t before the valid pose that brackets it."""
    imu, att, pose = streams(duration_s=1.0, bumps=())
    # pose stream first (it leads), then IMU/attitude: every sample is released on time
    out_a, st_a = run(pose + interleave([imu, att], random.Random(4)))
    # IMU/attitude first: samples are released only when valid poses bracket them
    out_b, st_b = run(
        interleave([imu, att], random.Random(4), max_lag=2)[:60]
        + pose
        + interleave([imu, att], random.Random(4), max_lag=2)[60:]
    )
    assert st_a.stats.no_pose == st_b.stats.no_pose
    assert keys(out_a) == keys(out_b)


def test_alignment_gaps_must_stay_below_the_wait():
    with pytest.raises(ConfigError, match="pose_max_gap_s"):
        AlignmentSettings(max_wait_s=0.1, pose_max_gap_s=0.15, attitude_max_gap_s=0.05)


def test_bad_messages_are_counted_and_skipped():
    imu, att, pose = streams(duration_s=1.0, bumps=())
    bad = [
        env("samples.imu", 5, gyro_radps=np.zeros(3)),  # no accel
        env("samples.pose", 5, {"valid": True}, position_m=np.zeros(3), q_wxyz=LEVEL),  # no body
        env("log", 5),
    ]
    out, st = run(bad + interleave([imu, att, pose], random.Random(1)))
    assert st.stats.bad == 3
    ref, _ = run(interleave([imu, att, pose], random.Random(1)))
    assert keys(out) == keys(ref)


def test_alignment_settings_validated():
    with pytest.raises(ConfigError, match="max_wait_s"):
        AlignmentSettings(max_wait_s=0)
    assert math.isclose(AlignmentSettings().pose_max_gap_s, 0.15)


def test_first_id_auto_numbers_after_any_earlier_incarnation():
    import argparse
    import time

    from groundstation.runtime.workers.detector import first_id

    assert first_id("7") == 7
    before = time.time_ns() // 1000
    a = first_id("auto")
    assert a >= before and first_id("auto") >= a
    with pytest.raises(argparse.ArgumentTypeError):
        first_id("-1")
    with pytest.raises(argparse.ArgumentTypeError):
        first_id("soon")


def test_events_without_mocap_encode_for_the_bus():
    """With the mocap gone (a restart, tracking loss) the evidence features that need it are
    not measurable: the event goes out with them as null, never as NaN the bus refuses (a live
    detector crashed on exactly that)."""
    from groundstation.bus.envelope import from_bytes, to_bytes

    imu, att, _ = streams(duration_s=5.0)
    out, st = run(interleave([imu, att], random.Random(4)), max_wait_s=0.25)
    events = [e for e in out if e.topic == "contact.event"]
    assert events and st.stats.no_pose == st.stats.imu
    for e in out:
        back = from_bytes(to_bytes(e))  # to_bytes raises on a NaN payload
        assert back.payload == e.payload
    feats = [e.payload["features"] for e in events if "features" in e.payload]
    assert feats and all(f["approach_mps"] is None and f["peak_g"] > 1.0 for f in feats)


def test_the_stage_counts_the_free_space_a_tilted_body_skips():
    from groundstation.contact.settings import ContactSettings

    imu, att, pose = streams(duration_s=6.0, bumps=())
    on_side = np.array([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0])  # 90 deg roll
    for k, e in enumerate(att):
        if 2.0 <= k / 200 < 4.0:
            att[k] = env("samples.attitude", e.header.source_ns, q_wxyz=on_side)
    free_t, tilted = {}, {}
    for limit in (45.0, 180.0):
        st = ContactStage(ContactSettings(external_max_tilt_deg=limit))
        msgs = sorted(imu + att + pose, key=lambda e: e.header.source_ns)
        out = st.push_many(msgs) + st.flush()
        t = [e.header.source_ns / 1e9 - 1.0 for e in out if e.topic == "observations"]
        free_t[limit] = np.array(t)
        tilted[limit] = st.stats.tilted
        assert st.stats.tilted == st.detector.stats.tilted
        # upset (past 60 deg) for the 2 s on its side, whatever the free-space limit
        assert st.stats.upset_ms == pytest.approx(2000, abs=10)
        assert st.stats.upset_first_ns == 1_000 * MS + 400 * 5 * MS
    # 0.3 m/s: a sample every 1/3 s of path; none while on its side with the limit, all without
    assert not np.any((free_t[45.0] >= 2.0) & (free_t[45.0] < 4.0))
    assert np.sum((free_t[180.0] >= 2.0) & (free_t[180.0] < 4.0)) >= 5
    skipped = len(free_t[180.0]) - len(free_t[45.0])
    assert skipped == pytest.approx(6, abs=1)  # 0.6 m of path on its side, one per 0.1 m
    assert tilted == {45.0: skipped, 180.0: 0}


def test_a_level_flight_is_never_upset():
    imu, att, pose = streams(duration_s=3.0, bumps=(1.0,))
    st = ContactStage()
    st.push_many(sorted(imu + att + pose, key=lambda e: e.header.source_ns))
    st.flush()
    assert st.stats.events == 1 and st.stats.upset_ms == 0 and st.stats.upset_first_ns == -1
