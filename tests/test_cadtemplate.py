"""Templates rendered from CAD meshes (gscan.scanning.cad)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gscan.demo import SAMPLES
from gscan.errors import InputError
from gscan.geometry.transforms import inv_T, transform_points
from gscan.io.camera import project
from gscan.scanning.cad import fibonacci_directions, template_from_mesh, view_poses
from gscan.synth import DEFAULT_INTRINSICS, load_textured_mesh
from gscan.template.db import TemplateDB

MESH = "Vans_Cereal_Honey_Nut_Crunch_11_oz_box"


@pytest.fixture(scope="module")
def built(meshes_dir: Path, tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("cad") / "vans.gscan"
    summary = template_from_mesh(meshes_dir / MESH / "model_0.obj", out, n_views=8, scale=1.0)
    return out, summary


def test_summary_and_database(built, meshes_dir):
    out, summary = built
    mesh = load_textured_mesh(meshes_dir / MESH / "model_0.obj")
    assert summary.output == out and summary.views == 8 and summary.source == "mesh"
    assert summary.descriptor == "rootsift"
    # the mesh's extent through the database's float storage: float32 rounding (6e-8 relative) of ~0.1 m
    np.testing.assert_allclose(summary.extent_m, mesh.extent, atol=1e-6)
    with TemplateDB.open(out, require_complete=True) as db:
        info = db.summary()
        assert info.status == "complete" and info.source == "mesh" and info.views == 8
        m = db.mesh()
        V, F, C = m.vertices, m.triangles, m.vertex_colors
        np.testing.assert_allclose(V, mesh.vertices)  # the mesh frame is kept
        assert F.shape == mesh.triangles.shape and C.shape == V.shape and C.dtype == np.uint8
        assert C.std() > 5  # colours come from the texture, not a flat grey
        P, _ = db.cloud()
        lo, hi = mesh.bounds
        assert len(P) > 1000 and np.all(lo - 2e-3 <= P) and np.all(hi + 2e-3 >= P)
        for v in db.views(load_images=True):
            assert v.T_obj_cam is not None and v.mask is not None and v.mask.any()
            assert not v.depth[~v.mask].any()  # depth only on the object
            assert np.percentile(v.color[~v.mask], 99) <= 8  # black background, no table (JPEG ringing at edges)
            f = db.features(v.name)
            px, pts_obj = f.pixels, f.points
            assert f.kind == "rootsift" and len(px) > 10
            # object-frame keypoints project back onto their pixels through the view pose
            uv = project(transform_points(inv_T(v.T_obj_cam), pts_obj), v.intrinsics)
            # keypoints lifted from rendered depth and projected back through the view pose: float32 depth and sub-pixel
            # keypoints, a few hundredths of a pixel
            np.testing.assert_allclose(uv, px, atol=0.05)
            u, w = np.rint(px).astype(int).T
            assert v.mask[w, u].all()


def test_a_mesh_template_stores_its_coverage(built, meshes_dir):
    """template-from-mesh stores the coverage of its rendered views and the mesh's surface (mesh frame, z up):
    the map `template_coverage` gives for the same views, reported by `info --json`."""
    from gscan.geometry.coverage import template_coverage
    from gscan.template.reports import template_info

    mesh = load_textured_mesh(meshes_dir / MESH / "model_0.obj")
    expected = template_coverage(view_poses(mesh, 8), mesh.to_mesh())
    with TemplateDB.open(built[0]) as db:
        c = db.coverage()
    assert c is not None and np.array_equal(c.counts, expected.counts) and np.array_equal(c.seen, expected.seen)
    assert int(c.counts.sum()) >= 8 and c.surface.any()
    assert template_info(built[0]).to_json()["coverage"] == expected.to_json()


def test_template_keypoints_are_the_estimators_query_keypoints(built):
    """A CAD template stores keypoints detected with the settings the estimator detects its queries with."""
    from gscan.estimate.estimator import EstimateParams

    q = EstimateParams().features
    with TemplateDB.open(built[0]) as db:
        assert db.get_meta("descriptor") == {"kind": q.kind, "max_keypoints": q.max_keypoints,
                                             "sift_contrast_threshold": q.sift_contrast_threshold}


def test_views_cover_both_hemispheres_at_fill_distance(meshes_dir):
    d = fibonacci_directions(36)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)  # unit directions: float64 normalisation
    assert (d[:, 2] > 0.3).sum() >= 10 and (d[:, 2] < -0.3).sum() >= 10
    mesh = load_textured_mesh(meshes_dir / MESH / "model_0.obj")
    for T_obj_cam in view_poses(mesh, 12):
        c_cam = transform_points(inv_T(T_obj_cam), mesh.center[None])[0]
        uv = project(c_cam[None], DEFAULT_INTRINSICS)[0]
        # every camera looks at the mesh's centre: float64 rounding, in pixels
        np.testing.assert_allclose(uv, [DEFAULT_INTRINSICS.cx, DEFAULT_INTRINSICS.cy], atol=1e-6)
        span = 2 * mesh.radius * DEFAULT_INTRINSICS.fx / c_cam[2] / DEFAULT_INTRINSICS.width
        # the fill distance frames the object at 45 % of the width (0.4-0.5 allows its radius bound)
        assert 0.4 <= span <= 0.5


def test_scale_converts_units(meshes_dir, tmp_path):
    out = tmp_path / "mm.gscan"
    s = template_from_mesh(meshes_dir / MESH / "model_0.obj", out, n_views=4, scale=0.5)
    mesh = load_textured_mesh(meshes_dir / MESH / "model_0.obj")
    # half the extent through float storage: float32 rounding of ~0.1 m
    np.testing.assert_allclose(s.extent_m, 0.5 * mesh.extent, atol=1e-6)


def test_vertex_coloured_ply(tmp_path):
    import trimesh

    box = trimesh.creation.box(extents=(0.1, 0.06, 0.04))
    rng = np.random.default_rng(0)
    box = box.subdivide().subdivide()
    box.visual.vertex_colors = np.c_[rng.integers(0, 256, (len(box.vertices), 3)), np.full(len(box.vertices), 255)]
    ply = tmp_path / "box.ply"
    box.export(ply)
    out = tmp_path / "box.gscan"
    s = template_from_mesh(ply, out, n_views=4)
    assert s.views == 4
    with TemplateDB.open(out) as db:
        v = db.views(load_images=True)[0]
        assert v.color[v.mask].std() > 20  # rendered with its colours, not grey


def test_template_from_a_scanned_mesh(sample_template, tmp_path, caplog):
    """A scan's exported PLY (vertex colours, 30k+ faces: more than OpenCV's 32767-pixel image side, which a
    one-row face-colour texture exceeded) becomes a CAD template that finds the held-out frame's pose as the
    scanned template does, with no warning about missing colours."""
    from gscan.estimate.estimator import Estimator
    from gscan.exporters import export
    from gscan.geometry.transforms import pose_error
    from gscan.io import load_frame

    ply = tmp_path / "scan.ply"
    export(sample_template, "ply", ply)
    out = tmp_path / "from_scan.gscan"
    with caplog.at_level("WARNING"):
        template_from_mesh(ply, out, n_views=24)
    assert not [r for r in caplog.records if "flat colour" in r.getMessage()]
    held = SAMPLES / "heldout"
    frame = load_frame(held / "rgb" / "000000.jpg", held / "depth" / "000000.png", held / "cam_K.txt",
                       depth_scale=0.001)
    a, b = Estimator.from_path(out).estimate(frame), Estimator.from_path(sample_template).estimate(frame)
    assert a.found and b.found, (a.reason, b.reason)
    deg, m = pose_error(a.T_cam_obj, b.T_cam_obj)
    # the template built from the scanned mesh finds the same pose as the scan's own template: within a degree and 2 mm
    assert deg < 1.0 and m < 0.002, (deg, m)


@pytest.mark.parametrize("content", [None, b"", b"v 0 0 0\nf 1 2 3\n", b"\x00\x01garbage"])
def test_bad_mesh_refused_and_nothing_written(tmp_path, content):
    mesh = tmp_path / "bad.obj"
    if content is not None:
        mesh.write_bytes(content)
    out = tmp_path / "out.gscan"
    with pytest.raises(InputError, match="bad.obj"):
        template_from_mesh(mesh, out, n_views=4)
    assert not out.exists()


def test_existing_output_refused_without_force(built, meshes_dir, tmp_path):
    out = tmp_path / "exists.gscan"
    out.write_bytes(b"keep me")
    with pytest.raises(InputError, match="exists.gscan"):
        template_from_mesh(meshes_dir / MESH / "model_0.obj", out, n_views=4)
    assert out.read_bytes() == b"keep me"


def test_failure_midway_removes_output(meshes_dir, tmp_path, monkeypatch):
    from gscan.synth import TexturedMesh

    def boom(*a, **k):
        raise RuntimeError("disk full")

    monkeypatch.setattr(TexturedMesh, "to_mesh", boom)  # the last step before the database is complete
    out = tmp_path / "half.gscan"
    with pytest.raises(RuntimeError):
        template_from_mesh(meshes_dir / MESH / "model_0.obj", out, n_views=4)
    assert not out.exists()
