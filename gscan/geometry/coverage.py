"""Coverage of an object's viewing directions: which sides of it were seen, one definition for the capture
preview and the template.

The sphere of directions around the object is cut into `COVERAGE_DIRECTIONS` cells, the points of a
Fibonacci lattice (`lattice`; equal-area bands in z, golden-angle steps in azimuth), in a frame whose z is up
(`CoverageMap.R_up_obj` turns object-frame directions into it: the identity for a scan with a support plane, whose
z is the plane's normal, and for a CAD template, whose +z is taken for up; the first camera's image up for a scan
without one; the capture preview has its own estimate of up).
A cell is seen when
  - a view looks at the object from within `COVERAGE_RADIUS_DEG` of it (the view's direction: from the
    object's centre to the camera centre; `view_counts` counts the views per cell), or
  - for a template, observed surface faces it: the fused surface's faces (not the ones hole filling added)
    whose normal lies within `COVERAGE_RADIUS_DEG` of the cell, and which some view saw within
    `MAX_INCIDENCE_DEG` of their normal, hold at least `MIN_AREA_SHARE` of that surface's area
    (`surface_seen`). A capture from 30 to 55 degrees above the table sees the top of the object through its
    normals although no camera was above it.
share = seen cells / all cells.

The bottom a static object stands on is never seen in one upright capture: no camera goes below the table,
and the support plane cuts the object's surface there, so no observed face points down. Its cells stay unseen
and the bottom is named missing; scanning the object again upside down (a second capture) covers it.

Missing regions are named in words, grouped rather than per cell (`regions`): the top (z above sin 50 deg),
the bottom (below -sin 20 deg: what a camera above the table cannot reach), and four sides by azimuth about
the direction of the first view (`front`: the side the scan started from; back, left and right as seen
from there). A region with less than `REGION_SEEN` of its cells seen is named, "not seen" below
`REGION_UNSEEN`, else "only partly seen", with what to do about it; a side missing mostly below the equator is
named by its lower part (all views were high above the table).

The numbers below are the definition, not settings: a stored map, another template's and the capture
preview's shares mean the same only when they are fixed.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gscan.geometry.mesh import MeshData

COVERAGE_DIRECTIONS = 96  # cells on the sphere of directions
COVERAGE_RADIUS_DEG = 20.0  # a view or a normal sees the cells this close to it (about 1.7 cell spacings)
MAX_INCIDENCE_DEG = 60.0  # a face counts as observed by a view this close to its normal
MIN_AREA_SHARE = 0.01  # of the observed surface area, facing a cell, for the surface to see that cell
TOP_Z = float(np.sin(np.radians(50.0)))  # cells above: the top
BOTTOM_Z = -float(np.sin(np.radians(20.0)))  # cells below: the bottom
REGION_SEEN = 0.6  # a region with less of its cells seen is named missing ...
REGION_UNSEEN = 0.25  # ... "not seen" below this share, "only partly seen" above

# region name -> what to do when it is missing
ACTIONS = {
    "top": "scan from higher above the object",
    "bottom": "scan the object upside down as well",
    "front": "move the camera round to the side the scan started from",
    "back": "move the camera round to the far side (or turn the object)",
    "left": "move the camera round to the left side (or turn the object)",
    "right": "move the camera round to the right side (or turn the object)",
}
LOWER_ACTION = "lower the camera towards the table's height as you go round"


def lattice(n: int = COVERAGE_DIRECTIONS) -> np.ndarray:
    """[n x 3] unit vectors of the Fibonacci lattice: z_k = 1 - (2k + 1) / n, azimuth k * pi * (1 + sqrt 5)."""
    if n < 1:
        raise ValueError(f"a lattice needs at least one direction, not {n}")
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = np.pi * (1.0 + 5.0 ** 0.5) * k
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64).reshape(-1, 3)
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)


def cells_within(directions: np.ndarray, d: np.ndarray, radius_deg: float = COVERAGE_RADIUS_DEG) -> np.ndarray:
    """[K] bool: the cells of `directions` [K x 3] within `radius_deg` of the direction `d` [3] (any length)."""
    return np.asarray(directions) @ _unit(d)[0] >= np.cos(np.radians(radius_deg))


def view_counts(view_dirs: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """[K] int64: how many of the views' directions [V x 3] (object centre to camera) lie within
    `COVERAGE_RADIUS_DEG` of each cell of `directions` [K x 3]."""
    counts = np.zeros(len(directions), dtype=np.int64)
    for d in np.asarray(view_dirs, dtype=np.float64).reshape(-1, 3):
        counts += cells_within(directions, d)
    return counts


def surface_seen(normals: np.ndarray, areas: np.ndarray, view_dirs: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """[K] bool: the cells that observed surface faces (module docstring). normals [F x 3] outward face normals,
    areas [F] (m^2), view_dirs [V x 3], directions [K x 3]."""
    N, A = _unit(normals), np.asarray(areas, dtype=np.float64).reshape(-1)
    V = _unit(view_dirs)
    if len(N) == 0 or len(V) == 0:
        return np.zeros(len(directions), dtype=bool)
    observed = (N @ V.T).max(axis=1) >= np.cos(np.radians(MAX_INCIDENCE_DEG))
    N, A = N[observed], A[observed]
    total = float(A.sum())
    if total <= 0:
        return np.zeros(len(directions), dtype=bool)
    facing = np.cos(np.radians(COVERAGE_RADIUS_DEG)) <= N @ np.asarray(directions).T  # [F' x K]
    return (A @ facing) >= MIN_AREA_SHARE * total


def regions(directions: np.ndarray, front: np.ndarray) -> dict[str, np.ndarray]:
    """Region name -> [K] bool over the cells `directions` [K x 3] (z up); the sides by azimuth about the
    horizontal direction `front` [3] (the first view's), each a quarter turn centred on its own direction."""
    D = np.asarray(directions, dtype=np.float64)
    f = np.array([front[0], front[1], 0.0], dtype=np.float64)
    f = f / np.linalg.norm(f) if np.linalg.norm(f) > 1e-6 else np.array([0.0, -1.0, 0.0])
    r = np.cross(f, [0.0, 0.0, 1.0])  # right of a viewer at `front` looking at the object
    top, bottom = D[:, 2] > TOP_Z, D[:, 2] < BOTTOM_Z
    side = ~(top | bottom)
    az = np.degrees(np.arctan2(D @ r, D @ f)) % 360.0  # 0 front, 90 right, 180 back, 270 left
    quarter = np.floor(((az + 45.0) % 360.0) / 90.0).astype(int)
    out = {"top": top, "bottom": bottom}  # the order `CoverageMap.missing` names them in
    for q, name in enumerate(("front", "right", "back", "left")):
        out[name] = side & (quarter == q)
    return out


@dataclass(frozen=True)
class CoverageMap:
    """Which cells of `lattice(len(counts))` (up frame: z up) are seen: counts [K] int (views within the radius),
    surface [K] bool (seen through observed surface normals), front [3] (the first view's direction, up frame:
    names the sides), R_up_obj [3 x 3] (object-frame directions into the up frame; identity when the object's
    z is up)."""

    counts: np.ndarray
    surface: np.ndarray
    front: np.ndarray
    R_up_obj: np.ndarray = field(default_factory=lambda: np.eye(3))

    @property
    def directions(self) -> np.ndarray:
        """[K x 3] the cells' directions (up frame)."""
        return lattice(len(self.counts))

    @property
    def directions_obj(self) -> np.ndarray:
        """[K x 3] the cells' directions in the object frame."""
        return self.directions @ np.asarray(self.R_up_obj)

    @property
    def seen(self) -> np.ndarray:
        """[K] bool."""
        return (np.asarray(self.counts) > 0) | np.asarray(self.surface, dtype=bool)

    @property
    def covered(self) -> int:
        """Cells seen."""
        return int(np.count_nonzero(self.seen))

    @property
    def share(self) -> float:
        """Seen cells / all cells."""
        return self.covered / max(len(self.counts), 1)

    def region_shares(self) -> dict[str, float]:
        """Region name -> share of its cells seen (`regions`)."""
        seen = self.seen
        return {name: float(seen[m].mean()) if m.any() else 1.0
                for name, m in regions(self.directions, self.front).items()}

    def missing(self) -> list[str]:
        """What is missing, a sentence per region (top, bottom, then the sides), with what to do. A side whose
        unseen cells lie below the equator on average is named by its lower part (the views were all high)."""
        out = []
        seen, D = self.seen, self.directions
        for name, m in regions(D, self.front).items():
            s = float(seen[m].mean()) if m.any() else 1.0
            if s >= REGION_SEEN:
                continue
            what = f"the {name}" if name in ("top", "bottom", "front", "back") else f"the {name} side"
            action = ACTIONS[name]
            if name not in ("top", "bottom") and float(D[m & ~seen, 2].mean()) < 0:
                what, action = f"the lower part of {what}", LOWER_ACTION
            how = "was not seen" if s < REGION_UNSEEN else f"was only partly seen ({s:.0%})"
            out.append(f"{what} {how}: {action}")
        return out

    def to_json(self) -> dict[str, Any]:
        """The contract's `"coverage"` object: {"share": float, "missing": [sentences]}."""
        return {"share": round(self.share, 4), "missing": self.missing()}

    def to_meta(self) -> dict[str, Any]:
        """The template's "coverage" meta value (JSON): the lattice size, per-cell counts and surface flags,
        front, R_up_obj, and the share (redundant, for readers without this module)."""
        return {"lattice": "fibonacci", "directions": len(self.counts), "radius_deg": COVERAGE_RADIUS_DEG,
                "counts": [int(c) for c in self.counts], "surface": [int(bool(s)) for s in self.surface],
                "front": [round(float(x), 6) for x in self.front],
                "R_up_obj": [[round(float(x), 9) for x in row] for row in np.asarray(self.R_up_obj)],
                "share": round(self.share, 4)}

    @classmethod
    def from_meta(cls, meta: Any) -> CoverageMap:
        """The map `to_meta` wrote; ValueError when `meta` is not one."""
        if not isinstance(meta, dict) or meta.get("lattice") != "fibonacci":
            raise ValueError("not a coverage map")
        n = meta.get("directions")
        counts, surface, front = meta.get("counts"), meta.get("surface"), meta.get("front")
        if not (isinstance(n, int) and n > 0 and isinstance(counts, list) and isinstance(surface, list)
                and len(counts) == len(surface) == n and isinstance(front, list) and len(front) == 3):
            raise ValueError("coverage map of the wrong size")
        c = np.asarray(counts, dtype=np.int64)
        if (c < 0).any():
            raise ValueError("negative view counts in the coverage map")
        R = np.asarray(meta.get("R_up_obj", np.eye(3).tolist()), dtype=np.float64)
        if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6):
            raise ValueError("the coverage map's R_up_obj is no rotation")
        return cls(c, np.asarray(surface, dtype=bool), np.asarray(front, dtype=np.float64), R)


