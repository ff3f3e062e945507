"""Calibration commands: ``groundstation joystick calibrate`` and ``groundstation calibrate
detector``.

``groundstation calibrate detector LOG [--segment S:E] [--out FILE]`` measures the impulse
detector's noise on a contact-free stretch of a recording (``contact/calibration.py``) and writes
a ``[contact]`` table that ``--config`` accepts, with the measured margins as comments.

``groundstation joystick calibrate`` walks the pilot through calibration in the terminal.

Steps (each ends when the pilot presses Enter; the device is read on its own thread meanwhile):

1. release all sticks -> every axis' centre;
2. move every stick to all its extremes -> every axis' min/max; axes that travelled at least
   ``--min-travel`` of the full scale are the candidate axes ("detect axes by movement");
3. for each role (roll, pitch, yaw, throttle), push that stick in the positive direction
   (right, forward, right, up) -> the candidate axis deflected most is that role's axis, and a
   negative deflection sets ``reversed`` (Linux reports stick-forward as negative Y);
4. confirm, then the calibration is written to the store keyed by the device name.

The pure helpers (:func:`extremes`, :func:`deflection`, :func:`pick_axis`) carry the logic; the
prompts only move data between stdin/stdout, the device and those helpers.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterable, Mapping
from typing import TextIO

from groundstation.pilot.calibration import AxisCalibration, DeviceCalibration, save_calibration
from groundstation.pilot.jsdev import JS_EVENT_AXIS, JoystickDevice, JoystickError, decode_events
from groundstation.pilot.settings import DEFAULT_CALIBRATION_PATH, ROLES

FULL_SCALE = 65534  # -32767..32767
ROLE_PROMPTS = {
    "roll": "push the ROLL stick fully RIGHT and hold it",
    "pitch": "push the PITCH stick fully FORWARD (away from you) and hold it",
    "yaw": "push the YAW stick fully RIGHT and hold it",
    "throttle": "push the THROTTLE stick fully UP (full thrust) and hold it",
}


class CalibrationAborted(JoystickError):
    """The pilot quit, or stdin ended, before the calibration was complete."""


def extremes(
    chunks: Iterable[bytes], start: Mapping[int, int]
) -> tuple[dict[int, int], dict[int, int]]:
    """Per-axis (min, max) over raw js_event byte chunks, starting from the values in ``start``."""
    lo, hi = dict(start), dict(start)
    pending = b""
    for chunk in chunks:
        events, pending = decode_events(pending + chunk)
        for ev in events:
            if ev.kind == JS_EVENT_AXIS:
                n, v = ev.number, ev.value
                lo[n] = min(lo.get(n, v), v)
                hi[n] = max(hi.get(n, v), v)
    return lo, hi


def deflection(raw: int, centre: int, lo: int, hi: int) -> float:
    """Signed deflection of ``raw`` from ``centre`` as a fraction of that side's travel."""
    if raw >= centre:
        return (raw - centre) / max(hi - centre, 1)
    return -(centre - raw) / max(centre - lo, 1)


def pick_axis(
    values: Mapping[int, int],
    centre: Mapping[int, int],
    lo: Mapping[int, int],
    hi: Mapping[int, int],
    candidates: Iterable[int],
    min_deflection: float = 0.5,
) -> tuple[int, bool] | None:
    """The candidate axis deflected most (and whether it went negative), or None if none moved."""
    best: tuple[float, int, bool] | None = None
    for a in candidates:
        if a not in values or a not in centre:
            continue
        d = deflection(values[a], centre[a], lo[a], hi[a])
        if abs(d) >= min_deflection and (best is None or abs(d) > best[0]):
            best = (abs(d), a, d < 0)
    return None if best is None else (best[1], best[2])


def add_joystick_calibrate_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--device", default="/dev/input/js0", help="joystick device or FIFO")
    parser.add_argument(
        "--out", default=DEFAULT_CALIBRATION_PATH, help="calibration store (TOML, per device name)"
    )
    parser.add_argument(
        "--name", default="", help="device name when the device cannot report one (FIFO)"
    )
    parser.add_argument(
        "--timeout", type=float, default=10.0, help="seconds to wait for the device"
    )
    parser.add_argument(
        "--min-travel",
        type=float,
        default=0.25,
        help="fraction of full scale an axis must travel in step 2 to count as a stick",
    )
    parser.add_argument("--yes", action="store_true", help="save without asking")


