"""report.html's summary rows of the truth scores (pipeline/report.py, pure part)."""

from __future__ import annotations

import math

from groundstation.bus.envelope import Envelope, Header
from groundstation.pipeline.report import (
    EventRow,
    observations_text,
    p_false_cell,
    refit_time_text,
    rejected_text,
    truth_rows,
    upset_text,
)


def test_the_summary_shows_what_accuracy_costs_and_where_the_map_invents_surface():
    report = {
        "mesh_to_truth_median_m": 0.031,
        "missing_share": 0.25,
        "missing_share_near": math.nan,  # no touch near enough: shown as a dash
        "phantom_area_m2": 0.4,
        "touch_events_flagged": 0.0,
        "phantom_patches": [
            {
                "area_m2": 0.3,
                "centre": [4.2, -1.0, 0.8],
                "lo": [4.0, -1.2, 0.7],
                "hi": [4.4, -0.8, 0.9],
                "farthest_m": 0.27,
            },
        ],  # fmt: skip
    }
    rows = dict(truth_rows(report))
    assert rows["mesh -> truth, median (m)"] == "0.031"
    assert rows["touched surface missing (within 0.5 m of a touch)"] == "0.25"
    assert rows["touched surface missing (within 0.2 m)"] == "–"
    assert rows["phantom patch 1"] == "0.3 m^2 at (4.20, -1.00, 0.80), up to 0.27 m from the truth"
    assert "gust events flagged" not in rows  # not in the report (no gusts): not invented
    assert truth_rows({"log": "x.mcap"}) == []  # no truth, no rows
    report["mask_curve"] = [
        {"max_std_fraction": 0.5, "phantom_max_patch_m2": 0.05, "phantom_area_m2": 0.1,
         "missing_share_near": 0.04, "missing_share": 0.3},
    ]  # fmt: skip
    assert dict(truth_rows(report))["at a stricter mask, 0.50 of the prior std"] == (
        "largest phantom patch 0.05 m^2, phantom surface 0.1 m^2; touched surface missing "
        "0.04 within 0.2 m, 0.3 within 0.5 m"
    )
    del report["mask_curve"]
    # with what drew it: the kept events near it (a flagged one drew nothing)
    report["phantom_patches"][0].update(
        cause="false contact",
        events=[
            {"id": 3, "kind": "touch", "flagged": False},
            {"id": 7, "kind": "gust", "flagged": False},
            {"id": 8, "kind": "gust", "flagged": True},
        ],
    )
    assert dict(truth_rows(report))["phantom patch 1"] == (
        "0.3 m^2 at (4.20, -1.00, 0.80), up to 0.27 m from the truth; drawn by false contact "
        "(events 3, 7)"
    )


def test_a_p_false_raised_by_a_gust_burst_shows_the_impulses_own_value():
    row = EventRow(4, 12.0, 12.05, (1.0, 2.0, 1.2), 2.1, 0.62, "flagged", "gust", 0.17)
    assert p_false_cell(row) == (
        "0.62 (0.17 on its own; a dropped impulse pushed the same way just before)"
    )
    assert p_false_cell(EventRow(5, 13.0, 13.03, None, 3.0, 0.05, "trusted", None, 0.05)) == "0.05"
    assert p_false_cell(EventRow(6, 14.0, None, None, 3.0, 0.05, "pending", None)) == "0.05"


def _event(state: str, **payload) -> Envelope:
    return Envelope("contact.event", Header("contact_event", 1, 0, 0, 0, 0),
                    {"id": 0, "state": state, "peak_g": 3.0, **payload}, {})  # fmt: skip


def test_the_summary_counts_the_candidates_rejected_at_the_floor():
    events = [_event("rejected", at_floor=True, floor_clearance_m=0.01),
              _event("rejected", at_floor=False, floor_clearance_m=0.6),
              _event("rejected"), _event("begin", at_floor=False)]  # fmt: skip
    assert rejected_text(events) == "3 (1 begun with the body at the floor)"
    assert rejected_text(events[1:]) == "2"


def test_the_summary_counts_the_free_space_samples_skipped_for_a_tilted_body():
    from types import SimpleNamespace

    crashed = SimpleNamespace(observations=[0] * 7, stats={"detector": {"tilted": 2750}})
    assert observations_text(crashed) == "7 (2750 free-space samples skipped: body tilted)"
    level = SimpleNamespace(observations=[0] * 7, stats={"detector": {"tilted": 0}})
    assert observations_text(level) == "7"
    assert observations_text(SimpleNamespace(observations=[], stats={})) == "0"


def test_the_summary_says_when_the_vehicle_was_upset():
    from types import SimpleNamespace

    crashed = SimpleNamespace(
        start_ns=10**9, stats={"detector": {"upset_ms": 470_212, "upset_first_ns": 125 * 10**9}}
    )
    assert (
        upset_text(crashed)
        == "tilted past 60 deg for 470.2 s, first at 124.0 s (a flip or a crash)"
    )
    level = SimpleNamespace(start_ns=0, stats={"detector": {"upset_ms": 0, "upset_first_ns": -1}})
    assert upset_text(level) == "no"
    assert upset_text(SimpleNamespace(start_ns=0, stats={})) == "no"  # a report before it
    null = SimpleNamespace(
        start_ns=0, stats={"detector": {"upset_ms": None, "upset_first_ns": None}}
    )
    assert upset_text(null) == "no"


def test_the_summary_says_where_the_refits_time_went():
    parts = {
        "total": {"sum_s": 160.8, "share": 1.0},
        "rows": {"sum_s": 46.0, "share": 0.286},
        "fit": {"sum_s": 46.3, "share": 0.288},
        "mesh": {"sum_s": 65.7, "share": 0.408},
        "mesh_gp": {"sum_s": 9.5, "share": 0.059},
        "mesh_offset": {"sum_s": 14.5, "share": math.nan},
    }
    assert refit_time_text(parts) == "160.8 s: rows 29 %, fits 29 %, mesh 41 % (GP means 6 %)"
    assert refit_time_text({}) == "" and refit_time_text({"total": {"sum_s": 0.0}}) == ""
