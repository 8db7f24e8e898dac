"""The web viewer (gscan.viewer.app, `gscan view`): server-side checks, and headless Chromium driving the real page.

The template is rendered with gscan.synth and written with TemplateDB (web/synth_template.py) until the
scan pipeline produces one. Browser tests use Debian's /usr/bin/chromium through Playwright (SwiftShader).
"""
from __future__ import annotations

import contextlib
import importlib.util
import itertools
import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gscan.demo import SAMPLES
from gscan.errors import InputError
from gscan.geometry.transforms import look_at
from gscan.io.camera import RGBDFrame
from gscan.template.db import TemplateDB
from gscan.viewer.app import PortInUseError, check_port, serve
from gscan.viewer.draw import (
    OBJECT_OUTLINE_COLOR,
    draw_matches,
    edge_color,
    outline_mask,
    quality_color,
    scale_pixels,
    thumbnail,
)

ROOT = Path(__file__).resolve().parents[1]


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "web" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


vp = _load("viewer_probe")
synth_template = _load("synth_template")

MIN_CANVAS_STD = 8.0  # an empty (white) 3D view has std ~0; the populated scene measures ~18-21


@pytest.fixture(scope="module")
def template(tmp_path_factory):
    """6 rendered views of a textured box; view 000004 unregistered (its two edges rejected), and an input
    frame 000009 the scan could not read (the "skipped" meta)."""
    from gscan.template.db import TemplateDB

    tpl = synth_template.build_synth_template(tmp_path_factory.mktemp("viewer") / "box.gscan", n_views=6,
                                              unregistered=(4,), max_keypoints=250)
    with TemplateDB.open(tpl.path, writable=True) as db:
        db.set_meta("skipped", {"000009": "rgb/000009.png: cannot decode the image"})
    return tpl


def _box_or_table_distance(p_obj: np.ndarray) -> np.ndarray:
    """[N] distance (m) of object-frame points to the box surface or to the table plane under it."""
    h = np.asarray(synth_template.BOX_SIZE) / 2
    q = np.abs(p_obj) - h
    sdf = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)
    return np.minimum(np.abs(sdf), np.abs(p_obj[:, 2] + h[2]))


# ------------------------------------------------------------------------------------ no browser
def test_refuses_partial_template_and_busy_port(template, tmp_path):
    partial = tmp_path / "partial.gscan"
    TemplateDB.create(partial).close()
    with pytest.raises(InputError, match="partial"):
        serve(partial, port=vp.free_port())
    with socket.socket() as s:  # a listening socket holds the port
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        with pytest.raises(PortInUseError, match=f"127.0.0.1:{port}") as ei:
            serve(template.path, port=port)
        assert isinstance(ei.value, InputError) and "\n" not in str(ei.value)
        with pytest.raises(PortInUseError):
            check_port("127.0.0.1", port)


def test_port_range_and_view_errors_are_one_line(template, tmp_path):
    """Ports outside 1-65535 are refused before viser (whose server thread died and left the process
    hanging on 70000); `gscan view` reports bad input and usage as one `error:` line, exit 2, --pose without
    a query frame too."""
    for port in (0, 70000, -1):
        with pytest.raises(InputError, match="1-65535"):
            check_port("127.0.0.1", port)
    pose = tmp_path / "T.json"
    pose.write_text(json.dumps(np.eye(4).tolist()))
    bad_pose = tmp_path / "bad.json"
    bad_pose.write_text(json.dumps([[1, 0], [0, 1]]))
    frame = [str(SAMPLES / "heldout" / sub / f"000000{ext}") for sub, ext in (("rgb", ".jpg"),
                                                                                       ("depth", ".png"))]
    query = ["--color", frame[0], "--depth", frame[1], "--intrinsics", str(SAMPLES / "heldout" / "cam_K.txt")]
    for args, named in (([tmp_path / "missing.gscan"], "missing.gscan"), ([], "Missing argument"),
                        ([template.path, "--port", "abc"], "--port"), ([template.path, "--pose", pose], "T.json"),
                        ([template.path, *query, "--pose", bad_pose], "bad.json")):
        r = subprocess.run([sys.executable, "-m", "gscan.cli", "view", *map(str, args)], capture_output=True,
                           text=True, timeout=60)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: ") and named in lines[0], r.stderr