class _Prompter:
    def __init__(self, device: JoystickDevice, stdin: TextIO, stdout: TextIO, steps: int):
        self.device, self.stdin, self.stdout, self.steps, self.k = device, stdin, stdout, steps, 0

    def say(self, text: str) -> None:
        print(text, file=self.stdout, flush=True)

    def step(self, text: str) -> str:
        """Print a numbered prompt, wait for a line, then let the reader apply pending input."""
        self.k += 1
        self.say(f"[step {self.k}/{self.steps}] {text}, then press Enter (q to quit)")
        line = self.stdin.readline()
        if line == "":
            raise CalibrationAborted("calibration aborted: end of input before it was complete")
        if line.strip().lower() in ("q", "quit"):
            raise CalibrationAborted("calibration aborted by the pilot")
        self.device.barrier(2.0)
        snap = self.device.snapshot()
        if not snap.connected:
            raise JoystickError(
                f"joystick {self.device.path} was lost during calibration",
                hint="reconnect it and start again",
            )
        return line.strip()


def calibrate(
    device: JoystickDevice,
    stdin: TextIO,
    stdout: TextIO,
    *,
    min_travel: float = 0.25,
) -> DeviceCalibration:
    """Run the interactive steps on a started device; returns the calibration (not saved)."""
    p = _Prompter(device, stdin, stdout, steps=2 + len(ROLES))
    snap = device.snapshot()
    p.say(
        f"Calibrating {snap.name!r} at {device.path} "
        f"({device.n_axes if device.n_axes is not None else '?'} axes, "
        f"{device.n_buttons if device.n_buttons is not None else '?'} buttons)."
    )
    p.step("let go of all sticks so that they rest at their centre")
    centre = dict(device.snapshot().axes)
    if not centre:
        raise JoystickError(f"{device.path} reported no axes", hint="is this a joystick?")
    device.drain_raw()
    p.step("move EVERY stick to all of its extremes, several times, then let go")
    chunks = [c for _, c in device.drain_raw()]
    lo, hi = extremes(chunks, centre)
    moved = sorted(a for a in centre if hi[a] - lo[a] >= min_travel * FULL_SCALE)
    p.say(f"axes that moved: {moved or 'none'}")
    if len(moved) < len(ROLES):
        raise JoystickError(
            f"only {len(moved)} axes moved (need {len(ROLES)}: {', '.join(ROLES)})",
            hint="move every stick fully in every direction during step 2",
        )
    roles: dict[str, int] = {}
    reversed_: dict[int, bool] = {}
    for role in ROLES:
        p.step(ROLE_PROMPTS[role])
        values = device.snapshot().axes
        free = [a for a in moved if a not in roles.values()]
        found = pick_axis(values, centre, lo, hi, free)
        if found is None:
            raise JoystickError(
                f"no stick was pushed for {role} (no free axis past half travel)",
                hint="hold the stick at its end while pressing Enter",
            )
        axis, rev = found
        roles[role], reversed_[axis] = axis, rev
        p.say(f"  {role}: axis {axis}{' (reversed)' if rev else ''}")
    axes: dict[int, AxisCalibration] = {}
    for role, a in roles.items():
        c = centre[a]
        if role == "throttle":
            c = (lo[a] + hi[a]) // 2  # a down-zero throttle maps min..max linearly
        if not lo[a] < c < hi[a]:
            raise JoystickError(
                f"{role} axis {a} did not travel on both sides of its centre "
                f"(min {lo[a]}, centre {c}, max {hi[a]})",
                hint="move the stick to both ends during step 2",
            )
        axes[a] = AxisCalibration(lo[a], c, hi[a], reversed_[a])
    return DeviceCalibration(snap.name, axes, roles)


