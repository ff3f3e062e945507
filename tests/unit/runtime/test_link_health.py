"""Link health: MAVLink frame loss from the sequence numbers, as a fraction of frames sent."""

from __future__ import annotations

from firmware_bridge.mavlink.codec import DecodeStats
from firmware_bridge.mavlink.health import LinkHealth


def test_loss_fraction_from_sequence_gaps():
    h = LinkHealth()
    assert h.loss_fraction() == 0.0
    h.total_records = 97
    st = DecodeStats()
    st.seq_gaps[(1, 1)] = 3
    h.on_stats(st)
    assert h.loss_fraction() == 0.03 and "lost 3 (3.00%)" in h.summary()
