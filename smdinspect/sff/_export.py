"""Writers of a reconstruction: TIFF maps, previews, point cloud, mesh, summary.

Every file is written atomically (temporary file + rename). Open3D, trimesh and VTK
are imported inside the functions that need them; ``smdinspect reconstruct`` imports
neither Open3D, trimesh nor matplotlib (the PLY files are written with plyfile and
numpy, ``height.png`` is drawn with OpenCV).
"""

from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable, Collection

import numpy as np

from .. import _atomic
from .._malloc import release_free_memory
from ..errors import InputError
from ._reasonpng import render_reason_map
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
    "height_mm.tiff", "confidence.tiff", "sigma_mm.tiff", "precision_mm.tiff", "aif.png",
    "height_filled_mm.tiff",
    "sigma_filled_mm.tiff", "filled.png", "field.png", "height.png", "reason.png", "view3d.png",
    "cloud.ply", "mesh.ply", "mesh.stl", "summary.json",
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


#: Maps larger than this (pixels) are written by one thread (see write_reconstruction).
SERIAL_WRITE_PIXELS = 8_000_000
#: Points of ``cloud.ply`` built at a time.
CLOUD_CHUNK = 1 << 20


#: The error of a cloud asked for both extra kinds of points.
CLOUD_EXCLUSIVE = ("cloud.ply holds either the unreliable readings (--keep-unreliable) or "
                   "the filled surface (--cloud-filled), not both")


def check_cloud_options(keep_unreliable: bool, cloud_filled: bool) -> None:
    """InputError (:data:`CLOUD_EXCLUSIVE`) when both extra kinds of cloud points are
    asked for; commands call it before any work."""
    if keep_unreliable and cloud_filled:
        raise InputError(CLOUD_EXCLUSIVE)


def write_point_cloud(surface: Surface, path: str | Path, *, keep_unreliable: bool = False,
                      filled: bool = False) -> Path:
    """Write ``cloud.ply``: binary little-endian PLY with float x, y, z (mm), uchar
    red/green/blue, float confidence and float precision (the height's 1σ random error
    in mm, NaN where unknown: :attr:`Surface.precision_mm`) per vertex (read by Open3D,
    trimesh, MeshLab, CloudCompare). Written with plyfile: importing Open3D only to write would cost more
    than the write. The points are those of :meth:`Surface.points`, built here straight
    into the file's float32/uint8 record (no float64 or full-image float copies).

    ``filled``: the dense surface's filled points too (:attr:`Surface.dense`, inside the
    field every frame sees), each vertex with a uchar ``filled`` (1: its height was
    filled in, not measured) and a float ``sigma_filled`` (the fill's uncertainty in mm,
    0 where measured); a filled point's confidence is 0 and its precision NaN. Not with
    ``keep_unreliable`` (whose extra points carry their own, unreliable readings)."""
    check_cloud_options(keep_unreliable, filled)
    plyfile = _require("plyfile")
    h, w = surface.shape
    z_plane, conf_plane, fill_flag, fill_sigma = surface.height_mm, surface.confidence, None, None
    keep = _cloud_mask(surface, keep_unreliable, filled)
    index = np.arange(h * w) if keep is None else np.flatnonzero(keep)
    if filled:
        z_plane, _, fill_sigma = surface.dense
        fill_flag = keep & ~surface.reliable  # the fill keeps every measured height
        conf_plane = np.where(fill_flag, np.float32(0), surface.confidence)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"),
              ("blue", "u1"), ("confidence", "<f4"), ("precision", "<f4")]
    if filled:
        fields += [("filled", "u1"), ("sigma_filled", "<f4")]
    vertex = np.empty(len(index), dtype=fields)
    p = 1.0 if surface.pixel_size_mm is None else float(surface.pixel_size_mm)
    planes = [("z", z_plane), ("confidence", conf_plane)]
    if surface.precision_mm is not None:
        planes.append(("precision", surface.precision_mm if fill_flag is None
                       else np.where(fill_flag, np.float32(np.nan), surface.precision_mm)))
    else:
        vertex["precision"] = np.nan
    if filled:
        planes += [("filled", fill_flag), ("sigma_filled", fill_sigma)]
    for a in range(0, len(index), CLOUD_CHUNK):  # chunks: no full-length temporaries
        at = index[a:a + CLOUD_CHUNK]
        part = vertex[a:a + CLOUD_CHUNK]
        rows, cols = np.divmod(at, w)
        part["x"] = cols * p
        part["y"] = (h - 1 - rows) * p
        for name, plane in planes:
            part[name] = plane.ravel()[at]
        rgb = _rgb8(surface.aif, at)
        for i, channel in enumerate(("red", "green", "blue")):
            part[channel] = rgb[:, i]
    del index
    ply = plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")], byte_order="<")
    with _atomic.atomic_path(path) as tmp:
        ply.write(str(tmp))
    return Path(path)


