"""groundstation batch, the pure part: variants, task keys, config hashing, pooling, summary."""

from __future__ import annotations

import math
import tomllib

import pytest

from groundstation.config import load_config
from groundstation.errors import ConfigError
from groundstation.pipeline.batch import (
    LogInput,
    Variant,
    config_hash,
    plan_batch,
    replay_settings_text,
)
from groundstation.pipeline.pooling import (
    TRUTH_METRICS,
    large_patches_text,
    log_names,
    metric_stats,
    pool,
    summarize,
    summary_markdown,
    u_auc,
    upset_text,
)
from groundstation.runtime.configuration import recording_resolver

A = LogInput("/data/a.mcap", "a" * 64)
B = LogInput("/data/b.mcap", "b" * 64, overrides=("vehicle.shape=guards",))


resolve = recording_resolver(None)


def settings(overrides):
    return load_config(None, list(overrides))


def test_variant_parsing_keeps_commas_inside_values():
    assert Variant.parse("default") == Variant("default", ())
    v = Variant.parse("floor:mapping.lengthscale_min=0.3, contact.external_spacing_m=0")
    assert v.overrides == ("mapping.lengthscale_min=0.3", "contact.external_spacing_m=0")
    v = Variant.parse("box:surface.region_min=0,0,0,surface.region_max=8,4,2")
    assert v.overrides == ("surface.region_min=0,0,0", "surface.region_max=8,4,2")
    settings(v.overrides)  # and they are valid settings
    with pytest.raises(ConfigError, match="key=value"):
        Variant.parse("x:mapping.lengthscale_min")
    with pytest.raises(ConfigError, match="name"):
        Variant.parse(":a=1")


def test_config_hash_follows_the_resolved_settings_not_their_spelling():
    base = config_hash(settings([]))
    assert base == config_hash(settings([]))
    # the default value spelled out is the same configuration, so the same task
    assert config_hash(settings(["contact.threshold_g=1.2"])) == base
    assert config_hash(settings(["contact.threshold_g=1.0"])) != base
    assert config_hash(settings([]), "final") != base
    assert config_hash(settings([]), "final", 2) != config_hash(settings([]), "final")
    assert config_hash(settings([]), "final", 0) != config_hash(settings([]), "final")  # growth
    assert len(base) == 64 and int(base, 16) >= 0
    # other code is another task: its results are not this code's
    assert config_hash(settings([]), software="0.1.0+0123456789ab") != base
    assert config_hash(settings([]), software="0.1.0+0123456789ab") != config_hash(
        settings([]), software="0.1.0+ba9876543210"
    )


def test_a_task_is_keyed_and_filed_by_the_software_that_runs_it():
    old = plan_batch([A], [Variant("base")], resolve, software="0.1.0+0123456789ab").tasks[0]
    new = plan_batch([A], [Variant("base")], resolve, software="0.1.0+ba9876543210").tasks[0]
    assert old.config == new.config
    assert old.key != new.key and old.folder != new.folder  # side by side, neither reused
    assert new.software == "0.1.0+ba9876543210"
    text = replay_settings_text(new.config, new.map_mode, new.checkpoints, new.software)
    assert text.endswith("\n[software]\ngroundstation = '0.1.0+ba9876543210'\n")
    assert tomllib.loads(text)["software"] == {"groundstation": "0.1.0+ba9876543210"}


def test_plan_makes_one_task_per_distinct_log_and_settings():
    variants = [Variant("base"), Variant("same", ("contact.threshold_g=1.2",)),
                Variant("low", ("contact.threshold_g=1.0",))]  # fmt: skip
    plan = plan_batch([A, B], variants, resolve, base_overrides=["mapper.flag_p=0.4"])
    assert len(plan.cells) == 6
    assert len(plan.tasks) == 4  # 'same' resolves to the settings of 'base'
    folders = {c.task.folder for c in plan.cells}
    assert len(folders) == 4
    for c in plan.cells:
        assert c.task.folder.startswith(c.log.name + "-")
        assert c.log.sha256[:12] in c.task.folder and c.task.config_hash[:12] in c.task.folder
        assert c.task.key == f"{c.log.sha256}-{c.task.config_hash}"
        assert c.task.config.mapper.flag_p == 0.4
    b_low = next(c for c in plan.cells if c.log is B and c.variant == "low")
    assert b_low.task.config.vehicle.shape == "guards"  # the log's own settings
    assert b_low.task.config.contact.threshold_g == 1.0  # the variant's


