"""Headless Chromium screenshots of the report and the viewer (Debian `chromium`).

Chromium is driven over its DevTools protocol (a websocket, through `websockets`, which viser already
needs): load the page, wait for its load event and `settle_ms`, then take pictures until one is ready
(by default: not one flat colour; a caller can ask for more, e.g. "the 3D canvas shows the splats"), in
real time, up to `timeout_s`. Chromium's own `--screenshot --virtual-time-budget` was used before: a page
that animates and streams over a websocket (the viewer) could keep virtual time from ever reaching the
budget on a loaded machine, so Chromium neither wrote a picture nor exited (three 45 s tries in a row in
CI). Here every step has its own time-out, a Chromium that stops answering is killed and started again,
and the error says what Chromium printed.

Background networking is switched off: the machines have no network beyond package registries, and
Chromium's own update/sync connections would otherwise hang or fail at start-up.
"""

from __future__ import annotations

import base64
import io as _io
import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from splattwin.errors import InputError

CHROMIUM_CANDIDATES = ("chromium", "chromium-browser", "google-chrome")
START_TIMEOUT_S = 30.0   # Chromium writing its DevTools port (~1 s normally)
CALL_TIMEOUT_S = 30.0    # one DevTools command (a screenshot of a busy WebGL page takes a few seconds)
POLL_S = 0.5             # between pictures that are not ready yet
MAX_TRIES = 3            # Chromium started at most this often for one picture
MAX_MESSAGE = 256 << 20  # a base64 PNG of a tall report page

Ready = Callable[[np.ndarray], bool]


def find_chromium() -> str:
    for name in CHROMIUM_CANDIDATES:
        p = shutil.which(name)
        if p:
            return p
    raise InputError("no Chromium found on PATH (Debian: apt-get install chromium)")


def not_blank(rgb: np.ndarray) -> bool:
    """True unless the picture (H, W, 3) uint8 is one flat colour (nothing drawn yet)."""
    return bool((rgb != rgb.reshape(-1, 3)[0]).any())


def screenshot(url: str, out_png: str | Path, width: int = 1280, height: int = 900, settle_ms: int = 2000,
               timeout_s: float = 120.0, ready: Ready | None = None) -> Path:
    """Load `url` (http:// or file://) in headless Chromium at `width` x `height` CSS px and save a PNG of
    the viewport to `out_png` (written atomically; an old file there is removed first, so it never passes
    for a new picture).

    The first picture is taken `settle_ms` after the page's load event, then one every 0.5 s until
    `ready(rgb)` ((H, W, 3) uint8; default `not_blank`) holds. When `timeout_s` runs out the last picture
    is saved if there is one (the caller judges it); RuntimeError when Chromium gave none, with what it
    printed."""
    from splattwin import io

    out_png = Path(out_png).resolve()
    out_png.parent.mkdir(parents=True, exist_ok=True)
    out_png.unlink(missing_ok=True)
    png = _capture(url, width, height, settle_ms / 1000.0, timeout_s, ready or not_blank)
    io.write_bytes(out_png, png)
    return out_png


def _capture(url: str, width: int, height: int, settle_s: float, timeout_s: float, ready: Ready) -> bytes:
    """`screenshot`'s tries (at most MAX_TRIES Chromiums): PNG bytes of the first ready picture, else the
    last one (RuntimeError if none)."""
    deadline = time.monotonic() + timeout_s
    last, problems = None, []
    for _ in range(MAX_TRIES):
        if time.monotonic() >= deadline:
            break
        try:
            last, done = _one_try(url, width, height, settle_s, deadline, ready, last)
            if done:
                return last
            break   # Chromium kept answering; the page never got ready in time
        except _Stuck as e:
            problems.append(str(e))
    if last is not None:
        return last
    raise RuntimeError(f"chromium produced no screenshot for {url} within {timeout_s:.0f} s: "
                       + " | ".join(problems[-3:] or ["no try could start"]))


class _Stuck(Exception):
    """Chromium did not start or stopped answering (it is killed and started again)."""