def test_query_frame_is_drawn_in_template_frame(template):
    """The hook for `gscan view --color/--depth`: the frame's cloud lands on the template's box and table."""
    scene, T_world_obj = template.scene, template.T_world_obj
    eye = T_world_obj[:3, 3] + np.array([0.25, -0.35, 0.3])
    fr = scene.render(look_at(eye, T_world_obj[:3, 3]), noise=False)
    frame = RGBDFrame("query", fr.color, fr.depth, fr.intrinsics, fr.mask)
    T_obj_grasp = np.eye(4)
    app = serve(template.path, port=vp.free_port(), scene_frame=frame, T_cam_obj=fr.T_cam_obj,
                grasps={"side": T_obj_grasp})
    try:
        pts = app.scene_points_obj
        assert pts is not None and len(pts) > 10_000
        # the scene's points lie on the box or the table within 4 mm (depth noise and quantisation) for nearly all of
        # them
        assert np.mean(_box_or_table_distance(pts) < 0.004) > 0.97
        assert app.layers["scene"] and len(app.layers["grasps"]) == 4  # "top" (database) + "side": axes + label
        # The inverse mistake (drawing by T_cam_obj instead of its inverse) would miss the box.
        wrong = (pts.astype(np.float64) @ fr.T_cam_obj[:3, :3].T + fr.T_cam_obj[:3, 3])
        wrong = wrong @ fr.T_cam_obj[:3, :3].T + fr.T_cam_obj[:3, 3]
        # the same points moved by the pose twice: most of them off both surfaces
        assert np.mean(_box_or_table_distance(wrong) < 0.004) < 0.5
    finally:
        app.stop()
    app = serve(template.path, port=vp.free_port(), scene_frame=frame, T_cam_obj=None)  # not found: no cloud
    try:
        assert app.scene_points_obj is None and not app.layers["scene"]
    finally:
        app.stop()


def test_selection_and_match_panel_state(template):
    app = serve(template.path, port=vp.free_port())
    try:
        names = [v.name for v in app.data.views]
        assert names == template.names and [v.name for v in app.data.views if v.T_obj_cam is None] == ["000004"]
        assert len(app.layers["frustums"]) == 5  # the unregistered view is not drawn
        app.select_view("000002")
        assert app._view_slider.value == 2 and app._view_dropdown.value == "000002"
        labels = list(app._edge_dropdown.options[1:])
        assert labels == ["000001 → 000002 (sequential)", "000002 → 000003 (sequential)"]
        app.select_edge(labels[1])
        with TemplateDB.open(template.path) as db:
            e = next(e for e in db.edges() if (e.src, e.tgt) == ("000002", "000003"))
        assert f"matches: {len(e.matches)}" in app._match_md.content and app._match_image.visible
        assert f"RMSE: {e.rmse * 1000:.2f} mm" in app._match_md.content
    finally:
        app.stop()


def test_coverage_map_is_drawn(template, tmp_path):
    """The coverage layer: nothing for a template without a coverage record; with one, a point per direction cell
    around the object, coloured as `coverage_points` says (the colours are the map's)."""
    import shutil

    from gscan.geometry.coverage import COVERAGE_DIRECTIONS, template_coverage
    from gscan.viewer.app import coverage_markdown
    from gscan.viewer.scene import coverage_points

    app = serve(template.path, port=vp.free_port())
    try:
        assert app.data.coverage is None and not app.layers["coverage"]
    finally:
        app.stop()
    assert coverage_markdown(None).startswith("coverage: unknown")
    path = tmp_path / "covered.gscan"
    shutil.copy(template.path, path)
    with TemplateDB.open(path, writable=True) as db:
        cov = template_coverage([v.T_obj_cam for v in db.views() if v.T_obj_cam is not None], db.mesh())
        db.set_meta("coverage", cov.to_meta())
    app = serve(path, port=vp.free_port())
    try:
        (cloud,) = app.layers["coverage"]
        pts, cols = coverage_points(cov, app.data.center, app.data.size)
        assert len(pts) == COVERAGE_DIRECTIONS
        np.testing.assert_allclose(np.asarray(cloud.points, np.float64), pts, atol=1e-4)  # viser sends float16
        np.testing.assert_array_equal(np.asarray(cloud.colors), cols)
        assert len(np.unique(cols, axis=0)) >= 2  # seen and unseen cells differ
    finally:
        app.stop()
    assert f"coverage: {cov.share:.0%} of the viewing directions seen" in coverage_markdown(cov)


