"""JSON export: intrinsics, per-view poses and flags, edges with their quality numbers, grasps.

    {"format": "gscan-template-json", "schema": 1, "units": "m", "source": ..., "descriptor": ...,
     "intrinsics": {fx, fy, cx, cy, width, height} | null (null when the views differ),
     "views": [{"name", "input_index", "intrinsics", "T_obj_cam" [[4x4]] | null, "keyframe", "quality",
                "n_keypoints"}],
     "edges": [{"src", "tgt", "kind", "accepted", "reason", "n_matches", "cost", "rmse", "fitness",
                "T_tgt_src" [[4x4]] | null}],
     "grasps": {name: [[4x4 T_obj_grasp]]}, "extent_m": [x, y, z]}

Matrices are nested row-major lists; no timestamps, so the same database gives the same file.
"""
from __future__ import annotations

import json
from pathlib import Path

from gscan.template.db import TemplateDB


def template_json(db: TemplateDB) -> dict:
    views = db.views(load_images=False)
    intr = {v.intrinsics for v in views}
    out_views = []
    for v in views:
        f = db.features(v.name)
        out_views.append({"name": v.name, "input_index": v.input_index, "intrinsics": v.intrinsics.to_dict(),
                          "T_obj_cam": None if v.T_obj_cam is None else v.T_obj_cam.tolist(),
                          "keyframe": v.keyframe, "quality": v.quality,
                          "n_keypoints": 0 if f is None else int(len(f.pixels))})
    edges = [{"src": e.src, "tgt": e.tgt, "kind": e.kind, "accepted": e.accepted, "reason": e.reason,
              "n_matches": int(len(e.matches)), "cost": e.cost, "rmse": e.rmse, "fitness": e.fitness,
              "T_tgt_src": None if e.T_tgt_src is None else e.T_tgt_src.tolist()} for e in db.edges()]
    return {"format": "gscan-template-json", "schema": db.get_meta("schema"), "units": "m",
            "source": db.get_meta("source", "scan"), "descriptor": db.descriptor_kind(),
            "intrinsics": next(iter(intr)).to_dict() if len(intr) == 1 else None,
            "views": out_views, "edges": edges,
            "grasps": {k: T.tolist() for k, T in db.grasps().items()},
            "extent_m": [float(x) for x in db.extent()]}


def write_json(db: TemplateDB, path: Path) -> int:
    doc = template_json(db)
    path.write_text(json.dumps(doc, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
    return len(doc["views"])
