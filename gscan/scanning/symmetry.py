"""An object's symmetries found on its template's surface: discrete 2- and 4-fold turns about its principal axes and
continuous revolution, each holding in shape alone or in shape and texture (`gscan.geometry.symmetry.Symmetries`).

Shape: the surface is sampled evenly by area (a dense reference set and a sparser test set, seeded). The candidate
axes are the principal axes of the area-weighted surface, through the centre of its bounding box in those axes. A
candidate rotation S holds when the rotated test samples S p lie on the surface: within `tol` of the reference set
for `inlier_share` of the samples tested. Revolution (S at every `360 / continuous_steps` degrees) is tested first;
about an axis of revolution only a flip end over end (about any perpendicular axis) is left to find. Otherwise each
axis gets a 4-fold, else a 2-fold test. A 4-fold axis has no preferred perpendicular direction (equal moments), so
unless a perpendicular turn is known, its perpendicular 2-fold axes are searched by angle in that plane (the least
residual). The discrete list is the closure (the group) of the turns found, the identity left out, each element
tested again (shape and texture).

Tolerance: `tol = spacing + tolerance_sigmas * surface_sigma`, with the reference set's sample spacing and the
template's own surface error: for a scan the fused surface's voxel (quantisation, voxel / 2) and the capture's depth
noise at the cameras' median distance from the object (its "noise" meta), combined in quadrature; for a mesh its
template cloud's voxel / 2.

Not searched: 3- and 6-fold turns, and the turns of a shape whose three principal moments are equal (a cube, a
sphere: its principal axes are arbitrary); a symmetry left unfound keeps poses apart, the safe side.

Unseen parts: a scanned surface is open where no camera saw it (above all the bottom, cut by the support plane). A
rotated sample that lands off the surface but no farther from an open boundary than from the surface (plus `tol`)
fell into such a hole: it is not tested, neither for nor against. A symmetry needs at least `min_tested_share` of the
samples tested, so an unseen part can neither make one nor break one.

Texture: each sample's appearance is its colour divided by the mean intensity of its neighbourhood, so smooth shading
baked into a scan's colours cancels while print and colour changes stay. Per tested sample, agreement means an
appearance difference at S p no larger than the median difference under the identity moved by the tolerance (what
the shape test allows); so the identity agrees for half of the samples and unrelated points for `f_rand` of them.
S holds in texture unless its agreeing share lies below the midpoint of those two and significantly (4 standard
errors) below one half: a plain surface, whose unrelated points agree as often as near ones, holds in texture.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from gscan.geometry.mesh import MeshData, to_u8_colors
from gscan.geometry.meshfill import boundary_edges
from gscan.geometry.symmetry import Symmetries, axis_rotation
from gscan.registration.noise import DepthNoise
from gscan.scanning.params import SymmetryParams
from gscan.synth.mesh import TexturedMesh, sample_bilinear
from gscan.template.db import TemplateDB

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Surface:
    """Samples of an object's surface: points [N x 3] (m, object frame), colours [N x 3] float (0-255, or None),
    the open boundary's samples [B x 3] (holes: unseen parts), and the surface's area (m^2)."""

    points: np.ndarray
    colors: np.ndarray | None
    boundary: np.ndarray
    area: float


def _sample_triangles(V: np.ndarray, F: np.ndarray, n: int, rng: np.random.Generator
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n points spread by area over the triangles: (points [n x 3], face index [n], barycentrics [n x 3])."""
    tri = V[F]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    face = rng.choice(len(F), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    bary = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    return np.einsum("nk,nkd->nd", bary, tri[face]), face, bary


WELD_M = 1e-6  # vertices this close are one (a mesh's copies of a vertex at a texture seam)


def _boundary_points(V: np.ndarray, F: np.ndarray, step: float) -> np.ndarray:
    """[B x 3] points every `step` (m) along the mesh's open edges (none for a closed mesh). Copies of a vertex (at
    texture seams, or a mesh whose faces share none) are welded first: their edges are not holes."""
    _, first, inverse = np.unique(np.round(V / WELD_M).astype(np.int64), axis=0, return_index=True,
                                  return_inverse=True)
    V, F = V[first], inverse.reshape(-1)[F]
    F = F[(F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])]
    E = boundary_edges(F)
    if len(E) == 0:
        return np.zeros((0, 3))
    a, b = V[E[:, 0]], V[E[:, 1]]
    k = np.maximum(1, np.ceil(np.linalg.norm(b - a, axis=1) / step)).astype(int)
    t = np.concatenate([np.arange(m) / m for m in k])
    return np.repeat(a, k, axis=0) + t[:, None] * np.repeat(b - a, k, axis=0)


