"""Holes of a triangle mesh: boundary edges and loops, and closing them so the mesh is watertight.

A scanned object's mesh is open where no camera saw its surface, above all at the bottom, where the
support plane cut it. `close_holes` makes it watertight: a loop at the bottom gets vertical walls down to the
plane (`floor_z`, in a frame whose z axis is the plane's normal, as the template frame's is) and a flat cap
there, so the model stands on the plane with its full volume; any other loop is closed by a fan. Every added
triangle runs the loop's edges the other way, so every edge ends up shared by exactly two triangles of
consistent winding.
"""
from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass

import numpy as np

FLOOR_GAP = 1e-4  # m: the floor lies at least this far below a bottom loop's lowest vertex


def boundary_edges(triangles: np.ndarray) -> np.ndarray:
    """[B x 2] directed edges (a, b) of the triangles [F x 3] used by one triangle alone, in the direction that
    triangle runs them (no other triangle runs b -> a or a -> b). Empty for a watertight mesh."""
    F = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if len(F) == 0:
        return np.zeros((0, 2), np.int64)
    directed = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    undirected = np.sort(directed, axis=1)
    _, inverse, counts = np.unique(undirected, axis=0, return_inverse=True, return_counts=True)
    return directed[counts[inverse.reshape(-1)] == 1]


def non_manifold_edges(triangles: np.ndarray) -> int:
    """Number of undirected edges of the triangles [F x 3] shared by more than two triangles."""
    F = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if len(F) == 0:
        return 0
    undirected = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    return int((np.unique(undirected, axis=0, return_counts=True)[1] > 2).sum())


def boundary_loops(triangles: np.ndarray) -> list[np.ndarray]:
    """The boundary edges of the triangles [F x 3] chained into closed loops: a list of [n] vertex index arrays,
    each running in the direction of its edges (v[i] -> v[i+1] -> ... -> v[0]). Where loops touch at a vertex,
    they are split there; deterministic (loops start at their smallest edge)."""
    edges = boundary_edges(triangles)
    out_edges: dict[int, list[int]] = defaultdict(list)
    for a, b in sorted(map(tuple, edges.tolist())):
        out_edges[a].append(b)
    loops = []
    for start in sorted(out_edges):
        while out_edges[start]:
            loop = [start]
            v = out_edges[start].pop(0)
            while v != start:
                if not out_edges[v]:  # an open chain (inconsistent winding): not a loop
                    loop = []
                    break
                loop.append(v)
                v = out_edges[v].pop(0)
            if len(loop) >= 3:
                loops.append(np.asarray(loop, dtype=np.int64))
    return loops


def ear_clip(poly: np.ndarray) -> np.ndarray:
    """Triangulate a polygon [n x 2] (vertices in order, either winding): [n-2 x 3] indices into it, each
    triangle running the same way round as the polygon. Always returns n-2 triangles: where no proper ear is
    left (a self-intersecting outline), the most convex corner is cut anyway, so the polygon's edges are
    each used exactly once."""
    P = np.asarray(poly, dtype=np.float64).reshape(-1, 2)
    n = len(P)
    if n < 3:
        return np.zeros((0, 3), np.int64)
    x, y = P[:, 0], P[:, 1]
    area2 = float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
    sign = 1.0 if area2 >= 0 else -1.0
    idx = list(range(n))
    tris = []

    def turn(a: int, b: int, c: int) -> float:  # > 0: a convex corner at b (in the polygon's winding)
        return sign * ((P[b, 0] - P[a, 0]) * (P[c, 1] - P[b, 1]) - (P[b, 1] - P[a, 1]) * (P[c, 0] - P[b, 0]))

    i = 0
    misses = 0
    while len(idx) > 3:
        m = len(idx)
        a, b, c = idx[(i - 1) % m], idx[i % m], idx[(i + 1) % m]
        is_ear = turn(a, b, c) > 0
        if is_ear:
            others = np.array([j for j in idx if j not in (a, b, c)], dtype=np.int64)
            if len(others):
                q = P[others]
                # inside or on the triangle a, b, c (same side of all three edges)
                d1 = sign * ((P[b, 0] - P[a, 0]) * (q[:, 1] - P[a, 1]) - (P[b, 1] - P[a, 1]) * (q[:, 0] - P[a, 0]))
                d2 = sign * ((P[c, 0] - P[b, 0]) * (q[:, 1] - P[b, 1]) - (P[c, 1] - P[b, 1]) * (q[:, 0] - P[b, 0]))
                d3 = sign * ((P[a, 0] - P[c, 0]) * (q[:, 1] - P[c, 1]) - (P[a, 1] - P[c, 1]) * (q[:, 0] - P[c, 0]))
                is_ear = not bool(np.any((d1 >= 0) & (d2 >= 0) & (d3 >= 0)))
        if not is_ear and misses >= m:  # a full round without an ear: cut the most convex corner
            turns = [turn(idx[(k - 1) % m], idx[k], idx[(k + 1) % m]) for k in range(m)]
            i = int(np.argmax(turns))
            a, b, c = idx[(i - 1) % m], idx[i], idx[(i + 1) % m]
            is_ear = True
        if is_ear:
            tris.append((a, b, c))
            idx.pop(i % m)
            i = i % max(len(idx), 1)
            misses = 0
        else:
            i = (i + 1) % m
            misses += 1
    tris.append((idx[0], idx[1], idx[2]))
    return np.asarray(tris, dtype=np.int64)


