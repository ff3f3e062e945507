"""``groundstation sitl``: the simulated vehicle and mocap over real transports.

groundstation sitl [--scene NAME|FILE] [--link pty|pty:/path|udp://HOST:PORT]
                   [--mocap udp://HOST:PORT] [--pilot script:NAME|manual] [--speed X] [--seed N]
                   [--duration SECONDS] [--truth FILE] [--record LOG.mcap [--force]]
                   [--log-commands FILE] [--no-wait-for-station]
                   [--gust-rate PER_MIN] [--gust-force MIN:MAX] [--gust-duration MIN:MAX]
                   [--gust-cluster P] [--gust-cluster-size A:B]
                   [--physics simple|mujoco] [--friction MU]

By default the vehicle waits on the ground (a standby HEARTBEAT once a second, nothing else)
until the station's first message: the flight and its clock start when a station listens, so
no frame is lost before it connects (``--no-wait-for-station``: start at once, as before).
``--link pty:/path`` also makes ``/path`` a link to the pseudo-terminal, valid only while this
SITL runs: a station given ``serial:///path`` cannot attach to another process's vehicle through
a reused ``/dev/pts/N``.

Physics: ``simple`` (default; the home-made rigid body, the drone a 0.2 m x 0.1 m cylinder,
spring-damper contacts with restitution 0.5) or ``mujoco`` (MuJoCo with the 1 kg guarded X quad's
real geometry, rotors with lag and limits, soft contacts with restitution ~0.4 and friction
``--friction`` on the scene's geometry, 1 kHz); same controller, pilots, gusts, IMU model and
wire outputs.

Gusts: Poisson arrivals at ``--gust-rate``; each a half-sine force pulse of peak ``--gust-force``
newtons (default 2.5-4 G on the 1 kg vehicle) lasting ``--gust-duration`` seconds (default
0.04-0.06); with ``--gust-cluster P`` a gust starts a cluster of ``--gust-cluster-size`` gusts
(default 3:5) 0.2-1 s apart from about the same direction. Real wind: e.g.
``--gust-force 5:40 --gust-duration 0.05:0.3 --gust-cluster 0.3``.

With ``--speed max --record LOG.mcap`` no transport is opened: the run is written straight to an
MCAP recording in the station's layout, with simulated receive times and the truth embedded
(:mod:`groundstation.acquisition.sim_recording`).

``--log-commands FILE`` writes one JSON line per MANUAL_CONTROL as it arrives on the wire
(``{"kind": "manual", "t_ns": <monotonic receive time>, "sim_t": <s>, "x", "y", "z", "r",
"buttons"}``) and one per vehicle mode change (``{"kind": "mode", "t_ns", "sim_t", "mode"}``,
MANUAL / HOLD / LAND / LANDED), flushed per line, for measuring the station's send rate and
failsafe behaviour from outside the station.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import time
from pathlib import Path

from firmware_bridge.errors import BridgeError
from firmware_bridge.mavlink import MavlinkCodec
from firmware_bridge.mavlink.messages import ManualControl
from firmware_bridge.sitl.airframe import Airframe
from firmware_bridge.sitl.engine import ENGINES, MujocoParams
from firmware_bridge.sitl.gusts import GustParams
from firmware_bridge.sitl.pilots import PILOTS
from firmware_bridge.sitl.runner import MocapSettings, Simulation, run_paced
from firmware_bridge.sitl.scene import load_scene, named_scenes
from firmware_bridge.sitl.transport import PtyTransport, UdpTransport, open_transport
from firmware_bridge.sitl.vehicle import VehicleSettings, vehicle_settings


def _speed(text: str) -> float:
    if text == "max":
        return math.inf
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--speed {text!r}: expected a number or 'max'") from None
    if not value > 0 or not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"--speed {text!r}: must be > 0")
    return value


def _range(kind: type, what: str):
    """argparse type for ``MIN:MAX`` (a single value means MIN = MAX)."""

    def parse(text: str) -> tuple:
        parts = text.split(":")
        try:
            if len(parts) == 1:
                lo = hi = kind(parts[0])
            elif len(parts) == 2:
                lo, hi = kind(parts[0]), kind(parts[1])
            else:
                raise ValueError
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r}: expected MIN:MAX {what}") from None
        if not (math.isfinite(lo) and math.isfinite(hi)) or lo < 0 or hi < lo:
            raise argparse.ArgumentTypeError(f"{text!r}: need 0 <= MIN <= MAX ({what})")
        return lo, hi

    return parse


def add_sitl_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``groundstation sitl``."""
    parser.add_argument(
        "--scene", default="paper", help=f"named scene ({', '.join(named_scenes())}) or a JSON file"
    )
    parser.add_argument(
        "--link",
        default="pty",
        help="pty (prints the device to open), pty:/path (and a link to it at /path, valid "
        "while this SITL runs) or udp://HOST:PORT (MAVLink target)",
    )
    parser.add_argument(
        "--wait-for-station",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="hold the vehicle on the ground until the station's first message (default on)",
    )
    parser.add_argument(
        "--mocap",
        default=None,
        metavar="udp://HOST:PORT",
        help="send NatNet 4.1 frames of rigid body 1 there (default: no mocap)",
    )
    parser.add_argument(
        "--pilot",
        default="manual",
        help=f"manual (MANUAL_CONTROL) or script:{'|'.join(PILOTS)}",
    )
    parser.add_argument(
        "--speed", type=_speed, default=1.0, help="times real time (default 1); 'max' = unpaced"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--duration",
        type=float,
        default=None,
        metavar="SECONDS",
        help="simulated seconds (default: until Ctrl-C; scripts end 2 s after the script)",
    )
    parser.add_argument(
        "--truth",
        type=Path,
        default=None,
        metavar="FILE",
        help="write the ground-truth sidecar (JSON) here at exit",
    )
    parser.add_argument(
        "--gust-rate",
        type=float,
        default=GustParams().rate_per_min,
        metavar="PER_MIN",
        help="gusts per minute (false-positive contacts)",
    )
    parser.add_argument(
        "--gust-force",
        type=_range(float, "newtons"),
        default=None,
        metavar="MIN:MAX",
        help="peak gust force range, N (default 2.5-4 G times the vehicle mass)",
    )
    parser.add_argument(
        "--gust-duration",
        type=_range(float, "seconds"),
        default=None,
        metavar="MIN:MAX",
        help="gust duration range, s (default 0.04:0.06)",
    )
    parser.add_argument(
        "--gust-cluster",
        type=float,
        default=0.0,
        metavar="P",
        help="probability that a gust starts a cluster of gusts at one spot (default 0)",
    )
    parser.add_argument(
        "--gust-cluster-size",
        type=_range(int, "gusts"),
        default=GustParams().cluster_size,
        metavar="A:B",
        help="gusts per cluster, the first included (default 3:5)",
    )
    parser.add_argument(
        "--physics",
        choices=ENGINES,
        default="simple",
        help="physics engine: simple (default) or mujoco (real body geometry, soft contacts)",
    )
    parser.add_argument(
        "--friction",
        type=float,
        default=MujocoParams().friction,
        metavar="MU",
        help=f"mujoco: sliding friction of the body on structures (default "
        f"{MujocoParams().friction:g})",
    )
    parser.add_argument(
        "--record",
        type=Path,
        default=None,
        metavar="LOG.mcap",
        help="with --speed max: write the session straight to this recording (no transports)",
    )
    parser.add_argument("--force", action="store_true", help="replace an existing --record file")
    parser.add_argument(
        "--station-config",
        type=Path,
        default=None,
        metavar="FILE.toml",
        help="write the station's [vehicle] for the simulated airframe and its floor height "
        "([contact] floor_z_m) to this file, for "
        "'groundstation live/record --config FILE.toml' (a --record log stores it anyway)",
    )
    parser.add_argument(
        "--log-commands",
        type=Path,
        default=None,
        metavar="FILE",
        help="JSON lines: receive time of each MANUAL_CONTROL and each vehicle mode change",
    )
    parser.add_argument(
        "--signing-key",
        type=Path,
        default=None,
        metavar="FILE",
        help="MAVLink 2 signing key: accept only commands signed with it (unsigned or wrongly "
        "signed MANUAL_CONTROL / COMMAND_LONG / ATT_POS_MOCAP are rejected and counted)",
    )
    parser.add_argument("--mocap-up", choices=("y", "z"), default="y", help="Motive up axis")
    parser.add_argument(
        "--mocap-drop",
        type=float,
        default=MocapSettings().drop_probability,
        help="probability that a mocap frame is dropped",
    )
    parser.add_argument(
        "--mocap-noise",
        type=float,
        default=MocapSettings().position_noise,
        metavar="METRES",
        help="mocap position noise, 1 sigma",
    )


