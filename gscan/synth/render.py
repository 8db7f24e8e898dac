"""CPU ray-cast RGB-D renderer (open3d RaycastingScene) with exact ground truth and RealSense-like noise.

World frame: z up, the table top is the plane z = 0. Cameras are OpenCV cameras (x right, y down,
z forward) given by T_world_cam. Each object is ray cast in its own mesh frame, so moving an
object (turntable) never rebuilds a scene. Depth is the camera-frame z, not the ray length.
"""
from __future__ import annotations

import logging
import zlib
from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np
import open3d as o3d

from gscan.geometry.transforms import inv_T
from gscan.io.camera import Intrinsics, pixel_rays
from gscan.synth.mesh import TexturedMesh, sample_mip_pixels, texture_pyramid
from gscan.synth.noise import DepthNoise, apply_depth_noise
from gscan.synth.textures import table_texture

log = logging.getLogger(__name__)

DEFAULT_INTRINSICS = Intrinsics(fx=615.0, fy=615.0, cx=319.5, cy=239.5, width=640, height=480)
DEFAULT_LIGHT_DIR = (0.35, -0.3, 1.0)  # towards the light (world): from above, slightly to one side
_SURF_NONE, _SURF_TABLE, _SURF_WALL, _SURF_OBJ = 0, 1, 2, 3


def _xform(pts: np.ndarray, R: np.ndarray, t: np.ndarray | None = None) -> np.ndarray:
    """[N x 3] points (or directions when t is None) mapped by R [3 x 3] (+ t [3]); keeps the dtype.

    cv2.transform is used because numpy's matmul with a tiny right-hand matrix is much slower on tall inputs."""
    M = np.zeros((3, 4), pts.dtype)
    M[:, :3] = R
    if t is not None:
        M[:, 3] = t
    return cv2.transform(np.ascontiguousarray(pts).reshape(-1, 1, 3), M).reshape(-1, 3)