def test_start_camera_keeps_clear_of_the_frustums():
    """The browser's start camera looks at the object from a direction away from every view's camera: with a
    view right on the default direction (a CAD template's first view at 62 deg elevation, 3.7 deg from it) the
    start direction turns at least 20 deg away from all views; with nothing that near, the default stays."""
    from gscan.scanning.cad import fibonacci_directions
    from gscan.viewer.scene import _clear_direction

    up, d0 = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    default = np.array([np.cos(np.radians(58)), 0.0, np.sin(np.radians(58))])
    cams = np.asarray(fibonacci_directions(12))
    cams = np.vstack([[np.cos(np.radians(62)), 0.0, np.sin(np.radians(62))], cams])
    c = _clear_direction(d0, up, cams)
    gap = np.degrees(np.arccos(np.clip(cams @ c, -1, 1)).min())
    # a unit direction at least 20 deg from every camera; float64 normalisation
    assert gap > 20.0 and abs(np.linalg.norm(c) - 1) < 1e-9
    ring = np.array([[np.cos(a), np.sin(a), 0.3] for a in np.linspace(0, 2 * np.pi, 12, endpoint=False)])
    # with no camera near, the default direction itself: float64 rounding
    np.testing.assert_allclose(_clear_direction(d0, up, ring), default, atol=1e-12)


@settings(max_examples=30, deadline=None)
@given(h=st.integers(20, 900), w=st.integers(20, 900), side=st.integers(16, 400))
def test_thumbnail_and_pixel_mapping(h, w, side):
    img = np.zeros((h, w, 3), np.uint8)
    th = thumbnail(img, side)
    assert max(th.shape[:2]) <= max(side, 1) or th.shape == img.shape
    corners = scale_pixels(np.array([[0, 0], [w - 1, h - 1]]), (w, h), (th.shape[1], th.shape[0]))
    assert np.all(corners >= -0.5) and corners[1, 0] <= th.shape[1] - 0.5 and corners[1, 1] <= th.shape[0] - 0.5
    back = scale_pixels(corners, (th.shape[1], th.shape[0]), (w, h))
    # pixel coordinates scaled to the thumbnail and back: float64 rounding (np.allclose's atol 1e-8)
    assert np.allclose(back, [[0, 0], [w - 1, h - 1]])


def test_object_outline_on_a_keyframe_thumbnail():
    """The chosen object's mask (full size) outlined on a half-size thumbnail: the outline's pixels lie on the
    mask's border, scaled, and nowhere inside or far outside it."""
    mask = np.zeros((240, 320), bool)
    mask[60:180, 100:220] = True
    th = np.zeros((120, 160, 3), np.uint8)
    out = outline_mask(th, mask)
    drawn = np.all(out == OBJECT_OUTLINE_COLOR, axis=2)
    assert not th.any() and drawn.sum() > 4 * 50
    ys, xs = np.nonzero(drawn)
    assert xs.min() >= 48 and xs.max() <= 111 and ys.min() >= 28 and ys.max() <= 91
    assert not drawn[40:80, 60:100].any()  # the inside is left as it was


def test_colour_scales_and_match_drawing():
    g_minus_r = [quality_color(q)[1] - quality_color(q)[0] for q in np.linspace(1, 0, 11)]
    assert all(a > b for a, b in itertools.pairwise(g_minus_r))  # greener is better
    assert quality_color(None) == quality_color(float("nan"))
    from gscan.template.db import Edge

    seq = Edge("a", "b", None, np.zeros((0, 2)), rmse=0.001, kind="sequential")
    loop = Edge("a", "b", None, np.zeros((0, 2)), rmse=0.001, kind="loop")
    assert edge_color(seq, 0.01) != edge_color(loop, 0.01)
    a, b = np.full((240, 320, 3), 50, np.uint8), np.full((480, 640, 3), 50, np.uint8)
    px = np.array([[10.0, 10.0], [300.0, 200.0]])
    out = draw_matches(a, px, (320, 240), b, px * 2, (640, 480), np.array([[0, 1], [1, 0]]), max_lines=10)
    assert out.shape == (240, 640, 3) and (out != 50).any(axis=2).sum() > 200


