"""``groundstation view --headless`` against a real bus publisher: PNG and PLY files per mesh.

A real :class:`Publisher` (tcp loopback) plays the mapper, detector and mocap; the viewer runs
as ``python -m groundstation.cli view ...`` in a subprocess (and in-process for --every).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from matplotlib.image import imread

from groundstation.bus.pubsub import Publisher
from groundstation.runtime.workers.viewer import VIEW_TOPICS, ViewerProcess
from groundstation.viewer.headless import HeadlessSink
from tests.unit.viewer.sphere import circle_pose, contact_points, sphere_mesh

pytestmark = pytest.mark.timeout(180)
ROOT = Path(__file__).resolve().parents[2]


def publish_mesh(pub: Publisher, fit: int, radius: float = 0.6, bad: bool = False) -> int:
    m = sphere_mesh(radius)
    tri = m.faces.copy()
    if bad:
        tri[0, 0] = m.vertices.shape[0] + 5  # passes the bus schema, fails the viewer's check
    pub.publish(
        "mesh",
        {"fit_index": fit},
        {"vertices": m.vertices, "triangles": tri, "vertex_std": m.std},
    )
    return m.vertices.shape[0]


def publish_fit(pub: Publisher, n_obs: int, fit: int) -> None:
    ids = np.arange(n_obs, dtype=np.int64)
    pub.publish(
        "mapper.fit",
        {"fit_index": fit},
        {"ids": ids, "u": np.ones(n_obs), "flags": (ids % 5 == 0).astype(np.uint8)},
    )


def publish_state(pub: Publisher, n_obs: int, fit: int, poses: range) -> None:
    for i, x in enumerate(contact_points(n_obs)):
        pub.publish(
            "observations", {"id": i, "label": 0}, {"x_m": x, "normal": np.array([0, 0, 1.0])}
        )
    publish_fit(pub, n_obs, fit)
    for k in poses:
        t, p, q = circle_pose(k)
        pub.publish("samples.pose", {"body_id": 1, "valid": True}, {"position_m": p, "q_wxyz": q},
                    source_ns=t)  # fmt: skip


def wait_for(path: Path, proc: subprocess.Popen, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not path.exists():
        if proc.poll() is not None:
            pytest.fail(f"viewer exited early ({proc.returncode}): {proc.stderr.read()[-3000:]}")
        if time.monotonic() > deadline:
            pytest.fail(f"{path.name} not written within {timeout_s} s")
        time.sleep(0.05)


def test_view_headless_subprocess_writes_snapshots_and_plys(tmp_path, zctx):
    import open3d as o3d

    out = tmp_path / "view"
    with Publisher(topics=VIEW_TOPICS, context=zctx, linger_ms=0) as pub:
        cmd = [
            sys.executable, "-m", "groundstation.cli", "view",
            "--connect", ",".join(pub.endpoints), "--headless", "--out", str(out),
            "--width", "480", "--height", "360",
        ]  # fmt: skip
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        env.pop("DISPLAY", None)
        proc = subprocess.Popen(
            cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
        )
        try:
            pub.wait_for_subscribers(1, timeout_s=60)
            publish_state(pub, 30, fit=1, poses=range(0, 100))
            n_vertices = publish_mesh(pub, fit=1)
            wait_for(out / "snapshot_000001.png", proc)
            publish_state(pub, 40, fit=2, poses=range(100, 200))
            publish_mesh(pub, fit=99, bad=True)  # skipped and counted, never drawn
            publish_mesh(pub, fit=2, radius=0.7)
            wait_for(out / "snapshot_000002.png", proc)
            proc.send_signal(signal.SIGINT)
            _, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    assert proc.returncode == 0, err[-3000:]
    assert "skipping bad mesh message" in err
    assert "1 bad" in err and "2 snapshot sets" in err
    assert sorted(p.name for p in out.iterdir()) == [
        "mesh_000001.ply", "mesh_000002.ply", "points_000001.ply", "points_000002.ply",
        "snapshot_000001.png", "snapshot_000002.png",
    ]  # fmt: skip
    mesh = o3d.io.read_triangle_mesh(str(out / "mesh_000001.ply"))
    assert len(mesh.vertices) == n_vertices and mesh.has_vertex_colors()
    assert len(o3d.io.read_point_cloud(str(out / "points_000002.ply")).points) == 40
    for fit in (1, 2):
        img = imread(str(out / f"snapshot_00000{fit}.png"))[..., :3]
        assert img.shape == (360, 480, 3)
        assert float(np.ptp(img)) > 0.5


def test_every_nth_mesh_and_the_latest_on_exit(tmp_path, zctx):
    with Publisher(topics=VIEW_TOPICS, context=zctx, linger_ms=0) as pub:
        sink = HeadlessSink(tmp_path, width=240, height=180, backend="matplotlib")
        proc = ViewerProcess(pub.endpoints, sink, every=3, context=zctx, log=lambda s: None)
        pub.wait_for_subscribers(1, timeout_s=10)
        publish_state(pub, 10, fit=1, poses=range(10))
        for fit in range(1, 6):
            publish_mesh(pub, fit)
            publish_fit(pub, 10, fit)  # after its mesh, as the mapper publishes them
            # one mesh at a time, as a mapper does (the mesh topic keeps only a few)
            while proc.model.meshes_received < fit or proc.settling:
                assert proc.step()
        proc.stop = True
        assert proc.run() == 0  # flushes the latest mesh skipped by --every
    pngs = sorted(p.name for p in tmp_path.glob("snapshot_*.png"))
    assert pngs == ["snapshot_000001.png", "snapshot_000004.png", "snapshot_000005.png"]
    assert proc.snapshots == 3 and proc.bad_messages == 0


def test_a_snapshot_waits_for_its_fit_and_points_then_settles(tmp_path, zctx):
    """The mapper publishes a mesh before its fit, and points come on other sockets: the files
    for a mesh wait (up to ``settle_s``) until that fit and its points are in."""
    import open3d as o3d

    now = [0]
    with Publisher(topics=VIEW_TOPICS, context=zctx, linger_ms=0) as pub:
        sink = HeadlessSink(tmp_path, width=200, height=150, backend="matplotlib")
        proc = ViewerProcess(
            pub.endpoints, sink, context=zctx, log=lambda s: None, settle_s=1.0,
            clock=lambda: now[0],
        )  # fmt: skip
        pub.wait_for_subscribers(1, timeout_s=10)
        publish_mesh(pub, fit=1)
        while proc.model.meshes_received < 1:
            assert proc.step()
        for _ in range(5):
            assert proc.step()
        assert proc.snapshots == 0  # the fit and its points are not in yet
        publish_state(pub, 25, fit=1, poses=range(10))
        while proc.snapshots == 0:
            assert proc.step()
        assert proc.model.fit_index == 1
        points = o3d.io.read_point_cloud(str(tmp_path / "points_000001.ply")).points
        assert len(points) == 25
        # a fit that never comes: the files are written once settle_s has passed
        publish_mesh(pub, fit=2)
        while proc.model.meshes_received < 2:
            assert proc.step()
        assert proc.step() and proc.snapshots == 1
        now[0] += 1_000_000_001
        assert proc.step() and proc.snapshots == 2
        proc.stop = True
        assert proc.run() == 0
    assert proc.snapshots == 2  # nothing written twice on exit


@pytest.mark.timeout(60)
def test_sink_failures_are_logged_and_survived_or_end_the_viewer_alone(tmp_path, zctx):
    import shutil

    import open3d as o3d

    from groundstation.viewer.window import WindowSink

    logs: list[str] = []
    out = tmp_path / "gone"
    with Publisher(topics=VIEW_TOPICS, context=zctx, linger_ms=0) as pub:
        # headless: the output folder disappears -> logged, the loop goes on, later meshes land
        sink = HeadlessSink(out, width=200, height=150, backend="matplotlib")
        proc = ViewerProcess(
            pub.endpoints, sink, context=zctx, log=logs.append, max_snapshots=1, settle_s=0
        )
        pub.wait_for_subscribers(1, timeout_s=10)
        shutil.rmtree(out)
        publish_mesh(pub, fit=1)
        while proc.model.meshes_received < 1:
            assert proc.step()
        assert proc.snapshots == 0 and proc.sink_failures == 1
        assert any("could not write files" in m and "is missing" in m for m in logs)
        out.mkdir()
        publish_mesh(pub, fit=2)
        assert proc.run() == 0  # stops at max_snapshots=1
        assert proc.snapshots == 1 and (out / "snapshot_000002.png").exists()
        # no observations yet: an empty (but valid) points file keeps the file set uniform
        assert len(o3d.io.read_point_cloud(str(out / "points_000002.ply")).points) == 0

        # window: a destroyed window fails every frame -> the viewer gives up alone (status 1)
        win = WindowSink(width=120, height=90, visible=False)
        win.close()
        logs.clear()
        proc = ViewerProcess(
            pub.endpoints, win, context=zctx, log=logs.append, fps=200, max_sink_failures=3
        )
        assert proc.run() == 1
        assert sum("frame failed" in m for m in logs) == 3
        assert "giving up after 3 failed frames" in logs[-1]
