"""A viewer never holds the pipeline: stalled (SIGSTOP) or killed (SIGKILL), its publisher keeps
publishing without blocking or errors, and other subscribers keep receiving.

The viewer runs in window mode (``groundstation view``, no ``--headless``) in a subprocess; with
no display the legacy Visualizer draws offscreen through EGL, so the real window loop runs.
"""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from groundstation.bus.pubsub import Publisher, Subscriber
from groundstation.runtime.workers.viewer import VIEW_TOPICS
from tests.integration.test_viewer_headless import publish_mesh, publish_state
from tests.unit.viewer.sphere import circle_pose

pytestmark = pytest.mark.timeout(180)
ROOT = Path(__file__).resolve().parents[2]


def read_until(proc: subprocess.Popen, needle: str, timeout_s: float = 60.0) -> str:
    """Read the viewer's stdout until a line contains ``needle``."""
    seen = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            pytest.fail(f"viewer exited ({proc.returncode}); stdout: {''.join(seen)[-2000:]}")
        ready, _, _ = select.select([proc.stdout], [], [], 0.2)
        if ready:
            line = proc.stdout.readline()
            seen.append(line)
            if needle in line:
                return line
    pytest.fail(f"{needle!r} not printed within {timeout_s} s; stdout: {''.join(seen)[-2000:]}")


def flood(pub: Publisher, n_mesh: int, n_pose: int, first_obs_id: int) -> int:
    """Publish meshes, poses and observations as fast as possible; returns messages sent."""
    sent = 0
    for i in range(n_pose):
        t, p, q = circle_pose(1000 + i)
        pub.publish("samples.pose", {"body_id": 1, "valid": True}, {"position_m": p, "q_wxyz": q},
                    source_ns=t)  # fmt: skip
        pub.publish("observations", {"id": first_obs_id + i, "label": 0},
                    {"x_m": p, "normal": np.array([1.0, 0, 0])})  # fmt: skip
        sent += 2
        if i % (n_pose // n_mesh) == 0:
            publish_mesh(pub, fit=100 + i)
            sent += 1
    return sent


def test_stalled_or_killed_viewer_does_not_affect_the_publisher(zctx):
    with Publisher(topics=VIEW_TOPICS, context=zctx, linger_ms=0) as pub:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        env.pop("DISPLAY", None)
        viewer = subprocess.Popen(
            [sys.executable, "-m", "groundstation.cli", "view", "--connect",
             ",".join(pub.endpoints), "--width", "320", "--height", "240"],
            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
        )  # fmt: skip
        try:
            pub.wait_for_subscribers(1, timeout_s=60)
            publish_state(pub, 20, fit=1, poses=range(50))
            publish_mesh(pub, fit=1)
            read_until(viewer, "mesh #1")  # the window loop drew it (caption echoed)

            # stalled: the viewer reads nothing, the publisher must not notice
            viewer.send_signal(signal.SIGSTOP)
            sent_stalled = flood(pub, n_mesh=50, n_pose=2000, first_obs_id=10_000)
            viewer.send_signal(signal.SIGCONT)
            read_until(viewer, "mesh #")  # and it recovers by itself

            # killed: same, and a new subscriber still gets everything published after it joins
            viewer.kill()
            viewer.wait(timeout=30)
            sent_killed = flood(pub, n_mesh=50, n_pose=2000, first_obs_id=20_000)
            with Subscriber(pub.endpoints, ["samples.pose", "mesh"], context=zctx) as sub:
                pub.wait_for_subscribers(1, topics=["samples.pose", "mesh"], timeout_s=10)
                for k in range(100):
                    t, p, q = circle_pose(k)
                    pub.publish("samples.pose", {"body_id": 1, "valid": True},
                                {"position_m": p, "q_wxyz": q}, source_ns=t)  # fmt: skip
                publish_mesh(pub, fit=7)
                got: list[str] = []
                while (e := sub.recv(2000)) is not None:
                    got.append(e.topic)
                    if got.count("samples.pose") == 100 and "mesh" in got:
                        break
        finally:
            if viewer.poll() is None:
                viewer.kill()
                viewer.wait()
            viewer.stdout.close()
    assert sent_stalled == sent_killed == 4050  # every publish call returned, none raised
    assert got.count("samples.pose") == 100 and got.count("mesh") == 1
    assert sub.gaps == {"samples.pose": 0, "mesh": 0}