def run_joystick_calibrate(
    args: argparse.Namespace, stdin: TextIO | None = None, stdout: TextIO | None = None
) -> int:
    stdin = stdin or sys.stdin
    stdout = stdout or sys.stdout
    device = JoystickDevice(args.device, name=args.name)
    with device:
        if not device.wait_connected(args.timeout):
            raise JoystickError(
                f"no joystick input from {args.device} within {args.timeout:g} s",
                hint="check the path (ls /dev/input/js*) and that you may read it (group 'input')",
            )
        if not device.snapshot().name:
            raise JoystickError(
                f"{args.device} reports no name (not a joystick device?)",
                hint="give one with --name; calibrations are stored per device name",
            )
        try:
            cal = calibrate(device, stdin, stdout, min_travel=args.min_travel)
        except CalibrationAborted as exc:
            print(exc.message, file=sys.stderr)
            return 1
        print("calibration:", file=stdout)
        for role in ROLES:
            a = cal.axes[cal.roles[role]]
            print(
                f"  {role:<8} axis {cal.roles[role]}: min {a.min} centre {a.centre} max {a.max}"
                f"{' reversed' if a.reversed else ''}",
                file=stdout,
            )
        if not args.yes:
            print(f"save to {args.out}? [Y/n]", file=stdout, flush=True)
            line = stdin.readline()  # end of input is not a yes
            if line == "" or line.strip().lower() not in ("", "y", "yes"):
                print("not saved", file=stdout)
                return 1
        path = save_calibration(args.out, cal)
        print(f"saved calibration of {cal.name!r} to {path}", file=stdout)
    return 0


# ---------------------------------------------------------------- calibrate detector


def _segment(text: str) -> tuple[float, float]:
    lo, sep, hi = text.partition(":")
    try:
        a = float(lo) if lo.strip() else 0.0
        b = float(hi) if sep and hi.strip() else float("inf")
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected START:END seconds") from None
    if not (a >= 0 and b > a):
        raise argparse.ArgumentTypeError(f"{text!r}: need 0 <= START < END")
    return a, b


def add_detector_calibrate_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``groundstation calibrate detector``."""
    parser.add_argument("log", help="recording (.mcap) with a contact-free segment")
    parser.add_argument(
        "--segment",
        type=_segment,
        default=(0.0, float("inf")),
        metavar="S:E",
        help="contact-free segment, seconds of log time from its start (default: all of it)",
    )
    parser.add_argument("--out", default=None, help="TOML file to write (default: print it)")
    parser.add_argument(
        "--margin", type=float, default=1.35, help="trigger level over the largest residual seen"
    )
    parser.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    parser.add_argument("--config", default=None, help="TOML configuration (window lengths)")
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="override a setting"
    )


def run_detector_calibrate(args: argparse.Namespace) -> int:
    """Read the segment's accelerometer samples, calibrate, write or print the TOML."""
    from pathlib import Path

    import numpy as np

    from groundstation.acquisition.reader import open_recording
    from groundstation.acquisition.replay import iter_replay
    from groundstation.contact.calibration import calibrate
    from groundstation.errors import InputDataError
    from groundstation.runtime.configuration import resolve_for_log

    cfg = resolve_for_log(args.log, args.config, args.set, "calibrate").config
    out = Path(args.out) if args.out else None
    if out is not None and out.exists() and not args.force:
        raise InputDataError(f"{out} exists", hint="pass --force to replace it")
    with open_recording(args.log) as rec:
        start = int(rec.summary.start_ns or 0)
    lo, hi = args.segment
    t, f = [], []
    for env in iter_replay(args.log, settings=cfg.acquisition):
        if env.topic != "samples.imu":
            continue
        rel = (env.header.recv_ns - start) / 1e9
        if rel < lo:
            continue
        if rel > hi:
            break
        ts = int(env.payload.get("t_station_ns", env.header.source_ns))
        if t and ts <= t[-1]:
            continue
        t.append(ts)
        f.append(np.asarray(env.arrays["accel_mps2"], dtype=np.float64))
    if not t:
        raise InputDataError(f"{args.log}: no IMU samples in the segment {lo:g}:{hi:g} s")
    cal = calibrate(np.array(t), np.array(f), cfg.contact, margin=args.margin)
    seg = f"{lo:g}:{'end' if hi == float('inf') else f'{hi:g}'}"
    text = cal.to_toml(f"{args.log} --segment {seg}")
    if out is None:
        print(text, end="")
    else:
        out.write_text(text)
        print(text, end="", file=sys.stderr)
        print(f"wrote {out} (use it with --config {out})", file=sys.stderr)
    return 0