def _one_try(url, width, height, settle_s, deadline, ready, last):
    from websockets.exceptions import WebSocketException
    from websockets.sync.client import connect

    with tempfile.TemporaryDirectory(prefix="splattwin-chromium-") as profile:
        log_path = Path(profile) / "chromium.log"
        cmd = [find_chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
               "--disable-background-networking", "--disable-component-update", "--disable-sync",
               "--disable-quic", "--no-first-run", "--hide-scrollbars", "--enable-unsafe-swiftshader",
               "--remote-debugging-port=0", f"--user-data-dir={profile}/data", f"--window-size={width},{height}",
               "about:blank"]
        with open(log_path, "wb") as log:
            proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=log, stderr=log, start_new_session=True)
        try:
            try:
                ws_url = _devtools_url(Path(profile) / "data", proc, min(deadline, time.monotonic() + START_TIMEOUT_S))
                with connect(ws_url, max_size=MAX_MESSAGE, open_timeout=CALL_TIMEOUT_S, proxy=None) as ws:
                    return _drive(_Cdp(ws), url, width, height, settle_s, deadline, ready, last)
            except (_Stuck, OSError, TimeoutError, EOFError, WebSocketException) as e:   # incl. Chromium dying
                raise _Stuck(f"{type(e).__name__}: {e}; chromium printed: {_tail(log_path)}") from None
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def _devtools_url(data_dir: Path, proc: subprocess.Popen, until: float) -> str:
    """The browser's DevTools websocket, from the DevToolsActivePort file Chromium writes at start-up."""
    port_file = data_dir / "DevToolsActivePort"
    while time.monotonic() < until:
        if proc.poll() is not None:
            raise _Stuck(f"chromium exited with code {proc.returncode} at start-up")
        try:
            lines = port_file.read_text().split("\n")
            if len(lines) >= 2 and lines[0].strip().isdigit() and lines[1].startswith("/"):
                return f"ws://127.0.0.1:{int(lines[0])}{lines[1].strip()}"
        except OSError:
            pass
        time.sleep(0.05)
    raise _Stuck("chromium did not open its DevTools port")


def _tail(log_path: Path, n: int = 600) -> str:
    try:
        text = log_path.read_bytes()[-n:].decode("utf-8", "replace").strip()
    except OSError:
        return "(no log)"
    return " / ".join(text.splitlines()[-4:]) or "(nothing)"


class _Cdp:
    """Just enough of the DevTools protocol: numbered commands on one flat session, events kept aside."""

    def __init__(self, ws):
        self.ws, self.next_id, self.events = ws, 0, []

    def _recv(self, until: float) -> dict:
        left = until - time.monotonic()
        if left <= 0:
            raise TimeoutError("no answer from chromium")
        return json.loads(self.ws.recv(timeout=left))

    def call(self, method: str, params: dict | None = None, session: str | None = None,
             timeout_s: float = CALL_TIMEOUT_S) -> dict:
        self.next_id += 1
        msg = {"id": self.next_id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        self.ws.send(json.dumps(msg))
        until = time.monotonic() + timeout_s
        while True:
            m = self._recv(until)
            if m.get("id") == self.next_id:
                if "error" in m:
                    raise RuntimeError(f"chromium: {method} failed: {m['error'].get('message')}")
                return m.get("result", {})
            if "method" in m:
                self.events.append(m)

    def wait_event(self, method: str, until: float) -> bool:
        """True once `method` has been seen (False when `until` passes first)."""
        while True:
            if any(e.get("method") == method for e in self.events):
                return True
            try:
                m = self._recv(until)
            except TimeoutError:
                return False
            if "method" in m:
                self.events.append(m)


def _drive(cdp: _Cdp, url, width, height, settle_s, deadline, ready, last):
    """Open `url` in a new page, then picture it until ready: (png bytes or `last`, ready?)."""
    from PIL import Image

    target = cdp.call("Target.createTarget", {"url": "about:blank"})["targetId"]
    session = cdp.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
    cdp.call("Page.enable", session=session)
    cdp.call("Emulation.setDeviceMetricsOverride",
             {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False}, session=session)
    nav = cdp.call("Page.navigate", {"url": url}, session=session)
    # a page that cannot be loaded (a missing file) still shows Chromium's error page, which is pictured
    if not nav.get("errorText"):
        cdp.wait_event("Page.loadEventFired", min(deadline, time.monotonic() + CALL_TIMEOUT_S))
    time.sleep(max(0.0, min(settle_s, deadline - time.monotonic())))
    while True:
        shot = cdp.call("Page.captureScreenshot", {"format": "png"}, session=session,
                        timeout_s=max(1.0, min(CALL_TIMEOUT_S, deadline - time.monotonic() + 1.0)))
        last = base64.b64decode(shot["data"])
        with Image.open(_io.BytesIO(last)) as im:
            rgb = np.asarray(im.convert("RGB"))
        if ready(rgb):
            return last, True
        if time.monotonic() + POLL_S >= deadline:
            return last, False
        time.sleep(POLL_S)