class CommandLog:
    """Wraps the uplink source: logs each MANUAL_CONTROL's wire arrival and each mode change.

    The bytes go on to the simulation unchanged; a second codec only watches them (the uplink
    carries tens of frames per second, so decoding twice is cheap).
    """

    def __init__(self, source, path: Path, sim: Simulation):
        self.source, self.sim = source, sim
        self.codec = MavlinkCodec(system_id=1, component_id=1)
        self.fh = open(path, "w", encoding="utf-8", buffering=1)  # noqa: SIM115 - closed in close()
        self._modes = 0
        self.manual = 0

    def fileno(self) -> int:
        return self.source.fileno()

    def flush(self) -> None:
        self.source.flush()

    def _line(self, **rec: object) -> None:
        self.fh.write(json.dumps(rec, separators=(",", ":")) + "\n")

    def recv(self) -> bytes:
        data = self.source.recv()
        if data:
            t_ns = time.monotonic_ns()
            for rec in self.codec.decode(data, t_ns):
                if isinstance(rec, ManualControl):
                    self.manual += 1
                    self._line(
                        kind="manual", t_ns=t_ns, sim_t=round(self.sim.vehicle.t, 4), x=rec.x,
                        y=rec.y, z=rec.z, r=rec.r, buttons=rec.buttons,
                    )  # fmt: skip
        self.modes()
        return data

    def modes(self) -> None:
        """Log mode changes of the manual-flight state machine since the last call."""
        manual = self.sim.vehicle.manual
        if manual is None:
            return
        for t, mode in manual.transitions[self._modes :]:
            self._line(kind="mode", t_ns=time.monotonic_ns(), sim_t=round(t, 4), mode=mode)
        self._modes = len(manual.transitions)

    def close(self) -> None:
        self.modes()
        self.fh.close()