def test_plan_starts_from_each_logs_recorded_configuration():
    """As ``replay`` does: a log's recorded settings (a live session's, a SITL flight's
    airframe) are its base; the log's, the batch's and the variant's overrides go on top."""
    guarded = '[vehicle]\nshape = "guards"\narm_length_m = 0.2\n[contact]\nthreshold_g = 2.0\n'
    C = LogInput("/data/c.mcap", "c" * 64, recorded=guarded)
    low = Variant("low", ("contact.threshold_g=1.0",))
    plan = plan_batch([C, A], [Variant("base"), low], resolve)
    c_base, a_base, c_low, a_low = (cell.task.config for cell in plan.cells)
    assert c_base.vehicle.shape == "guards" and c_base.vehicle.arm_length_m == 0.2
    assert c_base.contact.threshold_g == 2.0
    assert c_low.vehicle.shape == "guards" and c_low.contact.threshold_g == 1.0
    assert a_base == settings([]) and a_low == settings(low.overrides)
    assert plan.cells[0].task.config_hash != plan.cells[1].task.config_hash


def test_plan_order_log_then_batch_then_variant():
    log = LogInput("/data/c.mcap", "c" * 64, overrides=("contact.threshold_g=2.0",))
    plan = plan_batch(
        [log], [Variant("v", ("contact.threshold_g=0.9",))], resolve,
        base_overrides=["contact.threshold_g=1.5"],
    )  # fmt: skip
    assert plan.cells[0].task.config.contact.threshold_g == 0.9
    plan = plan_batch([log], [], resolve, base_overrides=["contact.threshold_g=1.5"])
    assert plan.cells[0].task.config.contact.threshold_g == 1.5
    assert plan.variants == (Variant("default"),)


def test_plan_rejects_bad_input_before_any_work():
    with pytest.raises(ConfigError, match="unique"):
        plan_batch([A], [Variant("x"), Variant("x", ("mapper.flag_p=0.1",))], resolve)
    with pytest.raises(ConfigError, match="map"):
        plan_batch([A], [], resolve, map_mode="fast")
    with pytest.raises(ConfigError):
        plan_batch([A], [Variant("bad", ("mapper.no_such_key=1",))], resolve)
    with pytest.raises(ConfigError, match="at least one log"):
        plan_batch([], [], resolve)


def test_metric_stats_worst_depends_on_direction():
    s = metric_stats([0.1, 0.3, None, math.nan, 0.2], "low")
    assert s["n"] == 3 and s["mean"] == pytest.approx(0.2) and s["median"] == pytest.approx(0.2)
    assert s["worst"] == pytest.approx(0.3)
    assert metric_stats([0.9, 0.5], "high")["worst"] == pytest.approx(0.5)
    assert math.isnan(metric_stats([], "low")["mean"])


def test_u_auc_is_the_probability_a_gust_outranks_a_touch():
    assert u_auc([0.5, 0.6], [0.0, 0.1]) == 1.0
    assert u_auc([0.0], [0.5]) == 0.0
    assert u_auc([0.3], [0.3]) == 0.5
    assert u_auc([0.5, 0.0], [0.1]) == 0.5
    assert math.isnan(u_auc([], [0.1]))


def _record(ch, false, flagged, correct, touch_share=0.0, touches=4, found=1.0, wall=2.0):
    report = {
        "chamfer_m": ch, "missing_share": ch / 2, "events_false": false,
        "events_flagged": flagged, "events_flagged_false": correct,
        "gust_events_flagged": correct / false if false else None,
        "touch_events_flagged": touch_share, "events_touch": touches,
        "detection_recall": found, "truth_touches": touches, "contacts": 10, "refits": 2,
    }  # fmt: skip
    done = {"refit_s": [0.1, 0.3], "task_wall_s": wall,
            "event_u": [["gust", 0.6], ["touch", 0.0]]}  # fmt: skip
    return {"status": "done", "report": report, "done": done}


