"""The capture's steady motion (gscan.registration.motion) and what a scan decides by it
(gscan.registration.sequence): loop closures told from the object's turns, edges the shape's checks refused, weak
edges joining two parts."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gscan.geometry.transforms import inv_T, rotation_angle_deg
from gscan.registration.edge import Edge
from gscan.registration.edges import LOOP_DEPTH_ONLY, LOOP_TURN
from gscan.registration.motion import steady_motion
from gscan.registration.pairwise import NO_TEXTURE_VERDICT, RegisterParams, refused_by_shape
from gscan.registration.params import SequenceParams
from gscan.registration.sequence import admit_by_motion, bridge_strength, capture_motion
from tests._scan_checks import plain_turntable_scan

NO_MATCHES = np.zeros((0, 2), np.int32)
SILHOUETTE = (f"silhouette disagrees (9.6% of the samples land off the other frame's surface; {NO_TEXTURE_VERDICT}, "
              "so at most 5.0%)")
SEEN_THROUGH = (f"depth disagrees (0.8% of the overlap of 253 samples seen through; {NO_TEXTURE_VERDICT}, so at most "
                "0.5%)")


def _rot(axis: np.ndarray, deg: float) -> np.ndarray:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = np.radians(deg)
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K


def _turntable(n: int, step_deg: float, jitter_deg: float, seed: int = 0) -> list[np.ndarray]:
    """T_world_cam of n cameras 0.6 m from an object turning step_deg (+- jitter) a frame about its vertical axis
    (world z), each looking at the object's centre."""
    rng = np.random.default_rng(seed)
    out, az = [], 0.0
    for _ in range(n):
        R_world_cam = _rot([0, 0, 1], az) @ np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], float)  # camera z: world -y
        T = np.eye(4)
        T[:3, :3] = R_world_cam
        T[:3, 3] = -0.6 * R_world_cam[:, 2]
        out.append(T)
        az += step_deg + rng.normal(0.0, jitter_deg)
    return out


def _edge(T_world: list[np.ndarray], i: int, j: int, kind: str = "sequential", reason: str | None = None,
          turn_deg: float = 0.0) -> Edge:
    """The true edge i -> j, its object turned turn_deg about the vertical axis through the centre (a rival)."""
    T = inv_T(T_world[j]) @ T_world[i]
    if turn_deg:
        turn = np.eye(4)
        turn[:3, :3] = _rot([0, 0, 1], turn_deg)
        T = inv_T(T_world[j]) @ turn @ T_world[i]
    return Edge(f"{i:06d}", f"{j:06d}", T, NO_MATCHES, kind=kind, accepted=reason is None, reason=reason)


def _chain(T_world: list[np.ndarray]) -> list[Edge]:
    return [_edge(T_world, k, k + 1) for k in range(len(T_world) - 1)]


def _index(n: int) -> dict[str, int]:
    return {f"{k:06d}": k for k in range(n)}


def _at_60cm(e: Edge) -> float:
    return 0.6


@settings(max_examples=25, deadline=None)
@given(st.floats(-30, 30), st.floats(-1, 1), st.floats(-1, 1), st.floats(0.1, 1), st.integers(1, 12))
def test_equal_steps_predict_their_powers_exactly(deg, x, y, z, gap):
    step = np.eye(4)
    step[:3, :3] = _rot([x, y, z], deg)
    step[:3, 3] = [0.05 * x, 0.02, -0.03 * y]
    m = steady_motion([step] * 10, min_steps=8)
    assert m is not None and m.sigma_deg < 1e-5 and m.sigma_m < 1e-9
    expected = np.eye(4)
    for _ in range(gap):
        expected = step @ expected
    np.testing.assert_allclose(m.predict(gap), expected, atol=1e-9)
    deg_off, m_off = m.deviation(expected, gap)
    assert deg_off < 1e-4 and m_off < 1e-9


def test_too_few_steps_measure_no_motion():
    T = _turntable(6, 10.0, 0.0)
    assert steady_motion([e.T_tgt_src for e in _chain(T)], min_steps=8) is None


def test_the_spread_is_the_steps_scatter():
    steady = steady_motion([e.T_tgt_src for e in _chain(_turntable(30, 10.0, 0.2))], 8)
    uneven = steady_motion([e.T_tgt_src for e in _chain(_turntable(30, 10.0, 3.0))], 8)
    assert steady is not None and uneven is not None
    assert abs(rotation_angle_deg(steady.T_step) - 10.0) < 0.2
    assert 0.1 < steady.sigma_deg < 0.4 and 1.5 < uneven.sigma_deg < 5.0


