"""SceneVisualizer / WindowSink on the legacy Open3D Visualizer (offscreen: no display here)."""

from __future__ import annotations

import numpy as np
import pytest

from groundstation.viewer.scene import ViewModel
from groundstation.viewer.window import SceneVisualizer, WindowSink
from tests.unit.viewer.sphere import circle_pose, populated_model, sphere_mesh

pytestmark = pytest.mark.timeout(120)


@pytest.fixture
def viz():
    v = SceneVisualizer(width=320, height=240, visible=False)
    yield v
    v.close()


def test_only_changed_parts_are_uploaded(viz):
    vm = populated_model()
    assert viz.update(vm.scene()) == 3  # mesh, points, pose
    assert viz.update(vm.scene()) == 0
    vm.ingest_pose(*circle_pose(300))
    assert viz.update(vm.scene()) == 1
    vm.ingest_observation(999, 0, [0.0, 0.0, 1.6])
    assert viz.update(vm.scene()) == 1
    assert len(viz._points.geometry.points) == 41
    triad = np.asarray(viz._triad.geometry.vertices)
    # the triad moved with the pose: its origin vertex set is centred near the new position
    assert np.linalg.norm(triad.mean(axis=0) - circle_pose(300)[1]) < 0.2


def test_a_new_mesh_replaces_the_old_one_in_the_picture(viz):
    vm = populated_model()
    viz.update(vm.scene())
    before = viz.capture()
    big = sphere_mesh(radius=0.9)
    vm.ingest_mesh(big.vertices, big.faces, big.std, fit_index=5)
    assert viz.update(vm.scene()) == 1
    assert len(viz._mesh.geometry.triangles) == big.faces.shape[0]
    after = viz.capture()
    background = np.all(np.abs(after - before[0, 0]) < 0.02, axis=-1)
    background_before = np.all(np.abs(before - before[0, 0]) < 0.02, axis=-1)
    assert background.sum() < background_before.sum()  # a bigger sphere covers more pixels


def test_window_sink_steps_and_echoes_the_caption():
    lines: list[str] = []
    sink = WindowSink(width=200, height=150, visible=False, caption_every=1, echo=lines.append)
    try:
        vm = ViewModel()
        for _ in range(3):
            assert sink.step(vm.scene())
        assert sink.frames == 3 and lines == [
            "fit - | contacts 0 | 0 obs | contact points 0: 0 trusted, 0 flagged, 0 pending | "
            "no mesh yet"
        ]
        m = sphere_mesh()
        vm.ingest_mesh(m.vertices, m.faces, m.std, fit_index=2)
        assert sink.step(vm.scene())
        assert len(lines) == 2 and "mesh #2" in lines[1]
    finally:
        sink.close()
