"""The gap a restarted worker must fill from the recording (pure)."""

from __future__ import annotations

from groundstation.bus.envelope import Envelope, Header
from groundstation.runtime.catchup import GapPlan, last_positions


def env(topic: str, origin: int, seq: int) -> Envelope:
    return Envelope(topic, Header(topic, 1, seq, seq, 0, origin))


def test_recorded_messages_between_consumed_and_first_live_fill_the_gap():
    plan = GapPlan({("samples.imu", 7): 9})
    plan.live(env("samples.imu", 7, 15))
    plan.live(env("samples.imu", 7, 16))
    wanted = [s for s in range(5, 20) if plan.wanted(env("samples.imu", 7, s))]
    assert wanted == [10, 11, 12, 13, 14]
    assert plan.missing() == {}


def test_what_the_recording_does_not_reach_yet_is_missing():
    plan = GapPlan({("samples.imu", 7): 9})
    plan.live(env("samples.imu", 7, 15))
    for s in (10, 11):
        plan.wanted(env("samples.imu", 7, s))
    assert plan.missing() == {("samples.imu", 7): 3}  # 12, 13, 14
    plan.reset_collected()
    assert plan.missing() == {("samples.imu", 7): 5}


def test_a_stream_of_a_dead_publisher_and_a_new_one_are_taken_whole():
    plan = GapPlan({("samples.imu", 1): 4})
    plan.live(env("samples.imu", 2, 0))  # restarted publisher: new origin from seq 0
    assert plan.wanted(env("samples.imu", 1, 5)) and plan.wanted(env("samples.imu", 1, 99))
    assert not plan.wanted(env("samples.imu", 2, 0))  # already live
    assert plan.missing() == {}
    assert last_positions([env("a", 1, 3), env("a", 1, 1), env("b", 1, 0)]) == {
        ("a", 1): 3,
        ("b", 1): 0,
    }
