"""The mapping pipeline on every bundled log, as real processes on a real bus (headless, CI).

Each ``replay_logs/`` session runs through the multi-process pipeline (replay source, detector
and mapper processes, ZeroMQ over ipc) and through the in-process pipeline. Checked:

- no sequence gaps on any topic the pipeline's subscribers saw;
- the contact events and observations are identical to the in-process run (the same pure core);
- the final mesh lies near the true structure where it was touched: Chamfer distance below
  ``CHAMFER_BOUND_M`` for every log;
- flagged false contacts against the truth's gusts, pooled over the three logs: precision at
  least ``PRECISION_BOUND`` and recall at least ``RECALL_BOUND`` in the in-process run
  (deterministic), and at least ``PRECISION_BOUND_MP`` / ``RECALL_BOUND`` in the multi-process
  run, whose flags depend on when its mapper refitted: it skips ahead to the newest data while
  busy, and each warm refit starts from the previous one, so a loaded machine gives another
  history.

Bounds, from ``groundstation bench sessions --quick`` (defaults) and the multi-process runs:
Chamfer 0.08-0.16 m (bound 0.2 m); in process 5 flags, all correct (bound 0.75), 5 of the 13
detected gust events (0.38, bound 0.25: one flag fewer still passes, two do not); multi-process
5 of 5 on an idle machine and 5 of 7 with a benchmark running beside it (bound 0.6: two wrong
flags of seven pass, three do not). Most unflagged gusts are ones no flown path refutes
(``bench sessions``).

A log imported from a real contact-free flight (``aggressive_flight`` via the CSV importer)
replays the same way, without truth metrics.
"""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from groundstation.cli.replay import REPORT_SUMMARY_KEYS
from groundstation.config import load_config
from groundstation.mapping.mapper import FLAG_AWAITING, FLAG_FALSE_POSITIVE
from groundstation.pipeline.multiprocess import run_multiprocess
from groundstation.pipeline.offline import event_key, run_offline
from groundstation.pipeline.outputs import build_report
from groundstation.pipeline.report import event_rows

ROOT = Path(__file__).resolve().parents[2]
NAMES = ("wall_survey", "pillar_survey", "wall_slow_touch_gusts")
CHAMFER_BOUND_M = 0.2
PRECISION_BOUND = 0.75
PRECISION_BOUND_MP = 0.6
RECALL_BOUND = 0.25

pytestmark = pytest.mark.timeout(900)


@pytest.fixture(scope="module")
def runs(bundled_replay) -> dict:
    """name -> (in-process result, multi-process result); each pipeline runs once per log."""
    out = {}
    for name in NAMES:
        log = str(ROOT / "replay_logs" / f"{name}.mcap")
        offline = bundled_replay(name)
        multi = run_multiprocess(log, timeout_s=600)
        out[name] = (offline, multi)
    return out


def _observation_keys(result) -> list[tuple]:
    return [(o.id, o.t_ns, o.label, o.event_id, o.position.tobytes()) for o in result.observations]


@pytest.mark.parametrize("name", NAMES)
def test_multiprocess_replay_has_no_gaps_and_matches_the_in_process_run(runs, name):
    offline, multi = runs[name]
    assert multi.mode == "multi-process" and multi.gaps, "the collector saw no topic"
    assert all(v == 0 for v in multi.gaps.values()), multi.gaps
    assert multi.contacts > 0
    assert [event_key(e) for e in multi.events] == [event_key(e) for e in offline.events]
    assert _observation_keys(multi) == _observation_keys(offline)
    assert multi.final is not None and multi.final.mesh is not None


@pytest.mark.parametrize("name", NAMES)
def test_final_mesh_is_near_the_touched_structure(runs, name):
    for result in runs[name]:
        report = build_report(result)
        assert report["chamfer_m"] < CHAMFER_BOUND_M, (result.mode, report["chamfer_m"])
        assert report["detection_recall"] == 1.0  # every scripted touch becomes an event


@pytest.mark.parametrize(
    ("which", "precision_bound"), [(0, PRECISION_BOUND), (1, PRECISION_BOUND_MP)]
)
def test_false_contacts_are_flagged_with_stated_precision_and_recall(runs, which, precision_bound):
    flagged = correct = false = 0
    for pair in runs.values():
        r = build_report(pair[which])
        flagged += r["events_flagged"]
        false += r["events_false"]
        correct += r["events_flagged_false"]
    assert false >= 10  # the logs carry gusts the detector fires on
    assert flagged > 0 and correct / flagged >= precision_bound, (correct, flagged)
    assert correct / false >= RECALL_BOUND, (correct, false)


@pytest.mark.parametrize("which", [0, 1])
def test_the_report_says_where_the_refits_time_went(runs, which):
    # in process and through the fitting child and the bus alike (issue 13, Build point 7)
    result = runs["wall_survey"][which]
    parts = build_report(result)["refit_time_s"]
    assert set(parts) == {"rows", "fit", "mesh", "mesh_gp", "mesh_offset", "total"}
    total = parts["total"]["sum_s"]
    assert total > 0 and parts["total"]["share"] == pytest.approx(1.0)
    assert sum(parts[k]["sum_s"] for k in ("rows", "fit", "mesh")) <= total * (1 + 1e-9)
    assert parts["mesh_gp"]["sum_s"] + parts["mesh_offset"]["sum_s"] <= parts["mesh"]["sum_s"]
    assert all(p["sum_s"] > 0 and 0 < p["p95_s"] <= p["sum_s"] for p in parts.values())


