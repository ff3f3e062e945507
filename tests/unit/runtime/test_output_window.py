"""Which outputs a restarted detector publishes again (pure).

A SIGKILLed detector may die with outputs it counted as published still in its ZeroMQ send
queue: delivered to the viewer but not to the recorder, say. The restarted one must send those
again rather than trust its counter, and the checkpoint must carry the ones it will not
re-derive.
"""

from __future__ import annotations

import pickle

from groundstation.bus.envelope import Envelope, Header
from groundstation.runtime.workers.detector import OutputWindow


def out(topic: str, seq: int) -> Envelope:
    return Envelope(topic, Header(topic, 1, seq, seq, 0, 1), {"id": seq})


def test_a_first_start_publishes_everything():
    w = OutputWindow()
    assert all(w.admit(out("observations", s)) for s in range(100))
    assert (w.suppressed, w.resent) == (0, 0)


def test_the_last_outputs_below_the_counter_go_out_again_and_older_ones_do_not():
    w = OutputWindow({"observations": 100, "contact.event": 3}, size=8)
    admitted = [s for s in range(110) if w.admit(out("observations", s))]
    assert admitted == list(range(92, 110))
    assert (w.suppressed, w.resent) == (92, 8)
    assert [s for s in range(5) if w.admit(out("contact.event", s))] == [0, 1, 2, 3, 4]


def test_the_checkpointed_recent_outputs_cover_the_window_before_the_checkpoint():
    # incarnation 1 publishes 0..49, checkpoints, publishes 50..59 and is killed
    first = OutputWindow(size=16)
    for s in range(50):
        assert first.admit(out("observations", s))
        first.sent(out("observations", s))
    recent = pickle.loads(pickle.dumps(first.recent()))  # what the checkpoint stores
    # incarnation 2: counter 60; it sends the checkpoint's recent ones, then re-derives 50..
    second = OutputWindow({"observations": 60}, size=16)
    again = [int(e.header.seq) for e in recent["observations"] if second.admit(e)]
    again += [s for s in range(50, 70) if second.admit(out("observations", s))]
    assert again == list(range(44, 70))  # 44..59 again (the last 16), 60.. new
    assert second.resent == 16
