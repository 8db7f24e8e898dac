"""Holes of a triangle mesh: boundary edges and loops, and closing them so the mesh is watertight.

A scanned object's mesh is open where no camera saw its surface, above all at the bottom, where the
support plane cut it. `close_holes` makes it watertight: a loop at the bottom gets vertical walls down to the
plane (`floor_z`, in a frame whose z axis is the plane's normal, as the template frame's is) and a flat cap
there, so the model stands on the plane with its full volume; any other loop is closed by a fan. Every added
triangle runs the loop's edges the other way, so every edge ends up shared by exactly two triangles of
consistent winding. `close_holes_cleanly` (the exports') first cuts a ragged bottom flat (`cut_below`) and
repairs what still crosses (`self_intersecting_pairs`), so that no two triangles of the result cross either.
"""
from __future__ import annotations

import logging
from collections import defaultdict
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

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


CHUNK_EDGES = 12.0  # the self-intersection test's cells: this many median edge lengths wide
MAX_REPAIR_ROUNDS = 8


def self_intersecting_pairs(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """[P x 2] sorted index pairs (i < j) of triangles [F x 3] that intersect while sharing no vertex, by open3d's
    own test (`TriangleMesh.get_self_intersecting_triangles`, the one `is_watertight` makes). Open3d compares all
    pairs (quadratic: 7 s for 34k triangles), so it runs here per cell of a grid: each triangle goes to every
    cell its bounding box touches, and two triangles that intersect share a cell."""
    import open3d as o3d

    V = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    F = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if len(F) < 2:
        return np.zeros((0, 2), np.int64)
    P = V[F]  # [F x 3 x 3]
    edge = float(np.median(np.linalg.norm(P[:, 1] - P[:, 0], axis=1)))
    lo = P.min(1).min(0)
    cell = max(CHUNK_EDGES * edge, float(np.ptp(P.reshape(-1, 3), axis=0).max()) / 64, 1e-12)
    c0 = np.floor((P.min(1) - lo) / cell).astype(np.int64)  # [F x 3] first and last cell of each box
    c1 = np.floor((P.max(1) - lo) / cell).astype(np.int64)
    span = c1 - c0 + 1
    dims = c1.max(0) + 1
    tri, key = [], []
    for dx in range(int(span[:, 0].max())):  # boxes spanning several cells (long cap triangles) go to each
        for dy in range(int(span[:, 1].max())):
            for dz in range(int(span[:, 2].max())):
                sel = np.flatnonzero((span[:, 0] > dx) & (span[:, 1] > dy) & (span[:, 2] > dz))
                c = c0[sel] + [dx, dy, dz]
                tri.append(sel)
                key.append((c[:, 0] * dims[1] + c[:, 1]) * dims[2] + c[:, 2])
    tri_all, key_all = np.concatenate(tri), np.concatenate(key)
    order = np.argsort(key_all, kind="stable")
    tri_all, key_all = tri_all[order], key_all[order]
    starts = np.flatnonzero(np.r_[True, key_all[1:] != key_all[:-1]])
    pairs = []
    for s, e in zip(starts, np.r_[starts[1:], len(key_all)], strict=True):
        if e - s < 2:
            continue
        members = tri_all[s:e]
        used, local = np.unique(F[members], return_inverse=True)  # shared vertices stay shared
        m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V[used]),
                                      o3d.utility.Vector3iVector(local.reshape(-1, 3).astype(np.int32)))
        hit = np.asarray(m.get_self_intersecting_triangles(), dtype=np.int64).reshape(-1, 2)
        if len(hit):
            pairs.append(np.sort(members[hit], axis=1))
    return np.unique(np.concatenate(pairs), axis=0) if pairs else np.zeros((0, 2), np.int64)


