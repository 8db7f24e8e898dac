"""Nearest neighbour within a radius by a uniform grid (numba), the query of ICP and of the keypoint support.

`NearestGrid(points, radius).query(q)` finds, for each query point, the nearest of `points` closer than
`radius` (squared distance (dx^2 + dy^2) + dz^2 < radius^2, the sum and the test scipy's cKDTree.query with
distance_upper_bound makes), or none. The grid's cells are a little larger than the radius, so that every
point within the radius lies in the 27 cells around the query's cell whatever the rounding of the cell
coordinates. Ties (two points at exactly the same distance) go to the lower index. A grid would hold too many
cells for points spread far wider than the radius: `NearestGrid.build` returns None then. Compiled with
`cache=True`, `nogil=True`; imported on first use, so that importing `gscan.geometry` does not load numba.
"""
from __future__ import annotations

import numpy as np
from numba import njit

MAX_CELLS = 1 << 22


@njit(cache=True, nogil=True)
def _cell_of(x, lo, cell, n):
    """Cell index along one axis of coordinate x, or -2 / n + 1 when the cell lies beyond the grid by more than
    one (its neighbours cannot be in the grid either)."""
    f = (x - lo) / cell
    if f < -1.0:
        return -2
    if f >= n + 1.0:
        return n + 1
    return int(np.floor(f))


@njit(cache=True, nogil=True)
def _build(P, lo, cell, dims):
    """(starts [cells + 1], members [N]): the points of cell c are members[starts[c]:starts[c+1]], ascending."""
    n = P.shape[0]
    ncell = dims[0] * dims[1] * dims[2]
    cid = np.empty(n, np.int64)
    starts = np.zeros(ncell + 1, np.int64)
    for i in range(n):
        ix = min(max(_cell_of(P[i, 0], lo[0], cell, dims[0]), 0), dims[0] - 1)
        iy = min(max(_cell_of(P[i, 1], lo[1], cell, dims[1]), 0), dims[1] - 1)
        iz = min(max(_cell_of(P[i, 2], lo[2], cell, dims[2]), 0), dims[2] - 1)
        c = (ix * dims[1] + iy) * dims[2] + iz
        cid[i] = c
        starts[c + 1] += 1
    for c in range(ncell):
        starts[c + 1] += starts[c]
    fill = starts[:-1].copy()
    members = np.empty(n, np.int64)
    for i in range(n):
        members[fill[cid[i]]] = i
        fill[cid[i]] += 1
    return starts, members


@njit(cache=True, nogil=True)
def _query(Q, SP, starts, members, lo, cell, dims, r2, found, nearest):
    """SP [N x 3]: the points in members' order (cell by cell), so that the three cells along z around a
    query are one run of memory."""
    for k in range(Q.shape[0]):
        qx, qy, qz = Q[k, 0], Q[k, 1], Q[k, 2]
        ix = _cell_of(qx, lo[0], cell, dims[0])
        iy = _cell_of(qy, lo[1], cell, dims[1])
        iz = _cell_of(qz, lo[2], cell, dims[2])
        c0, c1 = max(iz - 1, 0), min(iz + 1, dims[2] - 1)
        best = r2
        arg = -1
        if c0 <= c1:
            for a in range(max(ix - 1, 0), min(ix + 1, dims[0] - 1) + 1):
                for b in range(max(iy - 1, 0), min(iy + 1, dims[1] - 1) + 1):
                    base = (a * dims[1] + b) * dims[2]
                    for s in range(starts[base + c0], starts[base + c1 + 1]):
                        dx = qx - SP[s, 0]
                        dy = qy - SP[s, 1]
                        dz = qz - SP[s, 2]
                        d2 = dx * dx + dy * dy + dz * dz
                        if d2 < best or (d2 == best and arg >= 0 and members[s] < arg):
                            best = d2
                            arg = members[s]
        found[k] = arg >= 0
        nearest[k] = arg


class NearestGrid:
    """Points [N x 3] float64 on a grid of cells a little larger than `radius` (module docstring)."""

    def __init__(self, points: np.ndarray, radius: float, lo: np.ndarray, dims: np.ndarray):
        self.points = points
        self.radius = float(radius)
        self.lo = lo
        self.cell = 1.001 * self.radius
        self.dims = dims
        self.starts, self.members = _build(points, lo, self.cell, dims)
        self.sorted = np.ascontiguousarray(points[self.members])

    @classmethod
    def build(cls, points: np.ndarray, radius: float, max_cells: int = MAX_CELLS) -> NearestGrid | None:
        """The grid of points [N x 3] (N >= 1) for queries within radius > 0, or None when it would need more
        than max_cells cells."""
        points = np.ascontiguousarray(points, dtype=np.float64)
        lo, hi = points.min(axis=0), points.max(axis=0)
        ext = np.floor((hi - lo) / (1.001 * radius)) + 1
        if not np.all(np.isfinite(ext)) or float(np.prod(ext)) > max_cells:
            return None
        return cls(points, radius, lo, ext.astype(np.int64))

    def query(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(found [K] bool, nearest [K] int64: the index of the nearest point within the radius, -1 when none)
        of query points q [K x 3]."""
        q = np.ascontiguousarray(q, dtype=np.float64)
        found = np.empty(len(q), np.bool_)
        nearest = np.empty(len(q), np.int64)
        _query(q, self.sorted, self.starts, self.members, self.lo, self.cell, self.dims,
               self.radius * self.radius, found, nearest)
        return found, nearest
