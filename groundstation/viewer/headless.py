"""Headless sinks: PNG snapshots and PLY files of a :class:`~groundstation.viewer.scene.Scene`.

- PNG, backend ``"open3d"``: the same legacy Visualizer as the window, created offscreen (EGL
  when DISPLAY is unset, STACK.md), captured to a float buffer; matplotlib then overlays the
  caption, the std colour bar and the contact-state legend, keeping the framebuffer size.
- PNG, backend ``"matplotlib"`` (the default of ``groundstation view --headless`` and the only
  one replay snapshots and ``report.html`` use, so live and replay pictures look alike): three
  orthographic projections (top x-y, front x-z, side y-z) with metre axes, a grid and equal
  scales, of the mesh (painter's algorithm, faces shaded by their normal), points, trajectory,
  pose and, when given, the true structure outlined (``outline``: the ``objects`` of a
  ``truth.json`` scene). Also used when offscreen GL is not available (``"auto"`` falls back
  once and says so).
- PLY: ``mesh_<fit>.ply`` (mesh with std vertex colours, via ``mapping.surface.write_ply``) and
  ``points_<fit>.ply`` (observations coloured by contact state).

:func:`render_snapshot` needs no bus: the offline replay calls it with ``ViewModel.scene()``.
"""

from __future__ import annotations

import sys
import textwrap
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, BinaryIO, Literal

import numpy as np

from groundstation.errors import GroundstationError
from groundstation.mapping.surface import STD_COLORMAP, write_ply
from groundstation.viewer.scene import (
    EXTERNAL_COLOR,
    INTERNAL_COLOR,
    STATE_COLORS,
    STATE_NAMES,
    TRAJECTORY_COLOR,
    Scene,
)
from groundstation.viewer.window import BACKGROUND, SceneVisualizer, points_and_colors

Backend = Literal["auto", "open3d", "matplotlib"]
BACKENDS = ("auto", "open3d", "matplotlib")
_DPI = 100


class SnapshotError(GroundstationError, RuntimeError):
    """A snapshot or PLY file could not be produced."""


def _stderr(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# -- PLY ----------
def write_mesh_ply(scene: Scene, path: str | Path) -> Path:
    """Write the scene's mesh with std vertex colours and normals to a binary PLY.

    Raises
    ------
    SnapshotError
        When the scene has no mesh.
    """
    import open3d as o3d

    m = scene.mesh
    if m is None:
        raise SnapshotError(f"no mesh to write to {str(path)!r}", hint="wait for a mesh message")
    g = o3d.geometry.TriangleMesh()
    g.vertices = o3d.utility.Vector3dVector(np.ascontiguousarray(m.vertices))
    g.triangles = o3d.utility.Vector3iVector(np.ascontiguousarray(m.triangles))
    g.vertex_colors = o3d.utility.Vector3dVector(np.ascontiguousarray(m.colors))
    g.compute_vertex_normals()
    return write_ply(g, path)


def write_points_ply(scene: Scene, path: str | Path) -> Path:
    """Write the observation points (coloured by contact state) to a binary PLY."""
    import open3d as o3d

    xyz, rgb = points_and_colors(scene)
    if xyz.shape[0] == 0:  # Open3D refuses to write an empty cloud; the file set stays uniform
        header = (
            "ply\nformat binary_little_endian 1.0\nelement vertex 0\n"
            + "".join(f"property double {a}\n" for a in "xyz")
            + "".join(f"property uchar {c}\n" for c in ("red", "green", "blue"))
            + "end_header\n"
        )
        try:
            Path(path).write_bytes(header.encode("ascii"))
        except OSError as exc:
            raise SnapshotError(f"cannot write {str(path)!r}: {exc}") from exc
        return Path(path)
    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(xyz)
    pc.colors = o3d.utility.Vector3dVector(rgb)
    if not o3d.io.write_point_cloud(str(path), pc, write_ascii=False):
        raise SnapshotError(f"Open3D could not write the points to {str(path)!r}")
    return Path(path)


# -- caption, legend, colour bar ----------
def _figure(width: int, height: int) -> Any:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width / _DPI, height / _DPI), dpi=_DPI, facecolor=BACKGROUND)
    FigureCanvasAgg(fig)
    return fig


