"""What the status line says in upper case (pure, times given): every silent case of issue 14,
the events kept for the summary and what counts as data lost."""

from __future__ import annotations

from groundstation.bus.envelope import Envelope, Header
from groundstation.runtime.alerts import Alerts, AlertSettings
from groundstation.runtime.status import StatusBoard

S = 1_000_000_000


def env(topic: str, payload: dict | None = None, recv_ns: int = 0, **arrays) -> Envelope:
    return Envelope(topic, Header(topic, 1, 0, 0, recv_ns, 1), payload or {}, arrays)


def status(name: str, state: str = "running", **topics) -> Envelope:
    return env("status", {"process": name, "state": state, "topics": topics, "text": ""})


def texts(a: Alerts, now: int) -> str:
    return "  ".join(a.update(now))


def test_a_restarting_worker_is_shown_while_down_then_for_a_while_with_its_count():
    a = Alerts(0)
    a.on_worker("detector", "exited", 0, "", 10 * S)
    a.on_worker("detector", "restarting", 0, "in 0.0 s", 10 * S)
    assert "DETECTOR RESTARTING (restart 1)" in texts(a, 10 * S)
    a.on_worker("detector", "started", 1, "pid 5", 11 * S)
    assert "DETECTOR RESTARTED x1" in texts(a, 12 * S)
    assert "DETECTOR" not in texts(a, 30 * S)  # after restart_note_s: lower case in [...]
    a.on_worker("mocap", "gave_up", 5, "5 restarts in 60 s", 31 * S)
    assert "MOCAP GAVE UP (5 restarts in 60 s)" in texts(a, 31 * S)
    assert any("gave up" in d for d in a.data_loss())


def test_silent_streams_after_half_a_second_only_the_expected_ones():
    a = Alerts(0, expect=("samples.imu", "samples.attitude"))
    a.on_message(env("samples.imu"), 1 * S)
    a.on_message(env("samples.attitude"), 1 * S)
    assert texts(a, int(1.4 * S)) == ""
    t = texts(a, int(1.6 * S))
    assert "NO IMU 0.6 s" in t and "NO ATTITUDE 0.6 s" in t and "POSE" not in t


def test_mavlink_frame_loss_from_the_link_health_sequence_counters():
    a = Alerts(0)
    a.on_message(env("link.health", {"lost_frames": 0, "rx_messages": 1000}), 1 * S)
    assert texts(a, 1 * S) == ""
    a.on_message(env("link.health", {"lost_frames": 40, "rx_messages": 1960}), 2 * S)
    assert "LINK LOSS 40 FRAMES (4.0 %) IN 5 S" in texts(a, 2 * S)
    a.on_message(env("link.health", {"lost_frames": 40, "rx_messages": 3000}), 8 * S)
    a.on_message(env("link.health", {"lost_frames": 40, "rx_messages": 4000}), 9 * S)
    assert "LINK LOSS" not in texts(a, 9 * S)  # the window moved on
    assert a.data_loss() == ["40 MAVLink frames lost on the link"]


def test_link_device_silence_and_restart_gap():
    a = Alerts(0)
    a.on_message(status("link", "no_device", link={"device_error": "no /dev/ttyUSB0"}), S)
    assert "LINK NO DEVICE: no /dev/ttyUSB0" in texts(a, S)
    a.on_message(status("link", link={"silent_s": 1.5, "restart_gap_s": 0.43},
                        process={"pid": 9}), 2 * S)  # fmt: skip
    t = texts(a, 2 * S)
    assert "LINK SILENT 1.5 s" in t and "LINK RESTART GAP 0.43 s" in t and "NO DEVICE" not in t
    assert any("restart gap" in d for d in a.data_loss())


def test_mocap_failed_silent_rejected_and_bad():
    a = Alerts(0)
    a.on_message(status("mocap", "failed", mocap={"open_error": "cannot resolve"}), S)
    assert "MOCAP FAILED: cannot resolve" in texts(a, S)
    a.on_message(status("mocap", mocap={"silent_s": 4.2, "heard": False, "uri": "natnet://h"},
                        decoder={"bad": 3}, security={"rejected_sender": 12}), 2 * S)  # fmt: skip
    t = texts(a, 2 * S)
    assert "MOCAP SILENT 4 s (NO DATAGRAM FROM natnet://h: WRONG HOST?)" in t
    assert "MOCAP REJECTED 12" in t and "MOCAP BAD 3" in t


