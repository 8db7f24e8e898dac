"""The estimation service (`gscan serve`, gscan.serve) started as a subprocess on a free port, driven through
gscan.client: 20 frames posted (the object present, absent, and bad requests), tracking sessions, and the
request decoding on its own."""
from __future__ import annotations

import json
import os
import re
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from gscan.client import GscanClient, ServiceError
from gscan.geometry.transforms import look_at, pose_error, rotvec_to_R, transform_points
from gscan.scan.cad import template_from_mesh
from gscan.serve.decode import RequestError, decode_frame
from gscan.synth import (
    DEFAULT_INTRINSICS,
    SynthScene,
    default_distance,
    load_textured_mesh,
    place_distractors,
    rest_on_table,
)

TARGET = "Frozen_Scrabble_Jr"
DISTRACTORS = ("Crayola_Bonus_64_Crayons", "Little_Debbie_Cloud_Cakes_10_ct")
K_TEXT = "\n".join(" ".join(f"{x:.10g}" for x in row) for row in DEFAULT_INTRINSICS.K) + "\n"


def png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


def frame_bytes(r) -> tuple[bytes, bytes]:
    """(colour PNG, 16-bit depth PNG in millimetres) of a rendered frame."""
    mm = np.clip(np.rint(r.depth * 1000.0), 0, 65535).astype(np.uint16)
    return png(cv2.cvtColor(r.color, cv2.COLOR_RGB2BGR)), png(mm)


def render(meshes, seed: int, with_target: bool = True):
    rng = np.random.default_rng(seed)
    target, distractors = meshes[0], meshes[1:]
    T_wt = rest_on_table(target, rotvec_to_R([0.0, 0.0, rng.uniform(0, 2 * np.pi)]))
    d_poses = place_distractors(target, T_wt, list(distractors), rng)
    objs = ([(target, T_wt)] if with_target else []) + list(zip(distractors, d_poses))
    c = transform_points(T_wt, target.center[None])[0]
    el, az = np.radians(rng.uniform(30, 55)), rng.uniform(0, 2 * np.pi)
    eye = c + default_distance(target, fill=0.45) * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                                               np.sin(el)])
    T_wc = look_at(eye, c)
    r = SynthScene(objs, seed=seed, table_kind="wood").render(T_wc, DEFAULT_INTRINSICS, rng=np.random.default_rng(seed))
    return r, np.linalg.inv(T_wc) @ T_wt


def huge_png_header(width: int, height: int) -> bytes:
    """A PNG whose header claims width x height pixels (decoding it would take gigabytes)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\x00" * 64))
            + chunk(b"IEND", b""))


@pytest.fixture(scope="module")
def meshes(meshes_dir: Path):
    return [load_textured_mesh(meshes_dir / n / "model_0.obj") for n in (TARGET,) + DISTRACTORS]


@pytest.fixture(scope="module")
def template(meshes_dir: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("serve") / "scrabble.gscan"
    template_from_mesh(meshes_dir / TARGET / "model_0.obj", out, n_views=16)
    return out


@pytest.fixture(scope="module")
def service(template: Path):
    """`gscan serve` on a free port (--port 0; the address read from its ready line); stopped after the module."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "gscan.cli", "serve", str(template), "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    url = None
    t0 = time.monotonic()
    while time.monotonic() - t0 < 300:
        line = proc.stderr.readline()
        if not line:
            break
        m = re.search(r"at (http://127\.0\.0\.1:\d+)", line)
        if m:
            url = m.group(1)
            break
    if url is None:
        proc.kill()
        pytest.fail(f"the service did not start: {proc.stderr.read()}")
    yield proc, GscanClient(url, timeout=120)
    proc.terminate()
    try:
        proc.wait(30)
    except subprocess.TimeoutExpired:
        proc.kill()