def _dot(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """[N] row-wise dot products of [N x 3] a with [3] v (faster than a @ v for tall a)."""
    return a[:, 0] * v[0] + a[:, 1] * v[1] + a[:, 2] * v[2]


@lru_cache(maxsize=8)
def _pixel_rays_cached(intr: Intrinsics) -> np.ndarray:
    """[H*W x 3] read-only camera rays with z = 1."""
    r = pixel_rays(intr).reshape(-1, 3).astype(np.float32)
    r.setflags(write=False)
    return r


@dataclass(frozen=True)
class Gloss:
    """Specular highlights on glossy objects, and the depth a sensor loses on them.

    A glossy surface adds a Blinn-Phong highlight, strength * max(0, n.h)^shininess (h: the half vector
    between the light and the viewer), where the light reaches it; the highlight moves over the surface with
    the viewpoint and saturates the colour. Where its term (0..1) exceeds `dropout`, the depth is lost (with
    noise on): the mirror-like reflection sends the projector's pattern away from the sensor, which then sees
    no texture to match. objects: indices of the glossy objects (0 = the target).
    """

    strength: float = 255.0
    shininess: float = 40.0
    dropout: float = 0.35
    objects: tuple[int, ...] = (0,)


@dataclass
class RenderedFrame:
    """One rendered RGB-D frame with ground truth.

    color: [H x W x 3] uint8 RGB; depth: [H x W] float32 m (noisy, quantised, with holes; 0 invalid);
    depth_clean: [H x W] float32 m exact camera-frame z (0 where nothing is hit);
    mask: [H x W] bool visible pixels of the target (object 0); labels: [H x W] int16
    (-1 table/wall/background, k = object k); T_cam_obj: [4 x 4] target pose in the camera;
    T_world_cam: [4 x 4]; T_world_objs: [K x 4 x 4] every object's pose.
    """

    color: np.ndarray
    depth: np.ndarray
    depth_clean: np.ndarray
    mask: np.ndarray
    labels: np.ndarray
    T_cam_obj: np.ndarray
    T_world_cam: np.ndarray
    T_world_objs: np.ndarray
    intrinsics: Intrinsics = field(default=DEFAULT_INTRINSICS)


class SynthScene:
    """Textured objects on an optional textured table (z = 0) and an optional back wall, one directional light.

    objects: list of (TexturedMesh, T_world_obj [4 x 4]); object 0 is the target.
    table: draw a square table top of half side `table_half_extent` m (texture `table_kind`).
    wall_y: if given, a vertical textured wall in the plane y = wall_y facing -y.
    light_dir: direction towards the light (world); ambient + diffuse * max(0, n.l) * visibility.
    gloss: specular highlights and their depth dropouts on some objects (`Gloss`); None: every surface matte.
    """

    def __init__(self, objects: list[tuple[TexturedMesh, np.ndarray]], table: bool = True, seed: int = 0,
                 table_kind: str = "newspaper", table_half_extent: float = 0.75, table_texture_size: int = 2048,
                 wall_y: float | None = None, wall_kind: str = "wood",
                 light_dir: tuple[float, float, float] = DEFAULT_LIGHT_DIR, ambient: float = 0.5,
                 diffuse: float = 0.6, shadows: bool = True,
                 background_rgb: tuple[int, int, int] = (58, 60, 66), gloss: Gloss | None = None) -> None:
        if not objects:
            raise ValueError("a scene needs at least one object (object 0 is the target)")
        self.meshes = [m for m, _ in objects]
        self.T_world_objs = np.stack([np.asarray(T, dtype=np.float64).reshape(4, 4) for _, T in objects])
        self.table, self.table_half_extent = table, float(table_half_extent)
        self.wall_y = wall_y
        self.seed = seed
        self.ambient, self.diffuse, self.shadows = float(ambient), float(diffuse), shadows
        light = np.asarray(light_dir, dtype=np.float64)
        self.light_dir = light / np.linalg.norm(light)
        self.background_rgb = np.asarray(background_rgb, dtype=np.float32)
        self.gloss = gloss
        self._scenes = []
        for m in self.meshes:
            sc = o3d.t.geometry.RaycastingScene()
            sc.add_triangles(o3d.core.Tensor.from_numpy(m.vertices.astype(np.float32)),
                             o3d.core.Tensor.from_numpy(m.triangles.astype(np.uint32)))
            self._scenes.append(sc)
        self._density = [m.texels_per_metre() for m in self.meshes]
        self._pyramids = [m.pyramid() for m in self.meshes]
        self._table_pyr = texture_pyramid(table_texture(table_kind, seed, table_texture_size)) if table else None
        self._wall_pyr = texture_pyramid(table_texture(wall_kind, seed + 1, 1024)) if wall_y is not None else None
        self._table_density = table_texture_size / (2 * self.table_half_extent)
        self._wall_density = 1024 / 2.0  # wall texture covers 2 m x 2 m

    # ------------------------------------------------------------------ ray casting
    def _poses(self, override: np.ndarray | list | None) -> np.ndarray:
        T = self.T_world_objs.copy()
        if override is None:
            return T
        if isinstance(override, np.ndarray) and override.ndim == 3:
            ov = list(override)
        else:
            ov = override if isinstance(override, (list, tuple)) else [override]
        if len(ov) > len(T):
            raise ValueError(f"{len(ov)} pose overrides for {len(T)} objects")
        for k, Tk in enumerate(ov):
            if Tk is not None:
                T[k] = np.asarray(Tk, dtype=np.float64).reshape(4, 4)
        return T

    def _cast_objects(self, origin_w: np.ndarray, dirs_w: np.ndarray, T_wo: np.ndarray) -> dict[str, np.ndarray]:
        """First hits of rays (origin [3], dirs [N x 3] float32 world) over all objects."""
        n = len(dirs_w)
        best: dict[str, np.ndarray] = {"t": np.full(n, np.inf, np.float32), "label": np.full(n, -1, np.int16),
                "prim": np.zeros(n, np.int64), "bary": np.zeros((n, 2), np.float32),
                "normal": np.zeros((n, 3), np.float32)}
        rays = np.empty((n, 6), np.float32)
        for k, sc in enumerate(self._scenes):
            T_ow = inv_T(T_wo[k])
            rays[:, :3] = T_ow[:3, :3] @ origin_w + T_ow[:3, 3]
            rays[:, 3:] = _xform(dirs_w, T_ow[:3, :3])
            res = sc.cast_rays(o3d.core.Tensor.from_numpy(rays))
            t = res["t_hit"].numpy()
            closer = np.flatnonzero(t < best["t"])  # inf (miss) never compares smaller
            if len(closer) == 0:
                continue
            best["t"][closer] = t[closer]
            best["label"][closer] = k
            best["prim"][closer] = res["primitive_ids"].numpy()[closer]
            best["bary"][closer] = res["primitive_uvs"].numpy()[closer]
            best["normal"][closer] = _xform(res["primitive_normals"].numpy()[closer], T_wo[k][:3, :3])
        return best

    def _occluded(self, pts_w: np.ndarray, T_wo: np.ndarray, towards: np.ndarray | None = None) -> np.ndarray:
        """[N] bool: an object blocks the ray from each world point [N x 3] towards the light
        (towards=None) or the segment to the world point `towards` [3] (a second camera centre)."""
        occ = np.zeros(len(pts_w), bool)
        if towards is None:
            dirs = np.broadcast_to(self.light_dir, pts_w.shape)
            tfar = 10.0
        else:
            dirs = np.asarray(towards, dtype=np.float64) - pts_w  # unit of t: the segment length
            tfar = 1.0
        for k, sc in enumerate(self._scenes):
            # only rays passing the object's bounding sphere can be blocked by it
            c = T_wo[k][:3, :3] @ self.meshes[k].center + T_wo[k][:3, 3]
            r = self.meshes[k].radius * 1.01 + 1e-3
            rel = c - pts_w
            dd = np.einsum("ij,ij->i", dirs, dirs)
            along = np.einsum("ij,ij->i", rel, dirs) / np.sqrt(dd)
            reach = np.sqrt(dd) * tfar + r
            near = np.einsum("ij,ij->i", rel, rel) - along ** 2 < r * r
            cand = np.flatnonzero((along > -r) & (along < reach) & near)
            if len(cand) == 0:
                continue
            T_ow = inv_T(T_wo[k])
            o = _xform(pts_w[cand], T_ow[:3, :3], T_ow[:3, 3])
            d = _xform(np.ascontiguousarray(dirs[cand]), T_ow[:3, :3])
            rays = o3d.core.Tensor.from_numpy(np.concatenate([o, d], axis=1).astype(np.float32))
            occ[cand] |= sc.test_occlusions(rays, tnear=1e-4, tfar=tfar).numpy().astype(bool)
        return occ

    def _highlight(self, hit_idx: np.ndarray, label: np.ndarray, n_hit: np.ndarray, d_hit: np.ndarray,
                   lam: np.ndarray) -> np.ndarray:
        """[len(hit_idx)] Blinn-Phong highlight term in [0, 1] of the hit pixels: nonzero on the glossy objects
        where the light reaches them (lam > 0: lit and not in shadow); n_hit [N x 3] faces the camera, d_hit
        [N x 3] are the rays' world directions."""
        g = self.gloss
        assert g is not None
        glossy = np.isin(label[hit_idx], np.asarray(g.objects, np.int16)) & (lam > 0)
        spec = np.zeros(len(hit_idx), np.float32)
        sel = np.flatnonzero(glossy)
        if len(sel):
            v = -d_hit[sel] / np.linalg.norm(d_hit[sel], axis=1, keepdims=True)
            h = v + self.light_dir.astype(np.float32)
            h /= np.linalg.norm(h, axis=1, keepdims=True)
            spec[sel] = np.clip(np.einsum("ij,ij->i", n_hit[sel], h), 0.0, 1.0) ** np.float32(g.shininess)
        return spec

    # ------------------------------------------------------------------ rendering
    def render(self, T_world_cam: np.ndarray, intr: Intrinsics = DEFAULT_INTRINSICS, noise: bool = True,
               rng: np.random.Generator | None = None, T_world_obj_override: np.ndarray | list | None = None,
               shading: bool = True, noise_params: DepthNoise = DepthNoise()) -> RenderedFrame:
        """Render one frame seen from T_world_cam [4 x 4].

        T_world_obj_override: a [4 x 4] pose for the target, or a list of per-object poses (None keeps
        an object's scene pose). shading=False gives the raw texture colour (no light, no shadow).
        noise: RealSense-like depth noise and holes plus slight colour noise (see gscan.synth.noise);
        rng defaults to a generator seeded by the scene seed and the poses (same view, same noise).
        """
        T_world_cam = np.asarray(T_world_cam, dtype=np.float64)
        T_wo = self._poses(T_world_obj_override)
        H, W = intr.height, intr.width
        rays_c = _pixel_rays_cached(intr)  # z = 1: hit distance equals camera z
        R_wc, origin = T_world_cam[:3, :3], T_world_cam[:3, 3]
        dirs = _xform(rays_c, R_wc)  # [N x 3] float32 world directions
        hit = self._cast_objects(origin, dirs, T_wo)
        t, label, normal = hit["t"], hit["label"], hit["normal"]
        surf = np.where(label >= 0, _SURF_OBJ, _SURF_NONE).astype(np.int8)
        plane_uv = np.zeros((len(t), 2), np.float32)
        if self.table and origin[2] > 1e-9:
            down = np.flatnonzero(dirs[:, 2] < 0)
            tt = (-origin[2] / dirs[down, 2]).astype(np.float32)
            p = origin[:2] + tt[:, None] * dirs[down, :2]
            e = self.table_half_extent
            ok = (tt < t[down]) & (np.abs(p) <= e).all(1)
            idx = down[ok]
            t[idx], label[idx], surf[idx] = tt[ok], -1, _SURF_TABLE
            normal[idx] = (0.0, 0.0, 1.0)
            plane_uv[idx] = (p[ok] + e) / (2 * e)
        if self.wall_y is not None:
            fwd = np.flatnonzero(dirs[:, 1] * (self.wall_y - origin[1]) > 0)
            tw = ((self.wall_y - origin[1]) / dirs[fwd, 1]).astype(np.float32)
            p = origin + tw[:, None] * dirs[fwd]
            ok = (tw < t[fwd]) & (p[:, 2] >= 0) & (p[:, 2] <= 2.0) & (np.abs(p[:, 0]) <= 1.0)
            idx = fwd[ok]
            t[idx], label[idx], surf[idx] = tw[ok], -1, _SURF_WALL
            normal[idx] = (0.0, -1.0, 0.0)
            plane_uv[idx] = np.stack([(p[ok, 0] + 1.0) / 2.0, p[ok, 2] / 2.0], 1)

        hit_idx = np.flatnonzero(surf != _SURF_NONE)
        d_hit = dirs[hit_idx]
        n_hit = normal[hit_idx]
        c = np.einsum("ij,ij->i", n_hit, d_hit) / np.sqrt(np.einsum("ij,ij->i", d_hit, d_hit))
        n_hit[c > 0] *= -1  # face the camera (meshes are not closed / consistently wound)
        cos_view = np.zeros(len(t), np.float32)
        cos_view[hit_idx] = np.abs(c)
        # pixel footprint on the surface (m): z / f per pixel, stretched by the viewing obliquity
        footprint = np.zeros(len(t), np.float32)
        footprint[hit_idx] = t[hit_idx] / intr.fx / np.sqrt(np.maximum(cos_view[hit_idx], 0.05))

        rgb: np.ndarray = np.empty((len(t), 3), np.float32)
        rgb[:] = self.background_rgb
        for k in range(len(self.meshes)):
            sel = np.flatnonzero(label == k)
            if len(sel) == 0:
                continue
            prim = hit["prim"][sel]
            b = hit["bary"][sel].astype(np.float64)
            w = np.stack([1.0 - b[:, 0] - b[:, 1], b[:, 0], b[:, 1]], 1)
            uv = np.einsum("ij,ijk->ik", w, self.meshes[k].uv[prim])
            level = np.log2(np.maximum(footprint[sel] * self._density[k][prim], 1e-6))
            rgb[sel] = sample_mip_pixels(self._pyramids[k], uv, level, sel // W, sel % W)
        for code, pyr, dens in ((_SURF_TABLE, self._table_pyr, self._table_density),
                                (_SURF_WALL, self._wall_pyr, self._wall_density)):
            sel = np.flatnonzero(surf == code)
            if len(sel):
                assert pyr is not None  # a surface code only where that surface was rendered
                rgb[sel] = sample_mip_pixels(pyr, plane_uv[sel], np.log2(np.maximum(footprint[sel] * dens, 1e-6)),
                                             sel // W, sel % W)

        spec: np.ndarray | None = None  # [len(hit_idx)] highlight term of the glossy objects
        if shading:
            lam = np.clip(_dot(n_hit, self.light_dir.astype(np.float32)), 0.0, None)
            if self.shadows:
                cand = np.flatnonzero(lam > 0)
                pts = origin + t[hit_idx[cand], None].astype(np.float64) * d_hit[cand] + 5e-4 * n_hit[cand]
                lam[cand[self._occluded(pts, T_wo)]] = 0.0
            rgb[hit_idx] *= (self.ambient + self.diffuse * lam)[:, None]
            if self.gloss is not None:
                spec = self._highlight(hit_idx, label, n_hit, d_hit, lam)
                rgb[hit_idx] += np.float32(self.gloss.strength) * spec[:, None]

        depth_clean = np.where(np.isfinite(t), t, 0.0).reshape(H, W).astype(np.float32)
        depth_clean[depth_clean < 0] = 0.0
        labels = label.reshape(H, W)
        if noise:
            if rng is None:  # deterministic per (scene seed, camera pose, object poses), independent of call order
                rng = np.random.default_rng([self.seed, zlib.crc32(T_world_cam.tobytes() + T_wo.tobytes())])
            invalid: np.ndarray | None = None
            if noise_params.baseline > 0:  # stereo / projector occlusion: points the second imager cannot see
                T_w2 = T_world_cam[:3, :3] @ np.array([noise_params.baseline, 0.0, 0.0]) + origin
                pts = origin + t[hit_idx, None].astype(np.float64) * d_hit + 5e-4 * n_hit
                invalid = np.zeros(H * W, bool)
                invalid[hit_idx[self._occluded(pts, T_wo, towards=T_w2)]] = True
                invalid = invalid.reshape(H, W)
            if spec is not None and self.gloss is not None:  # glossy spots lose their depth
                lost = np.zeros(H * W, bool)
                lost[hit_idx[spec > self.gloss.dropout]] = True
                invalid = lost.reshape(H, W) if invalid is None else invalid | lost.reshape(H, W)
            depth = apply_depth_noise(depth_clean, labels, cos_view.reshape(H, W), rng, noise_params, invalid)
            if noise_params.color_blur_sigma > 0:
                rgb = cv2.GaussianBlur(rgb.reshape(H, W, 3), (0, 0), noise_params.color_blur_sigma).reshape(-1, 3)
            rgb += np.float32(noise_params.color_sigma) * rng.standard_normal(rgb.shape, dtype=np.float32)
        else:
            depth = depth_clean.copy()
        color = np.clip(np.rint(rgb), 0, 255).astype(np.uint8).reshape(H, W, 3)
        T_cam_obj = inv_T(T_world_cam) @ T_wo[0]
        return RenderedFrame(color, depth, depth_clean, labels == 0, labels, T_cam_obj, T_world_cam.copy(),
                             T_wo, intr)
