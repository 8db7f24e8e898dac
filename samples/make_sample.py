#!/usr/bin/env python3
"""Regenerate the bundled sample deterministically: `python samples/make_sample.py [--out DIR]`.

Writes into gscan/sample/ (the package data `gscan demo` reads; see samples/README.md) or DIR:
  object/box.obj, box.mtl, box_texture.png   the procedural printed box (metres, origin at its centre)
  capture/    30 frames, static box on a newspaper-covered table, camera on two orbit rings
  heldout/    4 frames of the same box in other poses / places, one with a distractor box
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np

from gscan.geometry.transforms import look_at, rotvec_to_R, transform_points
from gscan.synth import (
    DEFAULT_INTRINSICS,
    RenderedFrame,
    SynthScene,
    TexturedMesh,
    box_mesh,
    place_distractors,
    procedural_box_texture,
    rest_on_table,
    save_textured_mesh,
    write_capture,
)

BOX_SIZE = (0.16, 0.10, 0.07)
BOX_SEED = 7
N_PER_RING = 15
RINGS = ((30.0, 0.56), (55.0, 0.49))  # (elevation deg, nominal distance m)

# held-out views: (object rotation as rotvec, xy on the table, camera elevation, azimuth, distance,
#                  table kind, table seed, distractor?). Every view shows faces the capture saw
#                  (never the bottom face, which stands on the table throughout the capture).
HELDOUT = (
    ((0.0, 0.0, np.radians(40)), (0.05, -0.03), 40.0, 200.0, 0.50, "wood", 11, False),
    # lying on its long side, the capture's top face now looking at the camera (+y)
    ((-np.pi / 2, 0.0, 0.0), (-0.04, 0.02), 40.0, 100.0, 0.50, "fabric", 12, False),
    ((0.0, 0.0, np.radians(160)), (0.02, 0.06), 35.0, 320.0, 0.60, "newspaper", 13, True),
    # standing on its end, the capture's top face towards +x
    ((0.0, np.pi / 2, 0.0), (0.0, 0.0), 45.0, 10.0, 0.50, "wood", 14, False),
)


def camera(center: np.ndarray, elevation_deg: float, azimuth_deg: float, dist: float,
           target_jitter: np.ndarray) -> np.ndarray:
    """T_world_cam looking at center + jitter from the given spherical position."""
    e, a = np.radians(elevation_deg), np.radians(azimuth_deg)
    eye = center + dist * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    return look_at(eye, center + target_jitter)


def sample_box() -> TexturedMesh:
    """The sample object: procedural printed box, origin at its centre."""
    return box_mesh(BOX_SIZE, procedural_box_texture(BOX_SEED), name="printed_box")


def capture_setup(box: TexturedMesh, rng: np.random.Generator) -> tuple[SynthScene, list[np.ndarray]]:
    """The capture scene (box standing on a newspaper table) and its 30 T_world_cam, ring by ring."""
    T_world_obj = rest_on_table(box)
    center = transform_points(T_world_obj, box.center[None])[0]
    scene = SynthScene([(box, T_world_obj)], seed=BOX_SEED, table_kind="newspaper")
    cams = []
    for r, (el, dist) in enumerate(RINGS):
        for j in range(N_PER_RING):
            az = 360.0 * (j + 0.5 * r) / N_PER_RING
            cams.append(camera(center, el + rng.uniform(-3, 3), az + rng.uniform(-3, 3),
                               dist + rng.uniform(-0.04, 0.04), rng.uniform(-0.01, 0.01, 3)))
    return scene, cams


def render_capture_frame(scene: SynthScene, T_world_cam: np.ndarray, index: int) -> RenderedFrame:
    """Capture frame `index` (its noise is seeded by the index)."""
    return scene.render(T_world_cam, DEFAULT_INTRINSICS, noise=True, rng=np.random.default_rng([BOX_SEED, index]))


def make(out: Path) -> dict:
    rng = np.random.default_rng(2024)
    intr = DEFAULT_INTRINSICS
    box = sample_box()
    save_textured_mesh(box, out / "object" / "box.obj")

    # --- capture: static object, hand-held-like camera on two rings
    scene, cams = capture_setup(box, rng)
    frames = [render_capture_frame(scene, T_wc, i) for i, T_wc in enumerate(cams)]
    write_capture(out / "capture", frames, intr, jpeg=True, jpeg_quality=92)

    # --- held-out frames: same object elsewhere, other tables, one distractor
    held = []
    for k, (rv, xy, el, az, dist, kind, tseed, distractor) in enumerate(HELDOUT):
        T_wo = rest_on_table(box, rotvec_to_R(np.array(rv)), xy)
        objects = [(box, T_wo)]
        if distractor:
            other = box_mesh((0.09, 0.06, 0.12), procedural_box_texture(BOX_SEED + 100), name="distractor")
            objects.append((other, place_distractors(box, T_wo, [other], np.random.default_rng(k), gap=0.03)[0]))
        sc = SynthScene(objects, seed=tseed, table_kind=kind)
        c = transform_points(T_wo, box.center[None])[0]
        T_wc = camera(c, el, az, dist, rng.uniform([-0.05, -0.05, -0.01], [0.05, 0.05, 0.01]))  # off-centre
        held.append(sc.render(T_wc, intr, noise=True, rng=np.random.default_rng([BOX_SEED, 1000 + k])))
    write_capture(out / "heldout", held, intr, jpeg=True, jpeg_quality=92)
    meta = {"object": "object/box.obj", "box_size_m": list(BOX_SIZE), "texture_seed": BOX_SEED,
            "intrinsics": intr.to_dict(), "capture_frames": len(frames), "heldout_frames": len(held),
            "heldout_distractor": [bool(h[-1]) for h in HELDOUT]}
    (out / "sample.json").write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")
    return meta


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "gscan" / "sample",
                    help="output folder (default: gscan/sample/, the package data)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stderr)
    meta = make(args.out)
    logging.info("sample written to %s: %d capture frames, %d held-out frames", args.out,
                 meta["capture_frames"], meta["heldout_frames"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
