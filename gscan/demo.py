"""`gscan demo`: scan the bundled sample, estimate the held-back frames against it (the CLI prints
the results and opens the viewer).

The sample (`SAMPLES`: gscan/sample/, shipped in the package as package data; samples/make_sample.py in
a source checkout regenerates it, samples/README.md describes it) is a capture of a procedurally textured
box on a table with ground truth, plus held-back frames of the box in other poses. The scanned template's
frame is tied to the ground-truth object frame with the capture's own ground truth:
T_obj_gt = mean over frames of T_obj_cam[f] @ T_cam_gt[f].

The numeric kernels (numba, `cache=True`) are compiled on their first use and kept in numba's on-disk cache: the
first demo spends about half a minute compiling them, most of it in the scan's first stage. `kernels_cached` says
whether that cache already holds them; `scan_sample` logs FIRST_RUN (a warning) when it does not.
"""
from __future__ import annotations

import importlib
import logging
import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gscan.errors import InputError, OutputExists
from gscan.estimate.estimator import Estimator
from gscan.evaluate.bop19 import template_to_gt
from gscan.evaluate.metrics import add
from gscan.geometry.transforms import pose_error
from gscan.io import open_sequence
from gscan.io.output import check_not_input, check_output, occupied
from gscan.progress import Progress
from gscan.scanning.api import scan
from gscan.scanning.pipeline import ScanResult
from gscan.template.db import TemplateDB

#: The bundled sample (package data): capture/, heldout/, object/box.obj, sample.json.
SAMPLES = Path(__file__).resolve().parent / "sample"

log = logging.getLogger(__name__)

#: What the demo logs before a scan that will compile the numeric kernels (numba's cache does not hold them).
FIRST_RUN = "first run: compiling the numeric kernels (about half a minute, once)"

_PACKAGE = Path(__file__).resolve().parent
_CACHED_KERNEL = re.compile(r"^\s*@(?:numba\.)?n?jit\(.*\bcache=True", re.MULTILINE)  # @njit(cache=True, ...)


