"""Exporters of a complete template database to other tools' formats.

`export(db_path, fmt, out, force)` is the one entry point (`gscan export`). Formats:

| format | output |
|---|---|
| `bop` | a BOP dataset folder (camera.json, models/, test/000001/ with GT poses and masks) |
| `foundationpose` | FoundationPose model-free reference views (`ob_0000001/`) |
| `colmap` | a COLMAP sparse model (pycolmap `Reconstruction.write`) |
| `ply`, `obj`, `glb` | the template mesh (metres, object frame, vertex colours) |
| `json` | intrinsics, per-view poses, edges with their quality numbers, grasps |

Outputs are never half-written (`gscan.io.output.Output`): everything is written into a hidden temporary
sibling of `out` and renamed into place at the end. An existing non-empty `out` is refused without `force`;
a partial database is refused (InputError naming the file). File names derived from view names are made
safe (`gscan.export.common.safe_file_names`): no separators, `..`, control characters or overlong names.
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from gscan.errors import InputError
from gscan.io.output import Output
from gscan.template.db import TemplateDB

log = logging.getLogger(__name__)

FORMATS = ("bop", "foundationpose", "colmap", "ply", "obj", "glb", "json")
_FILE_FORMATS = ("ply", "obj", "glb", "json")


@dataclass
class ExportResult:
    """What an export wrote: `path` (folder or file), number of views and files written."""

    format: str
    path: Path
    views: int
    files: int

    def __str__(self) -> str:
        return f"{self.format} export of {self.views} views ({self.files} files) at {self.path}"


def _writer(fmt: str) -> Callable[[TemplateDB, Path], int]:
    """The format's writer: writer(db, tmp_out) -> number of views exported."""
    if fmt == "bop":
        from gscan.export.bop import write_bop
        return write_bop
    if fmt == "foundationpose":
        from gscan.export.foundationpose import write_foundationpose
        return write_foundationpose
    if fmt == "colmap":
        from gscan.export.colmap import write_colmap
        return write_colmap
    if fmt == "json":
        from gscan.export.jsonfmt import write_json
        return write_json
    from gscan.export.mesh import write_mesh
    return lambda db, path: write_mesh(db, path, fmt)


def export(db_path: str | Path, fmt: str, out: str | Path, force: bool = False) -> ExportResult:
    """Export the complete template database `db_path` as `fmt` to `out` (a folder, or a file for
    ply/obj/glb/json). Raises InputError for an unknown format, an occupied `out` without `force`,
    a partial / unreadable database, or a database lacking what the format needs."""
    db_path, out = Path(db_path), Path(out)
    if fmt not in FORMATS:
        raise InputError(out, f"unknown export format {fmt!r}; expected one of {', '.join(FORMATS)}")
    if fmt in _FILE_FORMATS and out.suffix.lower() in {f".{f}" for f in _FILE_FORMATS} - {f".{fmt}"}:
        raise InputError(out, f"a {out.suffix} name for {fmt} content; name the file .{fmt}")
    target = Output(out, force=force, folder=fmt not in _FILE_FORMATS, kind=f".{fmt} file path")
    if out.resolve() == db_path.resolve():
        raise InputError(out, "output would overwrite the template database itself")
    if out.resolve() in db_path.resolve().parents:
        raise InputError(out, f"output folder holds the template database {db_path.name}; replacing it would delete it")
    # parent folders are made only once the database is known good, and removed on failure
    with TemplateDB.open(db_path, require_complete=True) as db, target:
        n_views = _writer(fmt)(db, target.tmp)
        files = sum(len(f) for _, _, f in os.walk(target.tmp)) if target.tmp.is_dir() else 1
    log.info("exported %s as %s to %s (%d views, %d files)", db_path, fmt, out, n_views, files)
    return ExportResult(fmt, out, n_views, files)


__all__ = ["FORMATS", "ExportResult", "export"]
