"""Headless Chromium (Debian's `chromium`) for the viewer's tests: screenshots and the DOM after its scripts ran."""

from __future__ import annotations

import base64
import fcntl
import io
import json
import os
import select
import subprocess
import time

import numpy as np
from PIL import Image

CENTRE = (slice(100, 500), slice(150, 650))  # of an 800 x 600 screenshot: away from the viewer's corner panels
FREE_GREY = 235  # a free (near-white) map pixel is brighter
# The viewer's own word for what it shows (body[data-map]): every tile in view drawn, or the map refused.
VIEWER_SETTLED = "['drawn', 'refused'].includes(document.body && document.body.dataset.map)"
STATUS = "document.body ? `${document.body.dataset.map}: ${document.getElementById('status')?.textContent}` : ''"

FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-dev-shm-usage",
    "--window-size=800,600",
    "--hide-scrollbars",
]


def headless_chromium(tmp_path, *args: str) -> subprocess.CompletedProcess:
    """One run of chromium's own command line (--dump-dom, ...), pages given 8 s of virtual time.

    Virtual time stands still only while a fetch is pending: for pages that wait on a server
    working between requests (the viewer's tiles), use `screenshot`, which waits in real time."""
    command = ["chromium", *FLAGS, f"--user-data-dir={tmp_path / 'profile'}", "--virtual-time-budget=8000", *args]
    return subprocess.run(command, capture_output=True, timeout=120, check=False)


class DevTools:
    """Chromium driven over the DevTools protocol on a pipe (--remote-debugging-pipe): the browser
    reads NUL-terminated JSON commands on its fd 3 and writes replies and events on its fd 4."""

    def __init__(self, tmp_path, reply_timeout_s: float = 30):
        self.reply_timeout_s = reply_timeout_s
        to_browser, self._to_browser = _pipe_above(10)
        self._from_browser, from_browser = _pipe_above(10)

        def as_fds_3_and_4():  # in the child: dup2 leaves the copies inheritable, the originals close on exec
            os.dup2(to_browser, 3)
            os.dup2(from_browser, 4)

        self._process = subprocess.Popen(
            ["chromium", *FLAGS, f"--user-data-dir={tmp_path / 'profile'}", "--remote-debugging-pipe"],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            preexec_fn=as_fds_3_and_4,
            close_fds=False,  # the pipes' ends above 10 close on exec; 3 and 4 must stay
        )
        os.close(to_browser)
        os.close(from_browser)
        self._next_id = 0
        self._read = b""

    def __enter__(self) -> DevTools:
        return self

    def __exit__(self, *exc) -> None:
        try:
            self._process.terminate()
            self._process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()
        finally:
            os.close(self._to_browser)
            os.close(self._from_browser)

    def send(self, method: str, params: dict | None = None, session: str | None = None) -> dict:
        """The result of one command (events that come first are skipped)."""
        self._next_id += 1
        message = {"id": self._next_id, "method": method, "params": params or {}}
        if session:
            message["sessionId"] = session
        os.write(self._to_browser, json.dumps(message).encode() + b"\0")
        while True:
            reply = self._message()
            if reply.get("id") == self._next_id:
                assert "error" not in reply, f"{method}: {reply['error']}"
                return reply["result"]

    def _message(self) -> dict:
        while b"\0" not in self._read:
            if not select.select([self._from_browser], [], [], self.reply_timeout_s)[0]:
                raise TimeoutError(f"chromium sent nothing for {self.reply_timeout_s:g} s")
            chunk = os.read(self._from_browser, 1 << 20)
            assert chunk, "chromium closed its DevTools pipe"
            self._read += chunk
        message, self._read = self._read.split(b"\0", 1)
        return json.loads(message)


def _pipe_above(lowest: int) -> tuple[int, int]:
    """A pipe (read end, write end) on fds >= `lowest`, closed on exec: clear of 3 and 4 in the child."""
    ends = os.pipe()
    moved = tuple(fcntl.fcntl(end, fcntl.F_DUPFD_CLOEXEC, lowest) for end in ends)
    for end in ends:
        os.close(end)
    return moved


def screenshot(tmp_path, url: str, until: str = VIEWER_SETTLED, timeout_s: float = 90) -> np.ndarray:
    """The page at `url` once the script `until` holds there (polled in real time), as headless
    chromium draws it at 800 x 600: (600, 800, 3) int RGB."""
    deadline = time.monotonic() + timeout_s
    with DevTools(tmp_path) as browser:
        page = _settled_page(browser, url, until, deadline)
        png = base64.b64decode(browser.send("Page.captureScreenshot", {"format": "png"}, page)["data"])
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)


def clicked(tmp_path, url: str, at: tuple[int, int], read: str, timeout_s: float = 90):
    """The value of the script `read` once it is not null, after a left click at pixel `at` (x, y)
    of the page at `url` (800 x 600, clicked once the viewer has settled)."""
    deadline = time.monotonic() + timeout_s
    with DevTools(tmp_path) as browser:
        page = _settled_page(browser, url, VIEWER_SETTLED, deadline)
        for kind in ("mousePressed", "mouseReleased"):
            event = {"type": kind, "x": at[0], "y": at[1], "button": "left", "buttons": 1, "clickCount": 1}
            browser.send("Input.dispatchMouseEvent", event, page)
        return _wait(browser, page, f"({read}) ?? null", lambda value: value is not None, deadline)


def _settled_page(browser: DevTools, url: str, until: str, deadline: float) -> str:
    """A new 800 x 600 page at `url`, once the script `until` holds there; its session id."""
    target = browser.send("Target.createTarget", {"url": "about:blank"})["targetId"]
    page = browser.send("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
    metrics = {"width": 800, "height": 600, "deviceScaleFactor": 1, "mobile": False}
    browser.send("Emulation.setDeviceMetricsOverride", metrics, page)
    browser.send("Page.navigate", {"url": url}, page)
    _wait(browser, page, until, lambda value: value is True, deadline)
    return page


def _wait(browser: DevTools, page: str, script: str, done, deadline: float):
    """The value of `script` on the page once done(value), polled every 0.1 s until the deadline."""
    evaluate = {"expression": script, "returnByValue": True}
    while True:
        value = browser.send("Runtime.evaluate", evaluate, page)["result"].get("value")
        if done(value):
            return value
        if time.monotonic() > deadline:
            status = browser.send("Runtime.evaluate", {"expression": STATUS, "returnByValue": True}, page)
            raise AssertionError(f"{script!r} not done by the deadline; the page says {status['result']}")
        time.sleep(0.1)