def run_sitl(args: argparse.Namespace) -> int:
    """Run the SITL until ``--duration``, the end of a script, SIGINT or SIGTERM."""
    try:
        return _run(args)
    except BridgeError as exc:
        print(f"error: {exc.message}", file=sys.stderr)
        if exc.hint:
            print(f"hint: {exc.hint}", file=sys.stderr)
        return 2


def _station_config(args: argparse.Namespace, sim: Simulation) -> None:
    """``--station-config``: the station's ``[vehicle]`` for this airframe and the floor's
    height, written for a live session's ``--config``; without it a live run of an airframe
    other than the default cylinder says how to get it (the station cannot learn the body over
    MAVLink)."""
    from groundstation.acquisition.sim_recording import station_config

    text = station_config(sim)
    if args.station_config is not None:
        try:
            args.station_config.write_text(
                f"# groundstation sitl --physics {args.physics}: the simulated airframe\n{text}",
                encoding="utf-8",
            )
        except OSError as exc:
            raise BridgeError(
                f"--station-config {args.station_config}: cannot write it ({exc.strerror})"
            ) from exc
        where = args.station_config
        print(
            f"sitl: the station's [vehicle] for this airframe in {where} "
            f"(groundstation live --config {where})",
            file=sys.stderr,
            flush=True,
        )
    elif args.record is None and args.physics != "simple":
        print(
            f"sitl: the station must know this airframe (physics {args.physics}): rerun with "
            "--station-config FILE.toml and start the station with --config FILE.toml",
            file=sys.stderr,
            flush=True,
        )


