"""Open3D legacy ``Visualizer`` shell: draws a :class:`~groundstation.viewer.scene.Scene`.

:class:`SceneVisualizer` owns one legacy ``open3d.visualization.Visualizer`` (visible window, or
offscreen through EGL when there is no display, STACK.md) and keeps five geometries in it: the
mesh (vertex colours = std colormap), the observation points (coloured by contact state), the
vehicle's axis triad and its recent trajectory. :meth:`SceneVisualizer.update` re-uploads only the
parts whose version counter changed. The new renderer (``OffscreenRenderer``, ``draw``, ``gui``)
needs Vulkan and is deliberately not used.

:class:`WindowSink` is the interactive sink: the controller (:mod:`process`) calls
:meth:`WindowSink.step` at ~25 Hz from its loop; ``poll_events`` keeps the window responsive, and
a closed window ends the viewer alone. The window runs in the viewer's own process, which only
subscribes to the bus: nothing it does (or a crash) can block or stop the pipeline.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from groundstation.errors import GroundstationError
from groundstation.viewer.scene import TRAJECTORY_COLOR, Scene

#: Camera direction (from the look-at point towards the camera, world frame, z up) for the
#: default view: from the south-east, above.
DEFAULT_FRONT = (0.55, -0.75, 0.55)
BACKGROUND = (0.93, 0.93, 0.95)


class ViewerError(GroundstationError, RuntimeError):
    """The viewer could not open or drive its Open3D window / offscreen context."""


def _o3d() -> Any:
    import open3d as o3d

    return o3d


@dataclasses.dataclass
class _Slot:
    geometry: Any
    added: bool = False
    version: int = -1


class SceneVisualizer:
    """One legacy Open3D Visualizer showing a :class:`Scene`.

    Parameters
    ----------
    title : str
        Window title.
    width, height : int
        Window / offscreen framebuffer size in pixels.
    visible : bool
        False: offscreen (EGL when there is no display).

    Raises
    ------
    ViewerError
        When the window (or EGL context) cannot be created.
    """

    def __init__(
        self,
        title: str = "groundstation",
        width: int = 960,
        height: int = 720,
        visible: bool = True,
    ):
        o3d = _o3d()
        self.width, self.height = int(width), int(height)
        self.vis = o3d.visualization.Visualizer()
        if not self.vis.create_window(
            window_name=title, width=self.width, height=self.height, visible=visible
        ):
            raise ViewerError(
                f"Open3D could not create a {'window' if visible else 'offscreen context'} "
                f"({self.width}x{self.height})",
                hint="install libegl1/libgl1 (STACK.md), or use --headless --renderer matplotlib",
            )
        opt = self.vis.get_render_option()
        opt.background_color = np.asarray(BACKGROUND)
        opt.mesh_show_back_face = True  # marching-cubes surfaces are open at the grid border
        opt.point_size = 7.0
        opt.line_width = 2.0
        self._mesh = _Slot(o3d.geometry.TriangleMesh())
        self._points = _Slot(o3d.geometry.PointCloud())
        self._traj = _Slot(o3d.geometry.LineSet())
        self._triad = _Slot(o3d.geometry.TriangleMesh())
        self._triad_base: np.ndarray | None = None
        self._triad_size = 0.0
        self._view_fitted = False
        self.frames = 0
        self.closed = False

    # -- geometry sync -------------------------------------------------------------------------
    def _show(self, slot: _Slot, nonempty: bool) -> None:
        if slot.added:
            self.vis.update_geometry(slot.geometry)
        elif nonempty:
            self.vis.add_geometry(slot.geometry, reset_bounding_box=not self._view_fitted)
            slot.added = True

    def update(self, scene: Scene) -> int:
        """Upload the parts of ``scene`` that changed since the last call; returns how many."""
        o3d = _o3d()
        V3 = o3d.utility.Vector3dVector
        changed = 0
        if self._mesh.version != scene.mesh_version:
            g = self._mesh.geometry
            m = scene.mesh
            if m is None:
                g.clear()
            else:
                g.vertices = V3(np.ascontiguousarray(m.vertices))
                g.triangles = o3d.utility.Vector3iVector(np.ascontiguousarray(m.triangles))
                g.vertex_colors = V3(np.ascontiguousarray(m.colors))
                g.compute_vertex_normals()
            self._show(self._mesh, m is not None and m.triangles.size > 0)
            self._mesh.version = scene.mesh_version
            changed += 1
        if self._points.version != scene.points_version:
            xyz, rgb = points_and_colors(scene)
            g = self._points.geometry
            g.points, g.colors = V3(xyz), V3(rgb)
            self._show(self._points, xyz.shape[0] > 0)
            self._points.version = scene.points_version
            changed += 1
        if self._traj.version != scene.pose_version:
            tr = scene.trajectory_xyz
            g = self._traj.geometry
            g.points = V3(np.ascontiguousarray(tr))
            n = max(tr.shape[0] - 1, 0)
            g.lines = o3d.utility.Vector2iVector(np.stack([np.arange(n), np.arange(n) + 1], 1))
            g.colors = V3(np.tile(TRAJECTORY_COLOR, (n, 1)))
            self._show(self._traj, n > 0)
            self._update_triad(scene)
            self._traj.version = scene.pose_version
            changed += 1
        if changed and not self._view_fitted and scene.bounds() is not None:
            self.fit_view(scene)
        return changed

    def _update_triad(self, scene: Scene) -> None:
        if scene.pose_position is None or scene.pose_rotation is None:
            return
        o3d = _o3d()
        if self._triad_base is None or self._triad_size != scene.triad_size_m:
            frame = o3d.geometry.TriangleMesh.create_coordinate_frame(size=scene.triad_size_m)
            g = self._triad.geometry
            g.triangles = frame.triangles
            g.vertex_colors = frame.vertex_colors
            self._triad_base = np.asarray(frame.vertices).copy()
            self._triad_size = scene.triad_size_m
        # body -> world: x_w = R x_b + p
        verts = self._triad_base @ scene.pose_rotation.T + scene.pose_position
        self._triad.geometry.vertices = o3d.utility.Vector3dVector(verts)
        self._triad.geometry.compute_vertex_normals()
        self._show(self._triad, True)

    def fit_view(self, scene: Scene, front: tuple[float, float, float] = DEFAULT_FRONT) -> None:
        """Point the camera at everything in ``scene`` from ``front`` (z up)."""
        self.vis.reset_view_point(True)
        b = scene.bounds()
        vc = self.vis.get_view_control()
        if b is not None:
            vc.set_lookat(0.5 * (b[0] + b[1]))
        vc.set_front(np.asarray(front, dtype=float) / np.linalg.norm(front))
        vc.set_up(np.array([0.0, 0.0, 1.0]))
        vc.set_zoom(0.75)
        self._view_fitted = True

    # -- rendering -----------------------------------------------------------------------------
    def render(self) -> bool:
        """Process window events and redraw; False once the user closed the window."""
        alive = bool(self.vis.poll_events())
        self.vis.update_renderer()
        self.frames += 1
        if not alive:
            self.closed = True
        return alive

    def capture(self) -> np.ndarray:
        """Render and return the framebuffer, (height, width, 3) float32 RGB in [0, 1]."""
        return np.asarray(self.vis.capture_screen_float_buffer(do_render=True)).copy()

    def close(self) -> None:
        """Destroy the window / offscreen context (idempotent)."""
        if self.vis is not None:
            try:
                self.vis.destroy_window()
            finally:
                self.vis = None


def points_and_colors(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """Contacts, internal and external points of ``scene`` as one cloud: (n, 3) xyz, (n, 3) RGB."""
    from groundstation.viewer.scene import EXTERNAL_COLOR, INTERNAL_COLOR

    xyz = np.concatenate([scene.contacts_xyz, scene.internal_xyz, scene.external_xyz], axis=0)
    rgb = np.concatenate(
        [
            scene.contacts_rgb,
            np.tile(INTERNAL_COLOR, (scene.internal_xyz.shape[0], 1)),
            np.tile(EXTERNAL_COLOR, (scene.external_xyz.shape[0], 1)),
        ],
        axis=0,
    )
    return np.ascontiguousarray(xyz, dtype=np.float64), np.ascontiguousarray(rgb, dtype=np.float64)


class WindowSink:
    """Interactive sink: an Open3D window refreshed by :meth:`step`.

    The caption (which a legacy window cannot draw) is printed to the terminal when it changes
    (at most every ``caption_every`` frames).
    """

    def __init__(
        self,
        title: str = "groundstation view",
        width: int = 1280,
        height: int = 800,
        *,
        visible: bool = True,
        caption_every: int = 25,
        echo: Any = None,
    ):
        self.viz = SceneVisualizer(title, width, height, visible=visible)
        self.caption_every = max(1, int(caption_every))
        self._echo = echo
        self._last_caption = ""

    def step(self, scene: Scene) -> bool:
        """Upload changes and draw one frame; False once the window was closed."""
        self.viz.update(scene)
        alive = self.viz.render()
        if self._echo is not None and (self.viz.frames - 1) % self.caption_every == 0:
            # strip the age so an idle viewer does not print every second
            stable = scene.caption.split(", age")[0]
            if stable != self._last_caption:
                self._echo(scene.caption)
                self._last_caption = stable
        return alive

    @property
    def frames(self) -> int:
        return self.viz.frames

    def close(self) -> None:
        self.viz.close()
