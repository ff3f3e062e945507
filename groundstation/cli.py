"""The ``groundstation`` command.

Subcommands are listed in one table and imported lazily, so ``groundstation --help`` is quick and
a broken optional dependency of one command does not break the others. Each command module
provides ``add_arguments(parser)`` and ``run(args) -> int``.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from groundstation.errors import GroundstationError

# command path -> (module, one-line help)
COMMANDS: dict[tuple[str, ...], tuple[str, str]] = {
    ("bench", "paper2d"): (
        "groundstation.bench.paper2d",
        "reproduce the paper's 2D simulation (GPIS vs robust GPIS) with tables and figures",
    ),
    ("bench", "detector"): (
        "groundstation.bench.detector",
        "false contacts per minute on real flights vs recall on simulated touches, per threshold",
    ),
    ("bench", "pareto"): (
        "groundstation.bench.pareto",
        "speed against accuracy of every mapping method (Pareto chart and table)",
    ),
    ("bench", "stability"): (
        "groundstation.bench.stability",
        "sweeps where GPIS and robust GPIS break down, and whether failures are detected",
    ),
    ("live",): (
        "groundstation.live_cli",
        "fly a live session: link, mocap, joystick, detector, mapper, viewer, recorder",
    ),
    ("replay",): (
        "groundstation.replay_cli",
        "run the mapping pipeline on a recording: mesh, per-observation table, report",
    ),
    ("bench", "sessions"): (
        "groundstation.bench.sessions",
        "the whole pipeline on many SITL sessions, per setting variant, scored against truth",
    ),
    ("bench", "speed"): (
        "groundstation.bench.speed",
        "fit and prediction times of the estimators and the default mapper at the paper's sizes",
    ),
    ("config", "show"): ("groundstation.config_cli", "print the effective configuration as TOML"),
    ("record",): (
        "groundstation.acquisition.record_cli",
        "record a live session (link + mocap + recorder under the supervisor) to an MCAP log",
    ),
    ("sitl",): ("firmware_bridge.sitl.cli", "run the software-in-the-loop vehicle and mocap"),
    ("view",): (
        "groundstation.viewer.view_cli",
        "show the live mesh, flagged contacts and the vehicle (window or --headless PNG/PLY)",
    ),
    ("import", "csv"): (
        "groundstation.acquisition.importers.cli_csv",
        "convert a CSV IMU recording (e.g. aggressive_flight) into a replayable MCAP log",
    ),
    ("import", "ulog"): (
        "groundstation.acquisition.importers.cli_ulog",
        "convert a PX4 ULog into a replayable MCAP log",
    ),
    ("import", "tlog"): (
        "groundstation.acquisition.importers.cli_tlog",
        "convert a MAVLink .tlog into a replayable MCAP log",
    ),
    ("joystick", "calibrate"): (
        "groundstation.pilot.calibrate_cli",
        "walk through joystick calibration in the terminal and store it per device",
    ),
    ("export", "tlog"): (
        "groundstation.acquisition.importers.cli_export_tlog",
        "write the MAVLink traffic of an MCAP log as a .tlog (QGroundControl replay)",
    ),
}


def _groups() -> dict[str, list[tuple[tuple[str, ...], str]]]:
    groups: dict[str, list[tuple[tuple[str, ...], str]]] = {}
    for path, (_, help_) in COMMANDS.items():
        groups.setdefault(path[0], []).append((path, help_))
    return groups


def _top_usage() -> str:
    lines = ["usage: groundstation COMMAND [...]", "", "commands:"]
    for path, (_, help_) in COMMANDS.items():
        lines.append(f"  {' '.join(path):<20} {help_}")
    lines.append("")
    lines.append("Run 'groundstation COMMAND --help' for the options of one command.")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
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
    module_name, help_ = COMMANDS[match]
    module = importlib.import_module(module_name)
    parser = argparse.ArgumentParser(prog="groundstation " + " ".join(match), description=help_)
    module.add_arguments(parser)
    args = parser.parse_args(argv[len(match) :])
    try:
        return int(module.run(args) or 0)
    except GroundstationError as exc:
        print(f"error: {exc.message}", file=sys.stderr)
        if exc.hint:
            print(f"hint: {exc.hint}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
