"""Headless Chromium driven over the DevTools protocol on a pipe (``--remote-debugging-pipe``: JSON
messages separated by NUL bytes on file descriptors 3 and 4), standard library only.

``screenshot(url, width, height, out_png)`` opens ``url``, waits until the page sets
``document.body.dataset.ready = "1"`` (the viewer does once the drawn depth order belongs to the
drawn pose and view), and saves a PNG. Raises ``BrowserError`` with the page's error text on failure.
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
from pathlib import Path

__all__ = ["find_chromium", "screenshot", "BrowserError"]

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


def screenshot(
    url: str, width: int, height: int, out_png: Path, chromium: str | None = None, timeout: float = 120.0
) -> Path:
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

    proc = subprocess.Popen(
        [chromium, *FLAGS, f"--user-data-dir={profile}", f"--window-size={width},{height}"],
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
        pipe.call(
            "Emulation.setDeviceMetricsOverride",
            {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False},
            session,
        )
        pipe.call("Page.navigate", {"url": url}, session)
        probe = (
            "JSON.stringify([document.body ? document.body.dataset.ready || '' : '', "
            "(document.getElementById('error') || {}).textContent || ''])"
        )
        deadline = time.monotonic() + timeout
        while True:
            res = pipe.call("Runtime.evaluate", {"expression": probe, "returnByValue": True}, session)
            ready, error = json.loads(res.get("result", {}).get("value") or '["", ""]')
            if error:
                raise BrowserError(f"page error: {error}")
            if ready == "1":
                break
            if time.monotonic() > deadline:
                raise BrowserError(f"page not ready after {timeout:.0f} s")
            time.sleep(0.1)
        shot = pipe.call("Page.captureScreenshot", {"format": "png"}, session)
        out_png = Path(out_png)
        out_png.write_bytes(base64.b64decode(shot["data"]))
        return out_png
    finally:
        with contextlib.suppress(BrowserError):
            pipe.call("Browser.close", timeout=5)
            pass
        os.close(to_w)
        os.close(from_r)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        shutil.rmtree(profile, ignore_errors=True)
