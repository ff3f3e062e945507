"""Truth scores of a replay without a mesh (``pipeline/scoring.py``)."""

from __future__ import annotations

import math

from groundstation.pipeline.scoring import surface_scores


def test_without_a_mesh_all_touched_surface_is_missing_and_an_untouched_flight_misses_none():
    touched = {"contacts": [{"kind": "touch", "point": [1.0, 0.0, 1.0], "start": 3.0}]}
    gusts_only = {"contacts": [{"kind": "gust", "point": None, "start": 3.0}]}
    assert surface_scores(None, touched)["missing_share"] == 1.0
    assert math.isnan(surface_scores(None, gusts_only)["missing_share"])
    assert math.isnan(surface_scores(None, {"contacts": []})["missing_share"])
    assert math.isnan(surface_scores(None, touched)["chamfer_m"])
