"""The captures of one scan: each INPUT a capture of the object (upright, upside down, another session), or a BOP
dataset folder whose model-free onboarding captures of one object are read as its captures.

Names: a capture is named after its folder (a recording after its file name without the extension), made
unique with "-2", "-3", ... in input order; a scan of several captures names its frames `CAPTURE/FRAME`, a scan
of one keeps the frames' own names.

BOP model-free onboarding (the BOP toolkit's dataset format): `onboarding_static/obj_XXXXXX_up` and
`obj_XXXXXX_down` (the object upright, then upside down, each a BOP scene folder) and `onboarding_dynamic/
obj_XXXXXX` (the object in hand); those of the object `obj_id` names that exist are its captures, in that order.
Their ground-truth poses are read for evaluation only (`Sequence.gt_T_cam_obj`).
"""
from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from gscan.errors import InputError

ONBOARDING = ("onboarding_static", "onboarding_dynamic")
_OBJ = re.compile(r"^obj_(\d+)(?:_(up|down))?$")


@dataclass(frozen=True)
class CaptureInput:
    """One capture of a scan: its name (the frames' prefix when a scan has several), the folder or recording,
    and the BOP object it follows (onboarding captures; None: the scan's --obj-id)."""

    name: str
    source: Path
    obj_id: int | None = None
    format: str | None = None  # the layout, when known ("bop" for onboarding captures); None: the scan's


def is_onboarding(path: Path) -> bool:
    """Whether `path` is a BOP dataset folder with model-free onboarding captures."""
    return path.is_dir() and any((path / d).is_dir() for d in ONBOARDING)


def onboarding_objects(root: Path) -> dict[int, list[Path]]:
    """The onboarding captures of a BOP dataset folder by object id: up, down, then dynamic."""
    found: dict[int, list[tuple[int, Path]]] = {}
    rank = {"up": 0, "down": 1, None: 2}
    for d in ONBOARDING:
        folder = root / d
        if not folder.is_dir():
            continue
        for p in sorted(folder.iterdir()):
            m = _OBJ.match(p.name)
            if m is None or not p.is_dir() or (d == "onboarding_static") != (m.group(2) is not None):
                continue
            found.setdefault(int(m.group(1)), []).append((rank[m.group(2)], p))
    return {k: [p for _, p in sorted(v)] for k, v in sorted(found.items())}


def capture_inputs(sources: Sequence[Path], obj_id: int | None, taken: Sequence[str] = ()) -> list[CaptureInput]:
    """The captures of a scan (module docstring), their names unique among themselves and `taken` (the captures of
    a template they are appended to). InputError: a BOP onboarding folder given with others, or without the
    capture of the object asked for (or, without `obj_id`, holding several objects)."""
    sources = [Path(s) for s in sources]
    if not sources:
        raise ValueError("a scan needs at least one capture")
    onboarding = [s for s in sources if is_onboarding(s)]
    if onboarding and len(sources) > 1:
        raise InputError(onboarding[0], "a BOP onboarding folder holds all of an object's captures: give it alone")
    if onboarding:
        root = onboarding[0]
        objects = onboarding_objects(root)
        if not objects:
            raise InputError(root, f"no obj_XXXXXX capture in {' or '.join(ONBOARDING)}")
        if obj_id is None:
            if len(objects) > 1:
                raise InputError(root, "holds the onboarding captures of objects "
                                 f"{', '.join(map(str, objects))}: choose one", fix="obj_id")
            obj_id = next(iter(objects))
        if obj_id not in objects:
            raise InputError(root, f"holds no onboarding capture of object {obj_id} (objects: "
                             f"{', '.join(map(str, objects))})", fix="obj_id")
        return [CaptureInput(_unique(p.name, taken), p, obj_id, "bop") for p in objects[obj_id]]
    names: list[str] = []
    for s in sources:
        names.append(_unique((s.stem if s.is_file() else s.resolve().name) or "capture", [*taken, *names]))
    return [CaptureInput(n, s, obj_id) for n, s in zip(names, sources, strict=True)]


def _unique(base: str, taken: Sequence[str]) -> str:
    name, k = base, 1
    while name in taken:
        k += 1
        name = f"{base}-{k}"
    return name
