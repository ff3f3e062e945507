"""``groundstation bench detector``: flights, seeds, metrics, the evidence fit, and the production
detector on a bundled recording labelled against its truth."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import pytest

from groundstation.bench import detector as db
from groundstation.cli import bench as cli_bench
from groundstation.contact.evidence import EvidenceModel

LOGS = Path(__file__).resolve().parents[3] / "replay_logs"


def _event(kind: str, p: float, **kw) -> db.LabelledEvent:
    return db.LabelledEvent("f", kw.pop("engine", "simple"), kind, p, {}, False, **kw)


def test_parse_seeds_ranges_and_errors():
    assert db.parse_seeds("0-3,10, 2") == [0, 1, 2, 3, 10]
    for bad in ("", "a-b", "1-x"):
        with pytest.raises(db.BenchDataError, match="seeds"):
            db.parse_seeds(bad)


def test_flight_suite_names_are_stable_and_distinct():
    suite = db.flight_suite(["simple", "mujoco"], [0, 1])
    # every scene (around and away from the origin) per engine and seed, plus one free flight
    assert len(suite) == 2 * 2 * (len(db.SCENES) + 1)
    assert len({s.name for s in suite}) == len(suite)
    assert {s.scene for s in suite} >= {"yard", "dock", "wall"}
    mj = next(s for s in suite if s.engine == "mujoco")
    assert mj.argv()[:3] == ["sitl", "--physics", "mujoco"] and "--gust-force" in mj.argv()
    assert db.flight_suite(["simple"], [0])[0].name == suite[0].name  # a cache key
    quick = db.flight_suite(["simple"], [5], quick=True)
    assert [s.scene for s in quick] == ["wall"]


def test_roc_auc_is_mann_whitney():
    assert db.roc_auc([0.9, 0.8], [0.1, 0.2]) == 1.0
    assert db.roc_auc([0.1], [0.9]) == 0.0
    assert db.roc_auc([0.5, 0.5], [0.5]) == 0.5
    assert math.isnan(db.roc_auc([], [0.3]))
    assert db.roc_auc([0.9, float("nan")], [0.1]) == 1.0


def test_summarize_rates_by_speed_and_force():
    events = [
        _event("touch", 0.1, speed_mps=0.25, surface_m=0.004, point_m=0.01),
        _event("touch", 0.7, speed_mps=0.8, surface_m=0.006, point_m=0.02),
        _event("gust", 0.9, force_n=30.0, cluster=True),
        _event("gust", 0.2, force_n=8.0),
        _event("none", 0.95),
        _event("none", 0.1),
        _event("echo", 0.8, surface_m=0.3),  # the reaction after a touch: not a touch
        _event("echo", 0.4, surface_m=0.3),
        _event("echo", 0.9, surface_m=0.3),
        _event("slow_touch", 0.6, speed_mps=0.15),
        _event("slow_touch", 0.3, speed_mps=0.1),
        _event("slow_touch", 0.2, speed_mps=0.1),
        _event("slow_touch", 0.1, speed_mps=0.15),
    ]
    items = [
        db.TruthItem("f", "simple", "touch", True, 0.25),
        db.TruthItem("f", "simple", "touch", True, 0.8),
        db.TruthItem("f", "simple", "touch", False, 0.5),
        db.TruthItem("f", "simple", "gust", True, force_n=30.0, cluster=True),
        db.TruthItem("f", "simple", "gust", True, force_n=8.0),
        db.TruthItem("f", "simple", "gust", False, force_n=15.0),
    ]
    s = db.summarize(events, items)
    assert s["truth_touches"] == 3 and s["truth_touches_ge_0.3"] == 2
    assert s["recall_ge_0.3"] == 0.5
    assert s["speed_bins"]["0.2-0.3"] == {"touches": 1, "recall": 1.0, "p_false_gt": 0.0}
    assert s["touches_p_false_gt"] == 0.5
    assert s["slow_touches_p_false_gt"] == 0.25  # one of four lost to the map's prior
    assert s["gusts_p_false_gt_of_detected"] == 0.5
    # one gust flagged and one never detected, of three
    assert s["gusts_not_contacts_of_all"] == pytest.approx(2 / 3)
    assert s["cluster_gusts_p_false_gt"] == 1.0
    assert s["force_bins"]["20-45 N"]["detected"] == 1.0
    assert s["unmatched_candidates"] == 2 and s["unmatched_contacts"] == 1
    assert s["echo_candidates"] == 3 and s["echo_contacts"] == 1
    assert s["auc_p_false"] == pytest.approx(0.75)  # 3 of the 4 gust-touch pairs ordered
    assert s["placement_surface_median_m"] == pytest.approx(0.005)
    text = db.markdown({"variants": {"v": {"engines": {"simple": s}, "real": None}}})
    assert "| simple | 3 (2) | 0.500 |" in text
    # touches, slow touches, cluster gusts, unmatched and echoes kept
    assert "| 0.500 | 0.250 | 1.00 | 1 of 2 | 1 of 3 |" in text


def test_rejected_events_count_as_false():
    ev = db.LabelledEvent("f", "simple", "gust", math.nan, {}, True)
    assert ev.false_by_evidence
    assert not _event("touch", math.nan).false_by_evidence  # no evidence: a contact


def test_real_flight_rates():
    rates = db.real_flight_rates(
        [("a", 120.0, [_event("none", 0.9), _event("none", 0.2)]), ("b", 60.0, [])]
    )
    assert rates["minutes"] == 3.0 and rates["contacts"] == 1
    assert rates["contacts_per_min"] == pytest.approx(1 / 3)
    assert rates["max_contacts_per_flight"] == 1


def _features(rng, gust: bool) -> dict:
    """Separable synthetic evidence: gusts push without an approach, do not rebound, and come to
    a turning vehicle."""
    return {
        "peak_g": float(rng.uniform(0.5, 2.0)),
        "score": float(rng.uniform(1.0, 3.0)),
        "duration_s": float(rng.uniform(0.05, 0.3) if gust else rng.uniform(0.01, 0.05)),
        "dv_imu_mps": float(rng.uniform(0.1, 0.6)),
        "axial_fraction": float(rng.uniform(0.0, 0.5)),
        "approach_mps": float(rng.uniform(0.0, 0.05) if gust else rng.uniform(0.2, 1.0)),
        "rebound_mps": float(rng.uniform(0.0, 0.05) if gust else rng.uniform(0.1, 0.5)),
        "agreement": float(rng.uniform(-0.2, 0.3) if gust else rng.uniform(0.6, 1.0)),
        "turn_rate_radps": float(rng.uniform(0.2, 2.0) if gust else rng.uniform(0.0, 0.15)),
    }


@pytest.mark.parametrize("degree", [1, 2])
def test_fit_evidence_model_separates_and_round_trips(tmp_path, degree):
    rng = np.random.default_rng(0)
    events = [
        db.LabelledEvent(
            "f", "simple", kind, math.nan, _features(rng, kind in ("gust", "none")), False
        )
        for kind in ["touch"] * 180 + ["gust"] * 120 + ["none"] * 30 + ["slow_touch"] * 15
    ]
    model = db.fit_evidence_model(events, "unit test", db.EVIDENCE_FITS[degree])
    assert model.with_mocap.degree == model.imu_only.degree == degree
    path = tmp_path / "m.json"
    db.write_json(path, model.to_dict())
    again = EvidenceModel.load(path)
    assert again == model and again.provenance == "unit test"
    from groundstation.contact.evidence import ImpulseFeatures

    p_touch = again.p_false(ImpulseFeatures(**_features(rng, False)))
    p_gust = again.p_false(ImpulseFeatures(**_features(rng, True)))
    assert p_touch < 0.2 < 0.8 < p_gust
    with pytest.raises(db.BenchDataError, match="touches and gusts"):
        db.fit_evidence_model([e for e in events if e.kind == "touch"], "x")


def test_training_weights_balance_the_classes_and_give_false_alarms_their_share():
    kinds = ["touch"] * 50 + ["slow_touch"] * 10 + ["gust"] * 95 + ["none"] * 5
    w = db.training_weights(kinds)
    k = np.array(kinds)
    real = np.isin(k, db.REAL_KINDS)
    assert w[real].sum() == pytest.approx(w[~real].sum())
    assert w[k == "none"].sum() / w[~real].sum() == pytest.approx(db.UNMATCHED_SHARE)
    assert w.sum() == pytest.approx(len(kinds))
    assert np.allclose(w[real], w[0])  # a slow touch weighs as much as a touch
    no_none = db.training_weights(["touch"] * 3 + ["gust"])
    assert no_none.tolist() == pytest.approx([2 / 3, 2 / 3, 2 / 3, 2.0])
    # a touch's echo is one of the detector's own false alarms, weighed with them
    echoes = db.training_weights(kinds[:-2] + ["echo"] * 2)
    assert echoes.tolist() == pytest.approx(w.tolist())


def test_variant_parse():
    v = db.Variant.parse("low: contact.threshold_g=0.5, contact.detector=threshold")
    assert v == db.Variant("low", ("contact.threshold_g=0.5", "contact.detector=threshold"))
    with pytest.raises(db.BenchDataError):
        db.Variant.parse(":x=1")


@pytest.mark.timeout(600)
def test_production_detector_on_a_bundled_recording_finds_its_touches():
    log = LOGS / "wall_survey.mcap"
    events, items, duration = db.detect_and_label(str(log), "simple", None, ())
    assert duration > 10
    touches = [i for i in items if i.kind == "touch"]
    assert touches, "the bundled survey has truth touches"
    assert np.mean([i.found for i in touches]) >= 0.9
    placed = [e.surface_m for e in events if e.kind == "touch" and math.isfinite(e.surface_m)]
    assert placed and float(np.median(placed)) < 0.03  # contact points on the true wall
    assert all(math.isfinite(e.p_false) for e in events if not e.rejected)


def test_cli_refuses_overlapping_seeds_and_unknown_engines(tmp_path):
    def args(**kw):
        base = dict(out=str(tmp_path), engines="simple", seeds="0-1", train_seeds="1-2",
                    train=True, variant=[], paths="none", files=None, cache=None, jobs=1,
                    quick=True, config=None)  # fmt: skip
        return argparse.Namespace(**(base | kw))

    with pytest.raises(db.BenchDataError, match="overlap"):
        cli_bench.run_detector(args())
    with pytest.raises(db.BenchDataError, match="unknown engines"):
        cli_bench.run_detector(args(engines="bullet"))


def assert_bench_sees_what_replay_publishes(log, engine: str, overrides=()) -> list:
    """``bench detector`` labels exactly the events ``groundstation replay`` publishes on
    ``log`` with the same settings: same number, same order, same p_false and rejections."""
    from groundstation.cli.replay import _resolve
    from groundstation.pipeline.offline import detect_offline

    args = argparse.Namespace(config=None, set=list(overrides), quiet=True)
    cfg = _resolve(log, args).config  # what replay runs: the recorded settings as the base
    labelled, _, _ = db.detect_and_label(str(log), engine, None, tuple(overrides))
    replayed = [
        e.payload
        for e in detect_offline(str(log), cfg).events
        if e.payload["state"] in ("end", "rejected")
    ]
    assert len(labelled) == len(replayed) > 0
    for lab, ev in zip(labelled, replayed, strict=True):
        assert lab.rejected == (ev["state"] == "rejected")
        assert lab.p_false == pytest.approx(float(ev["p_false"]), abs=1e-12)
    return labelled


def test_bench_detector_sees_the_events_replay_publishes():
    assert_bench_sees_what_replay_publishes(LOGS / "wall_slow_touch_gusts.mcap", "simple")


def test_bench_detector_sees_the_events_replay_publishes_on_a_real_flight(external_data, tmp_path):
    """The same on a real flight (``aggressive_flight``, imported as the bench imports it), with
    the trigger lowered on both sides so that the contact-free flight makes candidates."""
    log = db.import_real_flight(external_data, db.REAL_PATHS[0], db.REAL_FILES[0], tmp_path)
    low = ("contact.lateral_threshold_g=0.4", "contact.axial_threshold_g=0.5")
    labelled = assert_bench_sees_what_replay_publishes(log, "real", low)
    assert all(lab.kind == "none" for lab in labelled)  # no truth on a real flight


def _pushed(kind, t, normal, p, *, flight="f", rejected=False, p_imp=math.nan):
    nx, ny, nz = normal
    return db.LabelledEvent(
        flight, "simple", kind, p, {}, rejected, onset_s=t,
        normal_x=nx, normal_y=ny, normal_z=nz, p_false_impulse=p_imp,
    )  # fmt: skip


def test_burst_context_counts_each_side_by_direction_window_and_flight():
    east, west, north = (1.0, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0)
    events = [
        _pushed("gust", 10.0, east, 0.99, rejected=True),  # the clearly false push
        _pushed("gust", 9.0, east, 0.10),  # 1 s before it, same way: context after it
        _pushed("gust", 11.5, (0.8, 0.6, 0.0), 0.10),  # 1.5 s after, 37 deg off: before
        _pushed("touch", 10.5, west, 0.02),  # pushed back: no context either way
        _pushed("touch", 11.0, north, 0.02),  # 90 deg off: not the same way
        _pushed("touch", 12.5, east, 0.02),  # 2.5 s after: outside the window
        _pushed("touch", 10.8, east, 0.02, flight="g"),  # another flight's clock
        # raised by the rule itself (p_false at the line), yet its own impulse says little:
        _pushed("gust", 13.0, east, 0.985, p_imp=0.30),
        _pushed("slow_touch", 12.2, east, 0.05),  # 0.8 s before that one: it gives no context
    ]
    ctx = db.burst_context(events, window_s=2.0, line=0.98)
    assert ctx["gust"] == {"kept": 3, "before": 1, "after": 1, "after_only": 1}
    assert ctx["touch"] == {"kept": 4, "before": 0, "after": 0, "after_only": 0}
    assert ctx["slow_touch"] == {"kept": 1, "before": 0, "after": 0, "after_only": 0}
    # the line and the window are the caller's
    assert db.burst_context(events, window_s=3.0, line=0.98)["touch"]["before"] == 1
    assert db.burst_context(events, window_s=2.0, line=0.3)["slow_touch"]["after"] == 1


def test_burst_context_is_in_the_bench_tables():
    events = [
        _pushed("gust", 10.0, (1.0, 0.0, 0.0), 0.99, rejected=True),
        _pushed("gust", 9.0, (1.0, 0.0, 0.0), 0.10),
    ]
    res = {"variants": {"impulse": {
        "engines": {},
        "burst_window_s": 2.0, "burst_line": 0.98,
        "burst_context": db.burst_context_by_engine(events, ["simple"], 2.0, 0.98),
    }}}  # fmt: skip
    md = db.markdown(res)
    assert "| simple | gust | 1 | 0 | 1 | 1 |" in md
