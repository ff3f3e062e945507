"""Recordings that cannot be erased: exclusive creation, --force, segments read as one."""

from __future__ import annotations

import warnings

import pytest

from groundstation.acquisition import layout
from groundstation.acquisition.recorder import Recorder, RecordingExistsError
from groundstation.acquisition.segments import (
    OutputExistsError,
    SegmentError,
    claim_output,
    next_segment,
    open_session,
    segment_path,
)


def _write(path, session, index, msgs, topics_first=()):
    meta = layout.station_metadata(
        station_version="t", created_by="pytest", session=session, segment=index,
        config="[contact]\nthreshold_g = 0.9\n",
    )  # fmt: skip
    with Recorder(path, metadata=meta) as rec:
        for topic in topics_first:  # registers channels in another order than later segments
            rec.write(b"first", topic, msgs[0][1])
        for topic, t, data in msgs:
            rec.write(data, topic, t)


def test_a_recorder_never_overwrites_and_force_removes_every_segment(tmp_path):
    first = tmp_path / "flight.mcap"
    _write(first, "s1", 0, [("samples.imu", 1, b"a")])
    with pytest.raises(RecordingExistsError, match="already exists"):
        Recorder(first)
    assert first.read_bytes()[:8] == b"\x89MCAP0\r\n"  # untouched
    assert segment_path(first, 1).name == "flight.001.mcap"
    assert next_segment(first) == (1, tmp_path / "flight.001.mcap")
    _write(segment_path(first, 1), "s1", 1, [("samples.imu", 2, b"b")])
    with pytest.raises(OutputExistsError, match="flight.mcap.*1 more segment") as info:
        claim_output(first)
    assert "--force" in info.value.hint
    claim_output(first, force=True)
    assert not first.exists() and not segment_path(first, 1).exists()
    with pytest.raises(SegmentError, match="folder"):
        claim_output(tmp_path)


def test_segments_read_as_one_in_log_time_order_with_one_channel_id_each(tmp_path):
    first = tmp_path / "s.mcap"
    _write(first, "abc", 0, [("raw.mavlink", 10, b"m0"), ("samples.imu", 20, b"i0")])
    # a later segment registers its channels in the other order: ids must be merged
    _write(segment_path(first, 1), "abc", 1, [("samples.imu", 30, b"i1"),
                                              ("raw.mavlink", 15, b"m1")])  # fmt: skip
    _write(segment_path(first, 2), "other-session", 2, [("samples.imu", 40, b"x")])
    for path in (first, segment_path(first, 1), tmp_path):
        if path == tmp_path:
            with pytest.raises(SegmentError, match=r"2 session\(s\)"):
                open_session(path)
            continue
        with open_session(path) as rec:
            msgs = list(rec.messages())
            assert [m.data for m in msgs] == [b"m0", b"m1", b"i0", b"i1"]
            ids = {m.topic: set() for m in msgs}
            for m in msgs:
                ids[m.topic].add(m.channel.id)
            assert all(len(v) == 1 for v in ids.values()), ids
            assert rec.summary.topic_counts == {"raw.mavlink": 2, "samples.imu": 2}
            assert rec.metadata()["segment"] == "0" and len(rec.segments) == 2
            assert [m.data for m in rec.messages("samples.imu", 25)] == [b"i1"]


def test_a_cut_segment_is_read_up_to_its_last_chunk_and_reported(tmp_path):
    first = tmp_path / "s.mcap"
    _write(first, "abc", 0, [("samples.imu", t, bytes(200)) for t in range(1, 2000)])
    data = first.read_bytes()
    first.write_bytes(data[: len(data) // 2])  # a killed recorder's segment
    _write(segment_path(first, 1), "abc", 1, [("samples.imu", 5000, b"after")])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with open_session(first) as rec:
            assert rec.truncated and len(rec.recoveries) == 1
            assert rec.recoveries[0][0] == first and "cut short" in rec.describe()
            last = list(rec.messages())[-1]
            assert last.data == b"after" and not rec.segments[-1].truncated


def test_a_growing_session_reopens_only_its_newest_segment_when_it_grew(tmp_path):
    from groundstation.acquisition.segments import GrowingSession

    first = tmp_path / "s.mcap"
    _write(first, "abc", 0, [("samples.imu", 1, b"a")])
    with GrowingSession(first) as grow:
        assert [m.data for m in grow.messages()] == [b"a"]
        seg0 = grow.session().segments[0]
        _write(segment_path(first, 1), "abc", 1, [("samples.imu", 2, b"b")])
        s = grow.session()
        assert [m.data for m in s.messages()] == [b"a", b"b"]
        assert s.segments[0] is seg0  # finished: opened once
        newest = s.segments[1]
        assert grow.session().segments[1] is newest  # not grown: kept
        assert [m.data for m in grow.messages("samples.imu", 2)] == [b"b"]
