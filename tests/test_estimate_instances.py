"""Every instance in one frame (gscan.estimate.instances): rendered piles of 2-5 copies (touching or nearly,
some lying on a side, one distractor), two templated objects in one pile, a look-alike box, a twin-printed box
whose view stays ambiguous, and the claims of two templates on the same pixels. Every test but the claims' builds
CAD templates and renders piles: slow (about 4 minutes in all on a loaded 2-core machine, most of it the
templates)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gscan.estimate import Estimator, estimate_templates
from gscan.estimate.instances import Instances, explained_pixels, resolve_claims, thinnest_extent
from gscan.estimate.result import found
from gscan.estimate.verify import Evidence
from gscan.geometry.transforms import pose_error
from gscan.io.camera import RGBDFrame
from gscan.scanning.cad import template_from_mesh
from gscan.synth import box_mesh, load_textured_mesh, procedural_box_texture, save_textured_mesh, view_on_table
from gscan.synth.piles import render_pile

BOX = "Crayola_Bonus_64_Crayons"
OTHER = "Little_Debbie_Cloud_Cakes_10_ct"
DISTRACTOR = "Whey_Protein_Chocolate_12_Packets"
TWIN_FACED = "Nestle_Raisinets_Milk_Chocolate_35_oz_992_g"  # the same print on both large faces
MIN_VISIBLE = 0.3  # instances less in sight need not be found (a pose of one must still be right)


def frame_of(pile) -> RGBDFrame:
    return RGBDFrame("pile", pile.frame.color, pile.frame.depth, pile.frame.intrinsics)


def check(est: Estimator, out: Instances, truths: np.ndarray, visible: np.ndarray) -> int:
    """Every returned pose within 5 deg / 1 cm of an instance (up to the template's symmetries), no instance
    twice, every instance with MIN_VISIBLE in sight found; returns the number found."""
    hit: list[int] = []
    for r in out.results:
        near = [i for i, T in enumerate(truths) if all(np.array(est.verifier.apart(r.T_cam_obj, T)) <= (5.0, 0.01))]
        assert near, ("a pose at no instance", [pose_error(r.T_cam_obj, T) for T in truths])
        assert near[0] not in hit, "two poses for one instance"
        hit.append(near[0])
    missed = [i for i in range(len(truths)) if visible[i] >= MIN_VISIBLE and i not in hit]
    assert not missed, (missed, visible, out.stopped)
    return len(hit)


@pytest.fixture(scope="module")
def meshes(meshes_dir: Path) -> dict:
    return {n: load_textured_mesh(meshes_dir / n / "model_0.obj") for n in (BOX, OTHER, DISTRACTOR, TWIN_FACED)}


@pytest.fixture(scope="module")
def templates(cad_template) -> dict:
    return {n: Estimator.from_path(cad_template(n, 36)) for n in (BOX, OTHER, TWIN_FACED)}


@pytest.mark.slow
@pytest.mark.parametrize("n, seed", [(2, 3), (3, 4), (5, 7)])
def test_every_instance_of_a_pile_is_found_once(n, seed, meshes, templates):
    """Piles of 2, 3 and 5 copies and a distractor: every copy in sight found within 5 deg / 1 cm, none twice,
    nothing at the distractor; ordered by score; the single estimate still gives at most one pose."""
    est = templates[BOX]
    pile = render_pile([meshes[BOX]] * n + [meshes[DISTRACTOR]], seed)
    out = est.estimate_all(frame_of(pile))
    assert check(est, out, pile.T_cam_objs[:n], pile.visible[:n]) >= 2
    assert out.reason is None
    scores = [(r.score, r.evidence.support) for r in out.results]
    assert scores == sorted(scores, reverse=True)
    for r in out.results:  # the pixels each explains: its own, within its silhouette
        assert r.pixels is not None and r.pixels.sum() > 500
    js = out.to_json()
    assert len(js["instances"]) == len(out.results) and js["instances"][0]["pixels"]["count"] > 0


@pytest.mark.slow
def test_no_instance_where_the_object_is_not(meshes, templates, meshes_dir):
    """A pile of other objects: no pose, and the reason says why."""
    others = [load_textured_mesh(meshes_dir / n / "model_0.obj") for n in
              ("Apples_to_Apples_Kids_Edition", "Clue_Board_Game_Classic_Edition")] + [meshes[DISTRACTOR]]
    out = templates[BOX].estimate_all(frame_of(render_pile(others, 77)))
    assert out.results == [] and out.reason


@pytest.mark.slow
def test_two_templated_objects_each_found_none_confused(meshes, templates):
    """Two copies of each of two templated objects and a distractor, both templates in one call: each finds its
    own copies only, the frame's features computed once."""
    a, b = templates[BOX], templates[OTHER]
    pile = render_pile([meshes[BOX], meshes[OTHER], meshes[BOX], meshes[OTHER], meshes[DISTRACTOR]], 21)
    outs = estimate_templates([a, b], frame_of(pile))
    assert [o.template for o in outs] == [a.name, b.name]
    assert check(a, outs[0], pile.T_cam_objs[[0, 2]], pile.visible[[0, 2]]) == 2
    assert check(b, outs[1], pile.T_cam_objs[[1, 3]], pile.visible[[1, 3]]) == 2
    assert outs[0].refused == [] and outs[1].refused == []


@pytest.mark.slow
def test_a_look_alike_box_is_not_an_instance(tmp_path):
    """Two copies of a printed box beside a box of the same size printed differently: the copies are found,
    the look-alike (whose depth alone would confirm a pose) is not."""
    size = (0.16, 0.11, 0.05)
    box = box_mesh(size, procedural_box_texture(3, (256, 384)), name="box")
    other = box_mesh(size, procedural_box_texture(1003, (256, 384)), name="lookalike")
    save_textured_mesh(box, tmp_path / "box.obj")
    template_from_mesh(tmp_path / "box.obj", tmp_path / "box.gscan", n_views=36)
    est = Estimator.from_path(tmp_path / "box.gscan")
    pile = render_pile([box, other, box], 5, lying_frac=0.0)
    out = est.estimate_all(frame_of(pile))
    assert check(est, out, pile.T_cam_objs[[0, 2]], pile.visible[[0, 2]]) == 2
    assert len(out.results) == 2


@pytest.mark.slow
def test_a_view_the_single_estimate_finds_ambiguous_stays_refused(meshes, templates):
    """The twin-printed box alone, at views where its two faces cannot be told apart: the rival pose lies on
    the same pixels, so --all refuses it as the single estimate does (never the turned pose, never two)."""
    est, mesh = templates[TWIN_FACED], meshes[TWIN_FACED]
    ambiguous = 0
    for az in (130.2, 140.2, 160.2, 170.2):
        r = view_on_table(mesh, 2.645, az, 51.7, 0.39)
        frame = RGBDFrame("query", r.color, r.depth, r.intrinsics)
        single = est.estimate(frame)
        out = est.estimate_all(frame)
        assert len(out.results) <= 1
        for res in out.results:
            deg, dist = pose_error(res.T_cam_obj, r.T_cam_obj)
            assert deg < 5 and dist < 0.01, (az, deg, dist)
        if not single.found and (single.reason or "").startswith("ambiguous view"):
            ambiguous += 1
            assert out.results == [], az
    assert ambiguous >= 1  # the case is exercised


def test_the_better_supported_template_keeps_the_pixels():
    """Two templates' instances on the same pixels: the one with more supporting keypoints keeps them, the other
    is refused there with that reason; instances apart are both kept."""
    def inst(support: int, box: tuple[int, int, int, int]):
        pix = np.zeros((60, 80), bool)
        pix[box[1]:box[3], box[0]:box[2]] = True
        r = found(np.eye(4), 0.99, 20, "v", "gmatch", Evidence(supporters=np.arange(support)))
        r.pixels = pix
        return r

    a, b = Instances("a", [inst(40, (0, 0, 30, 30)), inst(12, (50, 0, 80, 30))]), \
        Instances("b", [inst(25, (5, 5, 30, 30)), inst(30, (50, 40, 80, 60))])
    resolve_claims([a, b], [0.3, 0.3])
    assert [r.evidence.support for r in a.results] == [40, 12]
    assert [r.evidence.support for r in b.results] == [30]
    assert len(b.refused) == 1 and "claimed by template a" in b.refused[0].reason
    assert b.to_json()["refused"][0]["T_cam_obj"] is None


@pytest.mark.slow
def test_explained_pixels_follow_the_surface(meshes, templates):
    """The pixels a pose explains lie on the object (the rendered labels), not on the table around it; a pose
    1.5 thinnest extents off explains almost none of them."""
    est, mesh = templates[BOX], meshes[BOX]
    r = view_on_table(mesh, 0.3, 40.0, 50.0, 0.5)
    frame = RGBDFrame("q", r.color, r.depth, r.intrinsics)
    q = est.prepare(frame)
    pix = explained_pixels(q, est.model.samples, r.T_cam_obj, 0.008, 0)
    on = r.mask & (r.depth > 0)
    assert (pix & on).sum() > 0.8 * on.sum() and (pix & ~r.mask).sum() < 0.1 * pix.sum()
    T = r.T_cam_obj.copy()
    T[:3, 3] += T[:3, 0] * 1.5 * thinnest_extent(est.model.samples) + T[:3, 1] * 0.1
    assert (explained_pixels(q, est.model.samples, T, 0.008, 0) & on).sum() < 0.3 * on.sum()


def test_explained_pixels_by_grid_equal_those_by_kd_tree(monkeypatch):
    """The grid's neighbours within the distance are the kd-tree's (its fallback when the points spread too wide
    for a grid): the same pixels at the true pose, a shifted one and several distances."""
    import gscan.estimate.instances as instances
    from gscan.estimate.query import QueryFrame
    from gscan.geometry.transforms import inv_T, transform_points

    box = box_mesh((0.12, 0.08, 0.05), procedural_box_texture(3, (256, 384)))
    r = view_on_table(box, 0.3, 40.0, 50.0, 0.5)
    q = QueryFrame(RGBDFrame("q", r.color, r.depth, r.intrinsics), None, 1.0)
    on = r.mask & (r.depth > 0)
    samples = transform_points(inv_T(r.T_cam_obj), q.cloud[on][::3].astype(np.float64))
    shifted = r.T_cam_obj.copy()
    shifted[:3, 3] += np.array([0.02, -0.01, 0.005])
    cases = [(T, dist, px) for T in (r.T_cam_obj, shifted) for dist, px in ((0.002, 0), (0.008, 2), (0.03, 4))]
    by_grid = [explained_pixels(q, samples, T, dist, px) for T, dist, px in cases]
    monkeypatch.setattr(instances.NearestGrid, "build", classmethod(lambda cls, *a, **k: None))
    by_tree = [explained_pixels(q, samples, T, dist, px) for T, dist, px in cases]
    assert by_grid[0].sum() > 0.8 * on.sum()
    for a, b in zip(by_grid, by_tree, strict=True):
        assert a.any() and np.array_equal(a, b)


def test_explained_pixels_in_the_silhouettes_box_equal_the_whole_frames():
    """explained_pixels works in the silhouette's bounding box: the same pixels as the plain computation over
    the whole frame (sampled, repeated and dilated there), for poses partly out of the frame, odd shifts and
    several dilations."""
    import cv2
    from scipy.spatial import cKDTree

    from gscan.estimate.query import QueryFrame
    from gscan.estimate.verify import visible
    from gscan.geometry.transforms import inv_T, transform_points

    def whole_frame(q, samples, T, dist, px):
        H, W = q.frame.depth.shape
        _, pc, uv = visible(T, q.frame.intrinsics, samples)
        sil = np.zeros((H, W), np.uint8)
        cv2.fillConvexPoly(sil, cv2.convexHull(uv.astype(np.int32)), 1)
        ys, xs = np.nonzero(sil[::2, ::2].astype(bool) & (q.frame.depth[::2, ::2] > 0))
        d, _ = cKDTree(pc).query(q.cloud[2 * ys, 2 * xs].astype(np.float64), distance_upper_bound=dist)
        half = np.zeros(((H + 1) // 2, (W + 1) // 2), bool)
        half[ys[d < dist], xs[d < dist]] = True
        out = np.repeat(np.repeat(half, 2, axis=0), 2, axis=1)[:H, :W].astype(np.uint8)
        return (cv2.dilate(out, np.ones((2 * px + 1,) * 2, np.uint8)) if px else out).astype(bool)

    box = box_mesh((0.12, 0.08, 0.05), procedural_box_texture(3, (256, 384)))
    r = view_on_table(box, 0.3, 40.0, 50.0, 0.5)
    q = QueryFrame(RGBDFrame("q", r.color, r.depth, r.intrinsics), None, 1.0)
    on = r.mask & (r.depth > 0)
    samples = transform_points(inv_T(r.T_cam_obj), q.cloud[on][::5].astype(np.float64))
    rng = np.random.default_rng(3)
    for k in range(8):
        T = r.T_cam_obj.copy()
        if k:  # shifted by up to a frame's half width: some partly out of the frame
            T[:3, 3] += rng.uniform(-1, 1, 3) * np.array([0.25, 0.2, 0.02]) + 0.0013 * k
        for dist, px in ((0.004, 0), (0.008, 1), (0.008, 2), (0.03, 5)):
            got = explained_pixels(q, samples, T, dist, px)
            assert np.array_equal(got, whole_frame(q, samples, T, dist, px)), (k, dist, px)
            if k == 0:
                assert got.sum() > 0.5 * on.sum()