def surface_of_mesh(mesh: MeshData, n: int, seed: int = 0) -> Surface:
    """The surface of a mesh with per-vertex colours (a scan's fused mesh), `n` samples."""
    V = np.asarray(mesh.vertices, np.float64)
    F = np.asarray(mesh.triangles, np.int64)
    P, face, bary = _sample_triangles(V, F, n, np.random.default_rng(seed))
    C = None
    if mesh.vertex_colors is not None:
        VC = to_u8_colors(mesh.vertex_colors).astype(np.float64)
        C = np.einsum("nk,nkd->nd", bary, VC[F[face]])
    area = _area(V, F)
    return Surface(P, C, _boundary_points(V, F, 0.5 * np.sqrt(area / n)), area)


def surface_of_textured_mesh(mesh: TexturedMesh, n: int, seed: int = 0) -> Surface:
    """The surface of a textured mesh (a CAD model), `n` samples coloured from its texture image."""
    V, F = mesh.vertices, mesh.triangles.astype(np.int64)
    P, face, bary = _sample_triangles(V, F, n, np.random.default_rng(seed))
    uv = np.einsum("nk,nkd->nd", bary, mesh.uv[face])
    C = sample_bilinear(mesh.texture, uv).astype(np.float64)
    area = _area(V, F)
    return Surface(P, C, _boundary_points(V, F, 0.5 * np.sqrt(area / n)), area)


def _area(V: np.ndarray, F: np.ndarray) -> float:
    tri = V[F]
    return float(0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())


@dataclass(frozen=True)
class _Verdict:
    holds: bool  # in shape
    inliers: float  # share of the tested samples within the tolerance
    tested: float  # share of the samples tested (not fallen into a hole)
    texture: bool  # holds in texture too (meaningful when `holds`)
    residual: float  # mean distance (m) of the tested samples to the surface, each capped at the tolerance


class _Detector:
    """The shape and texture tests of one surface (module docstring)."""

    def __init__(self, ref: Surface, test_idx: np.ndarray, tol: float, params: SymmetryParams):
        from scipy.spatial import cKDTree  # here: `template-from-mesh` refuses a bad mesh without scipy

        self.params, self.tol = params, tol
        self.Q = ref.points
        self.tree = cKDTree(self.Q)
        self.btree = cKDTree(ref.boundary) if len(ref.boundary) else None
        self.P = self.Q[test_idx]
        self.test_idx = test_idx
        self.colors = ref.colors
        if self.colors is not None:
            self._app = np.full((len(self.Q), 3), np.nan)  # appearances, computed where asked for
            self._local = np.full(len(self.Q), np.nan)  # ... and the local mean intensities they divide by
            rng = np.random.default_rng(1)
            a_p = self.appearance(test_idx)
            # the identity moved by half the tolerance in a random direction: what the shape test lets through
            d = rng.normal(size=self.P.shape)
            d *= 0.5 * tol / np.linalg.norm(d, axis=1, keepdims=True)
            _, j = self.tree.query(self.P + d)
            diff_id = np.linalg.norm(a_p - self.appearance(j), axis=1)
            # never below one level of an 8-bit colour in each channel: smaller differences are quantisation
            level = np.sqrt(3.0) / float(np.median(self._local[test_idx]))
            self.tau = max(float(np.median(diff_id)), level)
            jr = rng.integers(0, len(self.Q), len(self.P))
            self.f_rand = float(np.mean(np.linalg.norm(a_p - self.appearance(jr), axis=1) <= self.tau))

    def appearance(self, idx: np.ndarray) -> np.ndarray:
        """[K x 3] colour of samples `idx` [K] over the mean intensity of their 16 nearest neighbours (shading
        cancels)."""
        assert self.colors is not None
        todo = np.unique(idx[np.isnan(self._app[idx, 0])])
        if len(todo):
            _, nb = self.tree.query(self.Q[todo], k=16)
            local = np.maximum(self.colors[nb].mean(axis=(1, 2)), 1.0)
            self._app[todo] = self.colors[todo] / local[:, None]
            self._local[todo] = local
        return self._app[idx]

    def test(self, S: np.ndarray, texture: bool = True) -> _Verdict:
        """The shape test of S [4 x 4] and, when it holds and `texture`, the texture test."""
        X = self.P @ S[:3, :3].T + S[:3, 3]
        d, j = self.tree.query(X)
        off = d > self.tol
        if self.btree is not None and off.any():
            db, _ = self.btree.query(X[off])
            hole = np.zeros(len(X), bool)
            hole[off] = db <= d[off] + self.tol
        else:
            hole = np.zeros(len(X), bool)
        tested = ~hole
        n_tested = int(tested.sum())
        share_tested = n_tested / len(X)
        inl = float((~off & tested).sum() / max(n_tested, 1))
        holds = share_tested >= self.params.min_tested_share and inl >= self.params.inlier_share
        residual = float(np.minimum(d[tested], self.tol).mean()) if n_tested else self.tol
        in_texture = True
        if holds and texture and self.colors is not None:
            ok = ~off & tested
            diff = np.linalg.norm(self.appearance(self.test_idx[ok]) - self.appearance(j[ok]), axis=1)
            f = float(np.mean(diff <= self.tau))
            se = np.sqrt(0.25 / max(int(ok.sum()), 1))
            in_texture = not (f < 0.5 * (0.5 + self.f_rand) and f < 0.5 - 4 * se)
        return _Verdict(holds, inl, share_tested, in_texture, residual)

    def test_revolution(self, axis: np.ndarray, c: np.ndarray) -> _Verdict:
        """Every turn about the axis (the worst of `continuous_steps` angles)."""
        n = self.params.continuous_steps
        worst: _Verdict | None = None
        texture = True
        for k in range(1, n):
            v = self.test(axis_rotation(axis, c, 2 * np.pi * k / n))
            if not v.holds:
                return v
            texture &= v.texture
            worst = v if worst is None or v.inliers < worst.inliers else worst
        assert worst is not None
        return _Verdict(True, worst.inliers, worst.tested, texture, worst.residual)


