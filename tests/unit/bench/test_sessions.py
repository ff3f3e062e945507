"""bench sessions: variants, pooled scores and the separation metric (pure parts)."""

from __future__ import annotations

import math

import pytest

from groundstation.bench.sessions import BUNDLED, SUITE, Variant, pool, summary_markdown, u_auc
from groundstation.errors import ConfigError


def test_variant_parsing():
    assert Variant.parse("default") == Variant("default", ())
    v = Variant.parse("floor:mapping.lengthscale_min=0.3, contact.external_spacing_m=0")
    assert v.name == "floor"
    assert v.overrides == ("mapping.lengthscale_min=0.3", "contact.external_spacing_m=0")
    with pytest.raises(ConfigError, match="key=value"):
        Variant.parse("x:mapping.lengthscale_min")
    with pytest.raises(ConfigError, match="name"):
        Variant.parse(":a=1")


def test_u_auc_is_the_probability_a_gust_outranks_a_touch():
    assert u_auc([0.5, 0.6], [0.0, 0.1]) == 1.0
    assert u_auc([0.0], [0.5]) == 0.0
    assert u_auc([0.3], [0.3]) == 0.5
    assert u_auc([0.5, 0.0], [0.1]) == 0.5
    assert math.isnan(u_auc([], [0.1]))


def _report(ch, false, flagged, correct, events, touches=4, found=1.0, refits=(0.1, 0.3)):
    return {
        "chamfer_m": ch, "chamfer_full_m": 2 * ch, "events_false": false,
        "events_flagged": flagged, "events_flagged_false": correct,
        "fp_precision": correct / flagged if flagged else math.nan,
        "detection_recall": found, "truth_touches": touches, "event_u": events,
        "refit_s": list(refits), "refits": len(refits), "refit_s_median": 0.2,
    }  # fmt: skip


def test_pool_counts_events_over_sessions():
    a = _report(0.1, 3, 2, 2, [("gust", 0.6), ("gust", 0.5), ("touch", 0.0)])
    b = _report(0.2, 2, 1, 0, [("gust", 0.0), ("touch", 0.4)], found=0.5)
    p = pool([a, b])
    assert p["sessions"] == 2 and p["fp_flagged"] == 3 and p["fp_correct"] == 2
    assert p["fp_precision"] == pytest.approx(2 / 3) and p["fp_recall"] == pytest.approx(2 / 5)
    assert p["chamfer_mean"] == pytest.approx(0.15) and p["chamfer_max"] == pytest.approx(0.2)
    assert p["detection_recall"] == pytest.approx(6 / 8)
    assert p["refits"] == 4 and p["refit_s_median"] == pytest.approx(0.2)
    assert p["u_auc"] == pytest.approx(u_auc([0.6, 0.5, 0.0], [0.0, 0.4]))
    text = summary_markdown({"default": {"overrides": [], "pooled": p,
                                         "sessions": {"a": a, "b": b}}})  # fmt: skip
    assert "| default | 2 |" in text and "2/3" in text and "### default (defaults)" in text


def test_suite_sessions_differ_from_the_bundled_logs():
    assert len({s.name for s in SUITE}) == len(SUITE)
    assert not {s.name for s in SUITE} & set(BUNDLED)
    assert SUITE[0].sitl_args()[:3] == ["sitl", "--scene", "wall"]
