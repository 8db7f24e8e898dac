"""The viewer with hostile templates and on the network (GitHub issue 21): names are shown as text, never run
as markup; a viewer served beyond loopback says so, and with `--token` serves nothing without the token.

Browser tests drive Debian's /usr/bin/chromium through Playwright (web/viewer_probe.py).
"""
from __future__ import annotations

import importlib.util
import json
import sqlite3
import sys
import urllib.error
import urllib.request
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "web" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


vp = _load("viewer_probe")
synth_template = _load("synth_template")

# each would change the page if it ran: its title, a global, an attribute of <body>
SCRIPT = "parent.document.title='pwned';parent.window.__pwned=1;parent.document.body.setAttribute('data-pwned','1')"
IFRAME_NAME = f'<iframe srcdoc="<script>{SCRIPT}</script>"></iframe>'
IMG_NAME = "<img src=x onerror=\"document.title='pwned';window.__pwned=2\">"
MD_NAME = "**bold** [link](javascript:alert(1)) | cell"
ESC_NAME = "esc\x1b[31mred"
ESC_SHOWN = "esc\\x1b[31mred"  # as the viewer shows it
FILE_NAME = "<img src=x onerror=window.__pwned=3>.gscan"  # a template file named with markup (no slash)


@pytest.fixture(scope="module")
def hostile(tmp_path_factory) -> tuple[Path, list[str]]:
    """A complete template whose view names, edge reason, skipped frame and file name hold markup."""
    folder = tmp_path_factory.mktemp("hostile")
    tpl = synth_template.build_synth_template(folder / "box.gscan", n_views=4, max_keypoints=120)
    names = [IFRAME_NAME, IMG_NAME, MD_NAME, ESC_NAME]
    with sqlite3.connect(tpl.path) as c:
        old = [r[0] for r in c.execute("SELECT name FROM views ORDER BY input_index")]
        for a, b in zip(old, names, strict=True):
            c.execute("UPDATE views SET name=? WHERE name=?", (b, a))
            c.execute("UPDATE edges SET src=? WHERE src=?", (b, a))
            c.execute("UPDATE edges SET tgt=? WHERE tgt=?", (b, a))
        c.execute("UPDATE edges SET reason=? WHERE id=(SELECT min(id) FROM edges)", (IMG_NAME,))
        c.execute("INSERT OR REPLACE INTO meta(key, value) VALUES ('skipped', ?)",
                  (json.dumps({IMG_NAME + "x": "bad"}),))
    c.close()
    path = folder / FILE_NAME
    tpl.path.rename(path)
    return path, names


def _label(path: Path, src: str, tgt: str) -> str:
    """The Match panel's label of the edge src -> tgt."""
    from gscan.template.db import TemplateDB
    from gscan.viewer.app import _edge_label

    with TemplateDB.open(path) as db:
        return _edge_label(next(e for e in db.edges() if (e.src, e.tgt) == (src, tgt)))


def _injected(page) -> dict:
    """What a script from a name would have changed."""
    return page.evaluate("() => ({title: document.title, pwned: window.__pwned === undefined ? null : window.__pwned,"
                         " body: document.body.getAttribute('data-pwned'),"
                         " iframes: document.querySelectorAll('iframe').length,"
                         " imgs: [...document.querySelectorAll('img')]"
                         ".filter(i => i.getAttribute('src') === 'x').length})")


@pytest.mark.browser
def test_names_with_markup_are_shown_as_text(hostile, tmp_path):
    """View names, an edge's reason, a skipped frame's name and the file name holding HTML and Markdown are shown
    as the characters they are: no iframe or img element appears, no script runs (title, globals and DOM as
    they were), and the text is on the page."""
    from playwright.sync_api import sync_playwright

    path, names = hostile
    port = vp.free_port()
    proc, _ = vp.start_viewer(path, port, log_path=tmp_path / "view.log")
    try:
        with sync_playwright() as p:
            browser = vp.launch(p)
            try:
                page = browser.new_page(viewport=vp.VIEWPORT)
                dialogs: list[str] = []
                page.on("dialog", lambda d: (dialogs.append(d.message), d.dismiss()))
                vp.open_viewer(page, f"http://127.0.0.1:{port}")
                title = page.title()
                page.get_by_text("(1/4)", exact=False).first.wait_for(timeout=20_000)  # the first view's panel
                page.wait_for_timeout(1000)  # time for anything injected to run
                state = _injected(page)
                assert state == {"title": title, "pwned": None, "body": None, "iframes": 0, "imgs": 0}, state
                assert page.get_by_text(f"{IFRAME_NAME} (1/4)").count() == 1  # the first view's name, as text
                assert page.get_by_text(FILE_NAME).count() >= 1  # the summary names the file, as text
                assert page.get_by_text(IMG_NAME + "x", exact=False).count() >= 1  # the skipped frame
                vp.select_option(page, "Edge", _label(path, IFRAME_NAME, IMG_NAME))  # its reason: markup
                page.get_by_text("matches:").first.wait_for(timeout=10_000)
                assert page.get_by_text(f"reason: {IMG_NAME}").count() == 1
                for k, name in enumerate(names[1:3], start=2):  # the other views' panels
                    vp.select_option(page, "View", name)
                    page.get_by_text(f"{name} ({k}/4)").wait_for(timeout=10_000)
                vp.gui_slider(page, "View #").focus()
                page.keyboard.press("ArrowRight")  # the name with an escape sequence, written out
                page.get_by_text(ESC_SHOWN + " (4/4)").wait_for(timeout=10_000)
                page.wait_for_timeout(1000)  # time for anything that was injected to run
                state = _injected(page)
                assert state == {"title": title, "pwned": None, "body": None, "iframes": 0, "imgs": 0}, state
                assert "pwned" not in title and not dialogs
                assert page.get_by_text("**bold**", exact=False).count() >= 1  # Markdown not interpreted either
            finally:
                browser.close()
    finally:
        vp.stop_viewer(proc)