def test_a_touch_awaiting_a_second_one_is_flagged_and_told_apart(runs):
    """The wall survey flags a doubted touch no other touch corroborates (the lone line): its
    contact and internal points carry flag bits 0 and 1 (the viewer draws them amber), every
    other flagged event's bit 0 alone, and the report's event table calls it awaiting. In the
    multi-process run, whose flags depend on when its mapper refitted, the same must hold of
    its own sets."""
    offline, multi = runs["wall_survey"]
    assert offline.final.awaiting_events  # measured: event 1 of 5 flagged
    for result in (offline, multi):
        fit = result.final
        assert set(fit.awaiting_events) <= set(fit.flagged_events)
        event_of = {o.id: o.event_id for o in result.observations}  # contacts, internal points
        for i, f in zip(fit.ids.tolist(), fit.flags.tolist(), strict=True):
            e = event_of.get(i)
            if e in fit.awaiting_events:
                assert f == FLAG_FALSE_POSITIVE | FLAG_AWAITING, (result.mode, i, e, f)
            else:
                assert not f & FLAG_AWAITING, (result.mode, i, e, f)
    rows = {r.id: r.state for r in event_rows(offline, offline.truth)}
    assert {e for e, s in rows.items() if s == "awaiting"} == set(offline.final.awaiting_events)
    flagged = {e for e, s in rows.items() if s in ("flagged", "awaiting")}
    assert flagged == set(offline.final.flagged_events)


def test_replay_command_writes_every_output(tmp_path):
    """``groundstation replay LOG --out DIR``: mesh.ply, observations.csv, snapshots, report."""
    out = tmp_path / "out"
    log = ROOT / "replay_logs" / "wall_slow_touch_gusts.mcap"
    done = subprocess.run(
        [sys.executable, "-m", "groundstation.cli", "replay", str(log), "--out", str(out),
         "--quiet", "--snapshots", "1"],
        capture_output=True, text=True, timeout=600, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    report = json.loads((out / "report.json").read_text())
    for key in REPORT_SUMMARY_KEYS:  # the keys the issue names, plus truth metrics
        assert key in report, key
    assert report["contacts"] > 0 and report["duration_s"] > 20
    # the final mesh also scored at each stricter confidence mask than the default 0.6: a
    # stricter mask keeps a subset of the faces, so it never adds phantom surface
    curve = report["mask_curve"]
    assert [r["max_std_fraction"] for r in curve] == [0.55, 0.5, 0.45, 0.4]
    areas = [report["phantom_area_m2"]] + [r["phantom_area_m2"] for r in curve]
    assert all(b <= a + 1e-12 for a, b in zip(areas, areas[1:], strict=False)), areas
    assert (out / "mesh.ply").read_bytes().startswith(b"ply")
    assert len(list((out / "snapshots").glob("*.png"))) == 1
    with (out / "observations.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    # the original columns first (a contract), the detector's evidence and the map's after
    assert list(rows[0])[:9] == ["id", "x", "y", "z", "label", "t_s", "event_id", "u", "flag"]
    assert {"p_false", "dv_mps", "rebound"} <= set(rows[0])
    assert len(rows) == report["observations"]
    assert {r["label"] for r in rows} == {"-1", "0", "1"}
    flagged = [r for r in rows if r["flag"] == "1"]
    assert all(r["label"] != "1" for r in flagged)  # external points are never flagged
    assert {r["awaiting"] for r in rows} <= {"", "0", "1"}
    assert all(r["flag"] == "1" for r in rows if r["awaiting"] == "1")  # awaiting: flagged
    assert "chamfer_m=" in done.stdout


def test_bad_replay_arguments_name_the_problem(tmp_path):
    missing = tmp_path / "nope.mcap"
    done = subprocess.run(
        [sys.executable, "-m", "groundstation.cli", "replay", str(missing)],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert done.returncode == 2 and "nope.mcap" in done.stderr and "does not exist" in done.stderr
    log = ROOT / "replay_logs" / "wall_slow_touch_gusts.mcap"
    done = subprocess.run(
        [sys.executable, "-m", "groundstation.cli", "replay", str(log), "--set", "mapping.nope=1"],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert done.returncode == 2 and "nope" in done.stderr


@pytest.mark.external
def test_a_contact_free_real_flight_replays_without_truth(external_data, tmp_path):
    from groundstation.acquisition.importers.csv_imu import import_csv

    log = tmp_path / "flight.mcap"
    import_csv(external_data / "aggressive_flight" / "Horizontal" / "path_1" / "IMU_1.csv", log)
    result = run_offline(str(log), load_config())
    report = build_report(result)
    assert report["duration_s"] > 15 and math.isfinite(report["contacts_per_min"])
    assert "chamfer_m" not in report and "fp_precision" not in report  # no truth in the log
    assert report["contacts_per_min"] < 1.0  # no contact happened in that flight
    assert np.isfinite(report["observations"])
