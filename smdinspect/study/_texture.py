"""The texture study: scenes × textures × sensor noise × focus operators × peak fits.

Each **cell** of the study is one rendered stack: a scene of known shape (``cone``,
``slanted_plane``, ``steps`` of :mod:`smdinspect.synth`) carrying one texture (kind,
RMS contrast, dominant frequency), seen through :func:`smdinspect.synth.render_gather`
(Gaussian PSF, ``σ = √(σ0² + (b·|z − h|)²)``) by a sensor with one read-noise level.
The stack is reconstructed with every operator and both fits; each reconstruction gives
one row of metrics (see :data:`METRICS`). A finished cell is stored atomically as
``cells/<key>.json`` and never recomputed while the settings that shape it are unchanged
(their fingerprint is in the file). Everything but the timings is deterministic for a
seed: the texture of a cell depends on (seed, scene, kind, frequency), so the contrast
and noise axes compare the same texture, and the sensor noise on the whole key.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import multiprocessing
import time
import zlib
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from .._proc import die_with_parent
from ..errors import InputError
from ..stack import FocalStack, Frame

__all__ = ["METRICS", "StudyCell", "TextureStudy", "TextureStudyConfig", "run_texture_study",
           "time_operators"]

log = logging.getLogger(__name__)

Progress = Callable[[int, int], None]

#: Bumped when a cell's computation changes; stored cells of another version are redone.
STUDY_VERSION = 1
STUDY_SCENES = ("cone", "slanted_plane", "steps")
#: Weight of a reliable-but-wrong pixel against a reliable-and-right one in ``score``:
#: a wrong height that is trusted is judged; a missing one is only not measured.
WRONG_WEIGHT = 3.0
#: Columns of a study row that measure one reconstruction (errors in frame steps Δd).
METRICS = (
    "rmse_steps",  # RMS error of the reliable pixels
    "bias_steps",  # median error of the reliable pixels
    "coverage",  # share of pixels marked reliable
    "wrong_share",  # share of the reliable pixels more than 1 Δd off
    "good_share",  # share of all pixels reliable and within 1 Δd
    "recoverable_share",  # share of all pixels within 1 Δd, reliable or not
    "confidence_auc",  # ROC AUC of the confidence as a predictor of "within 1 Δd"
    "score",  # good_share − WRONG_WEIGHT · (coverage · wrong_share)
    "ms_per_frame",  # reconstruct()'s wall time per frame, one worker thread
)
_DOF_SIGMA_PX = 1.0 / (2.0 * math.sqrt(2.0))  # σ of a 1-px blur circle


def _floats(values: Any, name: str, lo: float, hi: float) -> tuple[float, ...]:
    try:
        out = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a sequence of numbers; got {values!r}") from None
    if not out or any(not (lo <= v <= hi) or not math.isfinite(v) for v in out):
        raise InputError(f"{name} must be a non-empty list of numbers in [{lo:g}, {hi:g}]; "
                         f"got {values!r}")
    return tuple(sorted(set(out)))


def _names(values: Any, name: str, allowed: Sequence[str]) -> tuple[str, ...]:
    out = (values,) if isinstance(values, str) else tuple(values)
    bad = [v for v in out if v not in allowed]
    if not out or bad:
        raise InputError(f"{name} must name some of {', '.join(allowed)}; got {bad or 'none'}")
    return tuple(dict.fromkeys(out))


@dataclass(frozen=True)
class TextureStudyConfig:
    """Settings of :func:`run_texture_study`; the default is the full study.

    Parameters
    ----------
    scenes : tuple of {"cone", "slanted_plane", "steps"}
    textures : tuple of {"band", "weave", "grain", "marks"}
        Texture kinds (:func:`smdinspect.synth.texture`).
    contrasts : tuple of float
        RMS albedo contrast as a fraction of the mean (marks: their depth).
    freqs_cyc_px : tuple of float
        Dominant spatial frequency, cycles per pixel. Relative to the in-focus PSF it is
        ``f·2π·sigma0_px`` (the in-focus MTF at f is ``exp(−(f·2πσ0)²/2)``).
    read_noises : tuple of float
        Gaussian read noise, RMS as a fraction of full scale (shot noise is always on).
    operators : tuple of str
        Focus operators (default all of ``smdinspect.sff.OPERATORS``).
    fits : tuple of str
        Peak fits (``FitMethod`` values); default the default ``power`` and ``gauss3``.
    size_px, n_frames : int
        Side of the square scenes and frames per stack.
    relief_mm : float
        Height range of every scene; the sweep spans 1.2 × it (0.1 × beyond each end).
    step_per_dof : float
        Frame step Δd in depths of field (the defocus over which the blur circle stays
        under 1 px).
    sigma0_px : float
        In-focus Gaussian blur (the PSF at focus).
    photons_full_scale : float
        Shot noise: photo-electrons at full scale.
    window_px : int
        Focus window of every reconstruction.
    seed : int
        Study seed (tuning seeds 0–999; tests use ``smdinspect.synth.TEST_SEEDS``).
    workers : int
        Cells computed at once, one worker process each (each reconstruction single-threaded).
    """

    scenes: tuple[str, ...] = STUDY_SCENES
    textures: tuple[str, ...] = ("band", "weave", "grain", "marks")
    contrasts: tuple[float, ...] = (0.005, 0.01, 0.02, 0.05, 0.1, 0.3)
    freqs_cyc_px: tuple[float, ...] = (0.03, 0.08, 0.2)
    read_noises: tuple[float, ...] = (0.002, 0.01, 0.02)
    operators: tuple[str, ...] | None = None
    fits: tuple[str, ...] = ("power", "gauss3")
    size_px: int = 96
    n_frames: int = 16
    relief_mm: float = 1.0
    step_per_dof: float = 1.0
    sigma0_px: float = 0.7
    photons_full_scale: float = 20_000.0
    window_px: int = 9
    seed: int = 0
    workers: int = 2

    def __post_init__(self) -> None:
        from ..sff import OPERATORS, FitMethod
        from ..synth import TEXTURE_KINDS

        def put(name: str, value: Any) -> None:
            object.__setattr__(self, name, value)

        put("scenes", _names(self.scenes, "scenes", STUDY_SCENES))
        put("textures", _names(self.textures, "textures", TEXTURE_KINDS))
        put("contrasts", _floats(self.contrasts, "contrasts", 0.0, 1.0))
        put("freqs_cyc_px", _floats(self.freqs_cyc_px, "freqs_cyc_px", 1e-3, 0.5))
        put("read_noises", _floats(self.read_noises, "read_noises", 0.0, 0.5))
        put("operators", _names(OPERATORS if self.operators is None else self.operators,
                                "operators", OPERATORS))
        put("fits", _names(self.fits, "fits", [m.value for m in FitMethod]))
        for name, lo, hi in (("size_px", 32, 1024), ("n_frames", 5, 200), ("window_px", 1, 31),
                             ("workers", 1, 64)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise InputError(f"{name} must be an integer in {lo}..{hi}; got {v!r}")
        if self.window_px % 2 == 0:
            raise InputError(f"window_px must be odd; got {self.window_px}")
        for name in ("relief_mm", "step_per_dof", "sigma0_px", "photons_full_scale"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (
                    math.isfinite(v) and v >= 0) or (v == 0 and name != "photons_full_scale"):
                raise InputError(f"{name} must be a finite number > 0; got {v!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise InputError(f"seed must be an integer >= 0; got {self.seed!r}")

    @classmethod
    def quick(cls, **overrides: Any) -> "TextureStudyConfig":
        """The small study of ``--quick`` (72 cells of 64 px, 12 frames; well under a
        minute on 2 cores)."""
        base = dict(textures=("band", "marks"), contrasts=(0.01, 0.05, 0.2),
                    freqs_cyc_px=(0.04, 0.15), read_noises=(0.002, 0.02), size_px=64,
                    n_frames=12)
        return cls(**{**base, **overrides})

    @property
    def step_mm(self) -> float:
        """Frame step Δd (mm)."""
        return 1.2 * self.relief_mm / (self.n_frames - 1)

    @property
    def blur_px_per_mm(self) -> float:
        """Growth of the defocus σ per mm of defocus: one step is ``step_per_dof`` DOFs."""
        return self.step_per_dof * 2.0 * _DOF_SIGMA_PX / self.step_mm

    def z_mm(self) -> np.ndarray:
        """``(n_frames,) float64``: the sweep, ascending."""
        return -0.1 * self.relief_mm + self.step_mm * np.arange(self.n_frames, dtype=np.float64)

    def cells(self) -> list["StudyCell"]:
        """Every cell of the grid, in a fixed order."""
        return [StudyCell(s, t, c, f, n) for s in self.scenes for t in self.textures
                for f in self.freqs_cyc_px for c in self.contrasts for n in self.read_noises]

    def fingerprint(self) -> str:
        """Hash of the settings a cell's result depends on (not the grid, not workers)."""
        keep = {f.name: getattr(self, f.name) for f in fields(self)
                if f.name not in ("scenes", "textures", "contrasts", "freqs_cyc_px",
                                  "read_noises", "workers")}
        keep["version"] = STUDY_VERSION
        return hashlib.sha256(json.dumps(keep, sort_keys=True).encode()).hexdigest()[:16]

    def to_dict(self) -> dict:
        d = asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}