def _closure(gens: list[np.ndarray], limit: int = 64) -> list[np.ndarray]:
    """The group [4 x 4] the rotations `gens` generate, the identity first (at most `limit` elements)."""
    group = [np.eye(4)]
    frontier = list(group)
    while frontier and len(group) < limit:
        new: list[np.ndarray] = []
        for A in frontier:
            for G in gens:
                B = G @ A
                if not any(np.allclose(B, E, atol=1e-6) for E in group + new):
                    new.append(B)
        group += new
        frontier = new
    return group[:limit]


def _perpendicular(axis: np.ndarray, ref: np.ndarray, theta: float) -> np.ndarray:
    """Unit vector perpendicular to `axis`, at angle theta from the projection of `ref` into that plane."""
    u = ref - axis * (ref @ axis)
    u /= np.linalg.norm(u)
    w = np.cross(axis, u)
    return np.cos(theta) * u + np.sin(theta) * w


def detect_symmetries(surface: Surface, surface_sigma: float, params: SymmetryParams = SymmetryParams()
                      ) -> Symmetries:
    """The symmetries of a sampled surface (module docstring); `surface_sigma` (m) is the template's own surface
    error. Deterministic."""
    Q = surface.points
    n = len(Q)
    if n < 100:
        return Symmetries()
    spacing = float(np.sqrt(surface.area / n))
    tol = spacing + params.tolerance_sigmas * float(surface_sigma)
    test_idx = np.random.default_rng(2).choice(n, size=min(params.test_samples, n), replace=False)
    det = _Detector(surface, np.sort(test_idx), tol, params)
    mu = Q.mean(axis=0)
    _, vecs = np.linalg.eigh(np.cov((Q - mu).T))
    axes = [vecs[:, i] / np.linalg.norm(vecs[:, i]) for i in range(3)]
    local = (Q - mu) @ vecs
    c = mu + vecs @ (0.5 * (local.min(axis=0) + local.max(axis=0)))  # the box centre in the principal axes
    log.debug("symmetry: %d samples, spacing %.2f mm, tolerance %.2f mm", n, 1e3 * spacing, 1e3 * tol)

    continuous: list[tuple[np.ndarray, np.ndarray, bool]] = []
    gens: list[np.ndarray] = []
    for a in axes:
        v = det.test_revolution(a, c)
        if v.holds:  # a body of revolution: every other turn is one of its own times a flip
            continuous.append((a, c, v.texture))
            flip = axis_rotation(next(b for b in axes if b is not a), c, np.pi)
            if det.test(flip, texture=False).holds:
                gens.append(flip)
            break
    if not continuous:
        flips: list[np.ndarray] = []  # axes of the 2-fold turns found
        round_axes: list[np.ndarray] = []  # 4-fold axes: no preferred perpendicular direction (equal moments)
        for a in axes:
            R4 = axis_rotation(a, c, np.pi / 2)
            if det.test(R4, texture=False).holds:
                gens.append(R4)
                round_axes.append(a)
            elif det.test(axis_rotation(a, c, np.pi), texture=False).holds:
                gens.append(axis_rotation(a, c, np.pi))
                flips.append(a)
        for a in round_axes:
            if any(abs(float(f @ a)) < 1e-6 for f in flips + round_axes):
                continue  # a perpendicular 2-fold (or 4-fold) axis is known: the group follows from it
            # its perpendicular 2-fold axes repeat every 90 degrees: coarse, then fine angle steps
            ref = next(b for b in axes if b is not a)

            def residual(theta_deg: float, a: np.ndarray = a, ref: np.ndarray = ref) -> float:
                S = axis_rotation(_perpendicular(a, ref, np.radians(theta_deg)), c, np.pi)
                return det.test(S, texture=False).residual

            step = params.plane_step_deg
            th = min((float(x) for x in np.arange(0.0, 90.0, 5 * step)), key=residual)
            th = min((th + k * step for k in range(-5, 6)), key=residual)
            th = min((th + k * step / 5 for k in range(-5, 6)), key=residual)
            R2 = axis_rotation(_perpendicular(a, ref, np.radians(th)), c, np.pi)
            if det.test(R2, texture=False).holds:
                gens.append(R2)
    group = _closure(gens)[1:]
    disc, disc_tex = [], []
    for S in group:
        v = det.test(S)
        if v.holds:  # an element of the group the found turns generate: checked itself all the same
            disc.append(S)
            disc_tex.append(v.texture)
    return Symmetries(tuple(disc), tuple(disc_tex), tuple((a, o) for a, o, _ in continuous),
                      tuple(t for _, _, t in continuous))


