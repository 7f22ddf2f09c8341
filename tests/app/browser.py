"""Headless Chromium driven through the DevTools protocol over ``--remote-debugging-pipe`` (the
standard library only: JSON messages ended by a NUL byte on file descriptors 3 and 4 of the
browser). Used by the viewer's browser test; :func:`find_chromium` is None where no browser is
installed (Debian: ``apt-get install chromium``)."""
from __future__ import annotations

import base64
import fcntl
import io
import json
import os
import shutil
import subprocess
import tempfile
import time

import numpy as np
from matplotlib.image import imread

#: Executables tried, in order.
BROWSERS = ("chromium", "chromium-browser", "google-chrome")


def find_chromium() -> str | None:
    """The path of a Chromium executable, or None."""
    return next((p for p in map(shutil.which, BROWSERS) if p), None)


class Browser:
    """One headless Chromium with one page (a DevTools session attached to it)."""

    def __init__(self, executable: str, width: int = 1200, height: int = 900):
        # chromium's helper processes can still be writing to the profile as it is removed
        self._profile = tempfile.TemporaryDirectory(prefix="qr-cl-chromium-", ignore_cleanup_errors=True)
        to_browser, self._send_fd = os.pipe()
        self._recv_fd, from_browser = os.pipe()

        def pipes_as_3_and_4():                           # in the child, before exec
            high = [fcntl.fcntl(fd, fcntl.F_DUPFD, 10) for fd in (to_browser, from_browser)]
            os.dup2(high[0], 3)
            os.dup2(high[1], 4)
        self.process = subprocess.Popen(
            [executable, "--headless=new", "--no-sandbox", "--disable-gpu", "--no-first-run",
             "--no-default-browser-check", "--remote-debugging-pipe", f"--user-data-dir={self._profile.name}",
             f"--window-size={width},{height}", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, pass_fds=(3, 4), preexec_fn=pipes_as_3_and_4)
        os.close(to_browser)
        os.close(from_browser)
        self._buffer = b""
        self._next_id = 0
        target = self.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        self.session = self.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]

    def call(self, method: str, params: dict | None = None, session: bool = False, timeout: float = 30) -> dict:
        """Send a DevTools command (to the page's session when ``session``) and return its result;
        RuntimeError with the browser's message when it fails."""
        self._next_id += 1
        message = {"id": self._next_id, "method": method, "params": params or {}}
        if session:
            message["sessionId"] = self.session
        os.write(self._send_fd, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            reply = self._read()
            if reply.get("id") == self._next_id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})
        raise TimeoutError(f"{method}: no reply in {timeout} s")

    def _read(self) -> dict:
        while b"\0" not in self._buffer:
            chunk = os.read(self._recv_fd, 1 << 16)
            if not chunk:
                raise RuntimeError("the browser closed its DevTools pipe")
            self._buffer += chunk
        message, self._buffer = self._buffer.split(b"\0", 1)
        return json.loads(message)

    def page(self, method: str, params: dict | None = None) -> dict:
        """A command to the page's session."""
        return self.call(method, params, session=True)

    def evaluate(self, expression: str):
        """The value of a JavaScript expression in the page."""
        result = self.page("Runtime.evaluate", {"expression": expression, "returnByValue": True})
        return result["result"].get("value")

    def wait_for(self, expression: str, timeout: float = 60) -> None:
        """Poll until a JavaScript expression is true; TimeoutError naming it (and the page's
        status line) otherwise."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.evaluate(expression):
                return
            time.sleep(0.05)
        status = self.evaluate("document.getElementById('status') && document.getElementById('status').textContent")
        raise TimeoutError(f"{expression} still false after {timeout} s (page status: {status!r})")

    def type_text(self, text: str) -> None:
        """Type ``text`` key by key into the focused element, then press Enter."""
        for char in text:
            self.page("Input.dispatchKeyEvent", {"type": "keyDown", "key": char, "text": char})
            self.page("Input.dispatchKeyEvent", {"type": "keyUp", "key": char})
        enter = {"key": "Enter", "code": "Enter", "windowsVirtualKeyCode": 13}
        self.page("Input.dispatchKeyEvent", {"type": "keyDown", "text": "\r", **enter})
        self.page("Input.dispatchKeyEvent", {"type": "keyUp", **enter})

    def press(self, key: str, shift: bool = False) -> None:
        """Press and release one printable ``key`` (with Shift held when ``shift``) on the page."""
        event = {"key": key.upper() if shift else key, "modifiers": 8 if shift else 0}
        self.page("Input.dispatchKeyEvent", {"type": "keyDown", "text": event["key"], **event})
        self.page("Input.dispatchKeyEvent", {"type": "keyUp", **event})

    def click(self, element_id: str) -> None:
        """A left click at the centre of the element with id ``element_id``."""
        x, y = self.evaluate(f"(() => {{ const r = document.getElementById({element_id!r}).getBoundingClientRect();"
                             " return [r.x + r.width / 2, r.y + r.height / 2]; })()")
        for kind in ("mousePressed", "mouseReleased"):
            self.page("Input.dispatchMouseEvent", {"type": kind, "x": x, "y": y, "button": "left", "clickCount": 1})

    def drag(self, x0: float, y0: float, x1: float, y1: float, steps: int = 10, until: str | None = None,
             timeout: float = 60) -> None:
        """A left-button mouse drag from (x0, y0) to (x1, y1), page pixels; with ``until`` (a
        JavaScript expression) the mouse keeps moving, a pixel back and forth so that it stays on the
        page, before release, until it is true (TimeoutError after ``timeout`` s): on a busy machine
        one frame can outlast a short drag."""
        def mouse(kind: str, x: float, y: float) -> None:
            self.page("Input.dispatchMouseEvent", {"type": kind, "x": x, "y": y, "button": "left", "buttons": 1,
                                                   "clickCount": 1})
        mouse("mousePressed", x0, y0)
        for i in range(1, steps + 1):
            mouse("mouseMoved", x0 + i / steps * (x1 - x0), y0 + i / steps * (y1 - y0))
            time.sleep(0.03)
        deadline = time.monotonic() + timeout
        while until is not None and not self.evaluate(until):
            if time.monotonic() > deadline:
                raise TimeoutError(f"{until} still false after dragging for {timeout} s")
            x1 += 1
            mouse("mouseMoved", x1, y1)
            time.sleep(0.05)
        mouse("mouseReleased", x1, y1)

    def screenshot(self, element_id: str) -> np.ndarray:
        """A screenshot [H,W,3] float32 in [0,1] of the element with id ``element_id``."""
        box = self.evaluate(f"(() => {{ const r = document.getElementById({element_id!r}).getBoundingClientRect();"
                            " return [r.x, r.y, r.width, r.height]; })()")
        png = self.page("Page.captureScreenshot", {"format": "png", "clip": {
            "x": box[0], "y": box[1], "width": box[2], "height": box[3], "scale": 1}})["data"]
        return np.asarray(imread(io.BytesIO(base64.b64decode(png)), format="png"), np.float32)[..., :3]

    def close(self) -> None:
        """End the browser (it is this object's child) and remove its profile."""
        for fd in (self._send_fd, self._recv_fd):
            os.close(fd)
        self.process.terminate()
        try:
            self.process.wait(10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        self._profile.cleanup()
