"""Headless sinks: PNG snapshots (Open3D offscreen / matplotlib) and PLY files."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from matplotlib.image import imread

from groundstation.viewer.headless import (
    HeadlessSink,
    SnapshotError,
    render_snapshot,
    write_mesh_ply,
)
from groundstation.viewer.scene import FLAGGED, STATE_COLORS, ViewModel
from tests.unit.viewer.sphere import circle_pose, contact_points, populated_model, sphere_mesh

pytestmark = pytest.mark.timeout(120)


def _rgb(path) -> np.ndarray:
    img = imread(str(path))
    assert img.dtype == np.float32  # PNG read as floats in [0, 1]
    return img[..., :3]


def _pixels_near(img: np.ndarray, color: np.ndarray, tol: float = 0.06) -> int:
    return int(np.count_nonzero(np.all(np.abs(img - color) < tol, axis=-1)))


def _model_without_fit() -> ViewModel:
    vm = ViewModel()
    for i, x in enumerate(contact_points(40)):
        vm.ingest_observation(i, 0, x)
    for k in range(100):
        vm.ingest_pose(*circle_pose(k))
    m = sphere_mesh()
    vm.ingest_mesh(m.vertices, m.faces, m.std, fit_index=1)
    return vm


@pytest.mark.parametrize("backend", ["open3d", "matplotlib"])
def test_snapshot_has_the_size_asked_and_shows_flagged_contacts(tmp_path, backend):
    path = tmp_path / "flagged.png"
    used = render_snapshot(populated_model().scene(), path, width=640, height=480, backend=backend)
    assert used == backend
    img = _rgb(path)
    assert img.shape == (480, 640, 3)
    assert float(np.ptp(img)) > 0.5  # not one colour
    assert len(np.unique(img.reshape(-1, 3).round(2), axis=0)) > 50  # shaded mesh, not flat
    # the same scene without a fit has no flagged contact: only the legend marker has that colour
    none_path = tmp_path / "pending.png"
    render_snapshot(_model_without_fit().scene(), none_path, width=640, height=480, backend=backend)
    legend_only = _pixels_near(_rgb(none_path), STATE_COLORS[FLAGGED])
    assert 0 < legend_only < 200
    flagged = _pixels_near(img, STATE_COLORS[FLAGGED])
    assert flagged >= legend_only + 20, "flagged contacts are not drawn in their colour"


def test_headless_sink_writes_png_and_ply_that_open3d_reads_back(tmp_path):
    import open3d as o3d

    vm = populated_model()
    sink = HeadlessSink(tmp_path / "out", width=320, height=240, backend="auto")
    try:
        files = sink.write(vm.scene())
    finally:
        sink.close()
    names = sorted(p.name for p in files)
    assert names == ["mesh_000003.ply", "points_000003.ply", "snapshot_000003.png"]
    assert sink.backend == "auto"  # EGL worked: no fallback
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "out" / "mesh_000003.ply"))
    sm = vm.mesh
    assert len(mesh.vertices) == sm.vertices.shape[0]
    assert len(mesh.triangles) == sm.triangles.shape[0]
    np.testing.assert_allclose(np.asarray(mesh.vertices), sm.vertices, atol=1e-6)
    np.testing.assert_allclose(np.asarray(mesh.vertex_colors), sm.colors, atol=1 / 255)
    pc = o3d.io.read_point_cloud(str(tmp_path / "out" / "points_000003.ply"))
    assert len(pc.points) == 40  # contacts only (internal points are off by default)
    assert _rgb(tmp_path / "out" / "snapshot_000003.png").shape == (240, 320, 3)


def test_forced_matplotlib_backend(tmp_path):
    sink = HeadlessSink(tmp_path, width=400, height=300, backend="matplotlib")
    files = sink.write(populated_model().scene())
    sink.close()
    assert sink._o3d is None  # Open3D offscreen never created
    png = [p for p in files if p.suffix == ".png"][0]
    img = _rgb(png)
    assert img.shape == (300, 400, 3) and float(np.ptp(img)) > 0.5


def test_no_mesh_no_files_and_clear_errors(tmp_path):
    sink = HeadlessSink(tmp_path, backend="matplotlib")
    assert sink.write(ViewModel().scene()) == []
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(SnapshotError, match="no mesh"):
        write_mesh_ply(ViewModel().scene(), tmp_path / "x.ply")
    with pytest.raises(SnapshotError, match="backend"):
        HeadlessSink(tmp_path, backend="vulkan")  # type: ignore[arg-type]
    with pytest.raises(SnapshotError, match="backend"):
        render_snapshot(ViewModel().scene(), tmp_path / "x.png", backend="gui")  # type: ignore[arg-type]


def test_auto_falls_back_to_matplotlib_once_when_egl_is_missing(tmp_path):
    """A real EGL failure: libglvnd pointed at no vendor library (in a child process)."""
    code = textwrap.dedent(
        f"""
        import sys
        sys.path.insert(0, {os.getcwd()!r})
        from groundstation.viewer.headless import HeadlessSink
        from tests.unit.viewer.sphere import populated_model
        warnings = []
        sink = HeadlessSink({str(tmp_path)!r}, width=320, height=240, warn=warnings.append)
        vm = populated_model()
        sink.write(vm.scene())
        m = vm.mesh
        vm.ingest_mesh(m.vertices, m.triangles, m.std, fit_index=4)
        sink.write(vm.scene())
        print(sink.backend, len(warnings))
        """
    )
    env = dict(os.environ, __EGL_VENDOR_LIBRARY_FILENAMES="/nonexistent/egl_vendor.json")
    env.pop("DISPLAY", None)
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split()[-2:] == ["matplotlib", "1"]  # fell back, said so once
    for fit in (3, 4):
        img = _rgb(tmp_path / f"snapshot_00000{fit}.png")
        assert img.shape == (240, 320, 3) and float(np.ptp(img)) > 0.5