def _run(args: argparse.Namespace) -> int:
    scene = load_scene(args.scene)
    pilot = args.pilot
    if pilot != "manual" and not pilot.startswith("script:"):
        raise BridgeError(
            f"--pilot {pilot!r}: expected manual or script:NAME", hint="e.g. --pilot script:survey"
        )
    if not 0.0 <= args.mocap_drop <= 1.0:
        raise BridgeError(f"--mocap-drop {args.mocap_drop}: must be within 0..1")
    if not (math.isfinite(args.friction) and args.friction >= 0):
        raise BridgeError(f"--friction {args.friction}: must be >= 0", hint="e.g. --friction 0.3")
    if args.physics == "mujoco":
        mass = Airframe().mass
        mj = MujocoParams(friction=args.friction)
        vs = vehicle_settings("mujoco", gusts=_gusts(args, mass), mujoco=mj)
    else:
        vs = VehicleSettings(gusts=_gusts(args, VehicleSettings().quad.mass))
    if args.record is not None and math.isfinite(args.speed):
        raise BridgeError(
            "--record writes the simulation straight to a file and needs --speed max",
            hint="to record a paced session, run 'groundstation record' against the SITL",
        )
    mocap = MocapSettings(
        # no mocap sink: do not simulate it (a recording always holds mocap)
        rate=MocapSettings().rate if args.mocap or args.record else 0.0,
        up=args.mocap_up,
        drop_probability=args.mocap_drop,
        position_noise=max(0.0, args.mocap_noise),
    )
    key = None
    if getattr(args, "signing_key", None) is not None:
        from firmware_bridge.mavlink.signing import load_signing_key

        key = load_signing_key(args.signing_key)
    sim = Simulation(scene, pilot, args.seed, args.duration, vs, mocap, signing_key=key)
    _station_config(args, sim)
    if args.record is not None:
        return _record(args, sim)

    link = open_transport(args.link)
    mocap_tx = UdpTransport(args.mocap, receive=False) if args.mocap else None
    sinks: dict = {"mavlink": link}
    if mocap_tx is not None:
        sinks["mocap"] = mocap_tx
    if isinstance(link, PtyTransport):
        print(f"SITL MAVLink on {link.link_path or link.path}", flush=True)
        if link.link_path is not None:
            print(f"sitl: {link.link_path} -> {link.path} (while this SITL runs)",
                  file=sys.stderr, flush=True)  # fmt: skip
    else:
        print(f"SITL MAVLink to {args.link} (local port {link.local_port})", flush=True)  # type: ignore[union-attr]
    if mocap_tx is not None:
        print(f"SITL NatNet 4.1 to {args.mocap}", flush=True)
    uplink = link if args.log_commands is None else CommandLog(link, args.log_commands, sim)
    print(
        f"scene {scene.name}, pilot {pilot}, seed {args.seed}, speed {args.speed}, "
        f"physics {args.physics}",
        file=sys.stderr,
        flush=True,
    )

    stopping: list[str] = []

    def on_signal(signum: int, _frame: object) -> None:
        stopping.append(signal.Signals(signum).name)

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    script_end: list[float] = []

    def stop() -> bool:
        if stopping:
            return True
        if args.duration is None and pilot != "manual" and pilot != "script:hover":
            if sim.vehicle.pilot_done:
                if not script_end:
                    script_end.append(sim.vehicle.t)
                return sim.vehicle.t > script_end[0] + 2.0
        return False

    def status(t: float) -> None:
        if isinstance(uplink, CommandLog):
            uplink.modes()
        st = sim.stats
        dropped = link.stats.frames_dropped + (mocap_tx.stats.frames_dropped if mocap_tx else 0)
        print(
            f"sitl t={t:7.1f} s  mode {sim.vehicle.mode:<8} mavlink {st.mavlink_frames} "
            f"mocap {st.mocap_frames}  dropped {dropped}  rx cmds {st.commands} "
            f"manual {st.manual_controls}"
            + (f"  unsigned rejected {sim.codec.stats.rejected_signature}" if key else ""),
            file=sys.stderr,
            flush=True,
        )

    def waiting(waited_s: float) -> None:
        if waited_s == 0 or int(waited_s) % 10 == 0:
            print(f"sitl: on the ground, waiting for the station ({waited_s:.0f} s)",
                  file=sys.stderr, flush=True)  # fmt: skip

    wall0 = time.monotonic()
    try:
        run_paced(sim, sinks, [uplink], args.speed, stop, status, args.wait_for_station, waiting)
    finally:
        if isinstance(uplink, CommandLog):
            uplink.close()
        for s, h in old.items():
            signal.signal(s, h)
        if isinstance(link, PtyTransport):
            link.drain(3.0)  # under load the station may lag; closing would discard its input
        link.close()
        if mocap_tx is not None:
            mocap_tx.close()
        if args.truth is not None:
            args.truth.write_text(json.dumps(sim.truth(), indent=1), encoding="utf-8")
    wall = time.monotonic() - wall0
    why = stopping[0] if stopping else "end"
    status(sim.vehicle.t)
    print(
        f"sitl stopped ({why}) after {sim.vehicle.t:.2f} s simulated in {wall:.2f} s wall; "
        f"pty/udp dropped {link.stats.frames_dropped} frames",
        file=sys.stderr,
        flush=True,
    )
    return 0


