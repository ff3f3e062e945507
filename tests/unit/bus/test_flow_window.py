"""Pure credit-window bookkeeping."""

from __future__ import annotations

import pytest

from groundstation.bus.errors import BusError
from groundstation.bus.flow import CreditWindow


def test_window_limits_unacknowledged_messages_per_consumer_and_topic():
    w = CreditWindow(3)
    assert w.blocking("a", 100) == []  # no consumers: nothing holds the publisher back
    w.register(b"c1", ["a"])
    w.register(b"c2", ["a", "b"])
    assert [w.blocking("a", s) for s in range(3)] == [[], [], []]
    assert set(w.blocking("a", 3)) == {b"c1", b"c2"}  # seqs 0..3 would be 4 outstanding
    w.ack(b"c1", "a", 0)
    assert w.blocking("a", 3) == [b"c2"]
    w.ack(b"c2", "a", 1)
    assert w.blocking("a", 3) == [] and w.ahead("a", 3) == 3
    assert w.blocking("b", 3) == [b"c2"]  # topics are independent
    w.ack(b"c2", "a", 0)  # cumulative: an older ack does not move back
    assert w.blocking("a", 3) == []


def test_unregister_releases_the_publisher():
    w = CreditWindow(1)
    w.register(b"c", ["a"])
    assert w.blocking("a", 5) == [b"c"]
    w.unregister(b"c")
    assert w.blocking("a", 5) == [] and w.consumers == []


def test_window_must_be_positive():
    with pytest.raises(BusError, match="window"):
        CreditWindow(0)
