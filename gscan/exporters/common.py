"""Helpers shared by the exporters: view selection, image writing, mesh rendering."""
from __future__ import annotations

import hashlib
import logging
import unicodedata
from pathlib import Path

import cv2
import numpy as np

from gscan.errors import GscanError, InputError
from gscan.geometry.raycast import MeshRaycaster as RaycasterBase
from gscan.io.camera import Intrinsics
from gscan.template.db import MeshData, TemplateDB, View

log = logging.getLogger(__name__)


def posed_views(db: TemplateDB, need_images: bool = True, need_depth: bool = True) -> list[View]:
    """Registered views in input order; with `need_images` their images decoded and only the views that store
    colour (and depth, with `need_depth`). InputError naming the database when none is left; otherwise the
    views left out are named in one warning."""
    out, missing = [], []
    for v in db.views(load_images=False):
        if v.T_obj_cam is None:
            continue
        if need_images:
            v = db.view(v.name, load_images=True)
            if v.color is None or (need_depth and v.depth is None):
                missing.append(v.name)
                continue
        out.append(v)
    what = "colour and depth images" if need_depth else "colour image"
    if not out:
        with_images = " with colour and depth images" if need_depth else " with a colour image"
        raise InputError(db.path, f"no registered view{with_images if need_images else ''} to export")
    if missing:
        log.warning("%d view(s) store no %s and are not exported: %s", len(missing), what, ", ".join(missing))
    return out


MAX_STEM_BYTES = 200  # a file name made from a view name, before its extension (NAME_MAX is 255 bytes)
# characters a file name made from a name never holds: separators, NUL, and those that act on a terminal
_BIDI = set("\u061c\u200e\u200f\u202a\u202b\u202c\u202d\u202e\u2066\u2067\u2068\u2069")


def _unsafe_char(c: str) -> bool:
    return c in "/\\\0" or c in _BIDI or unicodedata.category(c) in ("Cc", "Cs", "Zl", "Zp")


def _is_safe(name: str, max_bytes: int) -> bool:
    try:
        size = len(name.encode("utf-8"))
    except UnicodeEncodeError:
        return False
    return (0 < size <= max_bytes and name not in (".", "..") and not name.startswith(".")
            and not any(_unsafe_char(c) for c in name))


def _fit(text: str, max_bytes: int) -> str:
    """`text` cut (at a character) to at most `max_bytes` UTF-8 bytes."""
    while len(text.encode("utf-8", "surrogatepass")) > max_bytes:
        text = text[:-1]
    return text


def _key(stem: str) -> str:
    """What two file names must not share: file systems that ignore case or Unicode normalisation would
    take them for one file."""
    return unicodedata.normalize("NFC", stem).casefold()


def safe_file_names(names: list[str], max_bytes: int = MAX_STEM_BYTES) -> list[str]:
    """A file-name stem for each of `names` (view names come from files and templates: data, never a path).

    A name that is already safe is kept as it is (1 to `max_bytes` UTF-8 bytes, no separator, no NUL or
    control character, not "." or "..", no leading dot), so existing exports do not change. Any other gets a
    safe form: those characters replaced by "_", a leading dot by "_", cut to fit, then "-" and 8 hex digits
    of the name's hash, so that it stays recognisable and distinct. The stems are unique, also where a file
    system ignores case or Unicode normalisation: a later clash gets "-2", "-3", ...
    """
    out: list[str | None] = [None] * len(names)
    taken: set[str] = set()
    for i, name in enumerate(names):  # safe names first: they keep their name unless they clash
        if _is_safe(name, max_bytes) and _key(name) not in taken:
            out[i] = name
            taken.add(_key(name))
    for i, name in enumerate(names):
        if out[i] is not None:
            continue
        digest = hashlib.blake2b(name.encode("utf-8", "surrogatepass"), digest_size=4).hexdigest()
        if _is_safe(name, max_bytes):  # a clash with an earlier name
            base = name
        else:
            base = "".join("_" if _unsafe_char(c) else c for c in name)
            base = "_" + base[1:] if base.startswith(".") else base
        base = f"{_fit(base, max_bytes - 9) or 'view'}-{digest}"
        stem, k = base, 1
        while _key(stem) in taken:
            k += 1
            stem = f"{_fit(base, max_bytes - len(f'-{k}'))}-{k}"
        taken.add(_key(stem))
        out[i] = stem
    return [s for s in out if s is not None]


def template_mesh(db: TemplateDB, close: bool = True) -> MeshData | None:
    """The template's mesh for an export, closed into a watertight model with `close`
    (`gscan.exporters.watertight`); None when the template has no mesh with triangles."""
    m = db.mesh()
    if m is None or len(m.vertices) == 0 or len(m.triangles) == 0:
        return None
    if close:
        from gscan.exporters.watertight import closed_mesh

        m = closed_mesh(db, m)
    return m


def require_mesh(db: TemplateDB, close: bool = True) -> MeshData:
    """`template_mesh`, or InputError naming the database when it has no mesh."""
    m = template_mesh(db, close)
    if m is None:
        raise InputError(db.path, "the template has no mesh to export")
    return m


def imwrite(path: Path, img: np.ndarray, rgb: bool = False) -> None:
    """Write a PNG (`rgb`: [H x W x 3] RGB uint8 -> stored as a normal colour PNG)."""
    data = cv2.cvtColor(img, cv2.COLOR_RGB2BGR) if rgb else img
    ok, buf = cv2.imencode(path.suffix, data)
    if not ok:
        raise GscanError(f"cannot encode {path}")
    path.write_bytes(buf.tobytes())


class MeshRaycaster(RaycasterBase):
    """Ray-casts the template mesh from many cameras (`gscan.geometry.raycast.MeshRaycaster`)."""

    def __init__(self, mesh: MeshData):
        super().__init__(mesh.vertices, mesh.triangles)


def render_depth(mesh: MeshData, intr: Intrinsics, T_obj_cam: np.ndarray) -> np.ndarray:
    """One-off ray-cast of the mesh: [H x W] float32 depth (m), 0 = no hit (see MeshRaycaster)."""
    return MeshRaycaster(mesh).depth(intr, T_obj_cam)


def bbox_xywh(mask: np.ndarray) -> list[int]:
    """BOP bounding box [x, y, width, height] of a [H x W] bool mask; [-1, -1, -1, -1] if empty.

    As the BOP toolkit's `calc_2d_bbox`: width and height are max - min of the pixel coordinates (a
    one-pixel mask has width 0)."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return [-1, -1, -1, -1]
    x0, y0 = int(xs.min()), int(ys.min())
    return [x0, y0, int(xs.max()) - x0, int(ys.max()) - y0]
