"""Playwright helpers that drive the gscan viewer (viser's web client) in headless Chromium.

Used by tests/test_viewer_browser.py and web/bench_viewer.py. Chromium is Debian's /usr/bin/chromium
(never `playwright install`); WebGL2 runs on SwiftShader, so the flags below are required.
"""
from __future__ import annotations

import io
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from PIL import Image

CHROMIUM = os.environ.get("GSCAN_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader", "--use-angle=swiftshader",
                 "--disable-background-networking", "--disable-component-update", "--no-first-run",
                 "--disable-sync"]
VIEWPORT = {"width": 1280, "height": 800}
READY_LINE = "viewer ready at"
HEADLESS_CSS = Path(__file__).with_name("headless.css")


def free_port() -> int:
    """A TCP port that was free on 127.0.0.1 a moment ago (bind to port 0)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_viewer(db: Path, port: int, extra: list[str] | None = None, timeout: float = 60.0,
                 log_path: Path | None = None) -> tuple[subprocess.Popen, float]:
    """Start `python3 -m gscan.cli view DB --port P` (`gscan view`) and wait for its ready line on stderr.

    Returns (process, seconds until ready). Raises RuntimeError (with the log) if it dies or times out.
    The caller must stop it (stop_viewer) in a finally.
    """
    log_path = log_path or Path(db).with_suffix(".viewer.log")
    t0 = time.perf_counter()
    with open(log_path, "w") as logf:  # the child holds its own copy of the descriptor
        proc = subprocess.Popen([sys.executable, "-m", "gscan.cli", "view", str(db), "--port", str(port),
                                 *(extra or [])], stdout=subprocess.DEVNULL, stderr=logf, start_new_session=True)
    while time.perf_counter() - t0 < timeout:
        text = log_path.read_text()
        if READY_LINE in text:
            return proc, time.perf_counter() - t0
        if proc.poll() is not None:
            raise RuntimeError(f"viewer exited with code {proc.returncode}:\n{text}")
        time.sleep(0.05)
    stop_viewer(proc)
    raise RuntimeError(f"viewer not ready after {timeout} s:\n{log_path.read_text()}")


def stop_viewer(proc: subprocess.Popen) -> None:
    """Terminate the viewer process started by start_viewer (SIGTERM, then SIGKILL)."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)


def launch(playwright):
    """Headless Chromium with the SwiftShader flags."""
    return playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)


def gui_image(page, label: str):
    """Locator of the <img> of a viser GUI image whose label is `label`."""
    return page.locator(f"xpath=//p[normalize-space()='{label}']/following-sibling::div//img")


def open_viewer(page, url: str, timeout_s: float = 30.0) -> None:
    """Load the viewer page and wait until the GUI (View image) and the 3D canvas exist."""
    page.goto(url)
    page.wait_for_selector("canvas", timeout=timeout_s * 1000)
    gui_image(page, "View image").wait_for(timeout=timeout_s * 1000)
    # viser warns about software WebGL (SwiftShader) in a toast: hide it so it does not cover the scene.
    page.add_style_tag(path=str(HEADLESS_CSS))


def gui_control_id(page, label: str) -> str:
    """DOM id of the viser GUI input labelled `label` (its <label for=...>)."""
    return page.locator(f"xpath=//label[normalize-space()='{label}']").first.get_attribute("for")


def uncheck(page, label: str, timeout_s: float = 20.0) -> None:
    """Uncheck the viser checkbox labelled `label`. A click while its folder still opens, on a loaded machine, can
    leave it checked (Playwright then raises): the state is read back and the click repeated until it holds."""
    t0 = time.perf_counter()
    while True:
        box = page.locator(f"[id='{gui_control_id(page, label)}']")
        if not box.is_checked():
            return
        if time.perf_counter() - t0 > timeout_s:
            raise AssertionError(f"checkbox {label!r} still checked after {timeout_s:.0f} s")
        box.click()
        wait_until(lambda b=box: not b.is_checked(), 3.0)


def gui_slider(page, label: str):
    """Locator of the thumb (role=slider) of the viser slider labelled `label`."""
    return page.locator(f"[id='{gui_control_id(page, label)}'] [role=slider]")


def select_option(page, label: str, option: str) -> None:
    """Choose `option` in the viser dropdown labelled `label`."""
    page.locator(f"input[id='{gui_control_id(page, label)}']").click()
    page.get_by_role("option", name=option, exact=True).click()


def png_array(png: bytes) -> np.ndarray:
    """PNG bytes -> [H x W x 3] uint8."""
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


def canvas_region(shot: np.ndarray) -> np.ndarray:
    """The 3D view of a full-page screenshot [H x W x 3]: left of viser's GUI panel (right ~27%)."""
    return shot[:, : int(shot.shape[1] * 0.72)]


def wait_scene_drawn(page, min_std: float, timeout_s: float = 30.0) -> tuple[np.ndarray, float]:
    """Take screenshots until the 3D region's pixel standard deviation exceeds `min_std` (SwiftShader needs
    a few seconds). Returns (last full screenshot [H x W x 3], its 3D-region std)."""
    t0 = time.perf_counter()
    while True:
        shot = png_array(page.screenshot())
        std = float(canvas_region(shot).std())
        if std > min_std or time.perf_counter() - t0 > timeout_s:
            return shot, std
        page.wait_for_timeout(500)


def wait_until(done, timeout_s: float, every_s: float = 0.2) -> bool:
    """Call done() until it is true or timeout_s passed (a loaded machine answers late); its last answer."""
    t0 = time.perf_counter()
    while not done():
        if time.perf_counter() - t0 > timeout_s:
            return False
        time.sleep(every_s)
    return True


def wait_image_changed(locator, before: bytes, timeout_s: float = 10.0) -> bytes:
    """Screenshot `locator` until it differs from the PNG `before`; returns the new PNG (or the last one)."""
    t0 = time.perf_counter()
    while True:
        now = locator.screenshot()
        if now != before or time.perf_counter() - t0 > timeout_s:
            return now
        time.sleep(0.2)