def coverage_map(view_dirs: np.ndarray, normals: np.ndarray | None = None, areas: np.ndarray | None = None,
                 front: np.ndarray | None = None, n: int = COVERAGE_DIRECTIONS) -> CoverageMap:
    """The coverage of views [V x 3] (directions from the object's centre to the cameras, z up), and of the
    observed surface (normals [F x 3] outward, areas [F]) when given; front [3]: the first view's direction
    by default."""
    D = lattice(n)
    V = _unit(view_dirs)
    counts = view_counts(V, D)
    surface = (surface_seen(normals, np.ones(len(normals)) if areas is None else areas, V, D)
               if normals is not None else np.zeros(n, dtype=bool))
    f = np.asarray(front, dtype=np.float64) if front is not None else (V[0] if len(V) else np.array([0.0, -1.0, 0.0]))
    return CoverageMap(counts, surface, f)


def viewing_directions(T_obj_cam: Sequence[np.ndarray], center: np.ndarray) -> np.ndarray:
    """[V x 3] unit directions from `center` [3] to each camera centre (T_obj_cam [4 x 4], object frame)."""
    C = np.array([np.asarray(T, dtype=np.float64)[:3, 3] for T in T_obj_cam]).reshape(-1, 3)
    return _unit(C - np.asarray(center, dtype=np.float64))


