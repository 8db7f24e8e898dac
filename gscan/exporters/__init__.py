"""Exporters of a complete template database to other tools' formats.

`export(db_path, fmt, out, force)` is the one entry point (`gscan export`). Formats:

| format | output |
|---|---|
| `bop` | a BOP dataset folder (camera.json, models/, models_eval/, test/000001/ with GT poses and masks) |
| `foundationpose` | FoundationPose model-free reference views (`ob_0000001/`) |
| `colmap` | a COLMAP sparse model (pycolmap `Reconstruction.write`) |
| `ply`, `obj`, `glb` | the template mesh (metres, object frame, vertex colours) |
| `json` | intrinsics, per-view poses, edges with their quality numbers, grasps |

The mesh of the bop, foundationpose, ply, obj and glb exports is closed (watertight, `export.watertight`)
unless `close=False`: the scan's mesh is open where the support plane cut it.

Outputs are never half-written (`gscan.io.output.Output`): everything is written into a hidden temporary
sibling of `out` and renamed into place at the end. An existing non-empty `out` is refused without `force`;
a partial database is refused (InputError naming the file). File names derived from view names are made
safe (`gscan.exporters.common.safe_file_names`): no separators, `..`, control characters or overlong names.
"""
from __future__ import annotations

import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gscan.errors import InputError
from gscan.io.output import Output, check_not_input
from gscan.template.db import TemplateDB

log = logging.getLogger(__name__)

FORMATS = ("bop", "foundationpose", "colmap", "ply", "obj", "glb", "json")
_FILE_FORMATS = ("ply", "obj", "glb", "json")


#: What each format holds, for the one-line report of an export.
_CONTENT = {"bop": "a BOP dataset of {views} views", "foundationpose": "FoundationPose reference views ({views})",
            "colmap": "a COLMAP model of {views} images", "json": "the template's metadata ({views} views)"}


@dataclass
class ExportResult:
    """What an export wrote: `path` (folder or file), number of views and files written, and for the mesh
    formats what the file holds (`content`, e.g. "mesh of 120 vertices / 236 triangles, watertight")."""

    format: str
    path: Path
    views: int
    files: int
    content: str = ""

    def __str__(self) -> str:
        what = self.content or _CONTENT.get(self.format, "{views} views").format(views=self.views)
        files = f", {self.files} files" if self.files > 1 else ""
        return f"{self.format} export at {self.path}: {what}{files}"

    def to_json(self) -> dict[str, Any]:
        """The `export --json` object."""
        return {"output": str(self.path), "format": self.format, "views": self.views, "files": self.files}


def _writer(fmt: str, close: bool) -> Callable[[TemplateDB, Path], int | tuple[int, str]]:
    """The format's writer: writer(db, tmp_out) -> number of views exported, or (views, content): the mesh
    formats (0 views) and colmap say what they wrote."""
    if fmt == "bop":
        from gscan.exporters.bop import write_bop
        return lambda db, path: write_bop(db, path, close=close)
    if fmt == "foundationpose":
        from gscan.exporters.foundationpose import write_foundationpose
        return lambda db, path: write_foundationpose(db, path, close=close)
    if fmt == "colmap":
        from gscan.exporters.colmap import write_colmap
        return write_colmap
    if fmt == "json":
        from gscan.exporters.jsonfmt import write_json
        return write_json
    from gscan.exporters.mesh import write_mesh
    return lambda db, path: write_mesh(db, path, fmt, close=close)


def export(db_path: str | Path, fmt: str, out: str | Path, force: bool = False, close: bool = True) -> ExportResult:
    """Export the complete template database `db_path` as `fmt` to `out` (a folder, or a file for
    ply/obj/glb/json); `close`: close the mesh's holes (watertight model) in the formats that hold it.
    Raises InputError for an unknown format, an occupied `out` without `force`, a partial / unreadable
    database, or a database lacking what the format needs."""
    db_path, out = Path(db_path), Path(out)
    if fmt not in FORMATS:
        raise InputError(out, f"unknown export format {fmt!r}; expected one of {', '.join(FORMATS)}")
    if fmt in _FILE_FORMATS and out.suffix.lower() in {f".{f}" for f in _FILE_FORMATS} - {f".{fmt}"}:
        raise InputError(out, f"a {out.suffix} name for {fmt} content; name the file .{fmt}")
    check_not_input(out, [db_path])
    target = Output(out, force=force, folder=fmt not in _FILE_FORMATS, kind=f".{fmt} file path")
    # parent folders are made only once the database is known good, and removed on failure
    with TemplateDB.open(db_path, require_complete=True) as db, target:
        wrote = _writer(fmt, close)(db, target.tmp)
        n_views, content = wrote if isinstance(wrote, tuple) else (wrote, "")
        files = sum(len(f) for _, _, f in os.walk(target.tmp)) if target.tmp.is_dir() else 1
    log.info("exported %s as %s to %s (%d views, %d files)", db_path, fmt, out, n_views, files)
    return ExportResult(fmt, out, n_views, files, content)


__all__ = ["FORMATS", "ExportResult", "export"]
