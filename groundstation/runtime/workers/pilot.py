"""The pilot process: joystick device shell + pure commander at a fixed rate, on the session bus.

``python -m groundstation.runtime.workers.pilot --session ID --device /dev/input/js0 [--rate HZ]
[--calibration FILE] [--wait-subscribers N] [--config FILE] [--set pilot.KEY=VALUE ...]``

- :class:`~groundstation.pilot.jsdev.JoystickDevice` reads the device (or a FIFO) in its own
  thread; :func:`~groundstation.pilot.loop.run_pilot_loop` ticks the pure
  :class:`~groundstation.pilot.commander.Commander` on absolute deadlines at ``pilot.rate_hz``
  (default 25 Hz, at most 50) in the main thread, and every tick is handed to :meth:`emit`.
- :meth:`emit` publishes, in this order, on the control thread (it owns the publisher):
  ``pilot.command`` at once when the mux sends (ARMED only: nothing in DISARMED / FAILSAFE /
  ESTOP, so the vehicle's own failsafe acts when input is lost), ``pilot.event`` for every mux
  event and device notice (opened / lost / read error), ``raw.pilot`` for every chunk of
  js_event bytes read (for the recording), and ``status`` once a second and on every state
  change (``text`` = the loud status line, e.g. ``!!! PILOT FAILSAFE: JOYSTICK LOST ...``).
- Latency budget of one command: input age at the tick < ``stale_ms`` (watchdog) + tick
  (~0.1 ms) + bus (< 1 ms) + link write; the link drops a command older than its
  ``--max-command-age-ms``.
- Waits (XPUB ready handshake) until ``N`` subscribers hold ``pilot.command`` (the link, and the
  recorder when recording) before opening the device, so the first command is not lost.
- SIGINT/SIGTERM stop it cleanly (exit 0): the loop ends within one tick, the device closes.
  It runs on the shared process shell (:class:`~groundstation.runtime.worker.Worker`): the
  pilot loop is its one long ``step``, stopped through the shell's stop event.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from collections.abc import Sequence

import numpy as np
import zmq

from groundstation.config import Config
from groundstation.pilot.calibration import load_calibrations
from groundstation.pilot.commander import Commander, Tick
from groundstation.pilot.jsdev import JoystickDevice
from groundstation.pilot.loop import LoopStats, run_pilot_loop
from groundstation.pilot.settings import PilotSettings
from groundstation.runtime.session import (
    Session,
    add_session_arguments,
    session_from_args,
    worker_config,
)
from groundstation.runtime.worker import Worker, worker_main

TOPICS = ("pilot.command", "pilot.event", "raw.pilot", "status", "log")
_STATUS_NS = 1_000_000_000


class PilotProcess(Worker):
    """The pilot process shell (see the module docstring).

    Parameters
    ----------
    session : Session
        Bus endpoints of the session (this process binds ``name``).
    device : str
        Joystick path (``/dev/input/jsN``) or a FIFO.
    settings : PilotSettings
        Rate, shaping, mux and watchdog settings.
    calibrations : dict, optional
        Device calibrations by name (default: read from ``settings.calibration_path``).
    name : str
        Process name (its endpoint in the session).
    wait_subscribers : int
        Subscribers of ``pilot.command`` to wait for before opening the device (0: none).
    wait_timeout_s : float
        Longest wait for them (then start anyway, with a warning on ``log``).
    config : Config, optional
        The session's configuration (its ``pilot`` section is replaced by ``settings``).
    """

    def __init__(
        self,
        session: Session,
        device: str,
        settings: PilotSettings,
        *,
        calibrations: dict | None = None,
        name: str = "pilot",
        wait_subscribers: int = 1,
        wait_timeout_s: float = 20.0,
        context: zmq.Context | None = None,
        config: Config | None = None,
    ) -> None:
        config = dataclasses.replace(config or Config(), pilot=settings)
        super().__init__(session, config, name=name, topics=TOPICS, context=context)
        self.device_path, self.settings = device, settings
        self.wait_subscribers, self.wait_timeout_s = wait_subscribers, wait_timeout_s
        if calibrations is None:
            calibrations = load_calibrations(settings.calibration_path)
        self.commander = Commander(settings, calibrations)
        self.max_ticks: int | None = None
        self._done = False
        self.device = JoystickDevice(
            device,
            name=settings.device_name,
            alive_period_ms=settings.alive_period_ms,
            reconnect_min_ms=settings.reconnect_min_ms,
            reconnect_max_ms=settings.reconnect_max_ms,
        )
        self.commands = 0
        self.events = 0
        self.raw_chunks = 0
        self.loop_stats = LoopStats()
        self._last: Tick | None = None
        self._next_status = 0
        self._status_count = 0
        self._status_ns: int | None = None

    # -- the per-tick sink (control thread) ------------------------------------------------------
    def emit(self, tick: Tick) -> None:
        """Publish one tick: command first (latency), then events, raw bytes and status."""
        cmd = tick.command
        if cmd is not None:
            self.pub.publish(
                "pilot.command", cmd.to_payload(), source_ns=cmd.t_ns, recv_ns=cmd.t_ns
            )
            self.commands += 1
        for ev in tick.events:
            self.pub.publish("pilot.event", ev.to_payload(), source_ns=ev.t_ns, recv_ns=ev.t_ns)
            self.events += 1
        for notice in self.device.drain_notices():
            self.pub.publish(
                "pilot.event",
                {"event": f"device_{notice.kind}", "text": notice.text},
                source_ns=notice.t_ns,
                recv_ns=notice.t_ns,
            )
            self.events += 1
        for t_ns, data in self.device.drain_raw():
            self.pub.publish(
                "raw.pilot",
                {"device": self.device_path},
                {"data": np.frombuffer(data, np.uint8)},
                source_ns=t_ns,
                recv_ns=t_ns,
            )
            self.raw_chunks += 1
        changed = self._last is None or (tick.state, tick.reason) != (
            self._last.state,
            self._last.reason,
        )
        self._last = tick
        if changed or tick.t_ns >= self._next_status:
            self._status(tick)
            self._next_status = tick.t_ns + _STATUS_NS

    def publish_status(self, now_ns: int | None = None) -> None:
        """The shell's periodic status is the pilot's own (each tick's state and text)."""
        self._status(self._last, None if self._last is not None else self.state)

    def _status(self, tick: Tick | None, state: str | None = None) -> None:
        now = time.monotonic_ns() if tick is None else tick.t_ns
        dt = None if self._status_ns is None else (now - self._status_ns) / 1e9
        rate = (self.commands - self._status_count) / dt if dt else 0.0
        self._status_count, self._status_ns = self.commands, now
        d = self.device.stats
        health = None if tick is None else tick.health
        self.pub.publish(
            "status",
            {
                "process": self.name,
                "state": state or (tick.state if tick is not None else "starting"),
                "topics": {
                    "pilot.command": {"count": self.commands, "rate_hz": round(rate, 2)},
                    "pilot.event": {"count": self.events},
                    "raw.pilot": {"count": self.raw_chunks},
                    "device": {
                        **dataclasses.asdict(d),
                        "path": self.device_path,
                        "age_ms": None
                        if health is None or health.age_ns is None
                        else round(health.age_ns / 1e6, 1),
                    },
                    "loop": {
                        "rate_hz": self.settings.rate_hz,
                        "ticks": self.loop_stats.ticks,
                        "missed": self.loop_stats.missed,
                    },
                    "process": {"pid": os.getpid(), "incarnation": self.incarnation},
                },
                "text": tick.status if tick is not None else f"pilot {state or 'starting'}",
            },
        )

    # -- worker hooks --------------------------------------------------------------------------
    def setup(self) -> int | None:
        if self.wait_subscribers > 0:
            self.wait_ready(self.wait_subscribers, ("pilot.command",), self.wait_timeout_s)
        self._status(None, "starting")
        if self.commander.calibration_for(self.settings.device_name) is None and (
            self.settings.device_name
        ):
            self.log(
                "warning",
                f"no calibration for {self.settings.device_name!r} in "
                f"{self.settings.calibration_path}: the joystick will not fly",
                "run 'groundstation joystick calibrate'",
            )
        self.device.start()
        return None

    def step(self) -> None:
        """The pilot loop, until the stop event (or ``max_ticks``)."""
        event = getattr(self.stop, "event", self.stop)
        run_pilot_loop(
            self.device.snapshot,
            self.commander,
            self.emit,
            event,
            max_ticks=self.max_ticks,
            stats=self.loop_stats,  # updated in place: the status shows live counts
        )
        self._done = True

    def finished(self) -> bool:
        return self._done

    def run(self, stop=None, max_ticks: int | None = None) -> int:  # type: ignore[override]
        """Tick until ``stop`` is set (a ``threading.Event`` or the shell's stop signals), or
        ``max_ticks``; returns the exit code (0)."""
        if max_ticks is not None:
            self.max_ticks = max_ticks
        return super().run(stop)

    def teardown(self) -> None:
        self.device.stop()
        self.state = "stopped"

    def shutdown(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.teardown()
        try:
            self._status(self._last, "stopped")
        except Exception:  # noqa: BLE001 - best effort at shutdown
            pass
        self.pub.close()
        if self._own_ctx:
            self.ctx.term()

    def close(self) -> None:
        self.shutdown()


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m groundstation.runtime.workers.pilot")
    add_session_arguments(p)
    p.add_argument("--device", required=True, help="joystick: /dev/input/js0 (or a FIFO)")
    p.add_argument("--name", default="pilot", help="process name (its endpoint in the session)")
    p.add_argument("--rate", type=float, default=None, help="MANUAL_CONTROL rate, Hz (<= 50)")
    p.add_argument("--calibration", default=None, help="calibration TOML (pilot.calibration_path)")
    p.add_argument("--wait-subscribers", type=int, default=1, help="pilot.command subscribers")
    p.add_argument("--max-ticks", type=int, default=None, help="stop after this many ticks")
    return p


def settings_from_args(args: argparse.Namespace) -> PilotSettings:
    """``Config.pilot`` of the session (or ``--config`` / ``--set``), then ``--rate`` /
    ``--calibration``."""
    settings = worker_config(args).pilot
    changes: dict[str, object] = {}
    if args.rate is not None:
        changes["rate_hz"] = args.rate
    if args.calibration is not None:
        changes["calibration_path"] = args.calibration
    return dataclasses.replace(settings, **changes) if changes else settings


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point (see the module docstring)."""

    def build(args: argparse.Namespace) -> PilotProcess:
        settings = settings_from_args(args)
        proc = PilotProcess(
            session_from_args(args),
            os.path.expanduser(args.device),
            settings,
            name=args.name,
            wait_subscribers=args.wait_subscribers,
            config=worker_config(args),
        )
        proc.max_ticks = args.max_ticks
        return proc

    return worker_main(argv, _parser(), build)


if __name__ == "__main__":
    sys.exit(main())