def kernel_modules() -> list[str]:
    """The modules of gscan that define a numba kernel cached on disk (`@njit(cache=True)`), by name."""
    names = []
    for path in sorted(_PACKAGE.rglob("*.py")):
        rel = path.relative_to(_PACKAGE.parent).with_suffix("")
        if _CACHED_KERNEL.search(path.read_text(encoding="utf-8")):
            names.append(".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts))
    return names


def _cached_dispatchers(module: Any) -> list[Any]:
    """The numba dispatchers of `module` that cache on disk (a `Cache` with an index file, not a `NullCache`)."""
    out = []
    for obj in vars(module).values():
        cache = getattr(obj, "_cache", None)
        if getattr(obj, "__module__", None) == module.__name__ and hasattr(cache, "_cache_file"):
            out.append(obj)
    return out


def _compiled_here(dispatcher: Any, magic: tuple) -> bool:
    """numba's on-disk cache holds a compiled version of `dispatcher` for this source (its stamp: the file's time
    and size), this numba and this CPU (the index keys' magic tuple)."""
    try:
        overloads = dispatcher._cache._cache_file._load_index()
    except Exception:  # noqa: BLE001 - an unreadable or foreign index: numba compiles again
        return False
    return any(isinstance(key, tuple) and len(key) > 1 and key[1] == magic for key in overloads)


def kernels_cached(modules: Iterable[str] | None = None) -> bool:
    """Whether numba's on-disk cache (`__pycache__` beside the modules, or NUMBA_CACHE_DIR) already holds the
    compiled kernels: each module of `modules` (default: `kernel_modules()`) that defines a cached kernel has at
    least one of them compiled for this source, numba and CPU. False on a first run, after an upgrade that changed
    a kernel's module, or with a new cache folder: the next scan or estimate compiles them (about half a minute
    for all of gscan's)."""
    from numba.core.registry import cpu_target

    magic = cpu_target.target_context.codegen().magic_tuple()
    for name in kernel_modules() if modules is None else modules:
        kernels = _cached_dispatchers(importlib.import_module(name))
        if kernels and not any(_compiled_here(k, magic) for k in kernels):
            return False
    return True


@dataclass
class HeldOutResult:
    name: str
    found: bool
    rot_err_deg: float
    trans_err_mm: float
    add_mm: float
    n_matches: int
    total_ms: float


def evaluate_heldout(db_path: Path, heldout_dir: Path, model_points: np.ndarray) -> list[HeldOutResult]:
    """Estimate every held-back frame and compare with its ground truth (errors in the GT frame)."""
    capture = open_sequence(SAMPLES / "capture")
    T_obj_gt = template_to_gt(db_path, capture.gt_T_cam_obj or {})
    seq = open_sequence(heldout_dir)
    if seq.gt_T_cam_obj is None:
        raise InputError(heldout_dir, "holds no ground-truth poses (scene_gt.json) to compare with")
    est = Estimator.from_path(db_path)
    out = []
    for name in seq.names:
        frame = seq[name]
        r = est.estimate(frame)
        T_gt = seq.gt_T_cam_obj[name]
        if r.T_cam_obj is None:
            out.append(HeldOutResult(name=name, found=False, rot_err_deg=float("nan"), trans_err_mm=float("nan"),
                                     add_mm=float("nan"), n_matches=r.n_matches, total_ms=r.timings_ms["total"]))
            continue
        T_cam_gt_est = r.T_cam_obj @ T_obj_gt
        rot, trans = pose_error(T_cam_gt_est, T_gt)
        out.append(HeldOutResult(name=name, found=True, rot_err_deg=rot, trans_err_mm=trans * 1000,
                                 add_mm=add(model_points, T_cam_gt_est, T_gt) * 1000, n_matches=r.n_matches,
                                 total_ms=r.timings_ms["total"]))
    return out


def _model_points() -> np.ndarray:
    import trimesh

    mesh = trimesh.load(SAMPLES / "object" / "box.obj", force="mesh")
    return np.asarray(trimesh.sample.sample_surface(mesh, 2000, seed=0)[0])


DEMO_MARK = {"written_by": "gscan demo"}  # meta of the templates the demo writes: the only ones it replaces


def check_demo_output(output: Path) -> Path:
    """The demo's template OUTPUT/sample.gscan; OutputExists when a file is there that the demo did not write
    (a template without the demo's mark, or any other file), InputError when it cannot be written."""
    path = output / "sample.gscan"
    check_not_input(path, [SAMPLES])
    if occupied(path) and not path.is_dir():
        try:
            with TemplateDB.open(path, require_complete=False) as db:
                ours = all(db.get_meta(k) == v for k, v in DEMO_MARK.items())
        except InputError:
            ours = False
        if not ours:
            raise OutputExists(path, "already exists and was not written by gscan demo", fix="output")
    check_output(path, force=True, kind=".gscan file path")
    return path


def scan_sample(output: Path, progress: Progress | None = None) -> ScanResult:
    """Scan the bundled capture (SAMPLES/capture) into OUTPUT/sample.gscan (replacing only a template the demo
    wrote, see `check_demo_output`); returns the ScanResult. Logs FIRST_RUN (a warning) first when numba's cache
    does not hold the numeric kernels yet (`kernels_cached`): the scan's first stage then takes half a minute more."""
    if not (SAMPLES / "capture").is_dir():
        raise InputError(SAMPLES / "capture", "bundled sample not found (an incomplete installation: reinstall gscan)")
    path = check_demo_output(output)
    if not kernels_cached():
        log.warning(FIRST_RUN)
    # the scan makes the missing folders; the mark is in the database from its first transaction
    return scan(SAMPLES / "capture", path, force=True, progress=progress, meta=DEMO_MARK)


def evaluate_sample(db_path: Path) -> list[HeldOutResult]:
    """Estimate the sample's held-back frames against the scanned template `db_path`."""
    return evaluate_heldout(db_path, SAMPLES / "heldout", _model_points())
