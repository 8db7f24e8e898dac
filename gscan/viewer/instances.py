"""The instances an estimate found in a query frame, as the viewer shows them (`gscan view --estimate RESULT.json`;
numpy only, no viser).

`read_estimate_result(path, template)` reads what `gscan estimate --json` writes: the `--all` object (a list of
results per template; the entry named as the template's file, or the only one), one template's entry of it, or a
single estimate's object (one pose or none). `ShownInstances` holds the poses found (T_cam_obj, best score first,
each with its rank and score), the instances refused (each with its reason) and why the search found nothing or
stopped. The scene draws each pose found (`gscan.viewer.scene.instance_poses`) relative to the first, which the
template's own frame shows, as the single estimate's query frame is shown.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gscan.errors import InputError, not_a_file
from gscan.io.poses import check_rigid
from gscan.viewer.text import md_text


@dataclass
class FoundInstance:
    """One pose found: rank (1 = best score), T_cam_obj [4 x 4], score, the template view it matched (or None) and
    the pixels it explains (count, 0 when not given)."""

    rank: int
    T_cam_obj: np.ndarray
    score: float
    view: str | None = None
    pixels: int = 0

    @property
    def label(self) -> str:
        """The scene's label of the pose: its rank and score."""
        return f"#{self.rank} · {self.score:.2f}"


@dataclass
class ShownInstances:
    """An estimate result shown in the viewer: `source` (the file's name), the template it is about, the poses
    found (best score first), the refused ones' reasons, `reason` (why none was found, or None) and `stopped`
    (why the search stopped, or None)."""

    source: str
    template: str
    found: list[FoundInstance] = field(default_factory=list)
    refused: list[str] = field(default_factory=list)
    reason: str | None = None
    stopped: str | None = None

    def markdown(self) -> str:
        """The GUI panel's text: each pose found by rank, each refused instance with its reason, why the search
        stopped."""
        lines = [f"**{md_text(self.source)}** · template {md_text(self.template)}  ",
                 f"found: {len(self.found)} · refused: {len(self.refused)}  "]
        for f in self.found:
            extra = "".join([f" · view {md_text(f.view)}" if f.view else "",
                             f" · {f.pixels} px" if f.pixels else ""])
            lines.append(f"{md_text(f.label)}{extra}  ")
        if not self.found:
            lines.append(f"none found: {md_text(self.reason or 'no reason given')}  ")
        for k, r in enumerate(self.refused, 1):
            lines.append(f"refused {k}: {md_text(r)}  ")
        if self.stopped and self.found:
            lines.append(f"search stopped: {md_text(self.stopped)}")
        return "\n".join(lines)


def read_estimate_result(path: Path, template: str) -> ShownInstances:
    """The instances of template `template` (its file name without .gscan) in the estimate result `path` (module
    docstring). InputError naming the file when it is unreadable, not an estimate result, holds no entry for the
    template (among several), or a pose that is not a finite rigid [4 x 4]."""
    if not path.is_file():
        raise not_a_file(path, "estimate result")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise InputError(path, f"unreadable ({e.__class__.__name__}: {e})"[:300]) from None
    if not isinstance(doc, dict):
        raise InputError(path, "not an estimate result: a JSON object expected")
    if isinstance(doc.get("templates"), list):  # `estimate --all --json`
        entries = [e for e in doc["templates"] if isinstance(e, dict)]
        named = [e for e in entries if e.get("template") == template]
        if not named and len(entries) == 1:
            named = entries
        if not named:
            names = ", ".join(str(e.get("template")) for e in entries)
            raise InputError(path, f"holds no result of template {template} (it holds {names or 'none'})")
        doc = named[0]
    if "instances" in doc:  # one template's `--all` entry
        found = _list(path, doc.get("instances"), "instances")
        refused = _list(path, doc.get("refused", []), "refused")
        return ShownInstances(path.name, template, [_found(path, r, k) for k, r in enumerate(found, 1)],
                              [str(r.get("reason") or "refused") for r in refused], _text(doc.get("reason")),
                              _text(doc.get("stopped")))
    if "T_cam_obj" in doc:  # a single estimate
        if doc["T_cam_obj"] is None:
            return ShownInstances(path.name, template, reason=_text(doc.get("reason")) or "not found")
        return ShownInstances(path.name, template, [_found(path, doc, 1)])
    raise InputError(path, "not an estimate result: no \"templates\", \"instances\" or \"T_cam_obj\" key")


def _list(path: Path, value: Any, key: str) -> list[dict]:
    if not isinstance(value, list) or not all(isinstance(r, dict) for r in value):
        raise InputError(path, f"\"{key}\" is not a list of results")
    return value


def _text(value: Any) -> str | None:
    return None if value is None else str(value)


def _found(path: Path, r: dict, rank: int) -> FoundInstance:
    """One found result of the file as a FoundInstance (InputError for a pose that is not a rigid transform)."""
    try:
        T = np.asarray(r.get("T_cam_obj"), dtype=np.float64)
        score = float(r.get("score", 0.0))
    except (TypeError, ValueError) as e:
        raise InputError(path, f"result {rank}: unreadable pose or score ({e.__class__.__name__})") from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not math.isfinite(score):
        raise InputError(path, f"result {rank}: T_cam_obj is not a finite 4 x 4 matrix")
    try:
        T = check_rigid(T, path)
    except InputError as e:
        raise InputError(path, f"result {rank}: {e.reason}") from None
    pixels = r.get("pixels")
    count = pixels.get("count") if isinstance(pixels, dict) else None
    view = r.get("view")
    return FoundInstance(rank, T, score, None if view is None else str(view), int(count) if isinstance(count, int)
                         else 0)
