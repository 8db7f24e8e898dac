"""Several instances per image in `gscan eval` / `score_results`, as the BOP toolkit scores them: its greedy
matching (`bop_matched`), the test targets' inst_count, and a BOP test split of rendered piles
(`gscan.synth.piles.write_bop_piles`). The CSV-scoring tests render two piles (a few seconds); the end-to-end
`gscan eval` test builds a CAD template: slow."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gscan.evaluate.bop19 import CSV_HEADER, evaluate, score_results, scored_instances
from gscan.evaluate.metrics import bop_matched, diameter, mssd
from gscan.geometry.transforms import rotvec_to_R
from gscan.synth import load_textured_mesh
from gscan.synth.piles import render_pile, write_bop_piles

BOX = "Crayola_Bonus_64_Crayons"
DISTRACTOR = "Whey_Protein_Chocolate_12_Packets"


def test_bop_matching_is_greedy_by_score_each_instance_once():
    """As the toolkit's match_poses: estimates in score order take the free instance with the smallest error under
    the threshold; a better-scoring estimate takes an instance first even when a later one is closer to it."""
    err = np.array([[0.2, 0.3],    # best score: instance 0, its smallest error
                    [0.1, 0.9]])   # closer to instance 0, which is taken; instance 1 too far
    np.testing.assert_array_equal(bop_matched(err, [0.5]), [[True], [False]])  # one match (not the two possible)
    np.testing.assert_array_equal(bop_matched(err, [0.15]), [[True], [False]])  # the second estimate's 0.1
    np.testing.assert_array_equal(bop_matched(err, [0.05, 0.35, 1.0]), [[False, True, True], [False, False, True]])
    # equal errors: the first instance (gt_id order); inf and NaN never match
    np.testing.assert_array_equal(bop_matched(np.array([[0.1, 0.1]]), [0.5]), [[True], [False]])
    np.testing.assert_array_equal(bop_matched(np.array([[np.inf, np.nan]]), [0.5]), [[False], [False]])
    assert bop_matched(np.zeros((0, 2)), [0.5, 1.0]).shape == (2, 2)


def test_the_most_visible_instances_are_scored():
    """BOP19 scores the inst_count most visible ground-truth instances of a target (scene_gt_info's visib_fract)."""
    insts = [(0, np.eye(4)), (2, 2 * np.eye(4)), (3, 3 * np.eye(4))]
    visib = [0.9, 0.5, 0.1, 0.8]  # by gt_id: instance gt_id 1 is another object
    assert [g for g, _ in scored_instances(insts, 2, visib)] == [0, 3]
    assert [g for g, _ in scored_instances(insts, 3, visib)] == [0, 2, 3]
    assert [g for g, _ in scored_instances(insts, 1, None)] == [0]  # no visibility known: the first


@pytest.fixture(scope="module")
def piles(meshes_dir: Path, tmp_path_factory):
    """A BOP test split of two rendered piles: 3 copies of BOX and a distractor (object 2), then 2 copies."""
    root = tmp_path_factory.mktemp("piles")
    box = load_textured_mesh(meshes_dir / BOX / "model_0.obj")
    other = load_textured_mesh(meshes_dir / DISTRACTOR / "model_0.obj")
    ps = [render_pile([box] * 3 + [other], 11), render_pile([box] * 2 + [other], 12)]
    scene = write_bop_piles(ps, root / "dataset", [[1, 1, 1, 2], [1, 1, 2]])
    return root, scene, ps, meshes_dir / BOX / "model_0.obj", diameter(box.vertices)


def _csv_row(im_id: int, score: float, T: np.ndarray, obj_id: int = 1) -> str:
    R = " ".join(f"{x:.9g}" for x in T[:3, :3].reshape(-1))
    t = " ".join(f"{x:.6f}" for x in T[:3, 3] * 1000)
    return f"1,{im_id},{obj_id},{score},{R},{t},0.5"


def test_piles_are_a_bop_split_with_targets(piles):
    root, scene, ps, _, _ = piles
    targets = json.loads((root / "dataset" / "test_targets_bop19.json").read_text())
    visible = [int((p.visible[:-1] >= 0.1).sum()) for p in ps]
    assert [t for t in targets if t["obj_id"] == 1] == [
        {"im_id": i, "inst_count": visible[i], "obj_id": 1, "scene_id": 1} for i in range(2)]
    gt = json.loads((scene / "scene_gt.json").read_text())
    info = json.loads((scene / "scene_gt_info.json").read_text())
    assert [e["obj_id"] for e in gt["0"]] == [1, 1, 1, 2] and len(info["1"]) == 3


def test_several_instances_scored_as_bop_does(piles, tmp_path):
    """Recall = instances matched / instances of the targets: a wrong pose with the best score matches nothing and
    takes one of the inst_count places (the estimate beyond them is not scored), two right poses match their two
    instances, never one instance twice."""
    _, scene, ps, model, diam = piles
    model_pts = ps[0].meshes[0].vertices
    T0 = ps[0].T_cam_objs[0]
    wrong = ps[0].T_cam_objs[2].copy()
    wrong[:3, :3] = wrong[:3, :3] @ rotvec_to_R([0.0, np.pi / 2, 0.0])
    wrong[:3, 3] += [0.0, 0.0, 1.0]  # a metre behind: near no instance
    n0 = int((ps[0].visible[:3] >= 0.1).sum())
    assert n0 == 3, ps[0].visible  # the seed's pile: every copy a target
    # the copies lie more than the loosest MSSD threshold (half the diameter) apart: a pose of one is a miss for the
    # others at every threshold
    assert min(mssd(model_pts, T0, T) for T in ps[0].T_cam_objs[1:3]) > 0.5 * diam
    rows = [_csv_row(0, 0.95, wrong), _csv_row(0, 0.9, T0), _csv_row(0, 0.8, T0),  # a duplicate of instance 0
            _csv_row(0, 0.1, ps[0].T_cam_objs[2]),  # right, but the fourth best of a 3-instance target
            *(_csv_row(1, 0.9 - 0.1 * k, T) for k, T in enumerate(ps[1].T_cam_objs[:2])),
            _csv_row(1, 0.99, ps[1].T_cam_objs[2], obj_id=2)]  # the distractor's own pose, as object 2
    csv = tmp_path / "r.csv"
    csv.write_text("\n".join([CSV_HEADER, *rows]) + "\n")
    rep = score_results(csv, scene.parent, model)
    n1 = int((ps[1].visible[:2] >= 0.1).sum())
    assert rep.n_images == 2 and len(rep.rows) == n0 + n1
    assert [(r.im_id, r.gt_id) for r in rep.rows] == [(0, 0), (0, 1), (0, 2), (1, 0), (1, 1)][:n0 + n1]
    # image 0: instance 0 matched (the duplicate matches nothing more), instances 1 and 2 not (the wrong pose and
    # the duplicate took the three places); image 1: both instances matched
    matched = 1 + n1
    for k in ("AR MSSD", "AR MSPD", "AR VSD"):
        assert rep.metrics[k] == pytest.approx(100.0 * matched / (n0 + n1), abs=2.0), (k, rep.metrics)
    assert rep.metrics["AR MSSD"] == pytest.approx(100.0 * matched / (n0 + n1))  # exact poses: every threshold
    r0 = rep.rows[0]
    assert r0.found and r0.mssd < 1e-4 and r0.score == pytest.approx(0.9)
    # the rows: the wrong pose and the duplicate are assigned the two instances left (found, far off)
    assert all(r.found for r in rep.rows[:3]) and min(rep.rows[1].mssd, rep.rows[2].mssd) > 0.5 * diam
    js = rep.to_json()
    assert js["n_instances"] == n0 + n1 and js["rows"][1]["gt_id"] == 1

    # only the single best estimate of each image: recall 2 of 5 (the wrong pose is image 0's best)
    one = tmp_path / "one.csv"
    one.write_text("\n".join([CSV_HEADER, rows[0], rows[4]]) + "\n")
    rep1 = score_results(one, scene.parent, model)
    assert rep1.metrics["AR MSSD"] == pytest.approx(100.0 / (n0 + n1))
    assert rep1.n_found == 2 and sum(r.found for r in rep1.rows[:n0]) == 1 and rep1.rows[n0].found


def test_without_targets_every_instance_is_scored(piles, tmp_path):
    """A BOP scene without test targets: every ground-truth instance of the object counts, as many estimates."""
    import shutil

    _, scene, ps, model, _ = piles
    bare = tmp_path / "bare" / "test" / "000001"
    shutil.copytree(scene, bare)
    csv = tmp_path / "r.csv"
    csv.write_text("\n".join([CSV_HEADER, *(_csv_row(0, 0.5, T) for T in ps[0].T_cam_objs[:3])]) + "\n")
    rep = score_results(csv, bare, model)
    assert len(rep.rows) == 5 and [r.found for r in rep.rows] == [True, True, True, False, False]
    assert rep.metrics["AR MSSD"] == pytest.approx(60.0)


@pytest.mark.slow
def test_gscan_eval_scores_every_instance_of_a_pile(piles, cad_template, tmp_path):
    """`evaluate` on the piles with a CAD template: estimate_all up to each target's inst_count; every pose it
    writes is right (MSSD under 5 % of the diameter) or counted as a miss, and the recall is the matched share of
    the instances (at least the issue's two per pile); --max-instances 1 scores one instance per image."""
    _, scene, ps, _, diam = piles
    tpl = cad_template(BOX, 36)
    rep = evaluate(tpl, scene.parent, tmp_path / "all.csv")
    lines = (tmp_path / "all.csv").read_text().splitlines()[1:]
    n_inst = len(rep.rows)
    assert rep.n_images == 2 and n_inst == sum(int((p.visible[:-1] >= 0.1).sum()) for p in ps)
    per_image = [sum(ln.split(",")[1] == str(i) for ln in lines) for i in range(2)]
    assert per_image[0] >= 2 and per_image[1] >= 2, lines  # several instances estimated per image
    found = [r for r in rep.rows if r.found]
    assert all(r.mssd < 0.05 * diam for r in found), [r.mssd for r in found]  # no wrong pose
    assert rep.metrics["AR MSSD"] == pytest.approx(100.0 * len(found) / n_inst, abs=1e-9)
    assert rep.metrics["AR"] > 60.0, rep.metrics
    one = evaluate(tpl, scene.parent, tmp_path / "one.csv", max_instances=1)
    assert len((tmp_path / "one.csv").read_text().splitlines()) == 1 + 2
    assert one.n_found == 2 and one.metrics["AR MSSD"] < rep.metrics["AR MSSD"]
