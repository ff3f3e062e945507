"""Joystick -> pilot process -> bus -> link process -> UDP -> SITL vehicle, all real.

``groundstation sitl --pilot manual --log-commands FILE`` logs every MANUAL_CONTROL as it arrives
on the wire and every vehicle mode change; ``groundstation live --no-viewer --no-mapping`` runs
the link, mocap, pilot and recorder processes; a kernel-style FIFO joystick scripts the sticks.
Checked, counting frames (never asserting on elapsed time): the vehicle moves forward and up as
the sticks say (poses from the recording), the send rate on the wire is the configured one
(median inter-arrival, counts), at most the 200 ms stale window's worth of MANUAL_CONTROL
arrives after the last joystick byte, the SITL's own failsafe engages (HOLD, then LAND), and the
recording holds every command and pilot event.
"""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from groundstation.acquisition.reader import open_recording
from groundstation.bus.envelope import decode, unpack_frames
from groundstation.pilot.calibration import AxisCalibration, DeviceCalibration, save_calibration
from tests.unit.pilot.fifo_joystick import FULL, FifoJoystick

ROOT = Path(__file__).resolve().parents[2]
PAD = "Fifo Pad"
RATE_HZ = 25.0
STALE_S = 0.2

pytestmark = pytest.mark.timeout(240)


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def write_calibration(path: Path) -> Path:
    """The FIFO pad: Linux-style axes (pitch and throttle up = negative raw)."""
    save_calibration(
        path,
        DeviceCalibration(
            PAD,
            {
                0: AxisCalibration(-FULL, 0, FULL),
                1: AxisCalibration(-FULL, 0, FULL, reversed=True),
                2: AxisCalibration(-FULL, 0, FULL),
                3: AxisCalibration(-FULL, 0, FULL, reversed=True),
            },
            {"roll": 0, "pitch": 1, "yaw": 2, "throttle": 3},
        ),
    )
    return path


def start(argv: list[str], out: Path, err: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen(
        [sys.executable, "-m", "groundstation.cli", *argv],
        cwd=ROOT, env=env, stdout=out.open("w"), stderr=err.open("w"), stdin=subprocess.DEVNULL,
    )  # fmt: skip


def stop(proc: subprocess.Popen, sig: int = signal.SIGINT, timeout: float = 60) -> int:
    """Send ``sig`` and wait; a command still running after ``timeout`` is first asked for its
    stacks (SIGUSR1: to its stderr, which the caller's failure message shows), then killed."""
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGUSR1)
            time.sleep(2.0)
            proc.kill()
            proc.wait(10)
    return proc.returncode


def read_log(path: Path) -> list[dict]:
    """The SITL's --log-commands lines written so far (a partial last line is skipped)."""
    out = []
    if path.exists():
        for line in path.read_text().splitlines():
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                pass
    return out


def wait_for(pred, timeout: float, what: str, poll: float = 0.02):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        got = pred()
        if got:
            return got
        time.sleep(poll)
    raise AssertionError(f"timed out waiting for {what}")


def manual(log: list[dict]) -> list[dict]:
    return [r for r in log if r["kind"] == "manual"]


def modes(log: list[dict]) -> list[str]:
    return [r["mode"] for r in log if r["kind"] == "mode"]


def jitter(t_ns: list[int], rate_hz: float) -> dict:
    """Inter-arrival statistics (ms) of MANUAL_CONTROL at the SITL."""
    dt = np.diff(np.asarray(t_ns, np.int64)) / 1e6
    period = 1e3 / rate_hz
    return {
        "n": int(dt.size + 1),
        "median_ms": round(float(np.median(dt)), 3),
        "p5_ms": round(float(np.percentile(dt, 5)), 3),
        "p95_ms": round(float(np.percentile(dt, 95)), 3),
        "max_ms": round(float(dt.max()), 3),
        "std_ms": round(float(dt.std()), 3),
        "abs_dev_p95_ms": round(float(np.percentile(np.abs(dt - period), 95)), 3),
    }


def arm(w: FifoJoystick, log_path: Path, tries: int = 5) -> None:
    """Chord with sticks centred and throttle low until MANUAL_CONTROL reaches the SITL."""
    for _ in range(tries):
        w.buttons_to({6: False, 7: False})
        time.sleep(0.3)
        w.buttons_to({6: True, 7: True})
        try:
            wait_for(lambda: manual(read_log(log_path)), 3.0, "the first MANUAL_CONTROL")
            w.set_axes(a3=0)  # throttle to the middle at once: z = 500 holds altitude
            w.buttons_to({6: False, 7: False})
            return
        except AssertionError:
            continue
    raise AssertionError("the pilot never armed (see live's stderr)")


def envelopes(rec_path: Path, topic: str) -> list:
    """Decoded bus messages of one (non-raw) topic of a recording, in log-time order."""
    with open_recording(rec_path) as rec:
        assert not rec.truncated
        return [decode(unpack_frames(m.data)) for m in rec.messages(topics=[topic])]