def test_twenty_frames_found_not_found_and_bad(service, meshes):
    proc, client = service
    assert client.health() == ["scrabble"]
    good = [(seed, True) for seed in range(8)] + [(seed, False) for seed in range(8, 12)]
    for seed, present in good:  # 12 frames the service answers with 200
        r, T_gt = render(meshes, seed, present)
        c, d = frame_bytes(r)
        res = client.estimate(c, d, K_TEXT)
        pose = res.results["scrabble"]
        assert res.timings_ms["total"] > 0 and set(pose.timings_ms) >= {"features", "match", "total"}
        if present:
            assert pose.found, (seed, pose.reason)
            deg, m = pose_error(np.asarray(pose.T_cam_obj), T_gt)
            assert deg < 5.0 and m < 0.01, (seed, deg, m)
        else:
            assert not pose.found and pose.reason, seed
    r, _ = render(meshes, 0)
    c, d = frame_bytes(r)
    half = png(cv2.resize(np.clip(np.rint(r.depth * 1000), 0, 65535).astype(np.uint16), (320, 240),
                          interpolation=cv2.INTER_NEAREST))
    bad = [  # 8 bad requests: (fields, expected status, field named in the detail)
        ({"color": c[: len(c) // 3], "depth": d}, 400, "color"),  # corrupt (truncated) PNG
        ({"color": c, "depth": half}, 400, "depth"),  # depth of another size than the colour image
        ({"color": c, "depth": d, "intrinsics": None}, 422, "intrinsics"),  # a missing field
        ({"color": c, "depth": png(cv2.cvtColor(r.color, cv2.COLOR_RGB2GRAY))}, 400, "depth"),  # 8-bit depth
        ({"color": huge_png_header(60000, 60000), "depth": d}, 413, "color"),  # decoding would take 10 GB
        ({"color": c, "depth": d, "intrinsics": "1 2 3"}, 400, "intrinsics"),
        ({"color": c, "depth": d, "depth_scale": "1000"}, 400, "depth_scale"),  # puts the scene at kilometres
        ({"color": c, "depth": d, "templates": "nonexistent"}, 404, "templates"),
    ]
    for fields, status, field in bad:
        parts = {"intrinsics": K_TEXT, **fields}
        body = [(k, "f.png" if k in ("color", "depth") else None, v if isinstance(v, bytes) else v.encode())
                for k, v in parts.items() if v is not None]
        with pytest.raises(ServiceError) as e:
            client._request("POST", "/estimate", body)
        assert e.value.status == status, (field, e.value)
        assert e.value.detail.startswith(field + ":") and "\n" not in e.value.detail, e.value.detail
    assert proc.poll() is None  # still running ...
    assert client.health() == ["scrabble"]  # ... and answering
    again = client.estimate(c, d, K_TEXT).results["scrabble"]
    assert again.found


def test_tracking_session_through_the_service(service, meshes):
    _, client = service
    rng_seed = 3
    r, T_gt = render(meshes, rng_seed)
    c, d = frame_bytes(r)
    steps = [client.track("cam-1", c, d, K_TEXT) for _ in range(3)]
    assert [s.status for s in steps] == ["found", "tracked", "tracked"]
    assert [s.frame for s in steps] == [0, 1, 2] and all(s.template == "scrabble" for s in steps)
    for s in steps:
        deg, m = pose_error(np.asarray(s.result.T_cam_obj), T_gt)
        assert deg < 5.0 and m < 0.01
    assert steps[1].result.method == "track"
    r0, _ = render(meshes, 9, with_target=False)
    lost = client.track("cam-1", *frame_bytes(r0), K_TEXT)
    assert lost.status == "lost" and not lost.result.found
    assert client.track("cam-1", c, d, K_TEXT).status == "refound"
    assert client.end_track("cam-1") == 5
    with pytest.raises(ServiceError) as e:
        client.end_track("cam-1")
    assert e.value.status == 404
    with pytest.raises(ServiceError) as e:
        client.track("bad id!", c, d, K_TEXT)
    assert e.value.status in (400, 404)


def test_openapi_page_and_unreachable_service(service):
    _, client = service
    import urllib.request

    with urllib.request.urlopen(client.url + "/openapi.json", timeout=30) as resp:
        spec = json.loads(resp.read())
    assert {"/health", "/estimate", "/track/{session}"} <= set(spec["paths"])
    with urllib.request.urlopen(client.url + "/docs", timeout=30) as resp:
        assert resp.status == 200 and b"swagger" in resp.read().lower()
    with pytest.raises(ServiceError) as e:
        GscanClient("http://127.0.0.1:9", timeout=5).health()
    assert e.value.status == 0 and "cannot reach" in e.value.detail


def test_decode_frame_checks_before_decoding(meshes):
    r, _ = render(meshes, 0)
    c, d = frame_bytes(r)
    f = decode_frame(c, d, K_TEXT, 0.001)
    assert f.color.shape == (480, 640, 3) and f.depth.dtype == np.float32
    np.testing.assert_allclose(f.depth[r.depth > 0], r.depth[r.depth > 0], atol=6e-4)
    with pytest.raises(RequestError, match="^color: .*larger") as e:
        decode_frame(huge_png_header(20000, 20000), d, K_TEXT, 0.001)
    assert e.value.status == 413
    with pytest.raises(RequestError, match="^mask: mask is 10x10"):
        decode_frame(c, d, K_TEXT, 0.001, mask=png(np.zeros((10, 10), np.uint8)))
    with pytest.raises(RequestError, match="^depth: all zero"):
        decode_frame(c, png(np.zeros((480, 640), np.uint16)), K_TEXT, 0.001)


def test_serve_from_python(template: Path):
    """gscan.serve (the public API's function, also the package's name) starts the service from Python."""
    code = ("import sys, gscan; gscan.serve([sys.argv[1]], port=0, on_ready=lambda url: print(url, flush=True))")
    proc = subprocess.Popen([sys.executable, "-c", code, str(template)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        url = proc.stdout.readline().strip()
        assert url.startswith("http://127.0.0.1:"), proc.stderr.read() if proc.poll() is not None else url
        assert GscanClient(url, timeout=60).health() == ["scrabble"]
    finally:
        proc.terminate()
        proc.wait(30)
    import gscan
    import gscan.serve.api  # the package imported as well: the name still starts the service

    assert callable(gscan.serve) and gscan.serve.create_app is not None


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_body_limit_and_framework_errors(template: Path):
    """A body over the limit gets 413 whether its size is announced (Content-Length) or not (chunked); the
    framework's own errors (an unparsable body, an unknown path) get one line naming the request."""
    from fastapi.testclient import TestClient

    from gscan.serve import ServeParams, create_app, load_service

    client = TestClient(create_app(load_service([template], ServeParams(max_request_bytes=10_000))))
    form = {"content-type": "multipart/form-data; boundary=b"}
    r = client.post("/estimate", content=b"x" * 20_000, headers=form)
    assert r.status_code == 413 and r.json()["detail"].startswith("request: ")
    r = client.post("/estimate", content=(b"x" * 1000 for _ in range(50)), headers=form)  # chunked
    assert r.status_code == 413 and r.json()["detail"].startswith("request: ")
    r = client.post("/estimate", content=b"x" * 100, headers=form)
    assert r.status_code == 400 and r.json()["detail"].startswith("request: ")
    r = client.get("/nowhere")
    assert r.status_code == 404 and r.json()["detail"] == "request: Not Found"
    assert client.get("/health").json() == {"templates": ["scrabble"]}