def test_map_stale_after_three_refit_periods_of_new_data_without_a_mesh():
    a = Alerts(0, AlertSettings(refit_period_s=4.0, min_contacts=2))
    for label in (0, 0, 1):
        a.on_message(env("observations", {"label": label}), 1 * S)
    assert texts(a, 12 * S) == ""  # ready at 1 s: stale after 12 s
    assert "MAP STALE 12 s" in texts(a, int(13.2 * S))
    a.on_message(env("mesh", {"fit_index": 0}), 14 * S)
    assert texts(a, 40 * S) == ""  # nothing new since the mesh: not stale
    a.on_message(env("observations", {"label": 1}), 41 * S)
    assert "MAP STALE 27 s" in texts(a, 41 * S)


def test_recorder_behind_failed_and_takeover_loss_and_catch_up_loss():
    a = Alerts(0)
    a.on_message(status("recorder", recording={"role": "active", "lag_s": 2.3}), S)
    a.on_message(status("recorder2", recording={"role": "standby", "lag_s": 9.0}), S)
    assert "REC BEHIND 2.3 s" in texts(a, S)
    a.on_message(status("recorder2", recording={"role": "active", "takeover_lost": 12}), S)
    a.on_message(status("detector", catchup={"lost": 40}), S)
    t = texts(a, 2 * S)
    assert "REC LOST 12 AT TAKEOVER" in t and "DETECTOR LOST 40 SAMPLES IN RESTART" in t
    loss = a.data_loss()
    assert any("rec lost 12" in d for d in loss) and any("lost 40 samples" in d for d in loss)


def test_events_keep_when_and_how_long_and_the_board_lists_them():
    b = StatusBoard(0, Alerts(0, expect=("samples.imu",)))
    b.ingest(env("samples.imu", recv_ns=S), S)
    b.line(S, {"link": True})
    b.line(3 * S, {"link": True})  # no IMU since 1 s
    b.ingest(env("samples.imu", recv_ns=4 * S), 4 * S)
    line = b.line(4 * S, {"link": True})
    assert "NO IMU" not in line
    ev = b.summary()["events"]
    assert len(ev) == 1 and ev[0]["t_s"] == 3.0 and ev[0]["duration_s"] == 1.0
    b.on_worker("link", "exited", 0, "", 5 * S)
    b.on_worker("link", "started", 1, "", 5 * S)
    line = b.line(6 * S, {"link": True})
    assert "LINK RESTARTED x1" in line and line.endswith("[all up; restarts link 1]")
    assert b.summary()["restarts"] == {"link": 1}


def test_a_worker_catching_up_says_so():
    a = Alerts(0)
    a.on_message(status("detector", "catching up", process={"uptime_s": 12.3}), S)
    assert "DETECTOR CATCHING UP 12 s" in texts(a, S)
    a.on_message(status("detector", "running"), 2 * S)
    assert "CATCHING" not in texts(a, 2 * S)


def test_an_expected_stream_that_never_came_counts_as_lost():
    a = Alerts(0, expect=("samples.imu", "samples.pose"))
    a.on_message(env("samples.imu"), S)
    assert a.data_loss() == ["no POSE ever received"]


def test_a_detector_reading_samples_late_is_shown_behind_until_it_catches_up():
    a = Alerts(0)
    a.on_message(status("detector", lag_s=0.4), S)
    assert "BEHIND" not in texts(a, S)
    a.on_message(status("detector", lag_s=12.3), 2 * S)
    assert "DETECTOR BEHIND 12.3 s" in texts(a, 2 * S)
    a.on_message(status("detector", lag_s=0.05), 3 * S)
    assert "BEHIND" not in texts(a, 3 * S)
    assert [e["text"] for e in a.events] == ["DETECTOR BEHIND 12.3 s"]


def test_a_body_tilted_past_60_deg_for_half_a_second_is_upset_until_it_is_level_again():
    import math

    import numpy as np

    def attitude(deg: float) -> Envelope:  # rolled by deg about the body's x axis
        h = math.radians(deg) / 2
        return env("samples.attitude", q_wxyz=np.array([math.cos(h), math.sin(h), 0.0, 0.0]))

    a = Alerts(0)
    a.on_message(attitude(5.0), 1 * S)
    a.on_message(attitude(40.0), int(1.5 * S))  # a hard manoeuvre: not upset
    assert "UPSET" not in texts(a, 2 * S)
    a.on_message(attitude(88.0), 3 * S)
    a.on_message(env("samples.attitude"), int(3.2 * S))  # unreadable: changes nothing
    a.on_message(attitude(89.0), int(3.4 * S))
    assert "UPSET" not in texts(a, int(3.4 * S))  # not yet half a second
    assert "UPSET 2.0 s (TILTED 89 DEG)" in texts(a, 5 * S)
    a.on_message(attitude(10.0), 6 * S)  # level again: righted, or a flip that recovered
    assert "UPSET" not in texts(a, 6 * S)
    (ev,) = [e for e in a.events if e["kind"] == "upset"]
    assert ev["t_s"] == 5.0 and ev["duration_s"] == 1.0
    assert a.data_loss() == []  # being upset loses no data