# ------------------------------------------------------------------------------------ browser
def _screenshot(page, tmp_path: Path, name: str) -> None:
    """Screenshot into the test's folder (kept when the test fails), and a copy into the folder the environment
    variable GSCAN_SCREENSHOTS names, if any, to look at."""
    page.screenshot(path=str(tmp_path / name))
    if os.environ.get("GSCAN_SCREENSHOTS"):
        out = Path(os.environ["GSCAN_SCREENSHOTS"])
        out.mkdir(parents=True, exist_ok=True)
        shutil.copy(tmp_path / name, out / name)


def _open_drawn_page(browser, port: int, tmp_path: Path, name: str):
    """A page on the viewer at `port`, once its 3D view is drawn (not blank), screenshot as `name`."""
    page = browser.new_page(viewport=vp.VIEWPORT)
    vp.open_viewer(page, f"http://127.0.0.1:{port}")
    _, std = vp.wait_scene_drawn(page, MIN_CANVAS_STD)
    _screenshot(page, tmp_path, name)
    assert std > MIN_CANVAS_STD, f"3D view looks blank (std {std:.1f})"
    return page


@contextlib.contextmanager
def _cli_viewer_page(db: Path, extra: list[str], tmp_path: Path, name: str):
    """`gscan view DB EXTRA...` in a subprocess and a Chromium page on it once its 3D view is drawn (screenshot
    `name`); afterwards the viewer's log must say it was ready."""
    from playwright.sync_api import sync_playwright

    port = vp.free_port()
    proc, _ = vp.start_viewer(db, port, extra=extra, log_path=tmp_path / "viewer.log")
    try:
        with sync_playwright() as p:
            browser = vp.launch(p)
            try:
                yield _open_drawn_page(browser, port, tmp_path, name)
            finally:
                browser.close()
    finally:
        vp.stop_viewer(proc)
    assert "viewer ready at" in (tmp_path / "viewer.log").read_text()


@pytest.mark.browser
def test_viewer_in_browser(template, tmp_path):

    # A query frame on disk with its pose: `gscan view --color --depth --intrinsics --pose`.
    from gscan.synth import write_capture

    T_world_obj = template.T_world_obj
    fr = template.scene.render(look_at(T_world_obj[:3, 3] + [0.3, 0.3, 0.35], T_world_obj[:3, 3]), noise=False)
    cap = write_capture(tmp_path / "query", [fr], fr.intrinsics)
    (tmp_path / "pose.json").write_text(json.dumps({"T": fr.T_cam_obj.tolist()}))
    query = ["--color", str(cap / "rgb" / "000000.png"), "--depth", str(cap / "depth" / "000000.png"),
             "--intrinsics", str(cap / "cam_K.txt"), "--pose", str(tmp_path / "pose.json")]
    with _cli_viewer_page(template.path, query, tmp_path, "viewer.png") as page:
        # The GUI lists the views and names the unregistered ones, the unreadable input frame too.
        assert page.locator(f"input[id='{vp.gui_control_id(page, 'View')}']").input_value() == "000000"
        assert page.get_by_text("unregistered (2):").count() == 1
        assert page.get_by_text("000004, 000009").count() == 1
        assert page.get_by_text("cloud placed by the estimated pose").count() == 1
        # Moving the view slider changes the displayed image.
        img = vp.gui_image(page, "View image")
        before = img.screenshot()
        vp.gui_slider(page, "View #").focus()
        page.keyboard.press("ArrowRight")
        after = vp.wait_image_changed(img, before)
        assert after != before
        page.get_by_text("000001 (2/6)").wait_for(timeout=10_000)
        assert page.get_by_text("000001 (2/6)").count() == 1
        # Choosing an edge opens the match panel with its numbers.
        assert page.get_by_text("matches:").count() == 0
        vp.select_option(page, "Edge", "000001 → 000002 (sequential)")
        page.get_by_text("matches:").first.wait_for(timeout=10_000)
        text = page.get_by_text("matches:").first.inner_text()
        with TemplateDB.open(template.path) as db:
            e = next(e for e in db.edges() if (e.src, e.tgt) == ("000001", "000002"))
        assert f"matches: {len(e.matches)}" in text
        assert vp.gui_image(page, "Matches").is_visible()
        _screenshot(page, tmp_path, "viewer_match.png")