@dataclass(frozen=True)
class StudyCell:
    """One rendered stack of the study."""

    scene: str
    texture: str
    contrast: float
    freq_cyc_px: float
    read_noise: float

    @property
    def key(self) -> str:
        return (f"{self.scene}_{self.texture}_c{self.contrast:g}_f{self.freq_cyc_px:g}"
                f"_n{self.read_noise:g}")

    def seeds(self, seed: int) -> tuple[int, int]:
        """(texture seed, sensor seed): the texture ignores contrast and noise."""
        tex = zlib.crc32(f"{self.scene}/{self.texture}/{self.freq_cyc_px:g}".encode())
        texture_seed = int(np.random.SeedSequence([seed, tex]).generate_state(1)[0])
        sensor_seed = int(np.random.SeedSequence(
            [seed, zlib.crc32(self.key.encode())]).generate_state(1)[0])
        return texture_seed, sensor_seed


@dataclass(frozen=True, eq=False)
class TextureStudy:
    """Result of :func:`run_texture_study`.

    Attributes
    ----------
    config : TextureStudyConfig
    cells : list of dict
        One document per cell: its parameters, the texture ``features`` measured on its
        stack and its ``rows`` (one per operator × fit).
    computed, reused : int
        Cells computed by this run, and cells found finished in ``cells/``.
    seconds : float
        Wall time of this run's computation.
    outputs, analysis : dict
        Files written and :func:`~smdinspect.study.analyse_study` (when written).
    focus_ms : dict
        Operator → ms of one focus measure of a 1024² frame (:func:`time_operators`;
        the study's small frames time the whole reconstruction's overhead instead).
    """

    config: TextureStudyConfig
    cells: list[dict]
    computed: int
    reused: int
    seconds: float
    outputs: dict[str, Path] = field(default_factory=dict)
    analysis: dict = field(default_factory=dict)
    focus_ms: dict = field(default_factory=dict)

    def rows(self) -> list[dict]:
        """One flat dict per cell × operator × fit: the cell's parameters, its measured
        features (``feat_*``) and the :data:`METRICS`."""
        out = []
        for doc in self.cells:
            base = {k: doc[k] for k in ("scene", "texture", "contrast", "freq_cyc_px",
                                        "freq_rel_psf", "read_noise", "key")}
            base.update({f"feat_{k}": v for k, v in doc["features"].items() if k != "frames"})
            for row in doc["rows"]:
                out.append({**base, **row})
        return out