def test_positions_are_compared_at_the_object():
    """Steps that differ by turns about the object 0.4 m in front of the camera (a turntable's jitter) spread in
    rotation alone at the object, and by 0.4 m x the turn at the camera's origin."""
    steps = []
    for k in range(10):
        T = np.eye(4)
        T[:3, :3] = _rot([0, 1, 0], 10.0 + (0.5 if k % 2 else -0.5))
        p = np.array([0.0, 0.0, 0.4])
        T[:3, 3] = p - T[:3, :3] @ p  # a turn about p
        steps.append(T)
    at_object = steady_motion(steps, 8, depth=0.4)
    at_origin = steady_motion(steps, 8)
    assert at_object is not None and at_origin is not None
    assert abs(at_object.sigma_deg - 0.5) < 1e-6 and at_object.sigma_m < 1e-4  # the mean step: second order
    assert abs(at_origin.sigma_m - 0.4 * np.radians(0.5)) < 1e-4


def test_a_loop_closure_the_steady_motion_tells_from_its_turns_is_accepted():
    """A plain box's loop closure the depth alone decided, refused as ambiguous: its right pose agrees with the
    turntable's steady motion and is accepted; its half and quarter turns, a loop refused for another reason and
    one on image keypoints of plain frames stay refused."""
    T = _turntable(36, 10.0, 0.2)
    right = _edge(T, 2, 30, "loop", LOOP_DEPTH_ONLY)
    half = _edge(T, 3, 31, "loop", LOOP_DEPTH_ONLY, turn_deg=180.0)
    on_image = _edge(T, 6, 28, "loop", LOOP_TURN.format("the object turned half a turn about its first axis"))
    quarter = _edge(T, 4, 20, "loop", LOOP_DEPTH_ONLY, turn_deg=90.0)
    refuted = _edge(T, 5, 12, "loop", "depth disagrees (3% of the overlap seen through)")
    edges = _chain(T) + [right, half, quarter, refuted, on_image]
    motion = capture_motion(edges, _index(36), 8)
    assert motion is not None
    assert admit_by_motion(motion, edges, _index(36), 3.0, 0, RegisterParams(), _at_60cm) == [right]
    assert right.accepted and right.reason is None and right.depth_only
    assert not half.accepted and not quarter.accepted and not refuted.accepted and not on_image.accepted


def test_an_uneven_capture_decides_no_loop_closure():
    """Steps scattered by 3 deg: over 28 frames the prediction may be off beyond half a quarter turn, so it tells
    the pose from no turn, and the loop stays refused."""
    T = _turntable(36, 10.0, 3.0)
    loop = _edge(T, 2, 30, "loop", LOOP_DEPTH_ONLY)
    edges = _chain(T) + [loop]
    motion = capture_motion(edges, _index(36), 8)
    assert motion is not None and 3.0 * motion.sigma(28)[0] > 45.0
    assert admit_by_motion(motion, edges, _index(36), 3.0, 0, RegisterParams(), _at_60cm) == [] and not loop.accepted


@pytest.mark.parametrize("jitter, off_deg, reason, admitted", [
    (0.2, 0.0, SILHOUETTE, True), (0.2, 0.0, SEEN_THROUGH, True), (0.2, 3.0, SILHOUETTE, False),
    (3.0, 0.0, SILHOUETTE, False),
    (0.2, 0.0, "colour disagrees (the texture lines up in 3 of 10 tiles of the overlap)", False),
    (0.2, 0.0, "too little depth overlap to verify the pose (40 samples)", False),
    (0.2, 0.0, "weak geometry (the depth alone pins the pose to 1.6 deg and the pairs' points to 2.0 mm, beyond 1 deg /"
               " 6.0 mm; the texture cannot judge the pose)", False)])
def test_an_edge_the_shapes_checks_refused_stands_where_the_steady_motion_pins_it(jitter, off_deg, reason, admitted):
    """A plain box seen edge on: the edge 7 -> 8, posed by the depth alone, refused by the silhouette or the depth
    seen through (its rims lose depth). Where the steps scatter little (0.2 deg) the motion pins it within
    registration's bounds and it is accepted where it agrees (not 3 deg off); where they scatter (3 deg) it stays
    refused, and so do a texture verdict against it, too little overlap to check it and a pose the depth cannot
    pin."""
    T = _turntable(36, 10.0, jitter)
    edge = _edge(T, 7, 8, reason=reason, turn_deg=off_deg)
    edges = [e for e in _chain(T) if e.src != "000007"] + [edge]
    motion = capture_motion(edges, _index(36), 8)
    assert motion is not None
    got = admit_by_motion(motion, edges, _index(36), 3.0, 12, RegisterParams(), _at_60cm)
    assert got == ([edge] if admitted else [])
    assert edge.accepted is admitted and edge.depth_only is admitted


