"""Time opening a template in the viewer: server ready + scene populated, and the browser's first frame.

    python web/bench_viewer.py --views 100 --db bench/out/viewer100.gscan
    python web/bench_viewer.py --views 24 --elevations 25 50 --db bench/out/viewer24.gscan \
        --screenshot docs/viewer.png

Builds the template with web/synth_template.py unless --db exists, then measures
- serve_s: `gscan.viewer.app.serve()` in this process (load the database, downscale the images, start viser,
  send every scene node and GUI element), median of --repeats;
- subprocess_ready_s: `python3 -m gscan.cli view DB` until its "viewer ready" line (includes interpreter
  start and imports);
- browser_gui_s / browser_scene_s: headless Chromium (SwiftShader) from navigation until the GUI's view
  image is shown / until the 3D view is drawn (pixel std above a threshold).
Prints one JSON object.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import viewer_probe as vp
from synth_template import build_synth_template


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=100)
    ap.add_argument("--elevations", type=float, nargs="+", default=[20.0, 40.0, 60.0])
    ap.add_argument("--db", type=Path, default=Path("bench/out/viewer100.gscan"))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--screenshot", type=Path, help="also save a screenshot with an edge's matches shown")
    a = ap.parse_args()

    from gscan.template.db import TemplateDB
    from gscan.viewer.app import serve

    res: dict = {"views": a.views}
    if not a.db.exists():
        t0 = time.perf_counter()
        unreg = (a.views // 3,) if a.views >= 6 else ()
        build_synth_template(a.db, n_views=a.views, elevations_deg=tuple(a.elevations), unregistered=unreg)
        res["build_template_s"] = round(time.perf_counter() - t0, 2)
    with TemplateDB.open(a.db) as db:
        res["db_mb"] = round(a.db.stat().st_size / 2**20, 1)
        res["edges"] = len(db.edges())
        res["views"] = len(db.views())

    times = []
    for _ in range(a.repeats):
        t0 = time.perf_counter()
        app = serve(a.db, port=vp.free_port())
        times.append(time.perf_counter() - t0)
        app.stop()
    res["serve_s"] = round(statistics.median(times), 3)

    from playwright.sync_api import sync_playwright

    port = vp.free_port()
    proc, ready = vp.start_viewer(a.db, port, log_path=a.db.with_suffix(".viewer.log"))
    res["subprocess_ready_s"] = round(ready, 2)
    try:
        with sync_playwright() as p:
            browser = vp.launch(p)
            # A taller page for the screenshot, so the match panel fits under the view image.
            page = browser.new_page(viewport={"width": 1400, "height": 1200} if a.screenshot else vp.VIEWPORT)
            t0 = time.perf_counter()
            page.goto(f"http://127.0.0.1:{port}")
            vp.gui_image(page, "View image").wait_for(timeout=60_000)
            res["browser_gui_s"] = round(time.perf_counter() - t0, 2)
            page.add_style_tag(path=str(vp.HEADLESS_CSS))
            _, std = vp.wait_scene_drawn(page, 8.0, timeout_s=60)
            res["browser_scene_s"] = round(time.perf_counter() - t0, 2)
            res["canvas_std"] = round(std, 1)
            if a.screenshot:
                page.wait_for_timeout(1500)
                vp.gui_slider(page, "View #").focus()
                page.keyboard.press("ArrowRight")
                page.wait_for_timeout(500)
                opts = _edge_options(page)
                if opts:
                    vp.select_option(page, "Edge", opts[0])
                    page.get_by_text("matches:").first.wait_for(timeout=10_000)
                page.wait_for_timeout(1000)
                a.screenshot.parent.mkdir(parents=True, exist_ok=True)
                page.screenshot(path=str(a.screenshot))
            browser.close()
    finally:
        vp.stop_viewer(proc)
    print(json.dumps(res))


def _edge_options(page) -> list[str]:
    page.locator(f"input[id='{vp.gui_control_id(page, 'Edge')}']").click()
    opts = [o.inner_text() for o in page.get_by_role("option").all()]
    page.keyboard.press("Escape")
    return [o for o in opts if "→" in o and "rejected" not in o]


if __name__ == "__main__":
    main()
