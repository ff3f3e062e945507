"""RerunLogger on bus arrays as they arrive: zero-copy views at any byte offset."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.unit.viewer.sphere import sphere_mesh

pytest.importorskip("rerun", reason="rerun-sdk is not installed (GS_NO_RERUN=1?)")
ROOT = Path(__file__).resolve().parents[3]


def misaligned(a: np.ndarray) -> np.ndarray:
    """A copy of ``a`` that starts one byte into its buffer, as a frame's payload can."""
    raw = bytearray(a.nbytes + 1)
    view = np.frombuffer(memoryview(raw)[1:], dtype=a.dtype).reshape(a.shape)
    view[...] = a
    assert not view.flags.aligned
    return view


def log_misaligned(rrd: str) -> None:
    """Log a mesh and a pose whose arrays are misaligned views to ``rrd`` (run in a child:
    an Arrow panic aborts the process)."""
    import rerun as rr

    from groundstation.viewer.rerun_sink import RerunLogger

    rec = rr.RecordingStream("gs-test")
    rec.save(rrd)
    logger = RerunLogger(rec)
    m = sphere_mesh(0.5)
    arrays = {
        "vertices": misaligned(m.vertices.astype(np.float32)),
        "triangles": misaligned(m.faces.astype(np.int32)),
        "vertex_std": misaligned(m.std.astype(np.float32)),
    }
    logger.ingest("mesh", {"fit_index": 3}, arrays, source_ns=1_000_000_000)
    pose = {"position_m": misaligned(np.array([1.0, 2.0, 3.0])),
            "q_wxyz": misaligned(np.array([1.0, 0.0, 0.0, 0.0]))}  # fmt: skip
    logger.ingest("samples.pose", {"body_id": 1, "valid": True}, pose, source_ns=1_100_000_000)
    logger.finish()
    rec.flush()
    print(f"messages {logger.messages} bad {logger.bad}")


def test_a_mesh_and_a_pose_in_misaligned_buffers_are_logged(tmp_path):
    """Rerun passes numpy buffers to Arrow, which panicked on a misaligned float32 vertex buffer
    and took the live web viewer down at every mesh (it showed none)."""
    rrd = tmp_path / "t.rrd"
    code = (
        "from tests.unit.viewer.test_rerun_logger import log_misaligned\n"
        f"log_misaligned({str(rrd)!r})"
    )
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         timeout=120)  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    assert "messages 2 bad 0" in res.stdout
    assert rrd.stat().st_size > 0