def _decorate(
    fig: Any,
    scene: Scene,
    width: int,
    cbar_rect: tuple[float, ...],
    legend_anchor: tuple[float, float] = (0.0, 0.0),
) -> None:
    """Caption (top), contact-state legend and std colour bar."""
    import matplotlib
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.lines import Line2D

    chars = max(40, int(width / 7.2))  # 8 pt monospace at 100 dpi: ~6.7 px per character
    fig.text(
        0.01, 0.995, textwrap.fill(scene.caption, chars), va="top", ha="left", fontsize=8,
        family="monospace", bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none"},
    )  # fmt: skip
    handles = [
        Line2D([], [], ls="", marker="o", color=STATE_COLORS[i], label=STATE_NAMES[i])
        for i in range(len(STATE_NAMES))
    ] + [Line2D([], [], color=TRAJECTORY_COLOR, label="trajectory")]
    for pts, color, name in (
        (scene.internal_xyz, INTERNAL_COLOR, "internal"),
        (scene.external_xyz, EXTERNAL_COLOR, "external"),
    ):
        if pts.shape[0]:
            handles.append(Line2D([], [], ls="", marker="o", color=color, label=name))
    fig.legend(
        handles=handles, loc="lower left", bbox_to_anchor=legend_anchor, fontsize=7, framealpha=0.8
    )
    if scene.mesh is not None:
        lo, hi = scene.mesh.std_range
        cax = fig.add_axes(cbar_rect)
        sm = ScalarMappable(Normalize(lo, hi), matplotlib.colormaps[STD_COLORMAP])
        cb = fig.colorbar(sm, cax=cax)
        cb.set_label("predictive std", fontsize=7)
        cb.ax.tick_params(labelsize=6)


def compose_png(image: np.ndarray, scene: Scene, path: str | Path) -> Path:
    """Save a rendered framebuffer with caption, legend and colour bar; same pixel size.

    Parameters
    ----------
    image : (H, W, 3) float in [0, 1]
    scene : Scene
    path : output PNG
    """
    h, w = image.shape[:2]
    fig = _figure(w, h)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.imshow(np.clip(image, 0, 1), interpolation="nearest")
    ax.set_axis_off()
    _decorate(fig, scene, w, (0.9, 0.25, 0.015, 0.5))
    fig.savefig(str(path), dpi=_DPI)
    return Path(path)


# -- matplotlib fallback ----------
# (name, horizontal axis, vertical axis, depth axis, sign): depth * sign grows towards the viewer.
_VIEWS = (
    ("top (x-y)", 0, 1, 2, +1.0),
    ("front (x-z)", 0, 2, 1, -1.0),
    ("side (y-z)", 1, 2, 0, +1.0),
)


#: Colour of the true structure's outline.
OUTLINE_COLOR = "#d62728"


def _draw_outline(ax: Any, objects: Sequence[Mapping[str, Any]], h: int, v: int) -> bool:
    """Outline truth objects (box min/max; vertical cylinder centre (base)/radius/height;
    sphere centre/radius) in the projection on axes (h, v); True when anything was drawn."""
    from matplotlib.patches import Circle, Rectangle

    style = {"fill": False, "edgecolor": OUTLINE_COLOR, "lw": 1.4, "ls": "--", "zorder": 6}
    drawn = False
    for o in objects:
        kind = o.get("type")
        if kind == "box":
            lo, hi = np.asarray(o["min"], float), np.asarray(o["max"], float)
            ax.add_patch(Rectangle((lo[h], lo[v]), hi[h] - lo[h], hi[v] - lo[v], **style))
        elif kind == "cylinder":
            c, r, ht = np.asarray(o["center"], float), float(o["radius"]), float(o["height"])
            if (h, v) == (0, 1):
                ax.add_patch(Circle((c[0], c[1]), r, **style))
            else:
                ax.add_patch(Rectangle((c[h] - r, c[2]), 2 * r, ht, **style))
        elif kind == "sphere":
            c, r = np.asarray(o["center"], float), float(o["radius"])
            ax.add_patch(Circle((c[h], c[v]), r, **style))
        else:
            continue
        drawn = True
    return drawn


def _draw_projection(ax: Any, scene: Scene, h: int, v: int, d: int, sign: float) -> None:
    from matplotlib.collections import PolyCollection

    m = scene.mesh
    if m is not None and m.triangles.size:
        tri = m.vertices[m.triangles]  # (T, 3, 3)
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        nn = np.linalg.norm(normal, axis=1)
        facing = np.abs(normal[:, d]) / np.where(nn > 0, nn, 1.0)
        depth = sign * tri[:, :, d].mean(axis=1)
        order = np.argsort(depth, kind="stable")  # far first (painter's algorithm)
        shade = (0.45 + 0.55 * facing)[:, None]
        face_rgb = np.clip(m.colors[m.triangles].mean(axis=1) * shade, 0, 1)
        ax.add_collection(
            PolyCollection(
                tri[order][:, :, [h, v]],
                facecolors=face_rgb[order],
                edgecolors="none",
                antialiased=False,
            )  # fmt: skip
        )
    xyz, rgb = points_and_colors(scene)
    if xyz.shape[0]:
        ax.scatter(xyz[:, h], xyz[:, v], s=10, c=rgb, edgecolors="k", linewidths=0.3, zorder=3)
    tr = scene.trajectory_xyz
    if tr.shape[0] > 1:
        ax.plot(tr[:, h], tr[:, v], color=TRAJECTORY_COLOR, lw=1.2, zorder=4)
    pts, cols = scene.triad_segments()
    if pts.shape[0]:
        for i in range(3):
            seg = pts[[0, i + 1]]
            ax.plot(seg[:, h], seg[:, v], color=cols[i], lw=2, zorder=5)
        ax.plot(pts[0, h], pts[0, v], "ko", ms=4, zorder=6)