def test_the_shape_checks_reasons_are_told_apart():
    assert refused_by_shape(SILHOUETTE) and refused_by_shape(SEEN_THROUGH)
    assert not refused_by_shape(LOOP_DEPTH_ONLY) and not refused_by_shape(None)
    assert not refused_by_shape("depth disagrees (3% of the overlap seen through)")  # a texture verdict was given


@pytest.mark.parametrize("jitter, off_deg, matches, strong", [
    (0.2, 0.0, 8, True), (0.2, 3.0, 8, False), (3.0, 0.0, 8, False), (0.2, 3.0, 40, True)])
def test_a_weak_bridge_stands_where_the_steady_motion_pins_it(jitter, off_deg, matches, strong):
    """An edge over two frames on 8 matches that alone joins two parts: where the steps scatter little (0.2 deg)
    the motion pins it within registration's bound, and it stands where it agrees (not 3 deg off); where they
    scatter (3 deg), it does not. On 40 matches it stands (`bridge_min_matches`, 12)."""
    T = _turntable(36, 10.0, jitter)
    chain = [e for e in _chain(T) if e.src not in ("000007", "000008")]  # frames 7 -> 9 joined by the bridge only
    bridge = _edge(T, 7, 9, turn_deg=off_deg)
    bridge.matches = np.zeros((matches, 2), np.int32)
    motion = capture_motion(chain + [bridge], _index(36), 8)
    assert bridge_strength(motion, bridge, 2, 0.6, RegisterParams(), SequenceParams()) is strong
    assert bridge_strength(None, bridge, 2, 0.6, RegisterParams(), SequenceParams()) is (matches >= 12)


@pytest.mark.slow
def test_a_plain_box_on_a_turntable_closes_its_ring_by_its_steady_motion(tmp_path, meshes_dir):
    """A 36-frame turntable of the Vans cereal box made plain (one colour), scanned at the defaults (`both` keypoints,
    by `auto`): its edge-on views split the chain, and the loop closures that would join the parts are ones the depth
    alone decides (refused as ambiguous without the motion: 17 of 36 frames registered). With the steady motion the weak
    bridges stand and the ring closes: at least 90 % of the frames registered, none wrong (5 deg / 2 cm relative to the
    others), the half-turn loop closures still refused. About 40 s."""
    res, poses, gt, edges = plain_turntable_scan("Vans_Cereal_Honey_Nut_Crunch_11_oz_box", tmp_path, meshes_dir)
    # the summary says what the motion decided: a 10 deg step, the loop closures it told from the turns
    motion = res.to_json()["motion"]
    assert abs(motion["step_deg"] - 10.0) < 0.5 and motion["spread_deg"] < 1.0 and motion["decided_edges"] >= 1
    # the loop closures the motion admitted are stored as accepted; those at a half turn stay refused
    index = {n: k for k, n in enumerate(sorted(gt))}
    turned = [e for e in edges if e.kind == "loop" and e.T_tgt_src is not None
              and rotation_angle_deg(np.asarray(e.T_tgt_src)[:3, :3] @ (inv_T(gt[e.tgt]) @ gt[e.src])[:3, :3].T) > 90]
    assert turned and not any(e.accepted for e in turned)
    assert any(e.accepted and e.kind == "loop" and index[e.tgt] - index[e.src] > 18 for e in edges)
    assert not any(e.accepted and e.reason == LOOP_DEPTH_ONLY for e in edges)


def _graph(edges: list[Edge], sigma_deg: float = 0.3, sigma_m: float = 0.002) -> list:
    from gscan.registration.posegraph import GraphEdge

    info = np.diag([np.radians(sigma_deg) ** -2] * 3 + [sigma_m ** -2] * 3)
    idx = _index(36)
    return [GraphEdge(idx[e.src], idx[e.tgt], e.T_tgt_src, info, weight=20, depth=0.6) for e in edges]


def _halves(T: list[np.ndarray]) -> list[Edge]:
    """The ring of 36 frames (its chain, and the loop closure 0 -> 35) broken at frames 9 and 27 (no edge to
    them, none across them)."""
    return [e for e in _chain(T) if e.src not in ("000008", "000009", "000026", "000027")] + [_edge(T, 0, 35, "loop")]