def scan_surface_sigma(voxel: float, depth_noise: DepthNoise | None, distance: float | None) -> float:
    """The surface error (m) of a fused scan: its voxel (quantisation, voxel / 2) and the capture's depth noise at
    the cameras' typical distance (m) from the object, in quadrature (the noise left out when either is None)."""
    sigma2 = (0.5 * float(voxel)) ** 2
    if depth_noise is not None and distance is not None:
        sigma2 += float(depth_noise.sigma(float(distance))) ** 2
    return float(np.sqrt(sigma2))


def scan_symmetries(mesh: MeshData, voxel: float, depth_noise: DepthNoise | None, distance: float | None,
                    params: SymmetryParams = SymmetryParams()) -> Symmetries:
    """The symmetries of a scan's fused mesh (object frame, per-vertex colours from the keyframes' images) with the
    tolerance `scan_surface_sigma` gives; none for an empty mesh or when `params.enabled` is off."""
    if not params.enabled or len(mesh.triangles) == 0:
        return Symmetries()
    sigma = scan_surface_sigma(voxel, depth_noise, distance)
    return detect_symmetries(surface_of_mesh(mesh, params.reference_samples), sigma, params)


def find_symmetries(db: TemplateDB, params: SymmetryParams = SymmetryParams()) -> Symmetries:
    """The symmetries of a scanned template (`scan_symmetries`): its fused mesh, "voxel_size" and "noise" meta, and
    its registered views' median distance from the object; none without a mesh or a voxel size."""
    mesh = db.mesh()
    voxel = db.get_meta("voxel_size")
    if mesh is None or not isinstance(voxel, (int, float)) or not voxel > 0:
        log.info("%s: no fused mesh or voxel size: symmetries not searched", db.path)
        return Symmetries()
    noise = db.get_meta("noise")
    depth = noise.get("depth") if isinstance(noise, dict) else None
    model = None
    if isinstance(depth, dict):
        try:
            model = DepthNoise(float(depth["c0"]), float(depth["c1"]), float(depth["c2"]))
        except (KeyError, TypeError, ValueError):
            model = None
    dists = [float(np.linalg.norm(v.T_obj_cam[:3, 3])) for v in db.views() if v.T_obj_cam is not None]
    return scan_symmetries(mesh, float(voxel), model, float(np.median(dists)) if dists else None, params)