def _rgb8(image: np.ndarray, index: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 colours of the pixels at flat ``index`` of an (H, W) or (H, W, 3)
    image; the same values as ``round(_unit_rgb(image) * 255)``, without converting
    the whole image."""
    img = np.asarray(image)
    flat = img.reshape(-1, 3) if img.ndim == 3 else img.reshape(-1)
    v = flat[index]
    if v.dtype != np.uint8:
        v = np.round(_unit_rgb(v) * 255).astype(np.uint8)
        return v.reshape(-1, 3)
    return v if v.ndim == 2 else np.repeat(v[:, None], 3, axis=1)


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
    colours = _rgb8(surface.aif, (rr * w + cc).ravel())
    used = np.zeros(len(verts), bool)
    used[faces.ravel()] = True
    remap = np.cumsum(used) - 1
    return verts[used], remap[faces], colours[used]


def write_mesh(surface: Surface, out_dir: str | Path, names: Collection[str] = ("mesh.ply", "mesh.stl"),
               *, keep_unreliable: bool = False) -> int:
    """Write the height-field mesh as ``mesh.ply`` (binary little-endian, float x, y, z in
    mm, uchar vertex colours, int triangle indices) and/or ``mesh.stl`` (binary;
    numpy-stl). Returns the face count.

    ``mesh.ply`` is written with numpy in the standard PLY layout (trimesh costs 0.5 s
    to import, plyfile writes list properties one face at a time)."""
    verts, faces, rgb = _mesh_arrays(surface, keep_unreliable=keep_unreliable,
                                     max_side=MESH_MAX_SIDE, dense=True)
    out = Path(out_dir)
    if "mesh.ply" in names:
        write_mesh_ply(out / "mesh.ply", verts, faces, rgb)
    if "mesh.stl" in names:
        stl = _require("stl.mesh")
        m = stl.Mesh(np.zeros(len(faces), dtype=stl.Mesh.dtype))
        m.vectors[:] = verts.astype(np.float32)[faces]
        m.update_normals()
        with _atomic.atomic_path(out / "mesh.stl") as tmp:
            m.save(str(tmp), mode=_require("stl").Mode.BINARY)
    return int(len(faces))


def write_mesh_ply(path: str | Path, vertices: np.ndarray, faces: np.ndarray,
                   rgb: np.ndarray | None = None) -> Path:
    """Write a triangle mesh as binary little-endian PLY, atomically.

    Parameters
    ----------
    vertices : (V, 3) float
        x, y, z in mm (stored as float32).
    faces : (F, 3) int
        Vertex indices of each triangle (stored as ``property list uchar int
        vertex_indices``, the layout trimesh, Open3D and MeshLab read).
    rgb : (V, 3) uint8, optional
        Vertex colours (``red``, ``green``, ``blue``).
    """
    vertices = np.asarray(vertices)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise InputError(f"vertices must be (V, 3); got shape {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise InputError(f"faces must be (F, 3); got shape {faces.shape}")
    if rgb is not None and np.shape(rgb) != (len(vertices), 3):
        raise InputError(f"rgb must be ({len(vertices)}, 3) colours, one per vertex; got shape "
                         f"{np.shape(rgb)}")
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if rgb is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vertex = np.empty(len(vertices), dtype=fields)
    for i, axis in enumerate("xyz"):
        vertex[axis] = vertices[:, i]
    if rgb is not None:
        for i, channel in enumerate(("red", "green", "blue")):
            vertex[channel] = rgb[:, i]
    face = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    face["n"] = 3
    face["v"] = faces
    kinds = {"<f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", "comment smdinspect height-field mesh, mm",
              f"element vertex {len(vertex)}",
              *(f"property {kinds[t]} {name}" for name, t in fields),
              f"element face {len(face)}", "property list uchar int vertex_indices", "end_header"]
    with _atomic.atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(vertex.data)
        fh.write(face.data)
    return Path(path)


def _display_range(surface: Surface) -> tuple[float, float]:
    from ._heightpng import display_range

    return display_range(surface.height_mm, surface.reliable)


def render_height_png(surface: Surface, path: str | Path) -> Path:
    """Write ``height.png``: colour-mapped heights (viridis over the robust range of
    :func:`_display_range`) with a colour bar in mm, a scale bar (mm; pixels when the
    pixel size is unknown) and the unreliable pixels pale grey, their share written on
    it. Drawn with OpenCV (:func:`smdinspect.sff._heightpng.render_height_map`)."""
    from ._heightpng import render_height_map

    image = render_height_map(surface.height_mm, surface.reliable, aif=surface.aif,
                              pixel_size_mm=surface.pixel_size_mm)
    return _atomic.write_image(path, image)


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
    cloud_filled: bool = False,
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
    ``reason.png`` (why heights are unreliable, where: :data:`~smdinspect.sff._surface.UNRELIABLE_REASONS`; only
    when the surface knows its reasons), ``view3d.png``, ``cloud.ply`` (measured points only), ``mesh.ply`` and ``mesh.stl``
    (the dense surface over the field) and ``summary.json``.

    When nothing could be measured (no reliable pixel) there is no cloud and no mesh
    (the dense surface would be all fill): ``summary.json`` says ``"measured": false``
    (logged); the maps and previews show what the stack holds.

    ``outputs`` names the files to write (from :data:`RECONSTRUCTION_OUTPUTS`);
    ``summary.json`` is always written. ``cloud_filled``: ``cloud.ply`` also holds the
    dense surface's filled points, flagged (:func:`write_point_cloud`'s ``filled``).

    Returns
    -------
    dict
        Name → path of every file written.
    """
    t0 = time.perf_counter()
    release_free_memory()  # what the reconstruction freed, before the writers allocate
    wanted = set(RECONSTRUCTION_OUTPUTS if outputs is None else outputs) | {"summary.json"}
    unknown = sorted(wanted - set(RECONSTRUCTION_OUTPUTS))
    if unknown:
        raise InputError(f"unknown output {', '.join(unknown)}; choose from "
                         f"{', '.join(RECONSTRUCTION_OUTPUTS)}")
    check_cloud_options(keep_unreliable, cloud_filled)
    if not previews:
        wanted -= {"height.png", "reason.png", "view3d.png"}
    if surface.reason is None:
        wanted.discard("reason.png")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    measured = bool(surface.reliable.any())
    if not measured:
        log.info("nothing could be measured: no pixel has a reliable focus peak; "
                 "no cloud.ply or mesh written")
        wanted -= {"cloud.ply", "mesh.ply", "mesh.stl"}

    dense_lock = threading.Lock()

    def dense():  # Surface.dense once, whichever thread asks first
        with dense_lock:
            return surface.dense

    def import_vtk() -> None:
        from ._view3d import _vtk

        _vtk()

    def mesh() -> int:
        dense()
        return write_mesh(surface, out, wanted & {"mesh.ply", "mesh.stl"},
                          keep_unreliable=keep_unreliable)

    def cloud() -> Path:
        if cloud_filled:
            dense()  # the fill once, under the lock (this lane may get there first)
        return write_point_cloud(surface, out / "cloud.ply", keep_unreliable=keep_unreliable,
                                 filled=cloud_filled)

    stats: dict[str, Any] = {}

    def height_stats() -> None:
        reliable = surface.height_mm[surface.reliable]
        stats["height_mm"] = None if reliable.size == 0 else {
            "min": float(reliable.min()), "p01": float(np.percentile(reliable, 1)),
            "median": float(np.median(reliable)), "p99": float(np.percentile(reliable, 99)),
            "max": float(reliable.max()),
        }

    f32 = np.float32
    # Two lanes of independent writers. This thread: the dense surface, then view3d.png
    # (offscreen VTK render, the longest); the other thread meanwhile imports VTK and
    # writes the rest. The big allocations (dense fill, render) stay on this thread,
    # whose heap the reconstruction has left free: a second thread allocates from a
    # malloc arena of its own, and more threads cost more memory than they save on two
    # cores.
    here: list[tuple[tuple[str, ...], Callable[[], Any]]] = [
        (tuple(_DENSE_OUTPUTS), dense),
        (("view3d.png",), lambda: render_view3d_png(surface, out / "view3d.png")),
    ]
    there: list[tuple[tuple[str, ...], Callable[[], Any]]] = [
        (("view3d.png",), import_vtk),
        (("height.png",), lambda: render_height_png(surface, out / "height.png")),
        (("reason.png",), lambda: _atomic.write_image(
            out / "reason.png", render_reason_map(surface.reason, surface.aif))),
        (("aif.png",), lambda: _atomic.write_image(out / "aif.png", _png_ready(surface.aif))),
        (("height_mm.tiff",), lambda: _atomic.write_tiff(
            out / "height_mm.tiff", np.asarray(surface.height_mm, f32))),
        (("confidence.tiff",), lambda: _atomic.write_tiff(
            out / "confidence.tiff", np.asarray(surface.confidence, f32))),
        (("sigma_mm.tiff",), lambda: _atomic.write_tiff(
            out / "sigma_mm.tiff", np.asarray(surface.sigma_mm, f32))),
        (("precision_mm.tiff",), lambda: _atomic.write_tiff(
            out / "precision_mm.tiff", _precision_plane(surface))),
        (("field.png",), lambda: _atomic.write_image(out / "field.png", _mask_png(surface.field))),
        (("mesh.ply", "mesh.stl"), mesh),
        (("height_filled_mm.tiff",), lambda: _atomic.write_tiff(
            out / "height_filled_mm.tiff", np.asarray(dense()[0], f32))),
        (("sigma_filled_mm.tiff",), lambda: _atomic.write_tiff(
            out / "sigma_filled_mm.tiff", np.asarray(dense()[2], f32))),
        (("filled.png",), lambda: _atomic.write_image(out / "filled.png", _mask_png(dense()[1]))),
        # last: its point record would add to the dense fill's planes if the two overlapped
        (("cloud.ply",), cloud),
        (("summary.json",), height_stats),
    ]
    here = [(names, fn) for names, fn in here if wanted & set(names)]
    there = [(names, fn) for names, fn in there if wanted & set(names)]
    lanes = [[fn for _, fn in here], [fn for _, fn in there]]
    if surface.height_mm.size > SERIAL_WRITE_PIXELS:
        # one lane: the dense fill's and the render's planes would add to the other
        # writers' (4096 x 3072: 1.28 -> ~1.0 GiB peak, for ~1 s more)
        lanes = [[_then_trim(job) for job in lanes[0] + lanes[1]], []]
    mine, results = _run_lanes(lanes)
    if not lanes[1]:
        results = mine[len(here):]
    mesh_faces = 0
    for (names, _), result in zip(there, results):
        if names == ("mesh.ply", "mesh.stl"):
            mesh_faces = int(result)
    paths = {name: out / name for name in RECONSTRUCTION_OUTPUTS
             if name in wanted and name != "summary.json"}
    summary = {
        "smdinspect": "reconstruction",
        "pixel_size_mm": surface.pixel_size_mm,
        "xy_units": "mm" if surface.pixel_size_mm else "px",
        "measured": measured,
        "coverage": round(surface.coverage, 4),
        "height_mm": stats["height_mm"],
        "precision_mm": _precision_summary(surface),
        "cloud_points": 0 if not measured else _cloud_points(surface, keep_unreliable,
                                                             cloud_filled),
        "cloud_filled": bool(cloud_filled),
        "mesh_faces": mesh_faces,
        "keep_unreliable": keep_unreliable,
        **surface.meta,
        **(extra_summary or {}),
    }
    summary["seconds"] = {**summary.get("seconds", {}), "write": round(time.perf_counter() - t0, 3)}
    summary["files"] = sorted(list(paths) + ["summary.json"])
    paths["summary.json"] = _atomic.write_json(out / "summary.json", summary)
    return paths


def _cloud_mask(surface: Surface, keep_unreliable: bool, filled: bool) -> np.ndarray | None:
    """The pixels ``cloud.ply`` holds (see :func:`write_point_cloud`); None: all."""
    if keep_unreliable:
        return None
    if filled:
        z, flag, _ = surface.dense
        return surface.reliable | (flag & surface.field & np.isfinite(z))
    return surface.reliable


def _cloud_points(surface: Surface, keep_unreliable: bool, filled: bool) -> int:
    """How many points ``cloud.ply`` holds."""
    keep = _cloud_mask(surface, keep_unreliable, filled)
    return int(surface.reliable.size if keep is None else np.count_nonzero(keep))


def _precision_plane(surface: Surface) -> np.ndarray:
    """``precision_mm.tiff``'s plane: the 1σ random error of every height, NaN unknown."""
    if surface.precision_mm is None:
        return np.full(surface.shape, np.nan, np.float32)
    return np.asarray(surface.precision_mm, np.float32)


def _precision_summary(surface: Surface) -> dict | None:
    """summary.json's ``precision_mm``: over the reliable pixels, the share whose random
    error is known (their curves split), and its median and 95th percentile there."""
    if surface.precision_mm is None or not surface.reliable.any():
        return None
    p = surface.precision_mm[surface.reliable]
    known = p[np.isfinite(p)]
    out = {"known_fraction": round(float(known.size / p.size), 4)}
    if known.size:
        out.update(median=round(float(np.median(known)), 5),
                   p95=round(float(np.percentile(known, 95)), 5))
    return out


#: Outputs made from :attr:`Surface.dense`.
_DENSE_OUTPUTS = frozenset({"view3d.png", "mesh.ply", "mesh.stl", "height_filled_mm.tiff",
                            "sigma_filled_mm.tiff", "filled.png"})


def _then_trim(job: Callable[[], Any]) -> Callable[[], Any]:
    """``job``, then the heap's free pages handed back (before the next job allocates)."""
    def run():
        try:
            return job()
        finally:
            release_free_memory()
    return run


def _run_lanes(lanes: list[list[Callable[[], Any]]]) -> list[list[Any]]:
    """Run the jobs of ``lanes[0]`` on this thread and those of every other lane on a
    thread of its own, each lane in order; returns every job's result, by lane.

    The first error stops this thread's lane, cancels the other lanes' jobs not yet
    started, waits for the running ones (nothing writes into the folder after this
    returns) and is raised.
    """
    if sum(1 for lane in lanes if lane) < 2:  # nothing to overlap
        return [[job() for job in lane] for lane in lanes]
    here, others = lanes[0], [lane for lane in lanes[1:] if lane]
    cancelled = threading.Event()

    def run(lane):
        results = []
        for job in lane:
            if cancelled.is_set():
                break
            results.append(job())
        return results

    with ThreadPoolExecutor(max_workers=len(others), thread_name_prefix="smdinspect-write") as pool:
        futures = [pool.submit(run, lane) for lane in others]
        try:
            mine = []
            for job in here:
                for f in futures:
                    if f.done() and f.exception() is not None:
                        raise f.exception()
                mine.append(job())
            theirs = [f.result() for f in futures]
        except BaseException:
            cancelled.set()  # leaving the pool waits for the running writers: none
            raise  # writes into the folder after the caller has removed it
    it = iter(theirs)
    return [mine] + [next(it) if lane else [] for lane in lanes[1:]]


def _mask_png(mask: np.ndarray) -> np.ndarray:
    """A bool mask as an 8-bit image: 255 where True."""
    return np.asarray(mask, bool).view(np.uint8) * np.uint8(255)


def _png_ready(image: np.ndarray) -> np.ndarray:
    """uint8/uint16 as they are; float frames (taken as [0, 1]) to 16-bit for the PNG."""
    if image.dtype in (np.uint8, np.uint16):
        return image
    return np.round(np.clip(image, 0.0, 1.0) * 65535).astype(np.uint16)