def poses(rec_path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(t_ns (n,), position (n, 3) m) of the valid mocap poses in the recording."""
    t, p = [], []
    for env in envelopes(rec_path, "samples.pose"):
        if env.payload.get("valid", True):
            t.append(env.header.recv_ns)
            p.append(np.asarray(env.arrays["position_m"], float))
    return np.asarray(t, np.int64), np.asarray(p)


def pose_at(t: np.ndarray, p: np.ndarray, t_ns: int) -> np.ndarray:
    i = int(np.searchsorted(t, t_ns))
    assert 0 < i < len(t), "no pose around that time"
    return p[i]


def test_joystick_flies_the_sitl_at_a_fixed_rate_and_silence_lets_its_failsafe_act(tmp_path):
    link_port, mocap_port = free_udp_port(), free_udp_port()
    cmd_log, rec_path = tmp_path / "commands.jsonl", tmp_path / "live.mcap"
    cal = write_calibration(tmp_path / "joystick.toml")
    fifo = tmp_path / "js0"
    os.mkfifo(fifo)
    sitl = start(
        ["sitl", "--scene", "wall", "--link", f"udp://127.0.0.1:{link_port}",
         "--mocap", f"udp://127.0.0.1:{mocap_port}", "--pilot", "manual", "--mocap-drop", "0",
         "--gust-rate", "0", "--log-commands", str(cmd_log)],
        tmp_path / "sitl.out", tmp_path / "sitl.err",
    )  # fmt: skip
    live = start(
        ["live", "--link", f"udp://127.0.0.1:{link_port}?mode=listen",
         "--mocap", f"natnet://127.0.0.1:{mocap_port}", "--joystick", str(fifo),
         "--record", str(rec_path), "--no-viewer", "--no-mapping",
         "--summary", str(tmp_path / "summary.json"),
         "--set", f"pilot.device_name={PAD}", "--set", f"pilot.calibration_path={cal}",
         "--set", f"pilot.rate_hz={RATE_HZ}"],
        tmp_path / "live.out", tmp_path / "live.err",
    )  # fmt: skip
    w = FifoJoystick(str(fifo), n_axes=4, n_buttons=8)
    w.axes[3] = FULL  # throttle low (the axis is reversed)
    try:
        w.open(timeout=60)  # blocks until the pilot process opens the FIFO
        w.start_heartbeat(0.01)
        arm(w, cmd_log)
        time.sleep(1.5)  # hover, sticks centred
        t_go = time.monotonic_ns()
        w.set_axes(a1=-FULL // 2, a3=-FULL // 4)  # half forward, gentle climb
        time.sleep(2.0)
        w.set_axes(a1=0, a3=0)
        t_end = time.monotonic_ns()
        time.sleep(1.0)
        n_before = len(manual(read_log(cmd_log)))
        last_write = w.stop_heartbeat()  # the FIFO stays open and says nothing more
        wait_for(lambda: "HOLD" in modes(read_log(cmd_log))[2:], 20, "the SITL's HOLD failsafe")
        wait_for(lambda: "LAND" in modes(read_log(cmd_log)), 20, "the SITL's LAND failsafe")
    finally:
        w.close()
        live_rc = stop(live)
        sitl_rc = stop(sitl, signal.SIGTERM)
    err = (tmp_path / "live.err").read_text()
    assert live_rc == 0, err[-3000:]
    assert sitl_rc == 0

    log = read_log(cmd_log)
    cmds = manual(log)
    # 1. silence -> MANUAL_CONTROL stops within the 200 ms stale window (+ loose slack)
    after = [c for c in cmds if c["t_ns"] > last_write]
    assert len(after) <= math.ceil(STALE_S * RATE_HZ) + 3, len(after)
    assert len(cmds) - n_before <= math.ceil(STALE_S * RATE_HZ) + 3
    # 2. then the SITL's own failsafe: MANUAL -> HOLD -> LAND, after the last command
    seq = modes(log)
    assert seq[:2] == ["HOLD", "MANUAL"] and seq[2:4] == ["HOLD", "LAND"], seq
    hold = [r for r in log if r["kind"] == "mode"][2]
    assert hold["sim_t"] > cmds[-1]["sim_t"]
    # 3. fixed send rate on the wire: median period and count over the armed span
    stats = jitter([c["t_ns"] for c in cmds], RATE_HZ)
    span_s = (cmds[-1]["t_ns"] - cmds[0]["t_ns"]) / 1e9
    assert 0.8 * 40.0 <= stats["median_ms"] <= 1.25 * 40.0, stats
    assert 0.7 * RATE_HZ * span_s <= len(cmds) <= 1.05 * RATE_HZ * span_s + 2, (len(cmds), span_s)
    # 4. the vehicle followed the sticks: forward (+x, heading 0) and up
    t, p = poses(rec_path)
    d = pose_at(t, p, t_end) - pose_at(t, p, t_go)
    assert d[0] > 0.5 and d[2] > 0.1 and abs(d[1]) < 0.5 * d[0], d
    still = pose_at(t, p, t_go) - pose_at(t, p, t_go - 1_000_000_000)
    assert np.linalg.norm(still) < 0.3, still  # centred sticks held position
    # 5. every command and pilot event is in the recording; each became one MANUAL_CONTROL
    summary = json.loads((tmp_path / "summary.json").read_text())
    counts = summary["recording"]["topic_counts"]
    # (a command the pilot sent before the listening link had heard the vehicle went nowhere:
    # counted as unsent, not as sent)
    stale, unsent = summary["manual_control_stale_dropped"], summary["manual_control_unsent"]
    dropped = (stale or 0) + (unsent or 0)
    assert counts["pilot.command"] - dropped == len(cmds), summary
    assert summary["manual_control_sent"] == len(cmds)
    assert counts["raw.pilot"] > 0 and summary["gaps_monitor"] == 0
    kinds = [e.payload["event"] for e in envelopes(rec_path, "pilot.event")]
    assert "armed" in kinds and kinds.count("failsafe") >= 1, kinds
    assert "JOYSTICK INPUT STALE" in err
    print(f"\nMANUAL_CONTROL at the SITL ({RATE_HZ:g} Hz): {stats}; after silence {len(after)}")
