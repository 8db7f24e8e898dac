"""What biases the glossy bottle's edges: the rendered bottle of tests/test_acceptance.py
(`gscan.synth.cases.glossy_bottle_capture`, seed 1, 36 turntable frames 10 deg apart), scanned at the defaults,
every edge the scan computed measured against the ground truth.

1. Highlights: the renderer's highlight term on the bottle (its largest value, in grey levels), the object's pixels
   at or near the sensor's saturation (a channel >= 250), and the keypoints of the edges' inlier pairs whose
   support (radius: the keypoint's size) touches a highlight pixel (term above 2 grey levels) or such a bright
   pixel.
2. Where the pairs' image motion falls short: of the sequential edges' inlier pairs, the share of the true image
   motion of the source keypoint (its surface point under the true turn, projected) that the matched target
   keypoint shows, by the source keypoint's distance to the object's outline and by its size; and each edge's
   turn solved by Kabsch on the exact (noise-free) depth at the matched pixels: the under-turn is in the matched
   pixels, not in the depth.
3. Each edge registered again (`register_features`, the scan's settings) without the weak-geometry bound (so the
   depth and colour checks judge it) on the keypoints that remain when those whose support crosses the object's
   outline are left out, in both frames: "outline, truth" uses the rendered object mask (support radius: k times
   half the keypoint's size), "outline, depth" a depth discontinuity (10-90 % spread above 3 % of the median,
   as `lift_keypoints`) or lost depth inside that radius. Per rule: keypoints kept, edges passing the other
   checks, their rotation error and claimed sigma (medians), error / sigma (median), edges beyond 5 deg, and
   the edges the defaults accept (wrong ones: beyond 5 deg); then, per rule, the edges passing the other checks
   beyond 5 deg. "bright pixels": the rule a colour image alone
   allows for highlights, keypoints whose support touches a pixel with a channel >= 250.

    python bench/bottle_edges.py [--work DIR]
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
SATURATED = 250  # a colour channel at or above this: at or near the sensor's saturation
HIGHLIGHT_GREY = 2.0  # a highlight pixel: the highlight adds more than this many grey levels
RULES = (("none", None, 0.0), ("bright pixels", "bright", 1.0), ("bright pixels", "bright", 3.0),
         ("outline, truth", "truth", 1.0), ("outline, truth", "truth", 3.0),
         ("outline, truth", "truth", 6.0), ("outline, depth", "depth", 3.0), ("outline, depth", "depth", 6.0))


def render_and_scan(work: Path) -> dict:
    """Render the bottle (keeping each frame's highlight term, exact depth and object mask) and scan it at the
    defaults (keeping each edge, both frames' registration data and the settings)."""
    from gscan.registration import edges as E
    from gscan.scanning.api import scan
    from gscan.synth import cases as C
    from gscan.synth import render as R

    frames: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []  # (spec, depth_clean, mask, colour)
    render, highlight = R.SynthScene.render, R.SynthScene._highlight
    last: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def kept_highlight(self, hit_idx, *a):
        spec = highlight(self, hit_idx, *a)
        last[id(self)] = (hit_idx.copy(), spec.copy())
        return spec

    def kept_render(self, *a, **k):
        last.pop(id(self), None)
        f = render(self, *a, **k)
        spec = np.zeros(f.depth.size, np.float32)
        if id(self) in last:
            spec[last[id(self)][0]] = last[id(self)][1]
        frames.append((spec.reshape(f.depth.shape), f.depth_clean.copy(), f.mask.copy(), f.color.copy()))
        return f

    R.SynthScene.render, R.SynthScene._highlight = kept_render, kept_highlight
    try:
        case = C.glossy_bottle_capture(work / "cap", n_views=36, seed=1)
    finally:
        R.SynthScene.render, R.SynthScene._highlight = render, highlight
    records, regs, lock = [], {}, threading.Lock()
    pair = E.Registrar._pair

    def kept_pair(self, p, loop=False):
        got = pair(self, p, loop)
        with lock:
            for k in p:
                regs.setdefault(self.names[k], self.frames.reg(k))
            if got is not None:
                records.append((got[0], self.rparams))
        return got

    E.Registrar._pair = kept_pair
    try:
        res = scan(case.path, work / "bottle.gscan")
    finally:
        E.Registrar._pair = pair
    from gscan.io import open_sequence

    seq = open_sequence(case.path)
    names = list(case.object_frames)
    return {"frames": dict(zip(names, frames, strict=True)), "truth": dict(seq.gt_T_cam_obj), "regs": regs,
            "records": sorted(records, key=lambda r: (r[0].src, r[0].tgt)), "result": res,
            "depth": {n: seq[n].depth for n in names}, "K": seq[names[0]].intrinsics}


def _pixels(px: np.ndarray, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Rounded (u, v) [N] int of pixels [N x 2], clipped to the image."""
    return (np.clip(np.rint(px[:, 0]).astype(int), 0, shape[1] - 1),
            np.clip(np.rint(px[:, 1]).astype(int), 0, shape[0] - 1))


def touches(px: np.ndarray, radius: np.ndarray, where: np.ndarray) -> np.ndarray:
    """[N] bool: the disc of `radius` [N] around pixel px [N x 2] holds a True pixel of `where` [H x W]."""
    from scipy.ndimage import distance_transform_edt

    dist = distance_transform_edt(~where)
    u, v = _pixels(px, where.shape)
    return dist[v, u] <= radius


def outline_keep(name: str, feats, data: dict, how: str, k: float) -> np.ndarray:
    """[N] bool: the keypoints whose support (radius k x half their size) does not cross the object's outline
    (how: "truth" or "depth") or touch a bright pixel ("bright")."""
    from gscan.io.lift_kernel import window_stats

    radius = k * feats.scales / 2
    if how == "truth":
        return ~touches(feats.pixels, radius, ~data["frames"][name][2])
    if how == "bright":
        return ~touches(feats.pixels, radius, data["frames"][name][3].max(axis=2) >= SATURATED)
    depth = np.ascontiguousarray(data["depth"][name])
    u, v = _pixels(feats.pixels, depth.shape)
    r = np.maximum(2, np.ceil(radius)).astype(int)
    keep = np.ones(len(feats), bool)
    for rr in np.unique(r):
        s = np.flatnonzero(r == rr)
        med, lo, hi, cnt = (np.empty(len(s)), np.empty(len(s)), np.empty(len(s)), np.empty(len(s), np.int64))
        window_stats(depth, np.ascontiguousarray(u[s]), np.ascontiguousarray(v[s]), int(rr), med, lo, hi, cnt)
        keep[s] = (hi - lo <= 0.03 * med) & (cnt >= 0.5 * (2 * rr + 1) ** 2)
    return keep


def _turn_deg(T: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1))))


def highlights(data: dict) -> None:
    """Part 1 (module docstring)."""
    spec = np.stack([f[0] for f in data["frames"].values()])
    masks = np.stack([f[2] for f in data["frames"].values()])
    colour = np.stack([f[3] for f in data["frames"].values()])
    hot = {n: f[0] * 255.0 > HIGHLIGHT_GREY for n, f in data["frames"].items()}
    bright = {n: f[3].max(axis=2) >= SATURATED for n, f in data["frames"].items()}
    on = near_saturated = total = 0
    for e, _ in data["records"]:
        if len(e.matches) == 0:
            continue
        for name, col in ((e.src, 0), (e.tgt, 1)):
            f = data["regs"][name].feats
            idx = e.matches[:, col]
            hit = touches(f.pixels[idx], f.scales[idx], hot[name])
            on += int(hit.sum())
            near_saturated += int(touches(f.pixels[idx], f.scales[idx], bright[name]).sum())
        total += len(e.matches)
    print(f"highlight term on the bottle: at most {255 * spec[masks].max():.2f} grey levels; object pixels with a "
          f"channel >= {SATURATED}: {int((colour.max(axis=3)[masks] >= SATURATED).sum())} in 36 frames; keypoints "
          f"of the edges' {total} inlier pairs on a highlight: {on}, touching such a bright pixel: {near_saturated}")


def image_motion(data: dict) -> None:
    """Part 2 (module docstring)."""
    from scipy.ndimage import distance_transform_edt

    from gscan.geometry.kabsch import kabsch
    from gscan.geometry.transforms import inv_T, transform_points

    K = data["K"]

    def lift(px, depth):
        u, v = _pixels(px, depth.shape)
        z = depth[v, u].astype(np.float64)
        return np.stack([(px[:, 0] - K.cx) * z / K.fx, (px[:, 1] - K.cy) * z / K.fy, z], 1)

    def proj(X):
        return np.stack([K.fx * X[:, 0] / X[:, 2] + K.cx, K.fy * X[:, 1] / X[:, 2] + K.cy], 1)

    inside = {n: distance_transform_edt(f[2]) for n, f in data["frames"].items()}
    share, dist, size, turns = [], [], [], {1: [], 2: [], 3: []}
    for e, _ in data["records"]:
        gap = int(e.tgt) - int(e.src)
        if e.kind != "sequential" or e.T_tgt_src is None or gap not in turns or not len(e.matches):
            continue
        fs, ft = data["regs"][e.src].feats, data["regs"][e.tgt].feats
        us = fs.pixels[e.matches[:, 0]].astype(np.float64)
        ut = ft.pixels[e.matches[:, 1]].astype(np.float64)
        T_gt = data["truth"][e.tgt] @ inv_T(data["truth"][e.src])
        Xs, Xt = lift(us, data["frames"][e.src][1]), lift(ut, data["frames"][e.tgt][1])
        ok = (Xs[:, 2] > 0) & (Xt[:, 2] > 0)
        turns[gap].append((_turn_deg(T_gt), _turn_deg(e.T_tgt_src), _turn_deg(kabsch(Xs[ok], Xt[ok]))))
        if gap != 1:
            continue
        m = proj(transform_points(T_gt, Xs)) - us
        share += list((np.sum((ut - us) * m, axis=1) / np.maximum(np.sum(m * m, axis=1), 1e-9))[ok])
        u, v = _pixels(us, data["frames"][e.src][2].shape)
        dist += list(inside[e.src][v, u][ok])
        size += list(fs.scales[e.matches[:, 0]][ok])
    s, d, z = np.array(share), np.array(dist), np.array(size)
    print(f"\nsequential edges 10 deg apart: {len(s)} inlier pairs; the matched keypoint moves a median "
          f"{np.median(s):.2f} (mean {np.mean(s):.2f}) of the true image motion\n")
    print("| source keypoint | pairs | share of the true image motion (median) |\n|---|---|---|")
    for lo, hi in ((0, 6), (6, 10), (10, 1e9)):
        sel = (d >= lo) & (d < hi)
        print(f"| {lo:g}-{hi:g} px inside the outline | {sel.sum()} | {np.median(s[sel]):.2f} |")
    for lo, hi in ((0, 4), (4, 8), (8, 1e9)):
        sel = (z >= lo) & (z < hi)
        print(f"| size {lo:g}-{hi:g} px | {sel.sum()} | {np.median(s[sel]):.2f} |")
    print("\n| frames apart | edges | true turn | edge's turn (median) | Kabsch on the exact depth at the matched "
          "pixels (median) |\n|---|---|---|---|---|")
    for gap, t in turns.items():
        a = np.median(np.array(t), axis=0)
        print(f"| {gap} | {len(t)} | {a[0]:.0f} deg | {a[1]:.1f} deg | {a[2]:.1f} deg |")


def rules(data: dict) -> None:
    """Part 3 (module docstring)."""
    from gscan.geometry.transforms import inv_T, pose_error
    from gscan.registration.edges import RegData
    from gscan.registration.pairwise import register_features

    print("\n| keypoints left out | kept | edges passing the other checks | error (median) | sigma claimed (median) "
          "| error / sigma (median) | beyond 5 deg | accepted at the defaults (wrong) |")
    print("|---|---|---|---|---|---|---|---|")
    beyond: dict[str, list[str]] = {}
    for label, how, k in RULES:
        kept = {}
        for n, rd in data["regs"].items():
            keep = np.ones(len(rd.feats), bool) if how is None else outline_keep(n, rd.feats, data, how, k)
            kept[n] = RegData(rd.feats.subset(keep), rd.cloud, rd.dense)
        share = np.mean([len(kept[n].feats) / max(1, len(data["regs"][n].feats)) for n in kept])
        err, sig, acc, wrong, far = [], [], 0, 0, []
        for e, rp in data["records"]:
            a, b = kept[e.src], kept[e.tgt]
            T_gt = data["truth"][e.tgt] @ inv_T(data["truth"][e.src])
            loose = dataclasses.replace(rp, max_sigma_deg=1e9, max_sigma_rel=1e9)
            r = register_features(a.feats, b.feats, loose, clouds=(a.cloud, b.cloud), dense=(a.dense, b.dense))
            if r.accepted and r.T_tgt_src is not None and r.sigma_deg is not None:
                err.append(pose_error(r.T_tgt_src, T_gt)[0])
                sig.append(r.sigma_deg)
                if err[-1] > 5.0:
                    n_pairs = 0 if r.inliers is None else len(r.inliers)
                    far.append(f"{e.src}-{e.tgt} ({e.kind}, {n_pairs} pairs) {err[-1]:.1f} deg, sigma {sig[-1]:.2f}")
            d = register_features(a.feats, b.feats, rp, clouds=(a.cloud, b.cloud), dense=(a.dense, b.dense))
            if d.accepted and d.T_tgt_src is not None:
                acc += 1
                wrong += pose_error(d.T_tgt_src, T_gt)[0] > 5.0
        ea, sa = np.array(err), np.array(sig)
        name = label if how is None else f"{label}, k {k:g}"
        print(f"| {name} | {share:.0%} | {len(ea)} of {len(data['records'])} | {np.median(ea):.2f} deg | "
              f"{np.median(sa):.2f} deg | {np.median(ea / sa):.2f} | {int((ea > 5).sum())} | {acc} ({wrong}) |")
        beyond[name] = far
    for name, far in beyond.items():
        print(f"\n{name}: passing the other checks beyond 5 deg: " + "; ".join(far))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=None, help="folder for the capture and the scan (default: temporary)")
    args = ap.parse_args()
    t0 = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        data = render_and_scan(work)
        res = data["result"]
        print(f"scan at the defaults: {res.registered} of {res.frames} frames registered, {len(data['records'])} "
              f"edges\n")
        highlights(data)
        image_motion(data)
        rules(data)
    print(f"\n{time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()