@pytest.mark.browser
def test_token_gate_serves_nothing_without_the_token(hostile, tmp_path):
    """`gscan view --host 0.0.0.0 --token T`: no warning (the token is required); a page opened without the
    token gets a 403 and no viewer, a WebSocket without it is refused, a wrong token too; the printed URL
    opens the viewer."""
    from playwright.sync_api import sync_playwright
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    path, _ = hostile
    port = vp.free_port()
    token = "t0ken-for.the_test~1"
    log = tmp_path / "view.log"
    proc, _ = vp.start_viewer(path, port, extra=["--host", "0.0.0.0", "--token", token], log_path=log)
    try:
        text = log.read_text()
        assert f"?token={token}" in text and "warning" not in text, text
        for url in (f"http://127.0.0.1:{port}/", f"http://127.0.0.1:{port}/?token=wrong"):
            with pytest.raises(urllib.error.HTTPError) as ei:
                urllib.request.urlopen(url, timeout=10)
            assert ei.value.code == 403
            assert b"<script" not in ei.value.read()
        with pytest.raises(InvalidStatus) as wi:
            connect(f"ws://127.0.0.1:{port}", subprotocols=["viser-v1"], open_timeout=10)
        assert wi.value.response.status_code == 403
        with connect(f"ws://127.0.0.1:{port}", additional_headers={"Cookie": f"gscan_token_{port}={token}"},
                     open_timeout=10) as ws:  # the cookie the token URL sets opens the WebSocket
            assert ws.protocol is not None
        with sync_playwright() as p:
            browser = vp.launch(p)
            try:
                page = browser.new_page(viewport=vp.VIEWPORT)
                resp = page.goto(f"http://127.0.0.1:{port}/")
                assert resp is not None and resp.status == 403
                assert page.locator("canvas").count() == 0 and "token" in page.content()
                page.wait_for_timeout(1000)
                assert page.locator("canvas").count() == 0  # nothing loads later either
                vp.open_viewer(page, f"http://127.0.0.1:{port}/?token={token}")  # the printed URL
                _, std = vp.wait_scene_drawn(page, 8.0)
                assert std > 8.0 and "token" not in page.url  # redirected to the page without it
            finally:
                browser.close()
    finally:
        vp.stop_viewer(proc)


def test_view_beyond_loopback_warns(hostile, tmp_path):
    """`gscan view --host 0.0.0.0` (no token) warns on one line before it serves that every image is served
    without authentication; on 127.0.0.1 it says nothing of the kind."""
    path, _ = hostile
    for host, warned in (("0.0.0.0", True), ("127.0.0.1", False)):
        log = tmp_path / f"view-{host}.log"
        proc, _ = vp.start_viewer(path, vp.free_port(), extra=["--host", host], log_path=log)
        vp.stop_viewer(proc)
        lines = log.read_text().splitlines()
        warning = [ln for ln in lines if ln.startswith("warning:")]
        if warned:
            assert len(warning) == 1 and "without authentication" in warning[0] and "--token" in warning[0], lines
            assert lines.index(warning[0]) < next(i for i, ln in enumerate(lines) if "viewer ready" in ln)
        else:
            assert warning == [], lines


def test_loopback_addresses():
    from gscan.viewer.access import is_loopback

    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("127.1.2.3") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("::") and not is_loopback("") and not is_loopback("10.0.0.1")


def test_markdown_text_is_literal():
    """Every ASCII punctuation character is escaped (CommonMark: a literal), control characters written out."""
    from gscan.viewer.text import md_text

    assert md_text("a<b>&c|d*e_f\\g") == "a\\<b\\>\\&c\\|d\\*e\\_f\\\\g"
    assert md_text("x\x1b[1m\ny\u202e") == "x\\\\x1b\\[1m\\\\ny\\\\u202e"
    assert md_text("ordinary name é 0001") == "ordinary name é 0001"
