"""Typed answers about a stored template, each with the `to_json()` object its command prints: `TemplateInfo`
(`gscan info --json`), `TemplatePoses` (`gscan poses --json`), `GraspList` (`gscan grasp list --json`). The
objects are the command line's contracts (docs/cli.md); the functions open the database, read and close it."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gscan.geometry.coverage import CoverageMap
from gscan.geometry.meshfill import boundary_edges
from gscan.geometry.symmetry import Symmetries
from gscan.template.db import TemplateDB
from gscan.template.records import TemplateSummary


@dataclass(frozen=True)
class MeshSize:
    """The stored mesh's vertices, triangles and open (boundary) edges (a scanned mesh is open where the support
    plane cut it)."""

    vertices: int
    triangles: int
    open_edges: int


@dataclass(frozen=True)
class TemplateInfo:
    """What a template database holds (`summary`), its mesh's size (None: no mesh), the scan's colour camera
    check (the "camera" meta of gscan.scanning.calibration; None: not run), its coverage of viewing directions
    (`TemplateDB.coverage`; None: unknown, a template made before it was recorded), the object's symmetries
    (none when not found or not searched) and the object segmentation chose and why (the "object" meta,
    `gscan.scanning.segment.ChosenObject.to_json`; None: not segmented)."""

    summary: TemplateSummary
    mesh: MeshSize | None
    camera: dict[str, Any] | None
    coverage: CoverageMap | None = None
    symmetries: Symmetries = field(default_factory=Symmetries)
    object: dict[str, Any] | None = None

    def to_json(self) -> dict[str, Any]:
        """The `info --json` object."""
        s = self.summary
        return {"schema": s.schema, "status": s.status, "views": s.views, "registered": s.registered,
                "keyframes": s.keyframes, "descriptor": s.descriptor, "source": s.source,
                "extent_m": list(s.extent_m), "grasps": list(s.grasps),
                "unregistered_reasons": dict(s.unregistered_reasons), "selection": dict(s.selection),
                "parts": [list(p) for p in s.parts], "mesh": None if self.mesh is None else asdict(self.mesh),
                "camera": self.camera, "coverage": None if self.coverage is None else self.coverage.to_json(),
                "symmetries": self.symmetries.to_json(), "object": self.object}


def template_info(path: str | Path) -> TemplateInfo:
    """The summary of the template database at `path` (a partial one too; InputError naming a bad file)."""
    with TemplateDB.open(path, require_complete=False) as db:
        summary, m, camera, obj = db.summary(), db.mesh(), db.get_meta("camera"), db.get_meta("object")
        coverage, symmetries = db.coverage(), db.symmetries()
    mesh = None if m is None else MeshSize(len(m.vertices), len(m.triangles), len(boundary_edges(m.triangles)))
    return TemplateInfo(summary, mesh, camera, coverage, symmetries, obj if isinstance(obj, dict) else None)


@dataclass(frozen=True)
class TemplatePoses:
    """The camera pose T_obj_cam (4 x 4, metres) of every registered input frame by name; the frames without
    one (`unregistered`, with `unregistered_reasons`), those frame selection left out (`skipped_by_selection`:
    name -> why; those of them with a pose are in `frames` too, placed by registration to the kept frame
    `from_reference` names, not fused) and the separate parts of the capture (`TemplateDB.parts`)."""

    frames: dict[str, list[list[float]]]
    unregistered: list[str] = field(default_factory=list)
    unregistered_reasons: dict[str, str] = field(default_factory=dict)
    skipped_by_selection: dict[str, str] = field(default_factory=dict)
    parts: list[list[str]] = field(default_factory=list)
    from_reference: dict[str, str] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """The `poses --json` object."""
        return {"frames": self.frames, "unregistered": self.unregistered,
                "unregistered_reasons": self.unregistered_reasons,
                "skipped_by_selection": self.skipped_by_selection, "from_reference": self.from_reference,
                "parts": self.parts}


def template_poses(path: str | Path) -> TemplatePoses:
    """The poses of the complete template database at `path` (InputError naming a bad or partial file)."""
    with TemplateDB.open(path, require_complete=True) as db:
        return TemplatePoses(**db.poses())


@dataclass(frozen=True)
class GraspList:
    """The named grasp poses T_obj_grasp (4 x 4, object frame, metres) stored in a template, by name."""

    grasps: dict[str, np.ndarray]

    def to_json(self) -> dict[str, Any]:
        """The `grasp list --json` object."""
        return {"grasps": {k: [[float(x) for x in row] for row in T] for k, T in self.grasps.items()}}


def template_grasps(path: str | Path) -> GraspList:
    """The grasps stored in the template database at `path` (a partial one too)."""
    with TemplateDB.open(path, require_complete=False) as db:
        return GraspList(db.grasps())


def store_grasp(path: str | Path, name: str, T_obj_grasp: np.ndarray) -> None:
    """Store the grasp `name` (T_obj_grasp) in the complete template database at `path` (InputError when the
    name is taken or not printable text)."""
    with TemplateDB.open(path, require_complete=True, writable=True) as db:
        db.add_grasp(name, T_obj_grasp)
