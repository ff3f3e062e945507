"""bench sessions: the task list (flights and their clean controls), groups and the comparison."""

from __future__ import annotations

import math

import pytest

from groundstation.bench.detector import GUSTS, FlightSpec, flight_suite
from groundstation.bench.sessions import compare, control_of, flights, groups, markdown, ratio
from groundstation.config import load_config
from groundstation.pipeline.batch import LogInput, Variant, plan_batch


def test_control_is_the_same_flight_without_gusts():
    spec = FlightSpec("mujoco", "pier", "script:varied", 101, (*GUSTS, "--duration", "60"))
    calm = control_of(spec)
    assert (calm.engine, calm.scene, calm.pilot, calm.seed) == ("mujoco", "pier", "script:varied",
                                                                101)  # fmt: skip
    assert not [a for a in calm.sitl_args if a.startswith("--gust") and a != "--gust-rate"]
    assert calm.sitl_args == ("--duration", "60", "--gust-rate", "0")
    argv = calm.argv()
    assert argv[argv.index("--gust-rate") + 1] == "0" and "--seed" in argv
    assert calm.name != spec.name  # cached separately
    assert control_of(FlightSpec("simple", "wall", "script:varied", 1, ("--gust-rate=8",))) \
        .sitl_args == ("--gust-rate", "0")  # fmt: skip


def test_every_generated_flight_has_its_control():
    fl = flights(["simple", "mujoco"], [100, 101])
    suite = flight_suite(["simple", "mujoco"], [100, 101])
    assert [f.spec for f in fl if f.role == "gusty"] == suite
    controls = {f.pair: f.spec for f in fl if f.role == "control"}
    assert set(controls) == {s.name for s in suite}
    for s in suite:
        assert controls[s.name] == control_of(s)
    assert {s.engine for s in suite} == {"simple", "mujoco"}


def _plan():
    logs = [
        LogInput("/c/g1.mcap", "1" * 64, (), (("engine", "simple"), ("role", "gusty"))),
        LogInput("/c/c1.mcap", "2" * 64, (), (("engine", "simple"), ("role", "control"))),
        LogInput("/c/g2.mcap", "3" * 64, ("vehicle.shape=guards",),
                 (("engine", "mujoco"), ("role", "gusty"))),
        LogInput("/c/c2.mcap", "4" * 64, ("vehicle.shape=guards",),
                 (("engine", "mujoco"), ("role", "control"))),
        LogInput("/r/wall.mcap", "5" * 64, (), (("engine", "simple"), ("role", "bundled"))),
    ]  # fmt: skip
    return plan_batch(logs, [Variant("base")], lambda _, ov: load_config(None, list(ov)))


def _rec(chamfer):
    report = {"chamfer_m": chamfer, "missing_share": chamfer,
              "touched_area_near_m2": 1.0, "missing_area_near_m2": chamfer}  # fmt: skip
    return {"status": "done", "report": report,
            "done": {"refit_s": [0.1], "task_wall_s": 1.0}}  # fmt: skip


def test_groups_and_ratio_to_the_control():
    plan = _plan()
    g = groups(plan, "base")
    assert list(g) == ["simple", "mujoco", "pooled", "bundled"]
    assert len(g["pooled"]["gusty"]) == 2 and len(g["pooled"]["control"]) == 2
    assert g["bundled"]["control"] == []
    values = {"g1": 0.2, "c1": 0.1, "g2": 0.3, "c2": 0.3, "wall": 0.05}
    records = {c.task.folder: _rec(values[c.log.name]) for c in plan.cells}
    cmp = compare(plan, records)["base"]
    assert cmp["simple"]["ratio"]["chamfer_m"] == pytest.approx(2.0)
    assert cmp["mujoco"]["ratio"]["chamfer_m"] == pytest.approx(1.0)
    assert cmp["pooled"]["ratio"]["chamfer_m"] == pytest.approx(0.25 / 0.2)
    assert cmp["pooled"]["gusty"]["metrics"]["chamfer_m"]["worst"] == pytest.approx(0.3)
    assert cmp["bundled"]["control"] is None
    text = markdown(compare(plan, records), {"base": []})
    assert "### simple (1/1 flights, controls 1/1)" in text
    assert "| chamfer_m | 0.200 / 0.200 / 0.200 | 0.100 / 0.100 / 0.100 | 2.00 |" in text
    assert "### bundled (1/1 flights)" in text
    by_area = "| touched surface missing within 0.2 m, by area (m²) |"
    assert f"{by_area} 0.200 (0.20/1.00) | 0.100 (0.10/1.00) | |" in text  # simple, gusty | control


def test_ratio_is_nan_when_undefined():
    assert math.isnan(ratio(1.0, 0.0)) and math.isnan(ratio(math.nan, 1.0))
    assert ratio(0.2, 0.1) == pytest.approx(2.0)


def test_the_mask_curve_is_pooled_per_mask_beside_the_configured_one():
    from groundstation.mapping.settings import SurfaceSettings
    from groundstation.pipeline.outputs import stricter_masks

    assert stricter_masks(SurfaceSettings()) == (0.55, 0.5, 0.45, 0.4)  # default 0.6
    assert stricter_masks(SurfaceSettings(max_std_fraction=0.5)) == (0.45, 0.4)

    def rec(patch, curve):
        r = _rec(0.1)
        r["report"].update(phantom_max_patch_m2=patch, phantom_area_m2=patch)
        r["report"]["mask_curve"] = [
            {"max_std_fraction": f, "phantom_max_patch_m2": p, "phantom_area_m2": p,
             "missing_area_near_m2": m, "touched_area_near_m2": 1.0, "missing_share": m,
             "mesh_to_truth_median_m": 0.02}
            for f, p, m in curve
        ]  # fmt: skip
        return r

    plan = _plan()
    curves = {
        "g1": rec(0.3, [(0.5, 0.2, 0.1), (0.4, 0.05, 0.3)]),
        "g2": rec(0.15, [(0.5, 0.12, 0.1), (0.4, 0.0, 0.2)]),
        "c1": rec(0.05, [(0.5, 0.0, 0.1), (0.4, 0.0, 0.1)]),
        "c2": rec(0.0, [(0.5, 0.0, 0.1), (0.4, 0.0, 0.1)]),
        "wall": _rec(0.05),
    }
    records = {c.task.folder: curves[c.log.name] for c in plan.cells}
    cmp = compare(plan, records)["base"]
    curve = cmp["pooled"]["gusty"]["mask_curve"]
    assert [r["max_std_fraction"] for r in curve] == [0.5, 0.4]
    assert [r["over"] for r in curve] == [2, 0]
    assert curve[1]["missing_near_by_area"]["share"] == pytest.approx(0.25)
    assert cmp["bundled"]["gusty"]["mask_curve"] == []
    text = markdown(compare(plan, records), {"base": []})
    assert "| configured | 2/2 (0/2) | 0.225 (0.025) |" in text  # pooled: both over, none
    assert "| 0.50 | 2/2 (0/2) | 0.160 (0.000) |" in text
    row = "| 0.40 | 0/2 (0/2) | 0.025 (0.000) | 0.025 (0.000) | 0.250 of 2.00 (0.100 of 2.00) |"
    assert row in text
