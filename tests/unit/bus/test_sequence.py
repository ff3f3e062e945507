"""Gap counting per topic and origin."""

from __future__ import annotations

from groundstation.bus.sequence import SequenceTracker


def test_in_order_has_no_gaps():
    t = SequenceTracker()
    assert [t.observe("a", 1, s) for s in range(10)] == [0] * 10
    st = t.stats["a"]
    assert (st.received, st.gaps, st.first_seq, st.last_seq, st.streams) == (10, 0, 0, 9, 1)


def test_dropped_sequence_numbers_are_counted():
    t = SequenceTracker()
    got = [t.observe("a", 1, s) for s in (0, 1, 3, 4, 8)]
    assert got == [0, 0, 1, 0, 3]
    assert t.stats["a"].gaps == 4 and t.total_gaps() == 4


def test_late_join_is_visible_not_a_gap():
    t = SequenceTracker()
    t.observe("a", 1, 57)
    t.observe("a", 1, 58)
    assert t.stats["a"].first_seq == 57 and t.stats["a"].gaps == 0


def test_origins_are_separate_streams_and_resets_are_not_gaps():
    t = SequenceTracker()
    for s in (0, 1, 2):
        t.observe("a", 1, s)
    t.observe("a", 2, 0)  # restarted publisher: new origin
    t.observe("a", 1, 3)
    t.observe("a", 1, 0)  # same origin went backwards (replay restarted)
    st = t.stats["a"]
    assert (st.gaps, st.streams, st.resets, st.received) == (0, 2, 1, 6)


def test_topics_are_independent_and_bad_is_counted():
    t = SequenceTracker()
    t.observe("a", 1, 0)
    t.observe("b", 1, 5)
    t.observe("a", 1, 2)
    t.bad("b")
    assert t.stats["a"].gaps == 1 and t.stats["b"].gaps == 0 and t.stats["b"].bad == 1
    assert set(t.stats["a"].as_dict()) >= {"received", "gaps", "last_seq", "first_seq", "bad"}
