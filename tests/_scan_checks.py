"""Checks of a scan against the ground truth of a rendered capture (`gscan.synth.cases`), shared by the hard-capture
and trap tests: which frames were registered, which at a wrong pose (`frame_errors`: each frame's median relative
pose error against the other registered frames), the ATE, the reasons of the unregistered frames, and where the
template's surface lies. `Outcome.describe()` gives what a failure message needs to act on: the wrong frames with
their errors and the accepted edges that placed them."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gscan import synth
from gscan.evaluate.bop19 import template_to_gt
from gscan.evaluate.metrics import ate, frame_errors
from gscan.geometry.transforms import inv_T, transform_points
from gscan.io import open_sequence
from gscan.io.camera import Intrinsics
from gscan.scanning.api import scan
from gscan.scanning.pipeline import ScanResult
from gscan.synth.cases import Case
from gscan.synth.mesh import TexturedMesh
from gscan.template.db import Edge, TemplateDB

#: a rendered frame is registered at a wrong pose beyond this (deg, m) of the ground truth (issue 17's bound)
WRONG_RENDERED = (5.0, 0.02)
# m: the ATE of a correct registration of a capture at the rig's distance. 7 mm, not the 5 mm of the other scan
# tests: a static scan does not refine its edges on the depth (registration.dense_refine, for real Kinect frames),
# and the glossy can reads 6.3 mm and the shifted depth 5.1 mm without it, every frame within the wrong-pose bound
ATE_NEAR = 0.007


@dataclass
class Outcome:
    """A scanned case. poses: frame -> T_obj_cam of the registered frames; gt: frame -> T_obj_cam's ground-truth
    counterpart inv(T_cam_obj) of the object's frames; wrong: frame -> (deg, m) errors of the frames beyond
    WRONG_RENDERED; ate_m: ATE (m) of the registered object frames (nan with fewer than two)."""

    case: Case
    db: Path
    result: ScanResult
    poses: dict[str, np.ndarray]
    gt: dict[str, np.ndarray]
    wrong: dict[str, tuple[float, float]]
    ate_m: float
    edges: list[Edge]

    @property
    def registered(self) -> list[str]:
        return list(self.poses)

    def describe(self) -> str:
        """One paragraph for an assertion message."""
        r = self.result
        lines = [f"{r.registered}/{r.frames} registered ({r.mode}), ATE {1000 * self.ate_m:.2f} mm, "
                 f"wrong {len(self.wrong)}: " + ", ".join(f"{n} {d:.1f} deg / {1000 * m:.0f} mm"
                                                           for n, (d, m) in self.wrong.items())]
        if r.unregistered_reasons:
            lines.append("unregistered: " + "; ".join(f"{n}: {why}" for n, why in r.unregistered_reasons.items()))
        if r.parts:
            lines.append(f"parts: {r.parts}")
        suspects = set(self.wrong) | set(self.case.other_frames)
        for e in self.edges:
            if e.accepted and {e.src, e.tgt} & suspects:
                lines.append(f"accepted edge {e.src}-{e.tgt} ({e.kind}, {len(e.matches)} matches)")
        return "\n".join(lines)

    def check_reasons(self) -> None:
        """Every unregistered frame has a reason, and only those."""
        r = self.result
        assert set(r.unregistered_reasons) == set(r.unregistered), (r.unregistered, r.unregistered_reasons)
        assert all(why.strip() for why in r.unregistered_reasons.values()), r.unregistered_reasons


def scan_case(case: Case, db: Path) -> Outcome:
    """Scan a case's capture with the defaults (what a user runs) and score it against its ground truth."""
    res = scan(case.path, db)
    with TemplateDB.open(db) as t:
        poses = {n: np.asarray(T) for n, T in t.poses()["frames"].items()}
        edges = t.edges()
    truth = open_sequence(case.path).gt_T_cam_obj
    gt = {n: inv_T(truth[n]) for n in case.object_frames}
    mine = {n: T for n, T in poses.items() if n in gt}
    wrong: dict[str, tuple[float, float]] = {}
    if len(mine) >= 2:
        fe = frame_errors(mine, gt)
        wrong = {n: (fe.rot_deg[n], fe.trans_m[n]) for n in fe.wrong(*WRONG_RENDERED)}
    ate_m = ate([mine[n] for n in mine], [gt[n] for n in mine]).rmse if len(mine) >= 2 else float("nan")
    return Outcome(case, db, res, poses, gt, wrong, ate_m, edges)