def _screen_xy(camera, p_world: np.ndarray) -> tuple[float, float]:
    """Pixel of a world point in the browser's view, from the camera state the client reports to viser."""
    import viser.transforms as vtf

    R = vtf.SO3(np.asarray(camera.wxyz)).as_matrix()  # OpenCV convention (x right, y down, z forward)
    pc = R.T @ (p_world - camera.position)
    f = camera.image_height / 2 / np.tan(camera.fov / 2)
    return pc[0] / pc[2] * f + camera.image_width / 2, pc[1] / pc[2] * f + camera.image_height / 2


@pytest.mark.browser
def test_frustum_click_and_go_to_view(template):
    from playwright.sync_api import sync_playwright

    app = serve(template.path, port=vp.free_port())
    try:
        with sync_playwright() as p:
            browser = vp.launch(p)
            try:
                page = browser.new_page(viewport=vp.VIEWPORT)
                vp.open_viewer(page, app.url)
                vp.wait_scene_drawn(page, MIN_CANVAS_STD)
                t0 = time.perf_counter()
                while not app.server.get_clients() and time.perf_counter() - t0 < 10:
                    time.sleep(0.1)
                (client,) = app.server.get_clients().values()
                # Clicking view 000002's frustum (its image, along its optical axis) selects that view.
                T2 = next(v.T_obj_cam for v in app.data.views if v.name == "000002")
                for k in (2.0, 2.4, 2.8, 3.2):  # depth of the snapshot in frustum sizes
                    page.mouse.click(*_screen_xy(client.camera, T2[:3, 3] + T2[:3, 2] * k * app.frustum_scale))
                    if vp.wait_until(lambda: app._current == "000002", 3.0):  # a loaded machine answers late
                        break
                assert app._current == "000002"
                page.get_by_text("000002 (3/6)").wait_for(timeout=10_000)  # the GUI text follows the server
                assert page.get_by_text("000002 (3/6)").count() == 1
                before = vp.canvas_region(vp.png_array(page.screenshot()))
                app.select_view("000003")
                page.get_by_role("button", name="Go to view").click()
                T = next(v.T_obj_cam for v in app.data.views if v.name == "000003")

                def looking() -> float:
                    look = client.camera.look_at - client.camera.position
                    return float(np.dot(look / np.linalg.norm(look), T[:3, 2]))

                # the browser reports position and look-at in separate updates: both are awaited
                vp.wait_until(lambda: np.allclose(client.camera.position, T[:3, 3], atol=1e-4) and looking() > 0.999,
                              10.0)
                # the browser's camera position as the client reports it back: 0.1 mm, far below a misplaced camera
                assert np.allclose(client.camera.position, T[:3, 3], atol=1e-4)
                assert looking() > 0.999
                def moved() -> float:
                    after = vp.canvas_region(vp.png_array(page.screenshot()))
                    return np.abs(after.astype(int) - before.astype(int)).mean()
                vp.wait_until(lambda: moved() > 2.0, 10.0)
                assert moved() > 2.0  # the browser view moved
                # Layer toggles: hide the frustums from the (collapsed) Layers folder.
                page.get_by_text("Layers", exact=True).click()
                vp.uncheck(page, "Frustums")
                t0 = time.perf_counter()
                while any(h.visible for h in app.layers["frustums"]) and time.perf_counter() - t0 < 10:
                    time.sleep(0.1)
                assert not any(h.visible for h in app.layers["frustums"])
                assert all(h.visible for h in app.layers["mesh"] + app.layers["edges"])
            finally:
                browser.close()
    finally:
        app.stop()


