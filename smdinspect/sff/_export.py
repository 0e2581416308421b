"""Writers of a reconstruction: TIFF maps, previews, point cloud, mesh, summary.

Every file is written atomically (temporary file + rename). Open3D, trimesh and
matplotlib are imported inside the functions that need them.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, Callable, Collection

import numpy as np

from .. import _atomic
from ..errors import InputError
from ._surface import Surface, _unit_rgb, pixel_to_xy_mm

__all__ = [
    "RECONSTRUCTION_OUTPUTS",
    "height_field_mesh",
    "render_height_png",
    "render_view3d_png",
    "surface_point_cloud",
    "write_point_cloud",
    "write_reconstruction",
]

log = logging.getLogger(__name__)

MESH_MAX_SIDE = 384  # the exported height-field mesh is at most this many vertices a side

#: Every file :func:`write_reconstruction` may write.
RECONSTRUCTION_OUTPUTS = (
    "height_mm.tiff", "confidence.tiff", "sigma_mm.tiff", "aif.png", "height_filled_mm.tiff",
    "sigma_filled_mm.tiff", "filled.png", "field.png", "height.png", "view3d.png", "cloud.ply",
    "mesh.ply", "mesh.stl", "summary.json",
)


def _require(module: str):
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:  # pragma: no cover - depends on the machine
        raise InputError(
            f"{module} is needed for this output but cannot be imported ({exc}); "
            "run scripts/setup.sh (on Debian, open3d also needs the libusb-1.0-0 package)"
        ) from None


def surface_point_cloud(surface: Surface, *, keep_unreliable: bool = False):
    """An ``open3d.t.geometry.PointCloud`` of the surface (mm, colour, confidence)."""
    o3d = _require("open3d")
    xyz, rgb, conf, _ = surface.points(keep_unreliable=keep_unreliable)
    pcd = o3d.t.geometry.PointCloud()
    pcd.point.positions = o3d.core.Tensor(xyz.astype(np.float32))
    pcd.point.colors = o3d.core.Tensor(np.round(rgb * 255).astype(np.uint8))
    pcd.point.confidence = o3d.core.Tensor(conf.astype(np.float32)[:, None])
    return pcd


def write_point_cloud(surface: Surface, path: str | Path, *, keep_unreliable: bool = False) -> Path:
    """Write ``cloud.ply``: binary little-endian PLY with float x, y, z (mm), uchar
    red/green/blue and float confidence per vertex (read by Open3D, trimesh, MeshLab,
    CloudCompare). Written with plyfile: importing Open3D only to write would cost more
    than the write."""
    plyfile = _require("plyfile")
    xyz, rgb, conf, _ = surface.points(keep_unreliable=keep_unreliable)
    vertex = np.empty(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"),
                                       ("green", "u1"), ("blue", "u1"), ("confidence", "<f4")])
    for i, axis in enumerate("xyz"):
        vertex[axis] = xyz[:, i]
    for i, channel in enumerate(("red", "green", "blue")):
        vertex[channel] = np.round(rgb[:, i] * 255)
    vertex["confidence"] = conf
    ply = plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")], byte_order="<")
    with _atomic.atomic_path(path) as tmp:
        ply.write(str(tmp))
    return Path(path)


def height_field_mesh(surface: Surface, *, keep_unreliable: bool = False,
                      max_side: int = MESH_MAX_SIDE, dense: bool = True):
    """Triangulate the height map as a ``trimesh.Trimesh`` (mm, vertex colours).

    The grid is subsampled so neither side exceeds ``max_side`` vertices. With
    ``dense`` (default) the mesh is the dense surface (:attr:`Surface.dense`: measured
    heights, edge-aware fill elsewhere) over the field every frame sees; otherwise a
    triangle is kept only if its three vertices are reliable (all, with
    ``keep_unreliable``).
    """
    trimesh = _require("trimesh")
    verts, faces, rgb = _mesh_arrays(surface, keep_unreliable=keep_unreliable,
                                     max_side=max_side, dense=dense)
    return trimesh.Trimesh(vertices=verts, faces=faces,
                           vertex_colors=np.column_stack([rgb, np.full(len(rgb), 255, np.uint8)]),
                           process=False)


def _mesh_arrays(surface: Surface, *, keep_unreliable: bool, max_side: int, dense: bool):
    """(vertices (V, 3) float64 mm, faces (F, 3) int64, colours (V, 3) uint8) of
    :func:`height_field_mesh`, unreferenced vertices removed."""
    h, w = surface.shape
    step = max(1, int(np.ceil(max(h, w) / max_side)))
    rows = np.arange(0, h, step)
    cols = np.arange(0, w, step)
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    x, y = pixel_to_xy_mm(rr, cc, shape=surface.shape, pixel_size_mm=surface.pixel_size_mm)
    z = surface.dense[0] if dense else surface.height_mm
    verts = np.column_stack([np.ravel(x), np.ravel(y), z[rr, cc].ravel().astype(np.float64)])
    if dense:
        keep = surface.field
    else:
        keep = np.ones(surface.shape, bool) if keep_unreliable else surface.reliable
    ok = keep[rr, cc].ravel()
    gh, gw = rr.shape
    idx = np.arange(gh * gw).reshape(gh, gw)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    # y grows upwards (rows downwards), so (a, c, b) is counter-clockwise seen from +z
    faces = np.concatenate([np.column_stack([a, c, b]), np.column_stack([b, c, d])])
    faces = faces[ok[faces].all(axis=1)]
    colours = np.round(_unit_rgb(surface.aif)[rr, cc].reshape(-1, 3) * 255).astype(np.uint8)
    used = np.zeros(len(verts), bool)
    used[faces.ravel()] = True
    remap = np.cumsum(used) - 1
    return verts[used], remap[faces], colours[used]


def write_mesh(surface: Surface, out_dir: str | Path, names: Collection[str] = ("mesh.ply", "mesh.stl"),
               *, keep_unreliable: bool = False) -> int:
    """Write the height-field mesh as ``mesh.ply`` (binary, vertex colours; trimesh) and/or
    ``mesh.stl`` (binary; numpy-stl). Returns the face count.

    trimesh (0.5 s to import) is loaded only for ``mesh.ply``: plyfile writes list
    properties one face at a time (0.77 s for 290 000 faces), numpy-stl has no PLY."""
    verts, faces, rgb = _mesh_arrays(surface, keep_unreliable=keep_unreliable,
                                     max_side=MESH_MAX_SIDE, dense=True)
    out = Path(out_dir)
    if "mesh.ply" in names:
        trimesh = _require("trimesh")
        mesh = trimesh.Trimesh(vertices=verts, faces=faces, process=False,
                               vertex_colors=np.column_stack([rgb, np.full(len(rgb), 255, np.uint8)]))
        with _atomic.atomic_path(out / "mesh.ply") as tmp:
            mesh.export(tmp, file_type="ply")
    if "mesh.stl" in names:
        stl = _require("stl.mesh")
        m = stl.Mesh(np.zeros(len(faces), dtype=stl.Mesh.dtype))
        m.vectors[:] = verts[faces].astype(np.float32)
        m.update_normals()
        with _atomic.atomic_path(out / "mesh.stl") as tmp:
            m.save(str(tmp), mode=_require("stl").Mode.BINARY)
    return int(len(faces))


def _figure(width_in: float, height_in: float, dpi: int = 110):
    _require("matplotlib")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=dpi)
    FigureCanvasAgg(fig)
    return fig


def _save_figure(fig, path: Path) -> Path:
    with _atomic.atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path


def _display_range(surface: Surface) -> tuple[float, float]:
    vals = surface.height_mm[surface.reliable]
    if vals.size < 10:
        vals = surface.height_mm.ravel()
    lo, hi = np.percentile(vals, [0.5, 99.5])
    if hi - lo < 1e-6:
        hi = lo + 1e-3
    return float(lo), float(hi)


def render_height_png(surface: Surface, path: str | Path) -> Path:
    """Colour-mapped heights with a legend in mm; unreliable pixels shown grey."""
    path = Path(path)
    h, w = surface.shape
    lo, hi = _display_range(surface)
    fig = _figure(7.0, 7.0 * h / w + 0.6)
    ax = fig.add_axes([0.02, 0.06, 0.80, 0.88])
    masked = np.ma.masked_where(~surface.reliable, surface.height_mm)
    ax.set_facecolor((0.55, 0.55, 0.55))
    im = ax.imshow(masked, cmap="viridis", vmin=lo, vmax=hi, interpolation="nearest")
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(f"height above board (mm); grey: unreliable ({100 * (1 - surface.coverage):.1f}%)",
                 fontsize=9)
    cax = fig.add_axes([0.85, 0.06, 0.035, 0.88])
    fig.colorbar(im, cax=cax, label="height (mm)")
    if surface.pixel_size_mm:
        bar_mm = _nice(w * surface.pixel_size_mm / 5)
        bar_px = bar_mm / surface.pixel_size_mm
        ax.plot([0.04 * w, 0.04 * w + bar_px], [0.95 * h] * 2, color="white", lw=3)
        ax.text(0.04 * w, 0.93 * h, f"{bar_mm:g} mm", color="white", fontsize=8)
    return _save_figure(fig, path)


def _nice(x: float) -> float:
    e = 10 ** np.floor(np.log10(x))
    for m in (1, 2, 5, 10):
        if m * e >= x:
            return float(m * e)
    return float(10 * e)


def render_view3d_png(surface: Surface, path: str | Path, *, max_side: int = 384,
                      size_px: tuple[int, int] = (1280, 960),
                      z_exaggeration: float | None = None) -> Path:
    """A perspective 3D preview of the textured surface (the picture users look at first).

    Rendered offscreen with VTK by :func:`smdinspect.sff._view3d.render_height_field`:
    the height field as a lit mesh of at most ``max_side`` vertices a side, textured
    with the all-in-focus image, axes in mm, the vertical exaggeration written on it.
    It shows the dense surface (:attr:`Surface.dense`); filled pixels are drawn with
    their colours faded towards grey, pixels outside the field grey.
    """
    from ._view3d import render_height_field

    height, filled, _ = surface.dense
    render_height_field(height, surface.aif, surface.field, pixel_size_mm=surface.pixel_size_mm,
                        out_path=path, size_px=size_px, z_exaggeration=z_exaggeration,
                        filled=filled, max_side=max_side)
    return Path(path)


def write_reconstruction(
    surface: Surface,
    out_dir: str | Path,
    *,
    keep_unreliable: bool = False,
    previews: bool = True,
    extra_summary: dict[str, Any] | None = None,
    outputs: Collection[str] | None = None,
) -> dict[str, Path]:
    """Write the outputs of a reconstruction into ``out_dir`` (all by default).

    Files: ``height_mm.tiff`` (float32, every pixel), ``confidence.tiff`` (float32,
    [0, 1]), ``sigma_mm.tiff`` (float32, fitted focus-peak width σ_F, NaN where the fit
    failed), ``aif.png``, the dense surface ``height_filled_mm.tiff`` (measured heights
    kept, the rest filled) with ``filled.png`` (255 = filled) and its uncertainty
    ``sigma_filled_mm.tiff``, ``field.png`` (255 = seen by every frame), ``height.png``,
    ``view3d.png``, ``cloud.ply`` (measured points only), ``mesh.ply`` and ``mesh.stl``
    (the dense surface over the field) and ``summary.json``.

    When nothing could be measured (no reliable pixel) there is no cloud and no mesh
    (the dense surface would be all fill): ``summary.json`` says ``"measured": false``
    (logged); the maps and previews show what the stack holds.

    ``outputs`` names the files to write (from :data:`RECONSTRUCTION_OUTPUTS`);
    ``summary.json`` is always written.

    Returns
    -------
    dict
        Name → path of every file written.
    """
    t0 = time.perf_counter()
    wanted = set(RECONSTRUCTION_OUTPUTS if outputs is None else outputs) | {"summary.json"}
    unknown = sorted(wanted - set(RECONSTRUCTION_OUTPUTS))
    if unknown:
        raise InputError(f"unknown output {', '.join(unknown)}; choose from "
                         f"{', '.join(RECONSTRUCTION_OUTPUTS)}")
    if not previews:
        wanted -= {"height.png", "view3d.png"}
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}

    def put(name: str, write: Callable[[Path], Any]) -> None:
        if name in wanted:
            write(out / name)
            paths[name] = out / name

    put("height_mm.tiff", lambda p: _atomic.write_tiff(p, surface.height_mm.astype(np.float32)))
    put("confidence.tiff", lambda p: _atomic.write_tiff(p, surface.confidence.astype(np.float32)))
    put("sigma_mm.tiff", lambda p: _atomic.write_tiff(p, surface.sigma_mm.astype(np.float32)))
    put("aif.png", lambda p: _atomic.write_image(p, _png_ready(surface.aif)))
    put("height_filled_mm.tiff", lambda p: _atomic.write_tiff(p, surface.dense[0]))
    put("sigma_filled_mm.tiff", lambda p: _atomic.write_tiff(p, surface.dense[2]))
    put("filled.png", lambda p: _atomic.write_image(p, surface.dense[1].astype(np.uint8) * 255))
    put("field.png", lambda p: _atomic.write_image(p, surface.field.astype(np.uint8) * 255))
    put("height.png", lambda p: render_height_png(surface, p))
    put("view3d.png", lambda p: render_view3d_png(surface, p))
    measured = bool(surface.reliable.any())
    mesh_faces = 0
    if measured:
        put("cloud.ply", lambda p: write_point_cloud(surface, p, keep_unreliable=keep_unreliable))
        names = wanted & {"mesh.ply", "mesh.stl"}
        if names:
            mesh_faces = write_mesh(surface, out, names, keep_unreliable=keep_unreliable)
            paths.update({name: out / name for name in names})
    else:
        log.info("nothing could be measured: no pixel has a reliable focus peak; "
                    "no cloud.ply or mesh written")
    reliable = surface.height_mm[surface.reliable]
    summary = {
        "smdinspect": "reconstruction",
        "pixel_size_mm": surface.pixel_size_mm,
        "xy_units": "mm" if surface.pixel_size_mm else "px",
        "measured": measured,
        "coverage": round(surface.coverage, 4),
        "height_mm": None if reliable.size == 0 else {
            "min": float(reliable.min()), "p01": float(np.percentile(reliable, 1)),
            "median": float(np.median(reliable)), "p99": float(np.percentile(reliable, 99)),
            "max": float(reliable.max()),
        },
        "cloud_points": 0 if not measured else int(surface.reliable.sum() if not keep_unreliable
                                                   else surface.reliable.size),
        "mesh_faces": mesh_faces,
        "keep_unreliable": keep_unreliable,
        **surface.meta,
        **(extra_summary or {}),
    }
    summary["seconds"] = {**summary.get("seconds", {}), "write": round(time.perf_counter() - t0, 3)}
    summary["files"] = sorted(list(paths) + ["summary.json"])
    paths["summary.json"] = _atomic.write_json(out / "summary.json", summary)
    return paths


def _png_ready(image: np.ndarray) -> np.ndarray:
    """uint8/uint16 as they are; float frames (taken as [0, 1]) to 16-bit for the PNG."""
    if image.dtype in (np.uint8, np.uint16):
        return image
    return np.round(np.clip(image, 0.0, 1.0) * 65535).astype(np.uint16)