def test_pool_counts_events_over_logs_and_ignores_failures_in_metrics():
    a = _record(0.1, 3, 2, 2, touch_share=0.25, wall=2.0)
    b = _record(0.3, 2, 1, 0, found=0.5, wall=4.0)
    failed = {"status": "failed", "error": "boom"}
    p = pool([a, b, failed])
    assert (p["tasks"], p["done"], p["failed"]) == (3, 2, 1)
    assert p["metrics"]["chamfer_m"]["mean"] == pytest.approx(0.2)
    assert p["metrics"]["chamfer_m"]["worst"] == pytest.approx(0.3)
    assert p["metrics"]["gust_events_flagged"]["worst"] == pytest.approx(0.0)
    assert p["shares"]["gust_events_flagged"]["share"] == pytest.approx(2 / 5)
    assert p["shares"]["fp_precision"]["share"] == pytest.approx(2 / 3)
    assert p["shares"]["touch_events_flagged"]["num"] == 1  # 0.25 x 4 touches
    assert p["shares"]["detection_recall"]["share"] == pytest.approx(6 / 8)
    assert p["refits"] == 4 and p["refit_s_median"] == pytest.approx(0.2)
    assert p["task_wall_s"]["median"] == pytest.approx(3.0) and p["task_wall_s"]["max"] == 4.0
    assert p["u_auc"] == 1.0
    assert set(p["metrics"]) == set(TRUTH_METRICS)


def test_pool_splits_touch_flags_by_where_the_contacts_lie():
    a = _record(0.1, 3, 2, 2, touch_share=0.5, touches=4)
    a["report"].update(events_touch_mislocated=1, touch_events_flagged_on_surface=1 / 3,
                       mislocated_touches_flagged=1.0)  # fmt: skip
    b = _record(0.1, 3, 2, 2, touch_share=0.0, touches=6)
    b["report"].update(events_touch_mislocated=0, touch_events_flagged_on_surface=0.0,
                       mislocated_touches_flagged=None)  # fmt: skip
    older = _record(0.1, 3, 2, 2, touch_share=0.5, touches=2)  # a report from before the split
    s = pool([a, b, older])["shares"]
    assert (s["touch_events_flagged"]["num"], s["touch_events_flagged"]["den"]) == (3, 12)
    on = s["touch_events_flagged_on_surface"]
    assert (on["num"], on["den"]) == (1, 9)  # 3 + 6 touches on the surface, one flagged
    off = s["mislocated_touches_flagged"]
    assert (off["num"], off["den"]) == (1, 1)


def test_pool_weighs_the_missing_surface_by_touched_area():
    # a flight with one touch that lost all of it weighs 0.1 m² against 2 m² half-kept:
    # by area 1.1 / 2.1, where the mean over flights would say 0.75
    one = _record(0.1, 3, 2, 2)
    one["report"].update(missing_share_near=1.0, touched_area_near_m2=0.1,
                         missing_area_near_m2=0.1)  # fmt: skip
    many = _record(0.1, 3, 2, 2)
    many["report"].update(missing_share_near=0.5, touched_area_near_m2=2.0,
                          missing_area_near_m2=1.0)  # fmt: skip
    untouched = _record(0.1, 3, 2, 2)  # a contact-free flight: nothing to miss
    untouched["report"].update(touched_area_near_m2=0.0, missing_area_near_m2=math.nan)
    older = _record(0.1, 3, 2, 2)  # a report from before the areas were scored
    p = pool([one, many, untouched, older])
    s = p["shares"]["missing_near_by_area"]
    assert (s["num"], s["den"]) == pytest.approx((1.1, 2.1))
    assert s["share"] == pytest.approx(1.1 / 2.1)
    assert p["metrics"]["missing_share_near"]["mean"] == pytest.approx(0.75)


def test_pool_counts_slow_touch_flags_over_the_reports_that_have_them():
    a = _record(0.1, 3, 2, 2)
    a["report"].update(events_slow_touch=4, slow_touch_events_flagged=0.25)
    b = _record(0.1, 3, 2, 2)
    b["report"].update(events_slow_touch=0, slow_touch_events_flagged=None)
    older = _record(0.1, 3, 2, 2)  # a report from before slow touches were scored
    s = pool([a, b, older])["shares"]["slow_touch_events_flagged"]
    assert (s["num"], s["den"], s["share"]) == (1, 4, 0.25)


def test_pool_counts_the_echoes_flagged_over_the_reports_that_have_them():
    a = _record(0.1, 3, 2, 2)
    a["report"].update(events_echo=2, echo_events_flagged=1.0)
    b = _record(0.1, 3, 2, 2)
    b["report"].update(events_echo=1, echo_events_flagged=0.0)
    older = _record(0.1, 3, 2, 2)  # a report from before echoes were told from touches
    s = pool([a, b, older])["shares"]["echo_events_flagged"]
    assert (s["num"], s["den"]) == (2, 3)