def template_surface_distances(out: Outcome, mesh: TexturedMesh) -> np.ndarray:
    """[V] distance (m) of every template mesh vertex to the true object surface, the template placed onto the
    ground truth by the scan's own registered frames (`template_to_gt`)."""
    import open3d as o3d

    truth = open_sequence(out.case.path).gt_T_cam_obj
    T_obj_gt = template_to_gt(out.db, {n: truth[n] for n in out.case.object_frames})
    with TemplateDB.open(out.db) as t:
        V = t.mesh().vertices
    pts = transform_points(inv_T(T_obj_gt), V)
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                     o3d.core.Tensor(mesh.triangles.astype(np.uint32)))
    return rc.compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy()


def check_template_is_object(out: Outcome, mesh: TexturedMesh, max_p95_m: float, max_width_ratio: float) -> None:
    """The template is the object alone: 95 % of its mesh vertices within max_p95_m of the true surface
    (`template_surface_distances`), and its widest extent at most max_width_ratio times the object's (a template
    that took in the table or a neighbour is wider)."""
    d = template_surface_distances(out, mesh)
    assert np.percentile(d, 95) <= max_p95_m, f"95th percentile {1000 * np.percentile(d, 95):.1f} mm from the surface"
    with TemplateDB.open(out.db) as t:
        size = np.ptp(t.mesh().vertices, axis=0).max()
    assert size <= max_width_ratio * np.ptp(mesh.vertices, axis=0).max(), f"template {size:.2f} m wide\n" + \
        out.describe()


def box_ring_capture(root: Path, n_views: int, intr: Intrinsics) -> Path:
    """`root`: a static capture of a small printed box (14 x 9 x 7 cm) from `n_views` cameras on one ring at
    40 deg elevation."""
    mesh = synth.box_mesh((0.14, 0.09, 0.07), synth.procedural_box_texture(3, (512, 768)))
    synth.render_capture(mesh, root, n_views, mode="static", elevations_deg=(40.0,), intr=intr)
    return root


def plain_turntable_scan(name: str, root: Path, meshes_dir: Path) -> tuple[ScanResult, dict, dict, list[Edge]]:
    """A shared mesh made plain (one colour) on a 36-frame turntable (`root`/cap), scanned at the defaults into
    `root`/box.gscan: (the scan's result, its poses, the true T_world_cam, its stored edges), after checking that the
    scan chose `both` keypoints from the frames' image keypoints (`features.keypoints: auto`), that at least 90 % of
    the frames are registered and that none is wrong (WRONG_RENDERED relative to the others)."""
    from gscan.synth.capture import render_capture
    from gscan.synth.mesh import load_textured_mesh, plain_mesh

    mesh = plain_mesh(load_textured_mesh(meshes_dir / name / "model_0.obj"))
    cap = root / "cap"
    render_capture(mesh, cap, 36, mode="turntable", seed=0, table_kind="plain")
    res = scan(cap, root / "box.gscan")
    assert (res.keypoints["source"], res.keypoints["chosen_by"]) == ("both", "auto"), res.keypoints
    gt = {n: inv_T(T) for n, T in open_sequence(cap).gt_T_cam_obj.items()}
    with TemplateDB.open(root / "box.gscan") as db:
        poses = {n: np.asarray(T) for n, T in db.poses()["frames"].items()}
        edges = db.edges()
    assert len(poses) >= 0.9 * 36, res.unregistered_reasons
    assert not frame_errors(poses, {n: gt[n] for n in poses}).wrong(*WRONG_RENDERED)
    return res, poses, gt, edges