class _MemoryStack(FocalStack):
    """A :class:`FocalStack` whose frames are already decoded in memory."""

    def __init__(self, frames: Sequence[np.ndarray], z_mm: np.ndarray, pixel_size_mm: float):
        super().__init__(tuple(Frame(Path(f"frame_{i:04d}.png"), float(z))
                               for i, z in enumerate(z_mm)), pixel_size_mm=pixel_size_mm)
        object.__setattr__(self, "_images", tuple(frames))

    def read_frame(self, index: int) -> np.ndarray:
        return self._images[index]


def render_cell(cell: StudyCell, config: TextureStudyConfig):
    """Render a cell: ``(frames, z_mm, height_mm)`` (frames are uint8 (H, W) images)."""
    from .. import synth

    tex_seed, sensor_seed = cell.seeds(config.seed)
    n = config.size_px
    tex = synth.texture(cell.texture, n, seed=tex_seed, freq_cyc_px=cell.freq_cyc_px,
                        contrast=cell.contrast, mean=0.5)
    top = config.relief_mm
    if cell.scene == "cone":
        rad, h = synth.cone(size_px=n, high_mm=top, radius_frac=0.45, texture=tex)
    elif cell.scene == "slanted_plane":
        rad, h = synth.slanted_plane(size_px=n, high_mm=top, azimuth_deg=30.0, texture=tex)
    else:
        rad, h = synth.steps(size_px=n, high_mm=top, n_steps=4, texture=tex)
    z = config.z_mm()
    noise = synth.GatherNoise(photons_full_scale=config.photons_full_scale,
                              read_noise=cell.read_noise)
    frames = synth.render_gather(rad, h, z, blur_px_per_mm=config.blur_px_per_mm,
                                 sigma0_px=config.sigma0_px, noise=noise, seed=sensor_seed)
    return frames, z, h