def _outline_bounds(objects: Sequence[Mapping[str, Any]]) -> tuple[np.ndarray, np.ndarray] | None:
    pts = []
    for o in objects:
        if o.get("type") == "box":
            pts += [o["min"], o["max"]]
        elif o.get("type") in ("cylinder", "sphere"):
            c, r = np.asarray(o["center"], float), float(o["radius"])
            top = c + [0, 0, float(o.get("height", r))]
            pts += [c - [r, r, 0 if "height" in o else r], top + [r, r, 0]]
    if not pts:
        return None
    a = np.asarray(pts, dtype=float)
    return a.min(axis=0), a.max(axis=0)


def draw_views(
    fig: Any,
    scene: Scene,
    rects: Sequence[tuple[float, float, float, float]],
    outline: Sequence[Mapping[str, Any]] = (),
) -> list[Any]:
    """Draw the three projections of ``scene`` into ``fig`` at ``rects`` (figure fractions):
    metre axes, grid, equal scales, everything drawn plus the truth ``outline``."""
    names = "xyz"
    b = scene.bounds()
    ob = _outline_bounds(outline)
    if b is not None and ob is not None:
        b = (np.minimum(b[0], ob[0]), np.maximum(b[1], ob[1]))
    elif b is None:
        b = ob
    axes = []
    for (title, h, v, d, sign), rect in zip(_VIEWS, rects, strict=True):
        ax = fig.add_axes(rect)
        ax.set_facecolor("white")
        ax.grid(True, color="0.85", lw=0.5, zorder=0)
        ax.set_axisbelow(True)
        _draw_projection(ax, scene, h, v, d, sign)
        _draw_outline(ax, outline, h, v)
        ax.set_title(title, fontsize=8)
        ax.set_xlabel(f"{names[h]} (m)", fontsize=7)
        ax.set_ylabel(f"{names[v]} (m)", fontsize=7)
        ax.tick_params(labelsize=6)
        if b is not None:
            lo, hi = b
            pad = 0.05 * max(float(np.max(hi - lo)), 0.2)
            ax.set_xlim(lo[h] - pad, hi[h] + pad)
            ax.set_ylim(lo[v] - pad, hi[v] + pad)
        ax.set_aspect("equal", adjustable="box")
        axes.append(ax)
    return axes


def render_matplotlib(
    scene: Scene,
    path: str | Path | BinaryIO,
    width: int = 960,
    height: int = 720,
    outline: Sequence[Mapping[str, Any]] = (),
) -> Path | BinaryIO:
    """Three orthographic projections of ``scene`` as one PNG of ``width`` x ``height`` pixels
    (a path or a binary file object), the true structure outlined when ``outline`` is given."""
    from matplotlib.lines import Line2D

    fig = _figure(width, height)
    rects = [(0.07, 0.54, 0.38, 0.36), (0.57, 0.54, 0.38, 0.36), (0.07, 0.07, 0.38, 0.36)]
    draw_views(fig, scene, rects, outline)
    _decorate(fig, scene, width, (0.88, 0.08, 0.015, 0.3), legend_anchor=(0.57, 0.08))
    if outline:
        fig.legend(
            handles=[Line2D([], [], color=OUTLINE_COLOR, ls="--", label="true structure")],
            loc="lower left", bbox_to_anchor=(0.57, 0.36), fontsize=7, framealpha=0.8,
        )  # fmt: skip
    fig.savefig(path if not isinstance(path, str) else str(path), dpi=_DPI, format="png")
    return Path(path) if isinstance(path, str | Path) else path


