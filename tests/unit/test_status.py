"""The live status line (pure): rates, gaps, contacts, refit time, mesh age, loud pilot faults,
and the contact-to-mesh latency bookkeeping."""

from __future__ import annotations

import numpy as np

from groundstation.bus.envelope import Envelope, Header
from groundstation.pilot.mux import FAILSAFE, status_line
from groundstation.runtime.status import StatusBoard, refit_seconds

S = 1_000_000_000


def env(topic: str, payload: dict | None = None, arrays: dict | None = None, seq: int = 0):
    return Envelope(topic, Header(topic, 1, seq, 0, 0, 1), payload or {}, arrays or {})


def feed(board: StatusBoard, topic: str, n: int, t0: int, t1: int) -> None:
    for i in range(n):
        board.ingest(env(topic, seq=i), t0 + (t1 - t0) * i // n)


def test_rates_over_the_line_interval_and_gaps():
    b = StatusBoard(0)
    b.line(0)
    feed(b, "samples.imu", 200, 0, S)
    feed(b, "samples.pose", 100, 0, S)
    line = b.line(S)
    assert "imu 200.0 Hz" in line and "pose 100.0 Hz" in line and "att   0.0 Hz" in line
    assert "gaps 0" in line and "t=   1.0 s" in line
    feed(b, "samples.imu", 50, S, 2 * S)
    b.set_gaps({"samples.imu": 3, "status": 7})  # status is latest-value: drops are by design
    line = b.line(2 * S)
    assert "imu  50.0 Hz" in line and "GAPS 3" in line
    assert b.summary()["gaps_monitor"] == 3


def test_recorder_gaps_and_bytes_come_from_its_status():
    b = StatusBoard(0)
    b.ingest(
        env(
            "status",
            {
                "process": "recorder", "state": "recording",
                "topics": {"samples.imu": {"gaps": 2, "bad": 0},
                           "recording": {"bytes_written": 2_500_000, "dropped": 0, "bad": 0}},
            },
        ),
        S,
    )  # fmt: skip
    line = b.line(S, {"recorder": True, "link": True})
    assert "GAPS 0/2 rec" in line and "rec 2.5 MB" in line and "[all up]" in line
    b.ingest(
        env("status", {"process": "recorder", "state": "recording",
                       "topics": {"mesh": {"gaps": 3}, "samples.imu": {"gaps": 0}}}),
        S,
    )  # fmt: skip
    line = b.line(S, {"recorder": True})
    assert "gaps 0/0 rec" in line and "(rec skipped 3 superseded)" in line  # latest: by design
    assert b.summary()["recorder_latest_dropped"] == 3 and b.summary()["gaps_recorder"] == 0
    line = b.line(2 * S, {"recorder": True, "link": False})
    assert "DOWN: link" in line


def test_contacts_observations_refit_and_mesh_age():
    b = StatusBoard(0)
    b.ingest(env("contact.event", {"id": 1, "state": "begin", "peak_g": 1.5}), S)
    b.ingest(env("contact.event", {"id": 1, "state": "end", "peak_g": 1.5}), S)
    for i, label in enumerate([0, -1, 1, 0]):
        b.ingest(env("observations", {"id": i, "label": label}), S)
    b.ingest(env("status", {"process": "mapper", "state": "idle",
                            "topics": {"mapper": {"last_refit_s": 0.42}}}), 2 * S)  # fmt: skip
    b.ingest(env("mesh", {"fit_index": 3}), 2 * S)
    line = b.line(int(4.5 * S), {"mapper": True})
    assert "contacts 1" in line and "obs 4" in line
    assert "refit 0.42 s" in line and "mesh #3 age 2.5 s" in line
    assert b.summary()["contact_observations"] == 2


def test_flagged_contacts_and_an_unreliable_fit_show_in_the_line():
    b = StatusBoard(0)
    b.ingest(env("contact.event", {"id": 1, "state": "begin", "peak_g": 1.5}), S)
    assert "contacts 1  " in b.line(S) + "  "  # no fit yet: no flag count
    fit = {"fit_index": 0, "reliable": True, "flagged_events": [1]}
    b.ingest(env("mapper.fit", fit, {"ids": np.array([0], np.int64)}), 2 * S)
    line = b.line(3 * S)
    assert "contacts 1 (1 flagged)" in line and "UNRELIABLE" not in line
    bad = {"fit_index": 1, "reliable": False, "flagged_events": [1]}
    b.ingest(env("mapper.fit", bad, {"ids": np.array([0], np.int64)}), 4 * S)
    assert "FIT UNRELIABLE (last good mesh kept)" in b.line(5 * S)
    assert b.summary()["contacts_flagged"] == 1
    assert "awaiting" not in b.line(5 * S)
    wait = {"fit_index": 2, "flagged_events": [1, 2], "awaiting_events": [2]}
    b.ingest(env("mapper.fit", wait, {"ids": np.array([0], np.int64)}), 6 * S)
    assert "(2 flagged)  1 awaiting a second touch" in b.line(7 * S)
    assert b.summary()["contacts_awaiting"] == 1


def test_refit_seconds_finds_nested_seconds_or_ms_and_ignores_junk():
    assert refit_seconds({"refit_s": 1.5}) == 1.5
    assert refit_seconds({"topics": {"fit": {"refit_ms": 250}}}) == 0.25
    assert refit_seconds({"refit_s": True, "x": {"refit_s": float("nan")}}) is None
    assert refit_seconds({"state": "idle"}) is None


def test_a_republished_mapper_status_is_not_a_second_refit():
    b = StatusBoard(0)
    st = env("status", {"process": "mapper", "state": "idle", "topics": {"refit_s": 0.3}})
    for k in range(3):
        b.ingest(st, k * S)
    b.ingest(env("status", {"process": "mapper", "state": "idle", "topics": {"refit_s": 0.5}}), S)
    assert b.summary()["refit_s"]["n"] == 2


def test_where_the_refits_time_went_is_summed_over_the_session_and_junk_is_ignored():
    b = StatusBoard(0)
    ids = {"ids": np.array([1], np.int64)}
    fits = [{"total_s": 0.4, "fit_s": 0.1, "mesh_s": 0.3, "mesh_offset_s": 0.1},
            {"total_s": 0.6, "fit_s": 0.3, "mesh_s": 0.3, "mesh_offset_s": float("nan")},
            {"total_s": True, "fit_s": "0.5"}]  # fmt: skip
    for k, timings in enumerate(fits):
        b.ingest(env("mapper.fit", {"fit_index": k, "timings": timings}, ids), k * S)
    b.ingest(env("mapper.fit", {"fit_index": 9, "timings": [0.1]}, ids), 9 * S)
    parts = b.summary()["refit_time_s"]
    assert parts["total"] == {"sum_s": 1.0, "share": 1.0}
    assert parts["fit"] == {"sum_s": 0.4, "share": 0.4}
    assert parts["mesh"]["share"] == 0.6 and parts["mesh_offset"]["sum_s"] == 0.1


def test_contact_to_mesh_latency_pairs_fit_ids_with_the_mesh_of_the_same_fit():
    b = StatusBoard(0)
    b.ingest(env("observations", {"id": 10, "label": 0}), 1 * S)
    b.ingest(env("observations", {"id": 11, "label": 1}), 1 * S)  # external: not a contact
    b.ingest(env("observations", {"id": 12, "label": 0}), 2 * S)
    # fit 1 has 10 and 11; its mesh arrives after the fit
    b.ingest(env("mapper.fit", {"fit_index": 1}, {"ids": np.array([10, 11], np.int64)}), 3 * S)
    b.ingest(env("mesh", {"fit_index": 1}), 4 * S)
    # fit 2: its mesh arrives first, then the fit with 10 (already meshed) and 12
    b.ingest(env("mesh", {"fit_index": 2}), 6 * S)
    b.ingest(env("mapper.fit", {"fit_index": 2}, {"ids": np.array([10, 11, 12], np.int64)}), 6 * S)
    s = b.summary()
    assert s["contact_to_mesh_s"]["n"] == 2
    assert s["contact_to_mesh_s"]["max"] == 4.0 and s["contact_to_mesh_s"]["median"] == 3.5
    assert s["mesh_interval_s"]["n"] == 1 and s["mesh_interval_s"]["median"] == 2.0


def test_pilot_failsafe_is_loud_first_and_printed_at_once():
    b = StatusBoard(0)
    b.ingest(env("status", {"process": "pilot", "state": "ARMED", "topics": {},
                            "text": "PILOT: ARMED - sending MANUAL_CONTROL"}), S)  # fmt: skip
    line = b.line(S, {"pilot": True})
    assert line.endswith("PILOT: ARMED - sending MANUAL_CONTROL  [all up]")
    loud = status_line(FAILSAFE, "stale")
    out = b.ingest(env("pilot.event", {"event": "failsafe", "text": loud}), 2 * S)
    assert out == [loud]
    b.ingest(
        env("status", {"process": "pilot", "state": FAILSAFE, "topics": {}, "text": loud}), 2 * S
    )
    line = b.line(2 * S, {"pilot": True})
    assert line.startswith("!!! PILOT FAILSAFE: JOYSTICK INPUT STALE - NOT SENDING")
    assert b.summary()["pilot_failsafes"] == 1
    line = b.line(3 * S, {"pilot": False})
    assert line.startswith("!!! PILOT PROCESS DOWN")


def test_log_warnings_are_returned_with_hints_and_info_is_quiet():
    b = StatusBoard(0)
    msg = {"process": "link", "level": "warning", "message": "link disconnected", "hint": "plug"}
    assert b.ingest(env("log", msg), S) == ["link: warning: link disconnected (hint: plug)"]
    assert b.ingest(env("log", {**msg, "level": "info"}), S) == []
    assert b.summary()["warnings"] == 1


def test_no_pilot_no_cmd_rate_and_link_disconnect_is_shown():
    b = StatusBoard(0)
    b.ingest(env("link.health", {"connected": False}), S)
    line = b.line(S, {"link": True})
    assert "cmd" not in line and "LINK DISCONNECTED" in line
