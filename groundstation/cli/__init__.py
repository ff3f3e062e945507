"""The ``groundstation`` command: the CLI room.

Every command's options and entry live in this package, one module per command family
(``live``, ``record``, ``replay``, ``batch``, ``view``, ``sitl``, ``import_export``, ``config``,
``calibrate``, ``bench``), and :data:`COMMANDS` is the one table of them. A command's module is
imported only when it runs, so ``groundstation --help`` is quick and a broken optional dependency
of one command does not break the others. Process entry points of a session are not commands:
they live in ``groundstation.runtime.workers``.
"""

from __future__ import annotations

import argparse
import dataclasses
import faulthandler
import importlib
import signal
import sys
from collections.abc import Callable, Sequence

from firmware_bridge.errors import BridgeError
from groundstation.errors import GroundstationError


@dataclasses.dataclass(frozen=True)
class Command:
    """One command: ``groundstation.cli.<module>`` provides ``add_<stem>_arguments(parser)`` and
    ``run_<stem>(args) -> int``."""

    module: str
    stem: str
    help: str


#: Every command of ``groundstation``, in the order ``groundstation --help`` lists them.
COMMANDS: dict[tuple[str, ...], Command] = {
    ("live",): Command(
        "live",
        "live",
        "fly a live session: link, mocap, joystick, detector, mapper, viewer, recorder",
    ),
    ("record",): Command(
        "record", "record", "record a live session (link + mocap + recorder) to an MCAP log"
    ),
    ("replay",): Command(
        "replay",
        "replay",
        "run the mapping pipeline on a recording: mesh, per-observation table, report",
    ),
    ("batch",): Command(
        "batch",
        "batch",
        "replay many logs x setting variants as tasks on Dask (local or remote), pooled summary",
    ),
    ("view",): Command(
        "view",
        "view",
        "show the live mesh, flagged contacts and the vehicle (window or --headless PNG/PLY)",
    ),
    ("sitl",): Command("sitl", "sitl", "run the software-in-the-loop vehicle and mocap"),
    ("import", "csv"): Command(
        "import_export",
        "import_csv",
        "convert a CSV IMU recording (e.g. aggressive_flight) into a replayable MCAP log",
    ),
    ("import", "ulog"): Command(
        "import_export", "import_ulog", "convert a PX4 ULog into a replayable MCAP log"
    ),
    ("import", "tlog"): Command(
        "import_export", "import_tlog", "convert a MAVLink .tlog into a replayable MCAP log"
    ),
    ("export", "tlog"): Command(
        "import_export",
        "export_tlog",
        "write the MAVLink traffic of an MCAP log as a .tlog (QGroundControl replay)",
    ),
    ("export", "foxglove"): Command(
        "import_export",
        "export_foxglove",
        "copy a recording with Foxglove channels added (mesh, contacts, pose, signal, logs)",
    ),
    ("config", "show"): Command(
        "config", "config_show", "print the effective configuration as TOML"
    ),
    ("joystick", "calibrate"): Command(
        "calibrate",
        "joystick_calibrate",
        "walk through joystick calibration in the terminal and store it per device",
    ),
    ("calibrate", "detector"): Command(
        "calibrate",
        "detector_calibrate",
        "measure the contact detector's noise on a contact-free segment and write its settings",
    ),
    ("bench", "paper2d"): Command(
        "bench",
        "paper2d",
        "reproduce the paper's 2D simulation (GPIS vs robust GPIS) with tables and figures",
    ),
    ("bench", "detector"): Command(
        "bench",
        "detector",
        "false contacts per minute on real flights vs recall on simulated touches, per threshold",
    ),
    ("bench", "sessions"): Command(
        "bench",
        "sessions",
        "the whole pipeline on many SITL sessions, per setting variant, scored against truth",
    ),
    ("bench", "pareto"): Command(
        "bench", "pareto", "speed against accuracy of every mapping method (Pareto chart and table)"
    ),
    ("bench", "stability"): Command(
        "bench",
        "stability",
        "sweeps where GPIS and robust GPIS break down, and whether failures are detected",
    ),
    ("bench", "speed"): Command(
        "bench",
        "speed",
        "fit and prediction times of the estimators and the default mapper at the paper's sizes",
    ),
    ("bench", "inject"): Command(
        "bench",
        "inject",
        "refit times and the flag of one false contact planted in each real contact-free flight",
    ),
    ("bench", "fuzz"): Command(
        "bench",
        "fuzz",
        "millions of hostile inputs per parser: only declared errors, no slow input, no hang",
    ),
}


def load(path: tuple[str, ...]) -> tuple[Callable, Callable]:
    """``(add_arguments, run)`` of the command at ``path`` (its module is imported now)."""
    cmd = COMMANDS[path]
    module = importlib.import_module(f"groundstation.cli.{cmd.module}")
    return getattr(module, f"add_{cmd.stem}_arguments"), getattr(module, f"run_{cmd.stem}")


def _groups() -> dict[str, list[tuple[tuple[str, ...], str]]]:
    groups: dict[str, list[tuple[tuple[str, ...], str]]] = {}
    for path, cmd in COMMANDS.items():
        groups.setdefault(path[0], []).append((path, cmd.help))
    return groups


def _top_usage() -> str:
    lines = ["usage: groundstation COMMAND [...]", "", "commands:"]
    for path, cmd in COMMANDS.items():
        lines.append(f"  {' '.join(path):<20} {cmd.help}")
    lines.append("")
    lines.append("Run 'groundstation COMMAND --help' for the options of one command.")
    return "\n".join(lines)


def _stacks_on_sigusr1() -> None:
    """`kill -USR1 PID` prints every thread's stack to stderr and lets the command go on: what a
    process that does not stop when asked is doing (README, Reliability). Not where stderr has
    no file descriptor (``main`` called in a process whose stderr is captured)."""
    try:
        faulthandler.register(signal.SIGUSR1, all_threads=True, chain=False)
    except (OSError, ValueError, AttributeError, RuntimeError):  # io.UnsupportedOperation: fileno
        pass


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    _stacks_on_sigusr1()
    if not argv or argv[0] in ("-h", "--help"):
        print(_top_usage())
        return 0 if argv else 2
    # Longest command path that matches the start of argv.
    match = None
    for path in sorted(COMMANDS, key=len, reverse=True):
        if tuple(argv[: len(path)]) == path:
            match = path
            break
    if match is None:
        group = _groups().get(argv[0])
        if group:
            print(f"groundstation {argv[0]}: choose one of:", file=sys.stderr)
            for path, help_ in group:
                print(f"  {' '.join(path):<20} {help_}", file=sys.stderr)
        else:
            print(f"groundstation: unknown command {argv[0]!r}\n\n{_top_usage()}", file=sys.stderr)
        return 2
    add_arguments, run = load(match)
    parser = argparse.ArgumentParser(
        prog="groundstation " + " ".join(match), description=COMMANDS[match].help
    )
    add_arguments(parser)
    args = parser.parse_args(argv[len(match) :])
    try:
        return int(run(args) or 0)
    except (GroundstationError, BridgeError) as exc:  # e.g. a bad link URI (firmware_bridge)
        print(f"error: {exc.message}", file=sys.stderr)
        if exc.hint:
            print(f"hint: {exc.hint}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
