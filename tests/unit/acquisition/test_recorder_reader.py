"""Recorder -> reader round trips, seeking, determinism, truncation recovery, write errors."""

from __future__ import annotations

import os
import random
import warnings

import numpy as np
import pytest

from groundstation.acquisition import layout
from groundstation.acquisition.reader import TruncatedRecordingWarning, open_recording
from groundstation.acquisition.recorder import Recorder, RecordingError
from groundstation.errors import GroundstationError

TOPICS = ["raw.mavlink", "raw.natnet", "samples.imu", "samples.attitude", "observations", "mesh"]


def _session(seed: int = 0, n: int = 3000) -> list[tuple[str, int, int, bytes]]:
    """Messages of several topics, log times mostly increasing with some jitter."""
    rng = random.Random(seed)
    out = []
    t = 1_000_000_000
    for i in range(n):
        t += rng.randint(0, 3_000_000)
        topic = rng.choice(TOPICS)
        recv = t + rng.randint(0, 500_000)  # arrival order != log-time order sometimes
        data = bytes([i % 251]) * rng.randint(0, 300) + i.to_bytes(4, "little")
        out.append((topic, recv, t - 1000, data))
    return out


def _write(path, msgs, **kw):
    with Recorder(
        path, metadata=layout.station_metadata(station_version="t", created_by="pytest"), **kw
    ) as rec:
        for topic, log_t, pub_t, data in msgs:
            rec.write(data, topic, log_t, pub_t)
    return rec.stats


def test_round_trip_many_topics_in_log_time_order(tmp_path):
    msgs = _session()
    path = tmp_path / "s.mcap"
    stats = _write(path, msgs, chunk_bytes=16 * 1024)
    assert stats.messages == len(msgs) and stats.chunks > 5
    with open_recording(path) as rec:
        assert not rec.truncated
        got = list(rec.messages())
        assert rec.topics() == {t: sum(m[0] == t for m in msgs) for t in TOPICS}
        assert rec.summary.start_ns == min(m[1] for m in msgs)
        assert rec.metadata()["created_by"] == "pytest"
    expected = sorted(msgs, key=lambda m: m[1])  # stable: ties keep write order
    assert [(m.topic, m.log_time_ns, m.publish_time_ns, m.data) for m in got] == [
        tuple(m) for m in expected
    ]
    assert {m.channel.message_encoding for m in got if m.topic == "raw.natnet"} == {"natnet"}


def test_time_window_and_topic_filter(tmp_path):
    msgs = _session(1)
    path = tmp_path / "s.mcap"
    _write(path, msgs, chunk_bytes=8 * 1024)
    lo, hi = msgs[1000][1], msgs[2000][1]
    with open_recording(path) as rec:
        got = list(rec.messages(topics=["samples.imu", "mesh"], start_ns=lo, end_ns=hi))
        with pytest.raises(layout.LayoutError):
            list(rec.messages(start_ns=hi, end_ns=lo))
    want = sorted(
        (m for m in msgs if m[0] in ("samples.imu", "mesh") and lo <= m[1] < hi),
        key=lambda m: m[1],
    )
    assert [(m.topic, m.log_time_ns, m.data) for m in got] == [(m[0], m[1], m[3]) for m in want]


def test_identical_input_gives_byte_identical_files(tmp_path):
    msgs = _session(2, 500)
    _write(tmp_path / "a.mcap", msgs)
    _write(tmp_path / "b.mcap", msgs)
    assert (tmp_path / "a.mcap").read_bytes() == (tmp_path / "b.mcap").read_bytes()


def test_chunks_close_after_max_span_of_log_time(tmp_path):
    path = tmp_path / "sparse.mcap"
    with Recorder(path, max_chunk_span_ns=1_000_000_000) as rec:
        for i in range(50):  # 10 Hz, tiny messages: only the time bound can close chunks
            rec.write(b"x", "samples.imu", i * 100_000_000)
            if i == 24:
                assert rec.stats.durable_messages >= 20  # never more than ~1 s in memory
    assert rec.stats.chunks >= 4


def test_envelopes_are_stored_as_blobs_and_raw_envelopes_as_wire_bytes(tmp_path):
    from groundstation.bus.envelope import Envelope, Header, from_bytes

    imu = Envelope(
        "samples.imu",
        Header("imu_sample", 1, 7, 123, 456),
        {},
        {"accel_mps2": np.array([0.0, 0.0, -9.81]), "gyro_radps": np.zeros(3)},
    )
    wire = bytes(range(40))
    raw = Envelope(
        "raw.mavlink",
        Header("raw_mavlink", 1, 0, 999, 1000),
        {"link": "serial:///dev/ttyUSB0"},
        {"data": np.frombuffer(wire, np.uint8)},
    )
    path = tmp_path / "env.mcap"
    with Recorder(path) as rec:
        rec.write(imu, "samples.imu", 456)
        rec.write(raw, "raw.mavlink", 1000)
    with open_recording(path) as r:
        a, b = list(r.messages())
    assert a.publish_time_ns == 123 and b.publish_time_ns == 999
    back = from_bytes(a.data)
    assert back.header.seq == 7 and np.array_equal(back.arrays["accel_mps2"], [0, 0, -9.81])
    assert b.data == wire and b.channel.metadata["source"] == "serial:///dev/ttyUSB0"


