"""The fixed-rate pilot loop: the thin shell between the device, the commander and a sink.

It reads the clock, waits on absolute deadlines (``threading.Event.wait``, so ``stop`` ends it at
once) and hands every :class:`~groundstation.pilot.commander.Tick` to ``emit``; the process shell
(a later step) publishes ``tick.command`` to the link process and records every event. Nothing
here decides anything: all decisions are in the pure commander.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable

from groundstation.pilot.commander import Commander, InputSnapshot, RateSchedule, Tick

log = logging.getLogger(__name__)
_LOUD = frozenset({"failsafe", "failsafe_reason", "estop"})


@dataclasses.dataclass
class LoopStats:
    """Counts of one run: ticks done, commands produced, deadlines missed."""

    ticks: int = 0
    commands: int = 0
    missed: int = 0


def run_pilot_loop(
    snapshot: Callable[[], InputSnapshot],
    commander: Commander,
    emit: Callable[[Tick], None],
    stop: threading.Event,
    *,
    clock: Callable[[], int] = time.monotonic_ns,
    max_ticks: int | None = None,
    stats: LoopStats | None = None,
) -> LoopStats:
    """Tick ``commander`` at ``settings.rate_hz`` until ``stop`` is set (or ``max_ticks``).

    Parameters
    ----------
    snapshot : callable
        Returns the device's latest :class:`InputSnapshot` (``JoystickDevice.snapshot``).
    commander : Commander
        The pure core.
    emit : callable
        Receives every tick; must not block for long (it runs on the control thread).
    stop : threading.Event
        Set to end the loop.
    clock : callable
        Monotonic ns clock, the same one the device stamps alive reports with.
    stats : LoopStats, optional
        Counters updated in place while the loop runs (a status reader sees them live);
        returned.
    """
    stats = stats if stats is not None else LoopStats()
    schedule = RateSchedule(commander.settings.period_ns, clock())
    while not stop.is_set():
        snap = snapshot()
        t = clock()  # read after the snapshot, so t >= every alive stamp in it
        tick = commander.tick(t, snap)
        stats.ticks += 1
        stats.commands += tick.command is not None
        for ev in tick.events:
            log.log(logging.WARNING if ev.kind in _LOUD else logging.INFO, "pilot: %s", ev.text)
        emit(tick)
        if max_ticks is not None and stats.ticks >= max_ticks:
            break
        deadline = schedule.advance(t)
        stats.missed = schedule.missed
        stop.wait(max(0.0, (deadline - clock()) / 1e9))
    return stats