def test_pool_counts_the_flights_over_the_patch_line_by_cause():
    largest = [(0.3, "touches"), (0.05, "touches"), (0.2, "false contact"), (0.15, "touches"),
               (0.1, "touches"), (None, None), (0.4, None)]  # fmt: skip
    reps = []
    for area, cause in largest:
        r = _record(0.1, 1, 1, 1)
        r["report"].update(phantom_max_patch_m2=area, phantom_max_patch_cause=cause)
        reps.append(r)
    p = pool(reps)["large_patches"]
    # 0.1 m² itself is on the line, not over it; a report without a mesh has no patch measured;
    # one written before causes were recorded says so
    assert (p["line_m2"], p["flights"], p["over"]) == (0.1, 6, 4)
    assert p["by_cause"] == {"touches": 2, "false contact": 1, "not recorded": 1}
    assert large_patches_text(p) == "4/6 (touches 2, false contact 1, not recorded 1)"
    assert large_patches_text(pool(reps[1:2])["large_patches"]) == "0/1"


def test_pool_counts_the_flights_upset_for_over_a_second():
    reps = []
    for ms in (0, 999, 1001, 470_000, None):
        r = _record(0.1, 1, 1, 1)
        if ms is not None:  # None: a report from before the stage counted it
            r["report"]["stats"] = {"detector": {"upset_ms": ms}}
        reps.append(r)
    p = pool(reps)
    assert p["upset"] == {"over": 2, "flights": 4}
    assert upset_text(p) == "2/4"
    assert upset_text(pool(reps[4:])) == "-"


def test_summary_lists_every_variant_log_and_failure():
    plan = plan_batch([A, B], [Variant("base"), Variant("low", ("contact.threshold_g=1.0",))],
                      resolve)  # fmt: skip
    records = {}
    for i, t in enumerate(plan.tasks):
        records[t.folder] = _record(0.1 * (i + 1), 2, 1, 1) if i else {
            "status": "failed", "error": "InputDataError: truncated log\n"}  # fmt: skip
    records[plan.tasks[1].folder]["report"]["phantom_patches"] = [
        {"area_m2": 0.2, "centre": [1.0, -2.5, 0.75], "lo": [0.9, -2.6, 0.7],
         "hi": [1.1, -2.4, 0.8], "farthest_m": 0.3}]  # fmt: skip
    s = summarize(plan, records)
    assert set(s["variants"]) == {"base", "low"} and set(s["logs"]) == {"a", "b"}
    assert s["variants"]["base"]["pooled"]["failed"] == 1
    assert [f["folder"] for f in s["failed"]] == [plan.tasks[0].folder]
    text = summary_markdown(s)
    assert "| chamfer_m | low |" in text and "truncated log" in text
    assert "| flights with a phantom patch over 0.1 m² (by cause) | 0/0 | 0/0 |" in text
    assert "| flights upset (tilted past 60 deg for over 1 s: flipped or crashed) | - | - |" in text
    assert "| a | base | failed |" in text
    assert text.count("(1.00, -2.50, 0.75)") == 1  # where that log's largest phantom patch is


def test_logs_sharing_a_name_stay_apart_in_the_summary():
    other = LogInput("/elsewhere/a.mcap", "f" * 64)
    assert log_names([A, B, other, A]) == {
        A.path: "a-aaaaaaaa",
        other.path: "a-ffffffff",
        B.path: "b",
    }
    plan = plan_batch([A, other], [], resolve)
    s = summarize(plan, {})
    assert set(s["logs"]) == {"a-aaaaaaaa", "a-ffffffff"}
    assert all(r["default"]["status"] == "missing" for r in s["logs"].values())


def test_cli_rejects_bad_input_before_starting_a_cluster(tmp_path, capsys):
    from pathlib import Path

    from groundstation.cli import main

    log = Path(__file__).resolve().parents[3] / "replay_logs" / "wall_slow_touch_gusts.mcap"
    out = tmp_path / "out"
    assert main(["batch", str(tmp_path / "missing.mcap"), "--out", str(out)]) == 2
    assert "missing.mcap" in capsys.readouterr().err
    assert main(["batch", str(log), "--out", str(out), "--variant", "x:mapper.nope=1"]) == 2
    assert "mapper" in capsys.readouterr().err
    assert main(["batch", str(log), "--out", str(out), "--workers", "0"]) == 2
    assert "--workers" in capsys.readouterr().err
    assert not out.exists()  # nothing was started or written
