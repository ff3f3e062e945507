"""A mapper.fit message's timings become a FitResult's, junk left out."""

from __future__ import annotations

import math

from groundstation.pipeline.multiprocess import plain_timings


def test_only_finite_seconds_by_part_are_taken():
    plain = {"fit_s": 0.25, "mesh_s": 1, "rows_s": math.nan, "x": True, "y": "0.5", "z": None}
    assert plain_timings(plain) == {"fit_s": 0.25, "mesh_s": 1.0}
    assert plain_timings(None) == {} and plain_timings([0.1]) == {}
