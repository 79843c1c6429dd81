"""Headless Chromium screenshots of the report and the viewer (Debian `chromium`).

Background networking is switched off: the machines have no network beyond package registries, and
Chromium's own update/sync connections would otherwise hang or fail at start-up.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import tempfile
from pathlib import Path

from splattwin.errors import InputError

CHROMIUM_CANDIDATES = ("chromium", "chromium-browser", "google-chrome")


def find_chromium() -> str:
    for name in CHROMIUM_CANDIDATES:
        p = shutil.which(name)
        if p:
            return p
    raise InputError("no Chromium found on PATH (Debian: apt-get install chromium)")


def _blank(png: Path) -> bool:
    """True when the picture is one flat colour (nothing rendered yet)."""
    from PIL import Image

    with Image.open(png) as im:
        return all(lo == hi for lo, hi in im.convert("RGB").getextrema())


def screenshot(url: str, out_png: str | Path, width: int = 1280, height: int = 900, budget_ms: int = 15000,
               timeout_s: float = 120.0) -> Path:
    """Load `url` (http:// or file://) in headless Chromium and save a PNG screenshot. Each try is given
    max(45 s, 3x its virtual-time budget), at most `timeout_s`: a Chromium that hangs (seen with the viewer's
    page: ~10 s normally, now and then the full 120 s) is retried sooner."""
    from splattwin import io

    out_png = Path(out_png).resolve()
    out_png.parent.mkdir(parents=True, exist_ok=True)
    out_png.unlink(missing_ok=True)  # an old picture must not pass for a new one
    # Chromium writes the picture itself: into a temporary file beside the target, renamed onto it when
    # done, so a killed run never leaves a half-written PNG under the artifact's name
    with io.atomic_path(out_png) as shot:
        shot.unlink()   # absent until Chromium writes it: a missing file is "no picture"
        _shoot(url, shot, width, height, budget_ms, timeout_s)
    return out_png


def _shoot(url: str, out_png: Path, width: int, height: int, budget_ms: int, timeout_s: float) -> None:
    """`screenshot`'s tries, Chromium writing to `out_png` (RuntimeError when none gave a picture)."""
    # A page that animates (the viewer's WebGL canvas) can keep a loaded machine from ever reaching the
    # virtual-time budget: on a time-out try again with a smaller budget. A page whose scripts had not
    # drawn anything yet when the budget ran out (one flat colour) gets a longer budget.
    budget, last_blank = budget_ms, None
    for _ in range(3):
        with tempfile.TemporaryDirectory(prefix="splattwin-chromium-") as profile:
            cmd = [find_chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                   "--disable-background-networking", "--disable-component-update", "--disable-sync",
                   "--disable-quic", "--no-first-run", "--hide-scrollbars", "--enable-unsafe-swiftshader",
                   f"--user-data-dir={profile}", f"--window-size={width},{height}",
                   f"--virtual-time-budget={budget}", f"--screenshot={out_png}", url]
            proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
            try:
                proc.wait(timeout=min(timeout_s, max(45.0, 3.0 * budget / 1000.0)))
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        if not out_png.is_file():
            budget = max(budget // 4, 1000)
        elif _blank(out_png):
            last_blank = out_png.read_bytes()
            out_png.unlink()
            budget *= 2
        else:
            break
    if not out_png.is_file() and last_blank is not None:  # blank every time: hand back what the page showed
        out_png.write_bytes(last_blank)
    if not out_png.is_file():
        raise RuntimeError(f"chromium produced no screenshot for {url}")