def measure(surface, height_mm: np.ndarray, step_mm: float) -> dict:
    """The :data:`METRICS` (but ``ms_per_frame``) of one reconstruction against the truth."""
    err = (surface.height_mm.astype(np.float64) - height_mm) / step_mm
    rel = np.asarray(surface.reliable, bool)
    ok = np.isfinite(err) & (np.abs(err) <= 1.0)
    coverage = float(rel.mean())
    if rel.any():
        e = np.where(np.isfinite(err[rel]), err[rel], 1e3)
        rmse, bias, wrong = (float(np.sqrt(np.mean(e * e))), float(np.median(e)),
                             float(np.mean(~ok[rel])))
    else:
        rmse = bias = wrong = math.nan
    good = float(np.mean(rel & ok))
    bad = float(np.mean(rel & ~ok))
    return {"rmse_steps": rmse, "bias_steps": bias, "coverage": coverage, "wrong_share": wrong,
            "good_share": good, "recoverable_share": float(ok.mean()),
            "confidence_auc": _auc(surface.confidence, ok),
            "score": good - WRONG_WEIGHT * bad}


def _auc(score: np.ndarray, positive: np.ndarray) -> float:
    """ROC AUC of ``score`` separating ``positive`` pixels (Mann–Whitney, ties halved)."""
    from scipy.stats import rankdata

    s = np.nan_to_num(np.asarray(score, np.float64).ravel(), nan=0.0)
    p = np.asarray(positive, bool).ravel()
    n_pos, n_neg = int(p.sum()), int((~p).sum())
    if n_pos == 0 or n_neg == 0:
        return math.nan
    ranks = rankdata(s)
    return float((ranks[p].sum() - n_pos * (n_pos + 1) / 2.0) / (n_pos * n_neg))


def run_cell(cell: StudyCell, config: TextureStudyConfig) -> dict:
    """Render one cell, measure its texture and reconstruct it with every operator × fit."""
    from ..sff import FocusConfig, FocusOperator, reconstruct
    from ._features import stack_features

    t0 = time.perf_counter()
    frames, z, truth = render_cell(cell, config)
    stack = _MemoryStack(frames, z, pixel_size_mm=0.01)
    features = stack_features(stack)
    rows = []
    for fit in config.fits:
        for op in config.operators:
            # the operators as they are, on the raw frames (no noise pre-filter)
            surface = reconstruct(stack, FocusConfig(operator=op, fit=fit, workers=1,
                                                     window_px=config.window_px,
                                                     prefilter_px=0.0))
            row = {"operator": op, "family": FocusOperator(op).family, "fit": fit}
            row.update(measure(surface, truth, stack.step_mm))
            row["ms_per_frame"] = 1000.0 * surface.meta["seconds"]["total"] / len(stack)
            rows.append({k: (round(v, 5) if isinstance(v, float) and math.isfinite(v) else v)
                         for k, v in row.items()})
    return {
        "key": cell.key, "fingerprint": config.fingerprint(), **asdict(cell),
        "freq_rel_psf": round(cell.freq_cyc_px * 2.0 * math.pi * config.sigma0_px, 4),
        "seeds": list(cell.seeds(config.seed)), "step_mm": stack.step_mm,
        "features": features.to_dict(), "rows": rows,
        "seconds": round(time.perf_counter() - t0, 3),
    }


