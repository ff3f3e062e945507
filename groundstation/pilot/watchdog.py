"""Input staleness watchdog (pure: the time is an argument, nothing reads a clock).

The rule (issue: "input staler than 200 ms must stop sending"):

- A joystick held still sends no events, so staleness cannot be judged on the last *event* time.
  The device shell (:mod:`groundstation.pilot.jsdev`) instead reports **alive at t** whenever it
  has proof the device is still there:

  * a Linux joystick character device: every select() wake-up without error -- an event read
    *or* a select timeout (``alive_period_ms``, default 50 ms). The kernel fails reads with
    ENODEV when the device goes away, so a quiet, healthy select is proof of life;
  * a FIFO or pipe (tests, recorded streams): only bytes actually read. A pipe has no presence
    signal, so a writer that stops writing is indistinguishable from a dead one and must be
    treated as stale.

- Input is **healthy at t** iff the device is connected, no fault (EOF/ENODEV = "device_lost",
  another read error = "read_error") was reported after the last alive report, and
  ``t - alive_ns < stale_ns``. At ``t - alive_ns >= stale_ns`` it is "stale"; with no alive report
  yet it is "no_input". A dead reader thread stops reporting and so goes stale by itself.

The commander sends nothing unless the input is healthy at the tick time, so no MANUAL_CONTROL
is produced for any tick time >= last alive + ``stale_ns``.
"""

from __future__ import annotations

import dataclasses

#: Fault reasons, most specific first. "uncalibrated" is added by the commander.
REASONS = ("device_lost", "read_error", "no_input", "stale", "uncalibrated")


@dataclasses.dataclass(frozen=True)
class Health:
    """Verdict on the input at one tick time.

    Attributes
    ----------
    ok : bool
        True when commands may be built from this input.
    reason : str or None
        One of :data:`REASONS` when not ok.
    age_ns : int or None
        ``t - alive_ns`` (ns) when an alive report exists.
    """

    ok: bool
    reason: str | None = None
    age_ns: int | None = None


def assess(
    t_ns: int,
    *,
    alive_ns: int | None,
    connected: bool,
    fault: str | None,
    stale_ns: int,
) -> Health:
    """Judge the input at tick time ``t_ns`` (integer ns, same monotonic clock as ``alive_ns``).

    Parameters
    ----------
    t_ns : int
        Tick time, ns.
    alive_ns : int or None
        Time of the device shell's last alive report, ns.
    connected : bool
        The device is open.
    fault : str or None
        "device_lost" or "read_error" reported since the last alive report (the shell clears it
        when it reopens the device and reads again).
    stale_ns : int
        Staleness window, ns (``PilotSettings.stale_ns``).
    """
    age = None if alive_ns is None else t_ns - alive_ns
    if fault is not None:
        return Health(False, fault if fault in REASONS else "read_error", age)
    if not connected:
        return Health(False, "device_lost", age)
    if alive_ns is None or age is None:
        return Health(False, "no_input", None)
    if age >= stale_ns:
        return Health(False, "stale", age)
    return Health(True, None, age)