def _vertex_fans(triangles: np.ndarray, n_vertices: int) -> np.ndarray:
    """[V] number of edge-connected fans of the triangles [F x 3] around each vertex (1 on a manifold, 0 unused).
    Open3d's `is_vertex_manifold` refuses a vertex of more than one (two holes touching there)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    F = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    fans = np.zeros(n_vertices, np.int64)
    if len(F) == 0:
        return fans
    # nodes: (vertex, neighbour) pairs; the corner of a triangle at v joins its two other vertices' pairs
    v, a, b = F.ravel(), F[:, [1, 2, 0]].ravel(), F[:, [2, 0, 1]].ravel()
    keys = np.unique(np.concatenate([v * n_vertices + a, v * n_vertices + b]))
    ia, ib = np.searchsorted(keys, v * n_vertices + a), np.searchsorted(keys, v * n_vertices + b)
    graph = coo_matrix((np.ones(len(ia)), (ia, ib)), shape=(len(keys), len(keys)))
    n_comp, comp = connected_components(graph, directed=False)
    comp_owner = np.zeros(n_comp, np.int64)
    comp_owner[comp] = keys // n_vertices
    np.add.at(fans, comp_owner, 1)
    return fans


def cut_below(vertices: np.ndarray, triangles: np.ndarray, vertex_colors: np.ndarray | None,
              z_cut: float) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The mesh (vertices [V x 3], triangles [F x 3], colours [V x C] or None) with everything below the plane
    z = z_cut removed: triangles the plane crosses are split along it (one new vertex per crossed edge, shared
    by its two triangles, colour interpolated), so the cut leaves loops lying in the plane. Returns vertices
    (the input's still used, in order, then the new ones), triangles (winding kept) and colours. No vertex may
    lie on the plane (`close_holes_cleanly` moves it off)."""
    V = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    F = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    above = V[:, 2] > z_cut
    n_up = above[F].sum(1)
    out_F = [F[n_up == 3]]
    cross = F[(n_up == 1) | (n_up == 2)]
    # rotate each crossed triangle so that its odd vertex (alone on its side) comes first, winding kept
    odd_first = np.where(above[cross].sum(1, keepdims=True) == 1, above[cross], ~above[cross])
    shift = np.argmax(odd_first, axis=1)
    idx = (shift[:, None] + np.arange(3)) % 3
    T = np.take_along_axis(cross, idx, axis=1)
    edges = np.sort(np.concatenate([T[:, [0, 1]], T[:, [0, 2]]]), axis=1)
    uniq, inv = np.unique(edges, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    za, zb = V[uniq[:, 0], 2], V[uniq[:, 1], 2]
    w = ((z_cut - za) / (zb - za))[:, None]  # the plane between the two ends: 0 < w < 1
    new_V = V[uniq[:, 0]] * (1 - w) + V[uniq[:, 1]] * w
    new_V[:, 2] = z_cut
    p01 = len(V) + inv[: len(T)]  # the new vertex on edge (odd, next)
    p02 = len(V) + inv[len(T):]  # ... on edge (odd, previous)
    up = above[T[:, 0]]
    out_F.append(np.stack([T[up, 0], p01[up], p02[up]], axis=1))  # the odd vertex alone above: a triangle
    dn = ~up  # the odd vertex alone below: the quad (next, previous, p02, p01) above, in two triangles
    out_F.append(np.stack([T[dn, 1], T[dn, 2], p02[dn]], axis=1))
    out_F.append(np.stack([T[dn, 1], p02[dn], p01[dn]], axis=1))
    all_V = np.concatenate([V, new_V])
    all_F = np.concatenate(out_F)
    C = None
    if vertex_colors is not None:
        C0 = np.asarray(vertex_colors)
        mixed = C0[uniq[:, 0]].astype(np.float64) * (1 - w) + C0[uniq[:, 1]].astype(np.float64) * w
        C = np.concatenate([C0, np.rint(mixed).astype(C0.dtype) if C0.dtype.kind in "iu" else mixed.astype(C0.dtype)])
    used = np.zeros(len(all_V), bool)
    used[all_F.ravel()] = True
    new_index = np.cumsum(used) - 1
    return all_V[used], new_index[all_F], None if C is None else C[used]


def _clear_plane(z: np.ndarray, z_min: float, edge: float) -> float:
    """A height above z_min (within an edge length) as far as can be from every vertex height z [V]: the middle
    of the widest gap between them. A plane passing close to a vertex would cut its edges next to it, into
    vertices as close to each other, whose walls and cap then touch."""
    zs = np.unique(np.concatenate([[z_min, z_min + edge], z[(z > z_min) & (z < z_min + edge)]]))
    k = int(np.argmax(np.diff(zs)))
    return float(zs[k] + zs[k + 1]) / 2


def _bottom_top(V: np.ndarray, F: np.ndarray, floor_z: float, bottom_band: float) -> float | None:
    """The highest vertex z of the mesh's bottom loops (`close_holes`'s rule), or None when it has none."""
    c = close_holes(V, F, None, floor_z=floor_z, bottom_band=bottom_band)
    if c.bottom_loops == 0:
        return None
    added = c.triangles[len(F):]
    low = np.any(c.vertices[added, 2] < V[F, 2].min(), axis=1)  # walls and caps reach below every input vertex
    v = np.unique(added[low].ravel())
    v = v[v < len(V)]
    return float(V[v, 2].max()) if len(v) else None


def weld_coincident(V: np.ndarray, F: np.ndarray, C: np.ndarray | None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Vertices [N x 3] at the same place merged into their first occurrence (order kept), triangles [F x 3]
    re-indexed, colours [N x k] of the kept vertices: a mesh written with a vertex per face corner (a CAD model's
    texture seams) has every triangle's edges on a boundary, and closing those "holes" would stack caps over it.
    A mesh without coincident vertices (a fused scan) comes back unchanged."""
    _, first, inverse = np.unique(V, axis=0, return_index=True, return_inverse=True)
    if len(first) == len(V):
        return V, F, C
    order = np.argsort(first)  # the kept vertices in the order of their first occurrence
    rank = np.empty(len(first), np.int64)
    rank[order] = np.arange(len(first))
    keep = first[order]
    return V[keep], rank[inverse.reshape(-1)][F], None if C is None else C[keep]


def close_holes_cleanly(vertices: np.ndarray, triangles: np.ndarray, vertex_colors: np.ndarray | None = None,
                        floor_z: float | None = None, bottom_band: float = 0.25) -> tuple[ClosedMesh, np.ndarray]:
    """`close_holes` with no two triangles crossing (`self_intersecting_pairs`, open3d's test).

    A cut bottom's boundary is ragged: walls hanging straight down from it fold over each other and through the
    surface under its overhangs. So the mesh is first cut flat (`cut_below`) just above its bottom loops'
    highest vertex (again, until the loops a cut leaves lie in its plane): walls down from a plane section of the
    surface cross nothing. Then holes are closed, and the observed triangles of any crossing left (a fan through
    the surface, the fused surface folded through itself), and those around the loop vertices of an added one
    (one edge-ring more each round), are removed and the holes closed again, up to MAX_REPAIR_ROUNDS times.
    Triangles at vertices with two separate fans (a hole touching itself) are removed too.

    Returns the closed mesh (the observed vertices kept, in order, then the added ones; the observed triangles
    kept, then the added ones) and `filled` [F] bool, True for the added triangles. Warns when crossings remain."""
    V, F, C = weld_coincident(np.asarray(vertices, dtype=np.float64).reshape(-1, 3),
                              np.asarray(triangles, dtype=np.int64).reshape(-1, 3),
                              None if vertex_colors is None else np.asarray(vertex_colors))
    edge = float(np.median(np.linalg.norm(V[F[:, 1]] - V[F[:, 0]], axis=1))) if len(F) else 0.0
    z_cut = None if floor_z is None or len(F) == 0 else _bottom_top(V, F, floor_z, bottom_band)
    for _ in range(MAX_REPAIR_ROUNDS):
        if z_cut is None:
            break
        z_cut = _clear_plane(V[:, 2], z_cut, edge)
        V, F, C = cut_below(V, F, C, z_cut)
        top = _bottom_top(V, F, floor_z, bottom_band)  # type: ignore[arg-type]
        if top is None or top <= z_cut + 1e-6 * edge:
            break
        z_cut = top  # a hole reached down into the cut: cut above it
    if z_cut is not None:
        log.info("closing holes: the mesh cut flat at z = %+.4f m above its bottom", z_cut)
    keep = np.ones(len(F), bool)
    for rnd in range(MAX_REPAIR_ROUNDS + 1):
        fans = _vertex_fans(F[keep], len(V))
        while np.any(fans > 1):  # a vertex where the kept triangles form two fans: open it up
            keep[np.flatnonzero(keep)[np.any(fans[F[keep]] > 1, axis=1)]] = False
            fans = _vertex_fans(F[keep], len(V))
        kept = np.flatnonzero(keep)
        c = close_holes(V, F[kept], C, floor_z=floor_z, bottom_band=bottom_band)
        pairs = self_intersecting_pairs(c.vertices, c.triangles)
        if len(pairs) == 0 or rnd == MAX_REPAIR_ROUNDS:
            break
        involved = np.unique(pairs)
        drop = np.zeros(len(F), bool)
        drop[kept[involved[involved < len(kept)]]] = True
        seeds = np.unique(c.triangles[involved[involved >= len(kept)]].ravel())
        drop[kept[_ring(F[kept], seeds[seeds < len(V)], rnd + 1)]] = True
        log.info("closing holes, round %d: %d pairs of crossing triangles; %d observed triangles removed", rnd + 1,
                 len(pairs), int(drop.sum()))
        keep &= ~drop
    if len(pairs):
        log.warning("the closed mesh still has %d pairs of crossing triangles", len(pairs))
    used = np.zeros(len(c.vertices), bool)  # drop the observed vertices no triangle uses any more
    used[c.triangles.ravel()] = True
    used[len(V):] = True
    new_index = np.cumsum(used) - 1
    out = ClosedMesh(c.vertices[used], new_index[c.triangles].astype(np.int32),
                     None if c.vertex_colors is None else c.vertex_colors[used], c.holes_closed, c.bottom_loops,
                     c.boundary_edges_left)
    return out, np.arange(len(c.triangles)) >= len(kept)


def _ring(triangles: np.ndarray, seeds: np.ndarray, rings: int) -> np.ndarray:
    """[F] bool: the triangles [F x 3] within `rings` edge-rings of the vertices `seeds`."""
    F = np.asarray(triangles, dtype=np.int64)
    near = np.zeros(int(F.max()) + 1 if len(F) else 0, bool)
    near[seeds] = True
    hit = np.zeros(len(F), bool)
    for _ in range(rings if len(seeds) else 0):
        hit = np.any(near[F], axis=1)
        near[F[hit].ravel()] = True
    return hit