def time_operators(operators: Sequence[str], *, size_px: int = 1024, window_px: int = 9,
                   repeats: int = 3) -> dict[str, float]:
    """Median wall time (ms) of :func:`smdinspect.sff.focus_measure` on a
    ``size_px``² float32 frame, per operator (single call, OpenCV's own threads)."""
    from ..sff import focus_measure

    rng = np.random.default_rng(0)
    frame = (128.0 + 20.0 * rng.standard_normal((size_px, size_px))).astype(np.float32)
    out = {}
    for op in operators:
        focus_measure(frame, operator=op, window_px=window_px)  # warm caches
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            focus_measure(frame, operator=op, window_px=window_px)
            times.append(time.perf_counter() - t0)
        out[op] = round(1000.0 * float(np.median(times)), 3)
    return out


def _stored(path: Path, cell: StudyCell, fingerprint: str) -> dict | None:
    """The finished cell in ``path``, or None (missing, unreadable or other settings)."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or doc.get("key") != cell.key or \
            doc.get("fingerprint") != fingerprint or not isinstance(doc.get("rows"), list):
        return None
    return doc


def _work(cell: StudyCell, config: TextureStudyConfig, cells_dir: Path) -> dict:
    """One cell in a worker process, stored atomically (a killed run keeps it whole)."""
    from .. import _atomic

    doc = run_cell(cell, config)
    _atomic.write_json(cells_dir / f"{cell.key}.json", doc)
    return doc


def run_texture_study(out_dir: str | Path, config: TextureStudyConfig | None = None, *,
                      progress: Progress | None = None, write: bool = True) -> TextureStudy:
    """Run (or resume) the texture study into ``out_dir``.

    Cells already stored in ``out_dir/cells/`` with the same settings are read, not
    recomputed; every newly finished cell is written there atomically, so an interrupted
    run loses at most the cells in flight. Then the tables, figures and summary are
    written (see :func:`smdinspect.study.write_study`) unless ``write`` is False.

    Parameters
    ----------
    out_dir : path
    config : TextureStudyConfig, optional
        Default the full study; ``TextureStudyConfig.quick()`` for the small one.
    progress : callable(done, total), optional
        Called with finished cells (stored ones count as done from the start).

    Returns
    -------
    TextureStudy
    """
    config = config or TextureStudyConfig()
    if not isinstance(config, TextureStudyConfig):
        raise InputError(f"config must be a TextureStudyConfig; got {type(config).__name__}")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out must be a folder; {out} is a file")
    cells_dir = out / "cells"
    cells_dir.mkdir(parents=True, exist_ok=True)
    fp = config.fingerprint()
    grid = config.cells()
    done: dict[str, dict] = {}
    todo = []
    for cell in grid:
        doc = _stored(cells_dir / f"{cell.key}.json", cell, fp)
        if doc is None:
            todo.append(cell)
        else:
            done[cell.key] = doc
    reused = len(done)
    log.info("texture study: %d cells (%d operators x %d fits each), %d already finished in %s",
             len(grid), len(config.operators), len(config.fits), reused, cells_dir)
    if progress is not None:
        progress(len(done), len(grid))

    t0 = time.perf_counter()
    # processes, not threads: a 64-px cell is mostly Python, which threads run one at a
    # time (the quick study took 131 s on 2 threads, 51 s on 2 processes)
    pool = ProcessPoolExecutor(max_workers=min(config.workers, max(len(todo), 1)),
                               mp_context=multiprocessing.get_context("spawn"),
                               initializer=die_with_parent)  # no orphans if killed
    try:
        futures = [pool.submit(_work, cell, config, cells_dir) for cell in todo]
        for fut in as_completed(futures):
            doc = fut.result()
            done[doc["key"]] = doc
            if progress is not None:
                progress(len(done), len(grid))
    finally:
        # an interrupt or an error: drop the cells not started, let running ones finish
        pool.shutdown(wait=True, cancel_futures=True)
    seconds = time.perf_counter() - t0
    study = TextureStudy(config, [done[c.key] for c in grid], computed=len(todo),
                         reused=reused, seconds=seconds)
    log.info("texture study: %d cells computed in %.1f s, %d reused", len(todo), seconds, reused)
    if write:
        from ._report import analyse_study, write_study

        study.focus_ms.update(time_operators(config.operators, window_px=config.window_px))
        study.analysis.update(analyse_study(study))
        study.outputs.update(write_study(study, out, study.analysis))
    return study