def test_the_steady_motion_bridges_the_breaks_of_a_ring_where_the_cycle_closes():
    """A turntable's ring split at frames 9 and 27 (a plain box seen edge on): the motion lays a weak edge at its
    prediction over each break (8 -> 10, 26 -> 28); the pose graph keeps both, the ring's cycle closing, and places
    every frame but 9 and 27 at its true pose. One break alone is not bridged (the edge alone joins two parts), and
    no bridge is laid where the steps scatter (3 deg)."""
    from gscan.registration.posegraph import optimize_pose_graph, spanning_poses
    from gscan.registration.sequence import motion_bridges

    T = _turntable(36, 10.0, 0.2)
    chain = _halves(T)
    motion = capture_motion(chain, _index(36), 8, depth=0.6)  # positions compared at the object
    assert motion is not None
    graph = _graph(chain)
    spans = [(g.src, g.tgt) for g in graph]
    bridges = motion_bridges(36, spans, motion, 3, RegisterParams())
    assert [(b.src, b.tgt) for b in bridges] == [(8, 10), (26, 28)] and not any(b.strong for b in bridges)
    res = optimize_pose_graph(36, graph + bridges, spanning_poses(36, graph + bridges),
                              SequenceParams().graph_params())
    assert all(r.accepted for r in res.edges[len(graph):])
    placed = [k for k in range(36) if res.T_world_node[k] is not None]
    assert placed == [k for k in range(36) if k not in (9, 27)]
    ref = res.reference_node
    for k in placed:  # relative to the reference frame, as the truth is
        rel = inv_T(res.T_world_node[ref]) @ res.T_world_node[k]
        true = inv_T(T[ref]) @ T[k]
        assert rotation_angle_deg(rel[:3, :3] @ true[:3, :3].T) < 2.0
        assert np.linalg.norm(rel[:3, 3] - true[:3, 3]) < 0.01

    # an open chain broken once (no loop closure): its bridge alone would join the parts: cut
    one = [e for e in _chain(T) if e.src not in ("000008", "000009")]
    g1 = _graph(one)
    b1 = motion_bridges(36, [(g.src, g.tgt) for g in g1], motion, 3, RegisterParams())
    assert [(b.src, b.tgt) for b in b1] == [(8, 10)]
    r1 = optimize_pose_graph(36, g1 + b1, spanning_poses(36, g1 + b1), SequenceParams().graph_params())
    assert not r1.edges[-1].accepted and len(r1.parts) == 1

    uneven = capture_motion(_halves(_turntable(36, 10.0, 3.0)), _index(36), 8, depth=0.6)
    assert uneven is not None and motion_bridges(36, spans, uneven, 3, RegisterParams()) == []


def test_a_bridge_the_cycle_refutes_is_cut():
    """The object slipped 6 deg on the turntable at frame 9: the prediction over 8 -> 10 is 6 deg off, the ring no
    longer closes through the two bridges, and the pose graph keeps no frame of the other half at a wrong pose."""
    from gscan.registration.posegraph import optimize_pose_graph, spanning_poses
    from gscan.registration.sequence import motion_bridges

    steps = [10.0] * 36
    steps[9] += 6.0
    T, az = [], 0.0
    for k in range(36):
        R_world_cam = _rot([0, 0, 1], az) @ np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], float)
        Tk = np.eye(4)
        Tk[:3, :3], Tk[:3, 3] = R_world_cam, -0.6 * R_world_cam[:, 2]
        T.append(Tk)
        az += steps[k] * (350.0 / 356.0)  # the turns still add up to one revolution over the ring
    chain = _halves(T)
    motion = capture_motion(chain, _index(36), 8, depth=0.6)
    assert motion is not None
    graph = _graph(chain)
    bridges = motion_bridges(36, [(g.src, g.tgt) for g in graph], motion, 3, RegisterParams())
    res = optimize_pose_graph(36, graph + bridges, spanning_poses(36, graph + bridges),
                              SequenceParams().graph_params())
    assert not all(r.accepted for r in res.edges[len(graph):])
    ref = res.reference_node
    for k in range(36):
        if res.T_world_node[k] is None:
            continue
        rel = inv_T(res.T_world_node[ref]) @ res.T_world_node[k]
        true = inv_T(T[ref]) @ T[k]
        assert rotation_angle_deg(rel[:3, :3] @ true[:3, :3].T) < 5.0


@pytest.mark.slow
def test_a_plain_box_seen_edge_on_is_joined_across_its_breaks(tmp_path, meshes_dir):
    """The Raisinets box made plain on a 36-frame turntable, scanned at the defaults (`both`): seen edge on at frames 9
    and 27, where every edge is 86-143 deg off or refused, its ring falls into two halves seen from opposite sides (17
    of 36 registered without the bridges). The steady motion's predictions bridge both breaks, the ring's cycle closes,
    and at least 90 % of the frames are registered, none wrong; the summary names the bridges. About 30 s."""
    res, _, _, _ = plain_turntable_scan("Nestle_Raisinets_Milk_Chocolate_35_oz_992_g", tmp_path, meshes_dir)
    assert len(res.to_json()["motion"]["bridges"]) >= 2