@pytest.mark.browser
def test_gscan_view_on_the_bundled_sample(sample_template, tmp_path):
    """`gscan view` on the sample's scanned template: scene drawn, view list, slider, match panel."""
    from playwright.sync_api import sync_playwright

    with TemplateDB.open(sample_template) as db:
        names = db.view_names()
        first_edge = next(e for e in db.edges() if e.accepted)
    port = vp.free_port()
    proc, _ = vp.start_viewer(sample_template, port, log_path=tmp_path / "view.log")
    try:
        with sync_playwright() as p:
            browser = vp.launch(p)
            try:
                page = _open_drawn_page(browser, port, tmp_path, "viewer_sample.png")
                assert page.locator(f"input[id='{vp.gui_control_id(page, 'View')}']").input_value() == names[0]
                img = vp.gui_image(page, "View image")
                before = img.screenshot()
                vp.gui_slider(page, "View #").focus()
                page.keyboard.press("ArrowRight")
                assert vp.wait_image_changed(img, before) != before
                page.get_by_text(f"{names[1]} (2/{len(names)})").wait_for(timeout=10_000)
                assert page.get_by_text(f"{names[1]} (2/{len(names)})").count() == 1
                vp.select_option(page, "Edge", f"{first_edge.src} → {first_edge.tgt} ({first_edge.kind})")
                page.get_by_text("matches:").first.wait_for(timeout=10_000)
                assert f"matches: {len(first_edge.matches)}" in page.get_by_text("matches:").first.inner_text()
                _screenshot(page, tmp_path, "viewer_sample_match.png")
            finally:
                browser.close()
    finally:
        vp.stop_viewer(proc)


# ------------------------------------------------------------------------------------ instances (`--estimate`)
def _shifted(T_cam_obj: np.ndarray, dx: float, turn: float = 0.0) -> np.ndarray:
    """T_cam_obj moved by dx (m) along the object's x axis and turned by `turn` (rad) about its z axis."""
    from gscan.geometry.transforms import rotvec_to_R

    M = np.eye(4)
    M[:3, :3] = rotvec_to_R([0.0, 0.0, turn])
    M[0, 3] = dx
    return T_cam_obj @ M


def _instances_result(T_cam_obj: np.ndarray, path: Path) -> list[np.ndarray]:
    """An `estimate --all --json` file for template "box": three instances (the true pose and two beside it) and
    one refused; returns the three poses in rank order."""
    poses = [T_cam_obj, _shifted(T_cam_obj, 0.12, np.pi / 2), _shifted(T_cam_obj, -0.12)]
    inst = [{"T_cam_obj": T.tolist(), "score": s, "view": f"00000{k}", "reason": None,
             "pixels": {"count": 9000 - 1000 * k, "box": [0, 0, 10, 10]}}
            for k, (T, s) in enumerate(zip(poses, (0.93, 0.8, 0.71), strict=True))]
    refused = [{"T_cam_obj": None, "score": 0.6, "reason": "its pixels are claimed by template mug, better supported"}]
    doc = {"templates": [{"template": "mug", "instances": [], "reason": "too few matches", "refused": []},
                         {"template": "box", "instances": inst, "reason": None, "refused": refused,
                          "stopped": "too few keypoints left that agree with the template"}]}
    path.write_text(json.dumps(doc))
    return poses