def _gusts(args: argparse.Namespace, mass: float) -> GustParams:
    """Gust settings from the command line (forces in N on a vehicle of ``mass`` kg)."""
    if not 0.0 <= args.gust_cluster <= 1.0:
        raise BridgeError(f"--gust-cluster {args.gust_cluster}: must be within 0..1")
    if args.gust_cluster_size[0] < 1:
        raise BridgeError(
            f"--gust-cluster-size {args.gust_cluster_size}: a cluster has >= 1 gust",
            hint="e.g. --gust-cluster-size 3:5",
        )
    if args.gust_duration is not None and args.gust_duration[0] <= 0:
        raise BridgeError(
            f"--gust-duration {args.gust_duration}: must be > 0 s", hint="e.g. 0.05:0.3"
        )
    return GustParams.from_forces(
        mass,
        force=args.gust_force,
        duration=args.gust_duration,
        rate_per_min=max(0.0, args.gust_rate),
        cluster_probability=args.gust_cluster,
        cluster_size=tuple(args.gust_cluster_size),
    )


def _gust_argv(args: argparse.Namespace) -> list[str]:
    """The gust options that differ from the defaults, as command-line words."""
    out = []
    if args.gust_force is not None:
        out += ["--gust-force", f"{args.gust_force[0]:g}:{args.gust_force[1]:g}"]
    if args.gust_duration is not None:
        out += ["--gust-duration", f"{args.gust_duration[0]:g}:{args.gust_duration[1]:g}"]
    if args.gust_cluster > 0:
        out += ["--gust-cluster", f"{args.gust_cluster:g}"]
        out += ["--gust-cluster-size", "{}:{}".format(*args.gust_cluster_size)]
    return out


#: A script that has not finished after this many simulated seconds ends the run (a vehicle stuck
#: against a structure would otherwise record for ever); scripts take 30-200 s.
SCRIPT_LIMIT_S = 600.0


def _stop_after_script(args: argparse.Namespace, sim: Simulation):
    """Stop rule without a duration: a script ends 2 s (simulated) after it is done, or at
    :data:`SCRIPT_LIMIT_S` if it never finishes (said on stderr)."""
    script_end: list[float] = []

    def stop() -> bool:
        if args.duration is None and args.pilot not in ("manual", "script:hover"):
            if sim.vehicle.pilot_done:
                if not script_end:
                    script_end.append(sim.vehicle.t)
                return sim.vehicle.t > script_end[0] + 2.0
            if sim.vehicle.t > SCRIPT_LIMIT_S:
                print(
                    f"sitl: warning: {args.pilot} did not finish within {SCRIPT_LIMIT_S:.0f} s "
                    "of simulated time (the vehicle may be stuck); stopping there",
                    file=sys.stderr,
                    flush=True,
                )
                return True
        return False

    return stop


def _record(args: argparse.Namespace, sim: Simulation) -> int:
    """``--speed max --record``: the simulation straight into an MCAP recording."""
    if args.duration is None and args.pilot in ("manual", "script:hover"):
        raise BridgeError("--record with this pilot needs --duration (it would never end)")
    from groundstation.acquisition.segments import claim_output
    from groundstation.acquisition.sim_recording import write_simulation  # station side
    from groundstation.errors import GroundstationError

    try:
        claim_output(args.record, args.force, "--record")
    except GroundstationError as exc:
        raise BridgeError(exc.message, exc.hint) from exc
    argv = ["groundstation", "sitl", "--scene", args.scene, "--pilot", args.pilot]
    argv += ["--seed", str(args.seed), "--gust-rate", str(args.gust_rate)]
    argv += _gust_argv(args)
    if args.physics != "simple":
        argv += ["--physics", args.physics]
        if args.friction != MujocoParams().friction:
            argv += ["--friction", f"{args.friction:g}"]
    argv += ["--speed", "max"]
    if args.duration is not None:
        argv += ["--duration", str(args.duration)]
    argv += ["--record", args.record.name]
    wall0 = time.monotonic()
    try:
        stats = write_simulation(
            sim,
            str(args.record),
            seed=args.seed,
            created_by=" ".join(argv),
            motive_up=args.mocap_up,
            stop=_stop_after_script(args, sim),
        )
    except GroundstationError as exc:
        raise BridgeError(exc.message, exc.hint) from exc
    if args.truth is not None:
        args.truth.write_text(json.dumps(sim.truth(), indent=1), encoding="utf-8")
    print(
        f"sitl recorded {sim.vehicle.t:.2f} s simulated in {time.monotonic() - wall0:.2f} s wall "
        f"to {args.record}: {stats.messages} messages, {stats.bytes_written / 1e6:.2f} MB",
        file=sys.stderr,
        flush=True,
    )
    return 0
