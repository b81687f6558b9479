"""Headless Chromium (Debian's `chromium`) for the viewer's tests: screenshots and the DOM after its scripts ran."""

from __future__ import annotations

import subprocess

import numpy as np
from PIL import Image

CENTRE = (slice(100, 500), slice(150, 650))  # of an 800 x 600 screenshot: away from the viewer's corner panels
FREE_GREY = 235  # a free (near-white) map pixel is brighter


def headless_chromium(tmp_path, *args: str) -> subprocess.CompletedProcess:
    command = [
        "chromium",
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--disable-dev-shm-usage",
        f"--user-data-dir={tmp_path / 'profile'}",
        "--window-size=800,600",
        "--hide-scrollbars",
        "--virtual-time-budget=8000",
        *args,
    ]
    return subprocess.run(command, capture_output=True, timeout=120, check=False)


def screenshot(tmp_path, url: str) -> np.ndarray:
    """The page at `url` as headless chromium draws it: (600, 800, 3) int RGB."""
    shot = tmp_path / "viewer.png"
    headless_chromium(tmp_path, f"--screenshot={shot}", url)
    assert shot.exists(), "chromium wrote no screenshot"
    return np.asarray(Image.open(shot).convert("RGB")).astype(int)
