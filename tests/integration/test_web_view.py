"""``--viewer rerun`` in a real browser (issue 15): Rerun's web viewer, served by ``replay`` and by
``live`` (against the SITL), opened in headless Chromium (software WebGL/WebGPU): the page
loads, the stream connects and a screenshot shows the mesh (its viridis std colours fill part of
the 3D view). The servers listen on 127.0.0.1 only; the saved ``.rrd`` passes ``rerun rrd
verify``. The live session's recording carries the Foxglove channels, decoded here with
``foxglove_schemas_protobuf`` alone.

Skipped with a message without rerun-sdk (``GS_NO_RERUN=1 ./bootstrap.sh``), Playwright or
Chromium. Waits are polls with generous deadlines; nothing is timed.
"""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests.integration.test_live_smoke import sitl_device, status_lines
from tests.integration.test_open_formats import decode_foxglove
from tests.integration.test_pilot_sitl import free_udp_port, start, stop, wait_for

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.timeout(900)


def _viridis_fraction(png: Path) -> float:
    """Share of the 3D view (left half of the page) drawn in viridis colours (the mesh)."""
    import matplotlib
    from PIL import Image

    img = np.asarray(Image.open(png).convert("RGB"), dtype=np.float32)
    h, w, _ = img.shape
    view = img[int(0.06 * h) : int(0.95 * h), : int(0.55 * w)][::3, ::3].reshape(-1, 3)
    lut = matplotlib.colormaps["viridis"](np.linspace(0, 1, 64))[:, :3] * 255
    d = np.min(np.linalg.norm(view[:, None, :] - lut[None, :, :], axis=2), axis=1)
    return float(np.mean(d < 20))


def _url(path: Path, prefix: str) -> str | None:
    for line in path.read_text().splitlines():
        if line.startswith(prefix):
            return line[len(prefix) :].split()[0]
    return None


def _listening_addresses(pid: int) -> set[str]:
    import psutil

    procs = [psutil.Process(pid), *psutil.Process(pid).children(recursive=True)]
    return {
        c.laddr.ip
        for p in procs
        for c in p.net_connections(kind="tcp")
        if c.status == psutil.CONN_LISTEN
    }


def _screenshot_until_mesh(url: str, png: Path, deadline_s: float) -> float:
    from tests.support.browser import browser_page

    console: list[str] = []
    frac = 0.0
    with browser_page(1280, 800) as page:
        page.on("console", lambda m: console.append(m.text) if m.type == "error" else None)
        page.goto(url)
        end = time.monotonic() + deadline_s
        while time.monotonic() < end:
            page.wait_for_timeout(3000)
            page.screenshot(path=str(png))
            frac = _viridis_fraction(png)
            if frac > 0.01:
                break
        title = page.title()
    assert "rerun" in title.lower(), title
    print(f"\nscreenshot {png}: {frac:.1%} of the 3D view in viridis; console errors: "
          f"{len(console)}")  # fmt: skip
    return frac


ENTITIES = ("world/mesh", "world/contacts", "world/trajectory", "signal/accel_g")


def _rrd_ok(path: Path, entities: tuple[str, ...] = ENTITIES) -> None:
    exe = shutil.which("rerun", path=str(Path(sys.executable).parent)) or "rerun"
    r = subprocess.run([exe, "rrd", "verify", str(path)], capture_output=True, text=True,
                       timeout=120)  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    p = subprocess.run([exe, "rrd", "print", str(path)], capture_output=True, text=True,
                       timeout=120)  # fmt: skip
    for entity in entities:
        assert entity in p.stdout, entity


def test_replay_serves_the_web_viewer_on_loopback_and_the_page_shows_the_mesh(tmp_path):
    pytest.importorskip("rerun", reason="rerun-sdk is not installed (GS_NO_RERUN=1?)")
    from tests.support.browser import chromium_path

    chromium_path()
    rrd = tmp_path / "replay.rrd"
    proc = start(
        ["replay", str(ROOT / "replay_logs/wall_survey.mcap"), "--end", "30", "--quiet",
         "--viewer", "rerun", "--web-port", "0", "--grpc-port", "0", "--serve-s", "600",
         "--rrd", str(rrd)],
        tmp_path / "out", tmp_path / "err",
    )  # fmt: skip
    try:
        url = wait_for(lambda: proc.poll() is None and _url(tmp_path / "err", "replay: serving "),
                       300, "the replay to finish and serve", poll=0.5)  # fmt: skip
        assert url.startswith("http://127.0.0.1:")
        assert _listening_addresses(proc.pid) == {"127.0.0.1"}
        frac = _screenshot_until_mesh(url, tmp_path / "replay_web.png", 300)
        assert frac > 0.01, f"no mesh in the screenshot {tmp_path / 'replay_web.png'}"
    finally:
        rc = stop(proc, signal.SIGINT, timeout=60)
    assert rc == 0, (tmp_path / "err").read_text()[-8000:]
    _rrd_ok(rrd)