def outward_faces(mesh: MeshData) -> tuple[np.ndarray, np.ndarray]:
    """(normals [F x 3] unit, areas [F] m^2) of the mesh's faces that hole filling did not add, oriented
    outwards as a whole (flipped when they point, by area, towards the mesh's centre: the TSDF's winding is
    not fixed)."""
    V = np.asarray(mesh.vertices, dtype=np.float64)
    F = np.asarray(mesh.triangles, dtype=np.int64).reshape(-1, 3)
    if mesh.filled is not None:
        F = F[~np.asarray(mesh.filled, dtype=bool)]
    if len(F) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    cross = np.cross(b - a, c - a)
    areas = 0.5 * np.linalg.norm(cross, axis=1)
    normals = _unit(cross)
    centre = 0.5 * (V.min(0) + V.max(0))
    if float(np.sum(areas * np.einsum("ij,ij->i", normals, (a + b + c) / 3.0 - centre))) < 0:
        normals = -normals
    return normals, areas


def up_rotation(up: np.ndarray) -> np.ndarray:
    """R_up_obj [3 x 3]: object-frame directions into a frame whose z is `up` [3] (object frame) and whose x is
    the object's x made perpendicular to it (its y when x is along `up`)."""
    z = _unit(up)[0]
    x = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = _unit(x - (x @ z) * z)[0]
    return np.stack([x, np.cross(z, x), z])


def template_coverage(T_obj_cam: Sequence[np.ndarray], mesh: MeshData | None,
                      up: np.ndarray | Sequence[float] | None = None) -> CoverageMap:
    """The coverage of a template: its registered views' poses (T_obj_cam [4 x 4]) and its mesh's observed
    faces; directions from the centre of the mesh's bounding box (the origin without a mesh). up [3]: the
    object's up in its frame (default +z, a scan's support-plane normal)."""
    R = np.eye(3) if up is None else up_rotation(np.asarray(up, dtype=np.float64))
    if mesh is not None and len(mesh.vertices):
        V = np.asarray(mesh.vertices, dtype=np.float64)
        centre = 0.5 * (V.min(0) + V.max(0))
        normals, areas = outward_faces(mesh)
        normals = normals @ R.T
    else:
        centre, normals, areas = np.zeros(3), None, None
    c = coverage_map(viewing_directions(T_obj_cam, centre) @ R.T, normals, areas)
    return CoverageMap(c.counts, c.surface, c.front, R)