def test_instances_of_an_estimate_are_drawn_at_their_poses(template, tmp_path):
    """`gscan view --estimate`: every instance found is drawn at its pose relative to the first (which the
    template frame shows, the frame's cloud placed by it), labelled with its rank and score; the refused one is
    named in the Instances panel. A result of other templates only, or a pose that is not rigid, is refused
    naming the file."""
    from gscan.viewer.instances import read_estimate_result
    from gscan.viewer.text import md_text

    T_world_obj = template.T_world_obj
    fr = template.scene.render(look_at(T_world_obj[:3, 3] + [0.25, -0.35, 0.3], T_world_obj[:3, 3]), noise=False)
    frame = RGBDFrame("query", fr.color, fr.depth, fr.intrinsics)
    poses = _instances_result(fr.T_cam_obj, tmp_path / "all.json")
    shown = read_estimate_result(tmp_path / "all.json", "box")
    assert [f.label for f in shown.found] == ["#1 · 0.93", "#2 · 0.80", "#3 · 0.71"]
    app = serve(template.path, port=vp.free_port(), scene_frame=frame, instances=shown)
    try:
        assert len(app.instances_obj) == 3 and len(app.layers["instances"]) == 9  # axes, mesh, label each
        for T_obj_inst, T in zip(app.instances_obj, poses, strict=True):  # inv(T_cam_first) @ T_cam_inst
            np.testing.assert_allclose(T_obj_inst, np.linalg.inv(fr.T_cam_obj) @ T, atol=1e-9)
        np.testing.assert_allclose(app.instances_obj[0], np.eye(4), atol=1e-9)
        assert np.linalg.norm(app.instances_obj[1][:3, 3] - [0.12, 0, 0]) < 1e-9
        # the frame's cloud is placed by the first instance: it lies on the template's box and table
        assert app.scene_points_obj is not None and np.mean(_box_or_table_distance(app.scene_points_obj) < 0.004) > 0.97
        text = shown.markdown()  # names and reasons are data: shown literally (md_text)
        assert "found: 3 · refused: 1" in text and md_text("#2 · 0.80 · view 000001 · 8000 px") in text
        assert "refused 1: " + md_text("its pixels are claimed by template mug, better supported") in text
    finally:
        app.stop()
    single = tmp_path / "one.json"  # a single estimate's result that found nothing: the reason shown
    single.write_text(json.dumps({"T_cam_obj": None, "reason": "ambiguous view", "score": 0.0}))
    none = read_estimate_result(single, "box")
    assert not none.found and "none found: ambiguous view" in none.markdown()
    other = tmp_path / "other.json"
    doc = json.loads((tmp_path / "all.json").read_text())
    doc["templates"][1]["template"] = "can"
    other.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="no result of template box") as e:
        read_estimate_result(other, "box")
    assert e.value.path == other
    doc["templates"][1]["template"] = "box"
    doc["templates"][1]["instances"][1]["T_cam_obj"][0][0] = 3.0
    other.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="result 2: pose is not a rigid transform"):
        read_estimate_result(other, "box")


@pytest.mark.browser
def test_instances_in_browser(template, tmp_path):
    """`gscan view box.gscan --estimate all.json --color ... ` in Chromium: the 3D view draws the three instances and
    the Instances panel lists them by rank and score, and the refused one with its reason."""

    from gscan.synth import write_capture

    T_world_obj = template.T_world_obj
    fr = template.scene.render(look_at(T_world_obj[:3, 3] + [0.3, 0.3, 0.35], T_world_obj[:3, 3]), noise=False)
    cap = write_capture(tmp_path / "query", [fr], fr.intrinsics)
    _instances_result(fr.T_cam_obj, tmp_path / "all.json")
    tpl = template.path  # box.gscan: the result's "box"
    query = ["--color", str(cap / "rgb" / "000000.png"), "--depth", str(cap / "depth" / "000000.png"),
             "--intrinsics", str(cap / "cam_K.txt"), "--estimate", str(tmp_path / "all.json")]
    with _cli_viewer_page(tpl, query, tmp_path, "viewer_instances.png") as page:
        for text in ("found: 3 · refused: 1", "#1 · 0.93 · view 000000 · 9000 px",
                     "refused 1: its pixels are claimed by template mug, better supported",
                     "cloud placed by the first instance's pose"):
            page.get_by_text(text).first.wait_for(timeout=10_000)
        _screenshot(page, tmp_path, "viewer_instances.png")
        # the instances (meshes and rank labels, drawn in WebGL) are what the Instances layer hides
        before = vp.canvas_region(vp.png_array(page.screenshot())).astype(int)
        page.get_by_text("Layers", exact=True).click()
        vp.uncheck(page, "Instances")

        def changed() -> int:  # pixels of the 3D view that changed clearly (the instances cover a few thousand)
            after = vp.canvas_region(vp.png_array(page.screenshot())).astype(int)
            return int((np.abs(after - before).max(axis=2) > 40).sum())
        vp.wait_until(lambda: changed() > 2000, 15.0)
        _screenshot(page, tmp_path, "viewer_instances_hidden.png")
        assert changed() > 2000