@dataclass
class ClosedMesh:
    """A mesh with its holes closed: vertices [V x 3], triangles [F x 3], vertex colours [V x 3] or None (the
    input's first vertices and triangles come first, unchanged); holes closed, bottom loops walled down to
    the floor, and the boundary edges left (0 when every loop could be closed)."""

    vertices: np.ndarray
    triangles: np.ndarray
    vertex_colors: np.ndarray | None
    holes_closed: int
    bottom_loops: int
    boundary_edges_left: int


def close_holes(vertices: np.ndarray, triangles: np.ndarray, vertex_colors: np.ndarray | None = None,
                floor_z: float | None = None, bottom_band: float = 0.25) -> ClosedMesh:
    """Close every boundary loop of the mesh (vertices [V x 3], triangles [F x 3], colours [V x C] or None).

    With `floor_z` (the support plane's height; z is its normal, pointing away from it), a loop whose
    vertices all lie in the lowest `bottom_band` of the mesh's height and whose missing surface faces down
    (its area vector within 60 deg of -z) is a cut bottom: each of its vertices gets a copy at
    z = min(floor_z, the loop's lowest z - FLOOR_GAP), walls join the loop to the copies and a flat cap,
    ear-clipped, closes them. Other loops (holes in the sides) are closed by a fan from a new vertex at their
    centroid. The winding of the added triangles follows the mesh's, so a mesh whose triangles face outwards
    stays so and its volume is that of the closed surface."""
    V = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    F = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    C = None if vertex_colors is None else np.asarray(vertex_colors)
    loops = boundary_loops(F)
    new_V: list[np.ndarray] = []
    new_C: list[np.ndarray] = []
    new_F: list[np.ndarray] = []
    n_v = len(V)
    z_lo, z_hi = (float(V[:, 2].min()), float(V[:, 2].max())) if len(V) else (0.0, 0.0)
    bottom = 0
    for loop in loops:
        pts = V[loop]
        # the missing surface's area vector (the cap's, running the loop backwards): down for a cut bottom
        cap_area = -0.5 * np.cross(pts - pts.mean(0), np.roll(pts, -1, axis=0) - pts.mean(0)).sum(0)
        facing_down = cap_area[2] < -0.5 * np.linalg.norm(cap_area)
        in_band = bool(np.all(pts[:, 2] <= z_lo + bottom_band * (z_hi - z_lo)))
        if floor_z is not None and facing_down and in_band:
            bottom += 1
            # a floor at least FLOOR_GAP below the loop, so no copy coincides with its vertex
            z_cap = min(float(floor_z), float(pts[:, 2].min()) - FLOOR_GAP)
            w = np.arange(n_v, n_v + len(loop))
            floor = pts.copy()
            floor[:, 2] = z_cap
            new_V.append(floor)
            if C is not None:
                new_C.append(C[loop])
            n_v += len(loop)
            nxt_v, nxt_w = np.roll(loop, -1), np.roll(w, -1)
            # the loop runs v[i] -> v[i+1] in its one triangle; the wall runs it back, down to the copies
            new_F.append(np.stack([nxt_v, loop, w], axis=1))
            new_F.append(np.stack([nxt_v, w, nxt_w], axis=1))
            # the cap runs the copies backwards (w[i+1] -> w[i]): each copy edge is used once more, the other way
            order = np.arange(len(w))[::-1]
            new_F.append(w[order][ear_clip(floor[order, :2])])
        else:
            # a fan from a new vertex at the loop's centroid: its edges are all new, so no cap edge can coincide
            # with an edge the mesh already has (an ear-clipped diagonal between two loop vertices could)
            c = n_v
            new_V.append(pts.mean(0, keepdims=True))
            if C is not None:
                new_C.append(np.asarray(C[loop], dtype=np.float64).mean(0, keepdims=True).astype(C.dtype))
            n_v += 1
            new_F.append(np.stack([np.roll(loop, -1), loop, np.full(len(loop), c)], axis=1))
    out_V = np.concatenate([V] + new_V) if new_V else V
    out_F = np.concatenate([F] + new_F) if new_F else F
    out_C = None if C is None else (np.concatenate([C] + new_C) if new_C else C)
    left = len(boundary_edges(out_F))
    return ClosedMesh(out_V, out_F.astype(np.int32), out_C, len(loops), bottom, left)
