"""The player page as a user meets it (docs/viewer.md): the view you find is the view you render
(``#view=`` and ``meshsplat render --camera 'page:FOLDER#view=...'``), the phone layout, the camera
controls and their limits, and clear messages for a cut or foreign page. Browser tests are slow and
need Chromium (CI installs it)."""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import pytest
import torch
from test_viewer import _chromium, _frames, _psnr, _small_blendshapes

from _browser import open_page
from _eval_kit import make_avatar
from meshsplat.camera import orbit_camera
from meshsplat.cli._options import orbit_request
from meshsplat.errors import MeshsplatError
from meshsplat.viewer import page_camera, read_viewer_bundle, write_viewer_bundle
from meshsplat.viewer.bundle import parse_view


def test_page_view_string_is_a_camera(tmp_path):
    av = make_avatar(n=20)
    write_viewer_bundle(av, _frames(av), tmp_path / "b", camera={"width": 200, "height": 100})
    view = "view=30.5,-12,2.75,0.1,-0.2,0.3,30,320,240"
    cam = page_camera(f"{tmp_path / 'b'}#{view}")
    assert cam["azimuth_deg"] == 30.5 and cam["elevation_deg"] == -12 and cam["distance"] == 2.75
    assert cam["center"] == (0.1, -0.2, 0.3) and (cam["width"], cam["height"]) == (320, 240)
    assert cam["up"] == (0.0, 1.0, 0.0)  # from the bundle
    # the page's address (a file:// URL of index.html) names the same camera
    assert page_camera((tmp_path / "b" / "index.html").as_uri() + "#" + view) == cam
    # the CLI's --camera page:...#view=... (render and view), flags still override
    args = argparse.Namespace(
        camera=f"page:{tmp_path / 'b'}#{view}",
        center=None,
        distance=None,
        azimuth=None,
        elevation=5.0,
        fov=None,
        up=None,
        front=None,
    )
    req = orbit_request(args, (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    assert req["azimuth_deg"] == 30.5 and req["elevation_deg"] == 5.0 and req["width"] == 320
    for bad in ("view=1,2,3", "view=1,2,0,0,0,0,30,10,10", "view=a,b,c,d,e,f,g,h,i", "nothing"):
        with pytest.raises(MeshsplatError, match="page view"):
            parse_view(bad)


def _settle(page, timeout: float = 60.0) -> None:
    time.sleep(0.3)  # the next frame notices the change
    page.wait_ready(timeout)


@pytest.mark.slow
def test_browser_dragged_view_renders_identically(tmp_path):
    """Orbit (left drag), pan (right drag) and zoom (wheel) in the page; its address's #view= through
    page_camera (what `render --camera 'page:FOLDER#view=...'` uses) renders the same image."""
    from PIL import Image

    av = make_avatar(n=400)
    frames = _frames(av)
    write_viewer_bundle(av, frames, tmp_path / "b", camera={"width": 256, "height": 256})
    url = (tmp_path / "b" / "index.html").as_uri() + "?frame=1&ui=0"
    with open_page(url, 256, 256, _chromium()) as page:
        page.wait_ready()
        page.mouse("mousePressed", 128, 128)
        for x, y in ((150, 135), (170, 140)):
            page.mouse("mouseMoved", x, y, button="left")
        page.mouse("mouseReleased", 170, 140)
        page.mouse("mousePressed", 128, 128, button="right")
        page.mouse("mouseMoved", 110, 120, button="right")
        page.mouse("mouseReleased", 110, 120, button="right")
        page.mouse("mouseWheel", 128, 128, button="none", deltaX=0, deltaY=-150)
        _settle(page)
        time.sleep(0.4)  # the address follows the view within 250 ms
        page.evaluate("1")
        view = page.evaluate("window.meshsplatViewer.viewString")
        assert page.evaluate("location.hash") == "#" + view
        page.screenshot(tmp_path / "dragged.png")
        v = page.evaluate("JSON.stringify(window.meshsplatViewer.view)")
    cam = page_camera(f"{tmp_path / 'b'}#{view}")
    v = json.loads(v)
    assert cam["azimuth_deg"] == pytest.approx(v["az"]) and cam["azimuth_deg"] != 0  # it moved
    assert np.abs(np.subtract(cam["center"], read_viewer_bundle(tmp_path / "b")[0]["camera"]["center"])).max() > 1e-3
    ref = av.render(frames[1], orbit_camera(**cam), background=torch.ones(3)).image.detach().clamp(0, 1).numpy() * 255
    img = np.asarray(Image.open(tmp_path / "dragged.png").convert("RGB"), dtype=np.float64)
    psnr = _psnr(img, ref)
    print(f"dragged view: page vs render of its #view= PSNR {psnr:.1f} dB")
    assert psnr > 40.0
    # the page opened at that address shows that view again
    with open_page(url + "#" + view, 256, 256, _chromium()) as page:
        page.wait_ready()
        page.screenshot(tmp_path / "reopened.png")
    again = np.asarray(Image.open(tmp_path / "reopened.png").convert("RGB"), dtype=np.float64)
    assert _psnr(again, img) > 50.0


def _rects(page, selector: str) -> list[dict]:
    return json.loads(
        page.evaluate(
            f"JSON.stringify([...document.querySelectorAll({json.dumps(selector)})].filter((e) => e.getClientRects().length"
            " && getComputedStyle(e).visibility !== 'hidden').map((e) => { const r = e.getBoundingClientRect();"
            " return {id: e.id || e.textContent.trim().slice(0, 20), x: r.left, y: r.top, w: r.width, h: r.height}; }))"
        )
    )


def _overlaps(r: dict, box: tuple[int, int, int, int]) -> bool:
    x0, y0, x1, y1 = box
    return r["x"] < x1 and r["x"] + r["w"] > x0 and r["y"] < y1 and r["y"] + r["h"] > y0


@pytest.mark.slow
def test_browser_phone_layout_and_controls(tmp_path):
    """An emulated 390x844 phone (3x pixels): the canvas is capped at 2x, nothing covers the subject,
    every control is a 44-px tap target and reachable; zoom stops at the subject's size; keyboard,
    double-click; a cut page and a short data section say so."""
    from PIL import Image

    av = make_avatar(n=300)
    drv = _small_blendshapes(av)
    drv.names = [f"shape{i}" for i in range(4)]
    write_viewer_bundle(av, None, tmp_path / "b", rig=drv)
    url = (tmp_path / "b" / "index.html").as_uri() + "?play=0"
    with open_page(url, 390, 844, _chromium(), mobile=True, scale=3) as page:
        page.wait_ready()
        assert page.evaluate("[canvas.width, canvas.height].join()") == "780,1688"  # 2x, not 3x
        assert page.evaluate("document.getElementById('more').hidden") is True
        # the subject's box: the pixels that differ from the background with the panels out of the way
        page.evaluate("for (const id of ['ui', 'hint']) document.getElementById(id).style.visibility = 'hidden'")
        page.screenshot(tmp_path / "bare.png", css_pixels=True)
        page.evaluate("for (const id of ['ui', 'hint']) document.getElementById(id).style.visibility = ''")
        page.screenshot(tmp_path / "phone.png", css_pixels=True)
        bare = np.asarray(Image.open(tmp_path / "bare.png").convert("RGB"), dtype=np.int32)
        ys, xs = np.nonzero(np.abs(bare - 255).sum(-1) > 30)
        s = bare.shape[1] / 390  # screenshot pixels per CSS pixel (1)
        box = (xs.min() / s, ys.min() / s, xs.max() / s, ys.max() / s)
        panels = _rects(page, "#ui, #hint, #campanel")
        assert len(panels) == 2 and not any(_overlaps(r, box) for r in panels), (box, panels)
        small = [r for r in _rects(page, "#ui button, #ui select, #ui input, #hint button") if min(r["w"], r["h"]) < 44]
        assert not small, small
        # "more" opens every control inside the screen (the panel scrolls if it must)
        page.evaluate("document.getElementById('menu').click()")
        page.screenshot(tmp_path / "phone_more.png", css_pixels=True)
        controls = _rects(page, "#ui button, #ui select, #ui input")
        assert len(controls) >= 10
        ui = _rects(page, "#ui")[0]
        assert ui["y"] + ui["h"] <= 844 and ui["x"] + ui["w"] <= 390
        assert not [r for r in controls if min(r["w"], r["h"]) < 44]
        # zoom stops at the subject's size, both ways
        lim = json.loads(page.evaluate("JSON.stringify(window.meshsplatViewer.limits)"))
        page.touch("touchStart", [(194, 400), (196, 400)])  # fingers 190 times apart: 190 times closer, unlimited
        page.touch("touchMove", [(5, 400), (385, 400)])
        assert page.evaluate("window.meshsplatViewer.view.dist") == pytest.approx(lim["minDist"])
        page.evaluate("document.getElementById('reset').click()")  # (a close-up is slow to draw in software)
        page.touch("touchEnd", [])
        # two fingers moving together pan
        c0 = page.evaluate("window.meshsplatViewer.view.center.join()")
        page.touch("touchStart", [(150, 400), (250, 400)])
        page.touch("touchMove", [(170, 430), (270, 430)])
        page.touch("touchEnd", [])
        assert page.evaluate("window.meshsplatViewer.view.center.join()") != c0
    with open_page((tmp_path / "b" / "index.html").as_uri() + "?play=0&hint=0", 640, 480, _chromium()) as page:
        page.wait_ready()
        v0 = page.evaluate("JSON.stringify(window.meshsplatViewer.view)")
        for _ in range(40):
            page.mouse("mouseWheel", 320, 240, button="none", deltaX=0, deltaY=500)
        lim = json.loads(page.evaluate("JSON.stringify(window.meshsplatViewer.limits)"))
        assert page.evaluate("window.meshsplatViewer.view.dist") == pytest.approx(lim["maxDist"])
        page.key("ArrowLeft", "ArrowLeft")
        page.key("+", "Equal", "+")
        assert page.evaluate("window.meshsplatViewer.view.az") == pytest.approx(json.loads(v0)["az"] + 5)
        assert page.evaluate("window.meshsplatViewer.view.dist") == pytest.approx(0.9 * lim["maxDist"])
        page.mouse("mousePressed", 320, 240, clicks=1)
        page.mouse("mouseReleased", 320, 240, clicks=1)
        page.mouse("mousePressed", 320, 240, clicks=2)
        page.mouse("mouseReleased", 320, 240, clicks=2)
        assert page.evaluate("JSON.stringify(window.meshsplatViewer.view)") == v0  # double-click: reset
        assert "--azimuth" in page.evaluate("document.getElementById('viewtext').value")
    # a page cut short (before the viewer's code) and one whose data section is short say so
    page_text = (tmp_path / "b" / "index.html").read_text()
    cut = page_text.index('id="avatar-data">') + 5000
    (tmp_path / "b" / "cut.html").write_text(page_text[:cut])
    data = page_text.index('id="avatar-data">') + len('id="avatar-data">')
    end = page_text.index("</script>", data)
    (tmp_path / "b" / "short.html").write_text(page_text[: data + 4000] + page_text[end:])
    for name, words in (("cut.html", "incomplete"), ("short.html", "cut short")):
        with open_page((tmp_path / "b" / name).as_uri(), 400, 300, _chromium()) as page:
            deadline = time.monotonic() + 30
            while not (text := page.evaluate("(document.getElementById('error') || {}).textContent || ''")):
                assert time.monotonic() < deadline, name
                time.sleep(0.1)
            assert words in text, text
            assert "Invalid typed array length" not in text
