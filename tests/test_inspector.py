"""The grasp inspector: a page served by the service, its vendored assets, the scene as GLB.

The browser test drives Debian's Chromium (``/usr/bin/chromium``; ``.ci/run`` installs it) with
Playwright against a real ``python -m service`` running the shipped MVP.
"""

import io
import os
import re
import shutil
from pathlib import Path

import httpx
import numpy as np
import pytest
import trimesh
from PIL import Image
from service_helpers import Server

from completion.scenes import make_sequence
from service.load import scene_views

CHROMIUM = "/usr/bin/chromium"
GRASP_QUERY = {"top_k": 3, "n_candidates": 16}
STATIC = Path(__file__).resolve().parents[1] / "service" / "static" / "inspector"


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """A real server with the shipped MVP and a session of 4 camera-pan views with poses."""
    tmp = tmp_path_factory.mktemp("inspector")
    server = Server(tmp, "mvp", tmp / "store.sqlite", max_candidates=64)
    try:
        seq = make_sequence("camera_pan", "test", 0, seed=0, keep_depth=True)
        sid = None
        for body in scene_views(seq)[:4]:  # posed views: the posed model, fused (issue 69)
            if sid:
                body["session_id"] = sid
            r = httpx.post(f"{server.url}/views", json=body, timeout=60)
            assert r.status_code == 200, r.text
            sid = r.json()["session_id"]
        yield server.url, sid
    finally:
        server.stop()


def test_page_and_assets_reference_no_outside_host(session):
    url, sid = session
    page = httpx.get(f"{url}/sessions/{sid}/view")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    links = re.findall(r'(?:src|href)="([^"]*)"', page.text)
    links += re.findall(r'"three":\s*"([^"]*)"', page.text)  # the import map
    assert links and all(link.startswith(("/", "data:")) for link in links), links
    for path in STATIC.rglob("*.js"):
        text = path.read_text()
        specifiers = re.findall(r"""(?:^|\n)\s*(?:import|export)[^;]*?from\s*['"]([^'"]+)['"]""",
                                text)
        specifiers += re.findall(r"""import\(\s*['"]([^'"]+)['"]""", text)
        for spec in specifiers:
            assert spec == "three" or spec.startswith("."), (path.name, spec)
        assert "fetch('http" not in text and 'fetch("http' not in text, path.name
        served = httpx.get(f"{url}/static/inspector/{path.relative_to(STATIC)}")
        assert served.status_code == 200 and served.text == text
    assert (STATIC / "vendor" / "three" / "LICENSE").read_text().startswith("The MIT License")


def test_scene_glb_holds_the_mesh_and_one_hand_per_grasp(session):
    url, sid = session
    query = {**GRASP_QUERY, "support_plane": "0,0,1,0.3"}  # a table 30 cm under the object
    plan = httpx.get(f"{url}/grasp", params={"session_id": sid, **query}, timeout=120)
    grasps = plan.json()["grasps"]
    assert len(grasps) >= 2, plan.json()["reason"]
    r = httpx.get(f"{url}/sessions/{sid}/scene.glb", params=query, timeout=120)
    assert r.status_code == 200 and r.headers["content-type"] == "model/gltf-binary", r.text
    scene = trimesh.load(io.BytesIO(r.content), file_type="glb")
    names = set(scene.geometry)
    assert {"completion", "observed", "support_plane"} <= names
    hands = sorted(n for n in names if n.startswith("grasp_"))
    assert hands == [f"grasp_{i}" for i in range(1, len(grasps) + 1)]
    mesh = httpx.get(f"{url}/sessions/{sid}/mesh", params={"format": "ply"}).content
    completion = trimesh.load(io.BytesIO(mesh), file_type="ply")
    np.testing.assert_allclose(scene.geometry["completion"].bounds, completion.bounds, atol=1e-6)
    # each hand sits at its grasp: the palm cylinder's centre near the palm pose
    for name, grasp in zip(hands, grasps, strict=True):
        palm = np.asarray(grasp["palm_pose"])[:3, 3]
        assert np.linalg.norm(scene.geometry[name].bounds.mean(axis=0) - palm) < 0.2


def _colours(png: bytes) -> int:
    pixels = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).reshape(-1, 3)
    return len(np.unique(pixels, axis=0))


@pytest.mark.slow
def test_page_renders_in_chromium_and_switches_grasps(session, tmp_path):
    from playwright.sync_api import sync_playwright

    assert Path(CHROMIUM).is_file(), "Debian's chromium is missing: apt-get install chromium"
    url, sid = session
    query = "&".join(f"{k}={v}" for k, v in GRASP_QUERY.items()) + "&support_plane=0,0,1,0.3"
    messages, requests = [], []
    with sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=CHROMIUM,
            args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"],
        )
        try:
            page = browser.new_page(viewport={"width": 1100, "height": 700})
            page.on("console", lambda m: messages.append(f"{m.type}: {m.text}"))
            page.on("pageerror", lambda e: messages.append(f"pageerror: {e}"))
            page.on("request", lambda r: requests.append(r.url))
            page.goto(f"{url}/sessions/{sid}/view?{query}")
            page.wait_for_selector('#status[data-state="ready"], #status[data-state="error"]',
                                   timeout=180_000)
            assert page.get_attribute("#status", "data-state") == "ready", page.inner_text(
                "#status")
            assert page.locator("#grasps li").count() >= 2
            canvas = page.locator("#viewport canvas")
            first = canvas.screenshot()
            whole = page.screenshot()
            page.click("#grasps li:nth-child(2)")
            assert "selected" in page.get_attribute("#grasps li:nth-child(2)", "class")
            second = canvas.screenshot()
            page.check("#all")  # the other grasps too
            everything = canvas.screenshot()
            listed = page.inner_text("#grasps")
        finally:
            browser.close()
    (tmp_path / "inspector.png").write_bytes(whole)
    errors = [m for m in messages if m.startswith(("error", "pageerror"))]
    assert not errors, errors
    assert all(r.startswith(url) or r.startswith("data:") for r in requests), requests
    assert _colours(first) > 200  # a rendered scene, not a blank canvas
    a = np.asarray(Image.open(io.BytesIO(first)).convert("RGB"), dtype=np.int16)
    b = np.asarray(Image.open(io.BytesIO(second)).convert("RGB"), dtype=np.int16)
    assert (np.abs(a - b).sum(axis=-1) > 30).mean() > 0.005  # the picture changed
    c = np.asarray(Image.open(io.BytesIO(everything)).convert("RGB"), dtype=np.int16)
    assert (np.abs(c - b).sum(axis=-1) > 30).mean() > 0.002  # the others appeared
    assert "approach stop: " in listed and "hold probability" in listed
    for picture in (a, b):  # framed on the object and where the grasp touches it
        orange = picture[..., 0] - picture[..., 2] > 60  # the completion
        ys, xs = np.nonzero(orange)
        h, w = orange.shape
        assert max((ys.max() - ys.min()) / h, (xs.max() - xs.min()) / w) > 0.3  # not a speck
        assert 0.2 < xs.mean() / w < 0.8 and 0.2 < ys.mean() / h < 0.8  # in the middle
        dark = picture.sum(axis=-1) < 3 * 170  # the hand
        ys, xs = np.nonzero(dark | orange)
        assert max((ys.max() - ys.min()) / h, (xs.max() - xs.min()) / w) > 0.5
    if os.environ.get("INSPECTOR_SCREENSHOT"):  # how the README's screenshot is made
        shutil.copy(tmp_path / "inspector.png", os.environ["INSPECTOR_SCREENSHOT"])
