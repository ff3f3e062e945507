"""bench speed: the table lists every measurement with its unit-bearing columns."""

from __future__ import annotations

from groundstation.bench.speed import PAPER_GRID, table


def test_table_rows_and_paper_grid():
    rows = [{"what": "3D default mapper cold fit", "n": 2686, "seconds": 3.0, "peak_mb": 30.4,
             "note": "exact, 558 merged rows"}]  # fmt: skip
    text = table(rows)
    assert "| 3D default mapper cold fit | 2,686 | 3.00 | 30 | exact, 558 merged rows |" in text
    lo, hi, spacing = PAPER_GRID
    shape = [round((h - l) / spacing) + 1 for l, h in zip(lo, hi, strict=True)]
    assert shape == [161, 81, 41] and 161 * 81 * 41 == 534_681  # the paper's 5.4e5 points
