"""ViewModel / Scene: pure draw data from mesh, fit, observation and pose messages."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from groundstation.errors import ConfigError
from groundstation.mapping.surface import std_colors
from groundstation.viewer.scene import (
    AWAITING,
    FLAGGED,
    PENDING,
    STATE_COLORS,
    TRUSTED,
    ViewerInputError,
    ViewModel,
    ViewSettings,
)
from tests.unit.viewer.sphere import circle_pose, contact_points, populated_model, sphere_mesh


def test_contact_states_follow_fit_flags():
    vm = ViewModel()
    pts = contact_points(6)
    for i, x in enumerate(pts):
        vm.ingest_observation(i, 0, x)
    vm.ingest_observation(100, -1, pts[0] * 0.9)  # internal: never a contact
    # ids 0..3 in the fit: 1 flagged (bit 0), 2 flagged awaiting a second touch (bits 0 and
    # 1), 3 has only bit 1 set (no flag to wait on) -> trusted
    vm.ingest_fit(
        np.array([3, 0, 1, 2, 100]),
        np.array([0.1, 0.1, 9.0, 9.0, 0.1]),
        np.array([0x02, 0, 1, 0x03, 0], dtype=np.uint8),
        fit_index=7,
    )
    sc = vm.scene()
    assert sc.contacts_xyz.shape == (6, 3)
    np.testing.assert_array_equal(sc.contacts_xyz, pts)
    want = [TRUSTED, FLAGGED, AWAITING, TRUSTED, PENDING, PENDING]
    np.testing.assert_array_equal(sc.contact_state, want)
    np.testing.assert_array_equal(sc.contacts_rgb, STATE_COLORS[want])
    assert len({tuple(c) for c in STATE_COLORS}) == 4
    assert sc.counts["flagged"] == 2 and sc.counts["awaiting"] == 1
    assert sc.counts["pending"] == 2 and sc.counts["trusted"] == 2
    assert "2 flagged (1 awaiting a second touch), 2 pending" in sc.caption
    # a newer fit supersedes the old one
    vm.ingest_fit(np.arange(6), np.ones(6), np.array([0, 0, 0, 0, 1, 1], np.uint8), fit_index=8)
    np.testing.assert_array_equal(vm.scene().contact_state, [TRUSTED] * 4 + [FLAGGED, FLAGGED])


def test_internal_external_points_only_when_enabled():
    vm = ViewModel(ViewSettings(show_internal=True))
    vm.ingest_observation(1, -1, [0, 0, 1])
    vm.ingest_observation(2, 1, [0, 0, 3])
    vm.ingest_observation(3, 0, [0, 0, 2])
    sc = vm.scene()
    np.testing.assert_array_equal(sc.internal_xyz, [[0, 0, 1]])
    assert sc.external_xyz.shape == (0, 3)
    assert sc.contacts_xyz.shape == (1, 3)
    sc = ViewModel(ViewSettings(show_external=True))
    sc.ingest_observation(2, 1, [0, 0, 3])
    assert sc.scene().external_xyz.shape == (1, 3)


def test_trajectory_keeps_only_the_window_and_resets_on_time_going_back():
    vm = ViewModel(ViewSettings(trajectory_window_s=10.0))
    q = np.array([1.0, 0, 0, 0])
    for k in range(301):  # 30 s at 10 Hz
        vm.ingest_pose(k * 100_000_000, [k * 0.01, 0, 1], q)
    tr = vm.scene().trajectory_xyz
    assert tr.shape == (101, 3)  # t in [20 s, 30 s]
    np.testing.assert_allclose(tr[0], [2.0, 0, 1])
    np.testing.assert_allclose(tr[-1], [3.0, 0, 1])
    assert np.all(np.diff(tr[:, 0]) > 0)  # oldest first
    vm.ingest_pose(5, [9, 9, 9], q)  # new replay: clock restarts
    np.testing.assert_array_equal(vm.scene().trajectory_xyz, [[9, 9, 9]])


def test_trajectory_ring_buffer_bounds_memory():
    vm = ViewModel(ViewSettings(trajectory_window_s=1e6, trajectory_max_points=50))
    for k in range(1000):
        vm.ingest_pose(*circle_pose(k))
    tr = vm.scene().trajectory_xyz
    assert tr.shape == (50, 3)
    np.testing.assert_allclose(tr[-1], circle_pose(999)[1])
    np.testing.assert_allclose(tr[0], circle_pose(950)[1])


def test_invalid_and_nan_poses_are_counted_not_drawn():
    vm = ViewModel()
    assert vm.ingest_pose(0, [0, 0, 1], [1, 0, 0, 0])
    assert not vm.ingest_pose(1, [np.nan, 0, 1], [1, 0, 0, 0])
    assert not vm.ingest_pose(2, [5, 5, 5], [1, 0, 0, 0], valid=False)
    assert not vm.ingest_pose(3, [5, 5, 5], [0, 0, 0, 0])
    assert vm.poses_invalid == 3
    sc = vm.scene()
    np.testing.assert_array_equal(sc.pose_position, [0, 0, 1])
    assert sc.trajectory_xyz.shape == (1, 3)
    with pytest.raises(ViewerInputError, match=r"\(4,\)"):
        vm.ingest_pose(4, [0, 0, 1], [1, 0, 0])


def test_observations_are_capped_and_counted():
    vm = ViewModel(ViewSettings(max_observations=10))
    pts = contact_points(25)
    for i, x in enumerate(pts):
        vm.ingest_observation(i, 0, x)
    sc = vm.scene()
    assert sc.contacts_xyz.shape == (10, 3)
    np.testing.assert_array_equal(sc.contacts_xyz, pts[15:])  # newest kept, oldest first
    assert vm.observations_dropped == 15 and vm.observations_total == 25
    assert sc.counts["observations_dropped"] == 15
    assert "+15 older not kept" in sc.caption
    # the fit refers to ids by value: evicted ids are simply not drawn
    vm.ingest_fit(np.arange(25), np.ones(25), np.ones(25, np.uint8), fit_index=1)
    assert np.all(vm.scene().contact_state == FLAGGED)
    # a repeated id replaces its point instead of adding one
    vm.ingest_observation(24, 0, [7.0, 7.0, 7.0])
    assert vm.observations_total == 25
    np.testing.assert_array_equal(vm.scene().contacts_xyz[-1], [7, 7, 7])


def test_mesh_colours_reuse_the_std_colormap_with_a_legend_range():
    m = sphere_mesh()
    vm = ViewModel()
    vm.ingest_mesh(m.vertices, m.faces, m.std, fit_index=4)
    mesh = vm.scene().mesh
    want, rng = std_colors(m.std)
    np.testing.assert_array_equal(mesh.colors, want)
    assert mesh.std_range == rng == (0.0, pytest.approx(m.std.max()))
    assert mesh.triangles.dtype == np.int32 and mesh.fit_index == 4
    fixed = ViewModel(ViewSettings(std_range=(0.0, 0.1)))
    fixed.ingest_mesh(m.vertices, m.faces, m.std, fit_index=4)
    assert fixed.mesh.std_range == (0.0, 0.1)
    # clipped at the top of the fixed range: every vertex with std >= 0.1 has the top colour
    top = fixed.mesh.colors[m.std >= 0.1]
    assert top.shape[0] > 0 and np.allclose(top, top[0])


@pytest.mark.parametrize(
    ("vertices", "triangles", "std", "match"),
    [
        (np.zeros((3, 2)), np.zeros((1, 3), int), np.zeros(3), "vertices"),
        (np.zeros((3, 3)), np.array([[0, 1, 3]]), np.zeros(3), "triangle indices"),
        (np.full((3, 3), np.nan), np.array([[0, 1, 2]]), np.zeros(3), "non-finite"),
        (np.zeros((3, 3)), np.array([[0, 1, 2]]), np.zeros(4), "vertex_std"),
        (np.zeros((3, 3)), np.array([[0.0, 1, 2]]), np.zeros(3), "int"),
        (np.zeros((3, 3)), np.array([[0, 1, 2]]), np.array([0, np.inf, 0]), "non-finite"),
    ],
)
def test_bad_meshes_are_rejected_with_a_clear_error(vertices, triangles, std, match):
    vm = ViewModel()
    with pytest.raises(ViewerInputError, match=match):
        vm.ingest_mesh(vertices, triangles, std, fit_index=0)
    assert vm.mesh is None and vm.mesh_version == 0


def test_ingest_message_dispatches_and_counts_malformed():
    vm = ViewModel()
    assert vm.ingest_message(
        "samples.pose",
        {"body_id": 1, "valid": True, "t_station_ns": 42},
        {"position_m": np.array([1.0, 2, 3]), "q_wxyz": np.array([1.0, 0, 0, 0])},
        source_ns=7,
    )
    assert vm._traj_t[0] == 42  # the station time axis wins over the mocap clock
    assert not vm.ingest_message("status", {}, {}, source_ns=0)
    with pytest.raises(ViewerInputError, match="observations"):
        vm.ingest_message("observations", {"id": 1}, {"x_m": np.zeros(3)}, source_ns=0)
    with pytest.raises(ViewerInputError):
        vm.ingest_message("observations", {"id": 1, "label": 5}, {"x_m": np.zeros(3)}, source_ns=0)
    assert vm.rejected == {"observations": 2}
    m = sphere_mesh()
    vm.ingest_message(
        "mesh",
        {"fit_index": 9},
        {"vertices": m.vertices, "triangles": m.faces, "vertex_std": m.std},
        source_ns=0,
        recv_ns=1_000_000_000,
    )
    assert vm.mesh.fit_index == 9 and vm.mesh.stamp_ns == 1_000_000_000
    assert "age 2.5 s" in vm.scene(now_ns=3_500_000_000).caption


def test_versions_change_only_with_their_part():
    vm = populated_model()
    a = vm.scene()
    vm.ingest_pose(*circle_pose(500))
    b = vm.scene()
    assert (b.mesh_version, b.points_version) == (a.mesh_version, a.points_version)
    assert b.pose_version == a.pose_version + 1
    assert b.contacts_xyz is a.contacts_xyz  # cached, not rebuilt
    vm.ingest_observation(5000, 0, [0, 0, 0])
    c = vm.scene()
    assert c.points_version > b.points_version and c.mesh_version == b.mesh_version


def test_caption_and_counts():
    sc = populated_model().scene(now_ns=2_000_000_000)
    assert sc.caption.startswith("fit 3 | contacts 0 (0 flagged) | 80 obs")
    assert "contact points 40: 25 trusted, 5 flagged, 10 pending" in sc.caption
    assert "age 2.0 s" in sc.caption and "std 0-" in sc.caption
    assert "no mesh yet" in ViewModel().scene().caption


def test_triad_follows_the_pose_rotation_and_bounds_cover_everything():
    vm = ViewModel(ViewSettings(triad_size_m=0.5))
    assert vm.scene().triad_segments()[0].shape == (0, 3) and vm.scene().bounds() is None
    yaw90 = [np.sqrt(0.5), 0, 0, np.sqrt(0.5)]
    vm.ingest_pose(0, [1, 2, 3], yaw90)
    pts, cols = vm.scene().triad_segments()
    np.testing.assert_allclose(pts[0], [1, 2, 3])
    np.testing.assert_allclose(pts[1], [1, 2.5, 3], atol=1e-12)  # body x -> world +y
    np.testing.assert_allclose(pts[2], [0.5, 2, 3], atol=1e-12)  # body y -> world -x
    np.testing.assert_allclose(pts[3], [1, 2, 3.5], atol=1e-12)
    np.testing.assert_array_equal(cols, np.eye(3))
    vm.ingest_observation(0, 0, [-4, 0, 0])
    lo, hi = vm.scene().bounds()
    np.testing.assert_array_equal(lo, [-4, 0, 0])
    np.testing.assert_array_equal(hi, [1, 2, 3])


@pytest.mark.parametrize(
    "kw",
    [
        {"trajectory_window_s": 0},
        {"max_observations": 1},
        {"trajectory_max_points": 0},
        {"std_range": (1.0, 1.0)},
        {"triad_size_m": float("nan")},
    ],
)
def test_bad_settings_raise_config_error(kw):
    with pytest.raises(ConfigError):
        ViewSettings(**kw)


def test_scene_module_imports_without_open3d_or_zmq():
    code = (
        "import sys, groundstation.viewer.scene; "
        "print(sorted(m for m in ('open3d', 'zmq') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_caption_counts_contacts_as_the_status_line_does():
    """Events begun and the events the fit flags (issue 15): the same numbers that
    ``runtime.status.StatusBoard`` prints as ``contacts N (F flagged)``, whatever the number of
    contact points per event."""
    import numpy as np

    from groundstation.bus.envelope import Envelope, Header
    from groundstation.runtime.status import StatusBoard

    vm = ViewModel()
    board = StatusBoard(0)
    msgs = []
    obs_id = 0
    for ev in range(5):
        msgs.append(("contact.event", {"id": ev, "state": "begin", "peak_g": 2.0}, {
            "position_m": np.zeros(3), "normal": np.array([1.0, 0, 0])}))  # fmt: skip
        for _ in range(3 + ev):  # a different number of points per event
            msgs.append(("observations", {"id": obs_id, "label": 0, "event_id": ev},
                         {"x_m": np.array([1.0, ev, 0.5]), "normal": np.zeros(3)}))  # fmt: skip
            obs_id += 1
        msgs.append(("contact.event", {"id": ev, "state": "end", "peak_g": 3.0}, {
            "position_m": np.zeros(3), "normal": np.array([1.0, 0, 0])}))  # fmt: skip
    ids = np.arange(obs_id)
    flags = np.isin(ids, [0, 1, 2, 9]).astype(np.uint8)  # every point of event 0, one of event 2
    msgs.append(("mapper.fit", {"fit_index": 0, "flagged_events": [0, 2]},
                 {"ids": ids, "u": np.ones(obs_id), "flags": flags}))  # fmt: skip
    for i, (topic, payload, arrays) in enumerate(msgs):
        vm.ingest_message(topic, payload, arrays, source_ns=i)
        board.ingest(Envelope(topic, Header(topic, 1, i, i, i), payload, arrays), i)
    line = board.line(10**9, {})
    assert "contacts 5 (2 flagged)" in line
    assert vm.scene().caption.split(" | ")[1] == "contacts 5 (2 flagged)"
    # without flagged_events in the fit, the events of its flagged points count
    vm.ingest_fit(ids, np.ones(obs_id), flags, fit_index=1)
    assert vm.scene().caption.split(" | ")[1] == "contacts 5 (2 flagged)"