def test_truth_and_metadata_survive(tmp_path):
    path = tmp_path / "t.mcap"
    with Recorder(path) as rec:
        rec.write(b"\x01", "raw.natnet", 5, channel_metadata={"natnet_version": "4.1"})
        rec.add_truth({"contacts": [{"t_ns": 5}]})
        rec.add_metadata("extra", {"k": "v"})
    with open_recording(path) as r:
        assert r.truth() == {"contacts": [{"t_ns": 5}]}
        assert r.metadata("extra") == {"k": "v"} and r.metadata() is None
        assert r.summary.channels[0].metadata["natnet_version"] == "4.1"


@pytest.mark.parametrize("fraction", [0.0, 0.1, 0.37, 0.5, 0.81, 0.999])
def test_truncated_file_is_recovered_up_to_its_last_complete_chunk(tmp_path, fraction):
    msgs = sorted(_session(3, 2000), key=lambda m: m[1])
    path = tmp_path / "full.mcap"
    _write(path, msgs, chunk_bytes=8 * 1024)
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: max(8, int(len(data) * fraction))])
    with pytest.warns(TruncatedRecordingWarning, match="recovered"):
        rec = open_recording(cut)
    with rec:
        got = list(rec.messages())
        rep = rec.recovery
        assert rec.truncated and rep is not None
        assert rep.recovered_messages == len(got) == rec.summary.message_count
        # what comes back is exactly a prefix of what was written (chunks are whole)
        assert [(m.topic, m.log_time_ns, m.data) for m in got] == [
            (m[0], m[1], m[3]) for m in msgs[: len(got)]
        ]
        if 0.1 <= fraction < 0.99:
            assert len(got) > 0 and rep.complete_chunks > 0
        if 0 < fraction < 0.99:
            assert rep.lost_bytes > 0 or rep.lost_records == 0


def test_corrupt_chunk_is_skipped_and_counted(tmp_path):
    msgs = sorted(_session(4, 1500), key=lambda m: m[1])
    path = tmp_path / "c.mcap"
    _write(path, msgs, chunk_bytes=8 * 1024, compression="none")
    data = bytearray(path.read_bytes())
    data = data[: len(data) // 2]  # truncated, so the file is scanned
    data[len(data) // 3] ^= 0xFF  # flip a byte inside some chunk's payload
    (tmp_path / "bad.mcap").write_bytes(bytes(data))
    with pytest.warns(TruncatedRecordingWarning):
        with open_recording(tmp_path / "bad.mcap") as rec:
            got = list(rec.messages())
            assert rec.recovery.corrupt_chunks + rec.recovery.lost_records >= 1
            assert rec.recovery.corrupt_chunks == 1
    assert 0 < len(got) < len(msgs)


def test_unwritable_path_raises_recording_error_naming_it(tmp_path):
    target = tmp_path / "missing-dir" / "x.mcap"
    with pytest.raises(RecordingError, match="missing-dir") as info:
        Recorder(target)
    assert isinstance(info.value, GroundstationError) and info.value.errno is not None
    if os.geteuid() != 0:
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o500)
        with pytest.raises(RecordingError, match="ro"):
            Recorder(ro / "x.mcap")


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="/dev/full not available")
def test_disk_full_raises_recording_error_then_refuses_writes():
    with pytest.raises(RecordingError, match=r"/dev/full.*(No space|errno 28)"):
        Recorder("/dev/full")


def test_bad_arguments_are_layout_errors(tmp_path):
    with Recorder(tmp_path / "x.mcap") as rec:
        with pytest.raises(layout.LayoutError, match="log_time_ns"):
            rec.write(b"x", "samples.imu", 1.5)
        with pytest.raises(layout.LayoutError, match="log_time_ns"):
            rec.write(b"x", "samples.imu", -1)
        with pytest.raises(layout.LayoutError, match="cannot record"):
            rec.write({"not": "bytes"}, "samples.imu", 1)
    with pytest.raises(RecordingError, match="closed"):
        rec.write(b"x", "samples.imu", 2)
    rec.close()  # twice is fine


def test_not_an_mcap_file_is_reported(tmp_path):
    p = tmp_path / "junk.mcap"
    p.write_bytes(b"hello world, not mcap")
    with pytest.raises(RecordingError, match="not an MCAP"):
        open_recording(p)
    with pytest.raises(RecordingError, match="cannot open"):
        open_recording(tmp_path / "nope.mcap")


def test_empty_recording_reads_as_empty(tmp_path):
    with Recorder(tmp_path / "e.mcap"):
        pass
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with open_recording(tmp_path / "e.mcap") as rec:
            assert list(rec.messages()) == [] and rec.summary.duration_s == 0.0


def test_merge_order_equals_the_mcap_readers_on_overlapping_chunks(tmp_path):
    # oracle: mcap's own log-time-ordered reader (the reader's merge is a sorted queue of
    # whole chunks instead of a per-message heap; chunks here overlap in log time)
    from mcap.reader import make_reader

    msgs = _session(seed=4, n=4000)
    path = tmp_path / "s.mcap"
    _write(path, msgs, chunk_bytes=8 * 1024)
    t0, t1 = msgs[0][1], msgs[-1][1]
    windows = [(None, None), (t0 + (t1 - t0) // 3, None), (t0 + 12_345_678, t1 - 98_765_432)]
    for start, end in windows:
        with open(path, "rb") as f:
            expected = [
                (ch.topic, m.log_time, m.data)
                for _s, ch, m in make_reader(f).iter_messages(
                    start_time=start, end_time=end, log_time_order=True
                )
            ]
        with open_recording(path) as rec:
            got = [(m.topic, m.log_time_ns, m.data) for m in rec.messages(None, start, end)]
        assert got == expected and len(got) > 1000
