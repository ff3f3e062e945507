"""Soak (opt-in, ``pytest -m soak``): ``groundstation live`` against ``groundstation sitl``
(pty MAVLink + UDP NatNet) for 10 minutes with the joystick armed the whole time.

Writes the measured numbers to ``GS_SOAK_OUT`` (default ``<tmp>/live_soak.json``) and prints
them: gaps (monitor and recorder), refit time, mesh update interval, contact-to-mesh latency (from
``live --summary``), and the MANUAL_CONTROL inter-arrival jitter at the SITL (``--log-commands``)
overall and while the mapper refits (arrivals inside ``[fit published - refit time, fit
published]`` of any refit in the recording). ``GS_SOAK_S`` changes the length (status lines);
``GS_SOAK_DIR`` keeps the artefacts (recording, logs, SITL command log) in that folder.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import pytest

from groundstation.acquisition.segments import open_session as open_recording
from groundstation.bus.envelope import decode, unpack_frames
from groundstation.runtime.status import refit_seconds
from tests.integration.test_live_smoke import run_live_against_sitl
from tests.integration.test_pilot_sitl import (
    PAD,
    RATE_HZ,
    arm,
    jitter,
    manual,
    read_log,
    write_calibration,
)
from tests.unit.pilot.fifo_joystick import FULL, FifoJoystick

SOAK_S = int(os.environ.get("GS_SOAK_S", "600"))


def refit_windows(rec_path: Path) -> list[tuple[int, int]]:
    """(start, end) ns of every refit: end = log time of its ``mapper.fit`` (or mapper status)."""
    out: dict[tuple, tuple[int, int]] = {}
    with open_recording(rec_path) as rec:
        for m in rec.messages(topics=["mapper.fit", "status"]):
            env = decode(unpack_frames(m.data))
            if env.topic == "status" and env.payload.get("process") != "mapper":
                continue
            s = refit_seconds(env.payload)
            if s is None:
                continue
            key = ("fit", env.payload["fit_index"]) if env.topic == "mapper.fit" else ("st", s)
            out.setdefault(key, (m.log_time_ns - int(s * 1e9), m.log_time_ns))
    return sorted(set(out.values()))


@pytest.mark.soak
@pytest.mark.timeout(SOAK_S * 3 + 600)
def test_live_soak_ten_minutes(tmp_path):
    if os.environ.get("GS_SOAK_DIR"):
        tmp_path = Path(os.environ["GS_SOAK_DIR"])
        tmp_path.mkdir(parents=True, exist_ok=True)
    rec_path, cmd_log = tmp_path / "live.mcap", tmp_path / "commands.jsonl"
    cal = write_calibration(tmp_path / "joystick.toml")
    fifo = tmp_path / "js0"
    os.mkfifo(fifo)
    w = FifoJoystick(str(fifo), n_axes=4, n_buttons=8)
    w.axes[3] = FULL

    def fly() -> None:  # the scripted SITL pilot flies; the joystick stays armed and centred
        w.open(timeout=60)
        w.start_heartbeat(0.01)
        arm(w, cmd_log)

    t0 = time.monotonic()
    try:
        rc, summary, lines, err = run_live_against_sitl(
            tmp_path,
            SOAK_S,
            ["--scene", "wall", "--pilot", "script:survey", "--duration", str(SOAK_S + 120),
             "--log-commands", str(cmd_log)],
            ["--record", str(rec_path), "--no-viewer", "--joystick", str(fifo),
             "--set", f"pilot.device_name={PAD}", "--set", f"pilot.calibration_path={cal}",
             "--set", f"pilot.rate_hz={RATE_HZ}"],
            during=fly,
        )  # fmt: skip
    finally:
        w.close()
    wall_s = time.monotonic() - t0
    cmds = manual(read_log(cmd_log))
    t = np.asarray([c["t_ns"] for c in cmds], np.int64)
    with open_recording(rec_path) as rec:  # the pilot's tick times, as published
        ticks = [
            decode(unpack_frames(m.data)).header.source_ns for m in rec.messages("pilot.command")
        ]
    windows = refit_windows(rec_path)
    in_refit = np.zeros(len(t), bool)
    for a, b in windows:
        in_refit |= (t >= a) & (t <= b)
    # inter-arrival intervals that end inside a refit window
    dt_refit = np.diff(t)[in_refit[1:]] / 1e6
    result = {
        "status_lines": len(lines),
        "wall_s": round(wall_s, 1),
        "gaps_monitor": summary.get("gaps_monitor"),
        "gaps_recorder": summary.get("gaps_recorder"),
        "recorder_latest_dropped": summary.get("recorder_latest_dropped"),
        "monitor_counts": summary.get("counts"),
        "recording": summary.get("recording"),
        "refit_s": summary.get("refit_s"),
        "refit_time_s": summary.get("refit_time_s"),
        "mesh_interval_s": summary.get("mesh_interval_s"),
        "contact_to_mesh_s": summary.get("contact_to_mesh_s"),
        "contacts": summary.get("contacts"),
        "observations": summary.get("observations"),
        "meshes": summary.get("meshes"),
        "manual_control": jitter(t.tolist(), RATE_HZ) if len(t) > 2 else None,
        "pilot_ticks": jitter(ticks, RATE_HZ) if len(ticks) > 2 else None,
        "manual_control_during_refits": {
            "refits": len(windows),
            "intervals": int(dt_refit.size),
            "median_ms": round(float(np.median(dt_refit)), 3) if dt_refit.size else None,
            "p95_ms": round(float(np.percentile(dt_refit, 95)), 3) if dt_refit.size else None,
            "max_ms": round(float(dt_refit.max()), 3) if dt_refit.size else None,
            "std_ms": round(float(dt_refit.std()), 3) if dt_refit.size else None,
        },
        "manual_control_sent": summary.get("manual_control_sent"),
        "manual_control_stale_dropped": summary.get("manual_control_stale_dropped"),
        "pilot_failsafes": summary.get("pilot_failsafes"),  # incl. "no input yet" at start
        "last_line": lines[-1] if lines else None,
    }
    out = Path(os.environ.get("GS_SOAK_OUT", tmp_path / "live_soak.json"))
    out.write_text(json.dumps(result, indent=1) + "\n")
    print("\n" + json.dumps(result, indent=1))
    assert rc == 0, err[-3000:]
    assert summary["recording"]["complete"] is True
    assert summary["gaps_monitor"] == 0 and summary["gaps_recorder"] == 0
    with open_recording(rec_path) as rec:
        kinds = [
            decode(unpack_frames(m.data)).payload["event"] for m in rec.messages("pilot.event")
        ]
    assert "armed" in kinds, kinds
    after_arm = kinds[kinds.index("armed") :]
    assert "failsafe" not in after_arm, kinds  # the heartbeat kept the joystick fresh throughout
    assert result["manual_control"]["n"] > 0.8 * RATE_HZ * (SOAK_S - 30)
    assert 0.8 * 40 <= result["manual_control"]["median_ms"] <= 1.25 * 40
