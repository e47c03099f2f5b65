"""Headless Chromium driven over the DevTools protocol on a pipe (``--remote-debugging-pipe``: JSON
messages separated by NUL bytes on file descriptors 3 and 4), standard library only.

``screenshot(url, width, height, out_png)`` opens ``url``, waits until the page sets
``document.body.dataset.ready = "1"`` (the viewer does once the drawn depth order belongs to the
drawn pose and view), and saves a PNG. ``open_page(url, width, height, mobile=...)`` gives a ``Page``
to evaluate JavaScript and send touch and key events (a phone when ``mobile``). Raises
``BrowserError`` with the page's error text on failure.
"""

from __future__ import annotations

import base64
import contextlib
import fcntl
import json
import os
import shutil
import subprocess
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

__all__ = ["find_chromium", "screenshot", "open_page", "Page", "BrowserError"]

FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
    "--remote-debugging-pipe",
]


class BrowserError(RuntimeError):
    pass


def find_chromium() -> str | None:
    return next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome") if shutil.which(n)), None)


class _Pipe:
    def __init__(self, proc, to_chrome: int, from_chrome: int):
        self.proc, self.w, self.r, self.buf, self.next_id = proc, to_chrome, from_chrome, b"", 1
        self.events: list[dict] = []

    def call(self, method: str, params: dict | None = None, session: str | None = None, timeout: float = 60.0):
        msg = {"id": self.next_id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        self.next_id += 1
        os.write(self.w, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + timeout
        while True:
            while b"\0" not in self.buf:
                if time.monotonic() > deadline or self.proc.poll() is not None:
                    raise BrowserError(f"chromium did not answer {method}")
                chunk = os.read(self.r, 1 << 20)
                if not chunk:
                    raise BrowserError("chromium closed the DevTools pipe")
                self.buf += chunk
            raw, self.buf = self.buf.split(b"\0", 1)
            reply = json.loads(raw)
            if reply.get("id") == msg["id"]:
                if "error" in reply:
                    raise BrowserError(f"{method}: {reply['error']}")
                return reply.get("result", {})
            self.events.append(reply)


class Page:
    """One tab of a headless Chromium: ``evaluate`` JavaScript, wait until the viewer is ready, send
    touch or key events (as a user's: through the browser's input pipeline), take a screenshot."""

    def __init__(self, pipe: _Pipe, session: str):
        self.pipe, self.session = pipe, session

    def call(self, method: str, params: dict | None = None, timeout: float = 60.0) -> dict:
        return self.pipe.call(method, params, self.session, timeout)

    def evaluate(self, expression: str):
        """The JSON value of ``expression`` in the page."""
        res = self.call("Runtime.evaluate", {"expression": expression, "returnByValue": True, "awaitPromise": True})
        if "exceptionDetails" in res:
            raise BrowserError(f"page exception: {res['exceptionDetails'].get('text')}")
        return res.get("result", {}).get("value")

    def wait_ready(self, timeout: float = 120.0) -> None:
        """Until the page sets ``document.body.dataset.ready = "1"``; its #error text raises."""
        probe = (
            "JSON.stringify([document.body ? document.body.dataset.ready || '' : '', "
            "(document.getElementById('error') || {}).textContent || ''])"
        )
        deadline = time.monotonic() + timeout
        while True:
            ready, error = json.loads(self.evaluate(probe) or '["", ""]')
            if error:
                raise BrowserError(f"page error: {error}")
            if ready == "1":
                return
            if time.monotonic() > deadline:
                raise BrowserError(f"page not ready after {timeout:.0f} s")
            time.sleep(0.1)

    def touch(self, kind: str, points: list[tuple[float, float]]) -> None:
        """``kind``: touchStart | touchMove | touchEnd | touchCancel; ``points``: the fingers down, in order
        (their index is their id; empty for touchEnd)."""
        pts = [{"x": x, "y": y, "id": i, "radiusX": 1, "radiusY": 1, "force": 1} for i, (x, y) in enumerate(points)]
        self.call("Input.dispatchTouchEvent", {"type": kind, "touchPoints": pts})

    def mouse(self, kind: str, x: float, y: float, button: str = "left", clicks: int = 1, **extra) -> None:
        """``kind``: mousePressed | mouseReleased | mouseMoved | mouseWheel (``deltaX``/``deltaY`` in
        ``extra``); ``button``: left | right | middle | none."""
        pressed = {"left": 1, "right": 2, "middle": 4}.get(button, 0)
        params = {"type": kind, "x": x, "y": y, "button": button, "clickCount": clicks, **extra}
        if kind == "mouseMoved":
            params["buttons"] = pressed
        self.call("Input.dispatchMouseEvent", params)

    def key(self, key: str, code: str, text: str = "") -> None:
        """Press and release one key (``key``/``code`` as KeyboardEvent's; ``text`` for printable keys)."""
        for kind in ("keyDown", "keyUp"):
            params = {"type": kind, "key": key, "code": code, "windowsVirtualKeyCode": ord(key.upper()[0])}
            if kind == "keyDown" and text:
                params["text"] = text
            self.call("Input.dispatchKeyEvent", params)

    def screenshot(self, out_png: Path, css_pixels: bool = False) -> Path:
        """A PNG of the viewport; ``css_pixels``: one pixel per CSS pixel (a 3x phone's is 9 times smaller)."""
        params: dict = {"format": "png"}
        if css_pixels:
            w, h = self.evaluate("[innerWidth, innerHeight]")
            params["clip"] = {"x": 0, "y": 0, "width": w, "height": h, "scale": 1 / self.evaluate("devicePixelRatio")}
        shot = self.call("Page.captureScreenshot", params)
        out_png = Path(out_png)
        out_png.write_bytes(base64.b64decode(shot["data"]))
        return out_png


@contextlib.contextmanager
def open_page(
    url: str,
    width: int,
    height: int,
    chromium: str | None = None,
    mobile: bool = False,
    scale: float = 1.0,
    fake_camera: Path | None = None,
) -> Iterator[Page]:
    """A headless Chromium showing ``url`` in a ``width`` x ``height`` viewport; ``mobile``: a phone
    (touch screen, mobile viewport, device pixel ratio ``scale``); ``fake_camera``: a ``.y4m`` video that
    the page's camera plays (``getUserMedia`` granted without asking). Closed on exit."""
    chromium = chromium or find_chromium()
    if chromium is None:
        raise BrowserError("chromium is not installed")
    profile = tempfile.mkdtemp(prefix="meshsplat-chromium-")
    to_r, to_w = os.pipe()  # we write to_w, chromium reads fd 3
    from_r, from_w = os.pipe()  # chromium writes fd 4, we read from_r

    # copies above 9, so that placing them at 3 and 4 in the child cannot overwrite one another
    hi_r, hi_w = fcntl.fcntl(to_r, fcntl.F_DUPFD_CLOEXEC, 10), fcntl.fcntl(from_w, fcntl.F_DUPFD_CLOEXEC, 10)

    def child_fds():
        os.dup2(hi_r, 3)  # dup2 leaves the new descriptors inheritable
        os.dup2(hi_w, 4)

    camera_flags = []
    if fake_camera is not None:
        camera_flags = [
            "--use-fake-ui-for-media-stream",
            "--use-fake-device-for-media-stream",
            f"--use-file-for-fake-video-capture={fake_camera}",
        ]
    proc = subprocess.Popen(
        [chromium, *FLAGS, *camera_flags, f"--user-data-dir={profile}", f"--window-size={width},{height}"],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        preexec_fn=child_fds,
        close_fds=False,
    )
    for fd in (to_r, from_w, hi_r, hi_w):
        os.close(fd)
    pipe = _Pipe(proc, to_w, from_r)
    try:
        target = pipe.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        session = pipe.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        page = Page(pipe, session)
        page.call(
            "Emulation.setDeviceMetricsOverride",
            {"width": width, "height": height, "deviceScaleFactor": scale, "mobile": mobile},
        )
        if mobile:
            page.call("Emulation.setTouchEmulationEnabled", {"enabled": True, "maxTouchPoints": 5})
        page.call("Page.navigate", {"url": url})
        yield page
    finally:
        with contextlib.suppress(BrowserError):
            pipe.call("Browser.close", timeout=5)
        os.close(to_w)
        os.close(from_r)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        shutil.rmtree(profile, ignore_errors=True)


def screenshot(
    url: str, width: int, height: int, out_png: Path, chromium: str | None = None, timeout: float = 120.0
) -> Path:
    """Open ``url``, wait until the viewer is ready, save a PNG."""
    with open_page(url, width, height, chromium) as page:
        page.wait_ready(timeout)
        return page.screenshot(out_png)