# -- Open3D offscreen ----------
class Open3DSnapshotter:
    """A persistent offscreen legacy Visualizer (EGL without a display) for repeated snapshots.

    Raises
    ------
    ViewerError
        (from :class:`SceneVisualizer`) when no offscreen context can be created.
    """

    def __init__(self, width: int = 960, height: int = 720):
        self.viz = SceneVisualizer("groundstation snapshot", width, height, visible=False)

    def render(self, scene: Scene) -> np.ndarray:
        """(H, W, 3) float32 image of ``scene``, camera fitted to everything drawn."""
        self.viz.update(scene)
        if scene.bounds() is not None:
            self.viz.fit_view(scene)
        img = self.viz.capture()
        if scene.bounds() is not None and float(np.ptp(img)) == 0.0:
            raise SnapshotError(
                "offscreen render came back blank although the scene has geometry",
                hint="offscreen GL is broken here: use --renderer matplotlib",
            )
        return img

    def close(self) -> None:
        self.viz.close()


def render_snapshot(
    scene: Scene,
    path: str | Path,
    *,
    width: int = 960,
    height: int = 720,
    backend: Backend = "auto",
    renderer: Open3DSnapshotter | None = None,
    outline: Sequence[Mapping[str, Any]] = (),
) -> str:
    """Render ``scene`` to a PNG (no bus needed; used by the offline replay).

    Parameters
    ----------
    scene : Scene
        From :meth:`ViewModel.scene`.
    path : str or Path
        Output PNG.
    width, height : int
        Pixels.
    backend : {"auto", "open3d", "matplotlib"}
        ``"auto"`` tries Open3D offscreen and falls back to matplotlib.
    renderer : Open3DSnapshotter, optional
        Reuse an offscreen context (otherwise one is created and closed).
    outline : sequence of dict, optional
        True structure (``truth.json`` scene objects) outlined by the matplotlib views.

    Returns
    -------
    str
        The backend that produced the file.
    """
    if backend not in BACKENDS:
        raise SnapshotError(f"unknown snapshot backend {backend!r}; choose one of {BACKENDS}")
    if backend != "matplotlib":
        own = renderer is None
        try:
            r = renderer or Open3DSnapshotter(width, height)
            try:
                compose_png(r.render(scene), scene, path)
            finally:
                if own:
                    r.close()
            return "open3d"
        except Exception:
            if backend == "open3d":
                raise
    render_matplotlib(scene, path, width, height, outline)
    return "matplotlib"


class HeadlessSink:
    """Writes ``snapshot_<fit>.png``, ``mesh_<fit>.ply`` and ``points_<fit>.ply`` per call.

    Parameters
    ----------
    out_dir : str or Path
        Created if missing.
    width, height : int
        Snapshot size in pixels.
    backend : {"auto", "open3d", "matplotlib"}
        With ``"auto"`` the first Open3D failure switches to matplotlib for good, reported once
        through ``warn``.
    warn : callable
        Receives one-line warnings (default: stderr).
    """

    def __init__(
        self,
        out_dir: str | Path,
        *,
        width: int = 960,
        height: int = 720,
        backend: Backend = "auto",
        warn: Callable[[str], None] = _stderr,
    ):
        if backend not in BACKENDS:
            raise SnapshotError(f"unknown snapshot backend {backend!r}; choose one of {BACKENDS}")
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.width, self.height = int(width), int(height)
        self.backend: str = backend
        self._warn = warn
        self._o3d: Open3DSnapshotter | None = None
        self.written: list[Path] = []

    def _fallback(self, exc: BaseException) -> None:
        self._warn(
            f"viewer: Open3D offscreen rendering failed ({exc}); "
            "writing matplotlib projections instead from now on"
        )
        self.backend = "matplotlib"
        if self._o3d is not None:
            try:
                self._o3d.close()
            except Exception:  # noqa: BLE001 - already broken
                pass
            self._o3d = None

    def write(self, scene: Scene) -> list[Path]:
        """Write the files for the scene's current mesh; returns their paths."""
        if scene.mesh is None:
            return []
        stem = f"{scene.mesh.fit_index:06d}"
        png = self.out_dir / f"snapshot_{stem}.png"
        out = [
            write_mesh_ply(scene, self.out_dir / f"mesh_{stem}.ply"),
            write_points_ply(scene, self.out_dir / f"points_{stem}.ply"),
        ]
        if self.backend != "matplotlib":
            try:
                if self._o3d is None:
                    self._o3d = Open3DSnapshotter(self.width, self.height)
                compose_png(self._o3d.render(scene), scene, png)
            except Exception as exc:
                if self.backend == "open3d":
                    raise
                self._fallback(exc)
        if self.backend == "matplotlib":
            render_matplotlib(scene, png, self.width, self.height)
        out.append(png)
        self.written += out
        return out

    def close(self) -> None:
        if self._o3d is not None:
            self._o3d.close()
            self._o3d = None