@pytest.mark.parametrize(
    ("sig", "ignored_at_start"),
    [(signal.SIGINT, True), (signal.SIGTERM, False)],
    ids=["SIGINT, ignored from birth like a shell's background job", "SIGTERM"],
)
def test_a_serving_replay_stops_on_its_signal_and_closes_the_rrd(tmp_path, sig, ignored_at_start):
    pytest.importorskip("rerun", reason="rerun-sdk is not installed (GS_NO_RERUN=1?)")
    rrd, err = tmp_path / "replay.rrd", tmp_path / "err"
    born = signal.SIG_IGN if ignored_at_start else signal.SIG_DFL
    proc = subprocess.Popen(
        [sys.executable, "-m", "groundstation.cli", "replay",
         str(ROOT / "replay_logs/wall_survey.mcap"), "--end", "15", "--quiet", "--viewer",
         "rerun", "--web-port", "0", "--grpc-port", "0", "--serve-s", "600", "--rrd", str(rrd)],
        cwd=ROOT, stdout=subprocess.DEVNULL, stderr=err.open("w"), stdin=subprocess.DEVNULL,
        preexec_fn=lambda: signal.signal(signal.SIGINT, born),
    )  # fmt: skip
    try:
        wait_for(lambda: proc.poll() is None and _url(err, "replay: serving "), 300,
                 "the replay to finish and serve", poll=0.5)  # fmt: skip
    finally:
        rc = stop(proc, sig, timeout=30)
    assert rc == 0, err.read_text()[-8000:]
    assert f"replay: stopped serving ({sig.name})" in err.read_text()
    _rrd_ok(rrd, ("world/mesh", "world/contacts"))


@pytest.mark.soak  # a few minutes of live session and browser polling
def test_live_web_view_and_the_live_recording_in_foxglove_schemas(tmp_path):
    """``live --viewer rerun --record`` against the SITL until the first meshes: the page shows
    the mesh, and the recording's Foxglove channels decode with the schema library alone."""
    pytest.importorskip("rerun", reason="rerun-sdk is not installed (GS_NO_RERUN=1?)")
    from tests.support.browser import chromium_path

    chromium_path()
    rec_path, rrd = tmp_path / "live.mcap", tmp_path / "live.rrd"
    mport = free_udp_port()
    sitl = start(
        ["sitl", "--scene", "wall", "--pilot", "script:survey", "--duration", "240", "--link",
         "pty", "--mocap", f"udp://127.0.0.1:{mport}"],
        tmp_path / "sitl.out", tmp_path / "sitl.err",
    )  # fmt: skip
    live = None
    try:
        dev = sitl_device(tmp_path / "sitl.out", sitl)
        live = start(
            ["live", "--link", f"serial://{dev}?baud=921600", "--mocap",
             f"natnet://127.0.0.1:{mport}", "--record", str(rec_path), "--viewer", "rerun",
             "--web-port", "0", "--grpc-port", "0", "--rrd", str(rrd)],
            tmp_path / "live.out", tmp_path / "live.err",
        )  # fmt: skip
        url = wait_for(lambda: _url(tmp_path / "live.err", "viewer: Rerun web viewer at "), 120,
                       "the viewer's address", poll=0.5)  # fmt: skip
        assert url.startswith("http://127.0.0.1:")

        def meshes() -> int:
            assert live.poll() is None, (tmp_path / "live.err").read_text()[-3000:]
            lines = status_lines(tmp_path / "live.out")
            return (
                sum("mesh #" in ln for ln in lines[-1:])
                and int(lines[-1].split("mesh #")[1].split()[0]) >= 1
            )

        wait_for(meshes, 200, "a second mesh on the status line", poll=1.0)
        frac = _screenshot_until_mesh(url, tmp_path / "live_web.png", 300)
        assert frac > 0.01, f"no mesh in the screenshot {tmp_path / 'live_web.png'}"
    finally:
        rc = stop(live) if live is not None else -1
        stop(sitl, signal.SIGTERM)
    assert rc == 0, (tmp_path / "live.err").read_text()[-3000:]
    counts = decode_foxglove(rec_path)
    for topic in ("/map/mesh", "/map/contacts", "/vehicle/trajectory", "/vehicle/pose", "/tf",
                  "/detector/signal", "/imu/accel", "/vehicle/attitude", "/log"):  # fmt: skip
        assert sum(counts.get(topic, {}).values()) > 0, (topic, counts)
    from groundstation.acquisition import layout
    from groundstation.acquisition.reader import open_recording

    with open_recording(rec_path) as rec:  # the wall clock of the session, for export tlog
        offset = layout.parse_utc_offset(rec.metadata())
        first = rec.summary.start_ns
    assert abs((first + offset) / 1e9 - time.time()) < 3600, "utc_offset_ns is not wall time"
    _rrd_ok(rrd)
