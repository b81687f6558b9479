"""Headless Chromium (Debian's `chromium`) for the viewer's tests: screenshots and the DOM after its scripts ran."""

from __future__ import annotations

import subprocess


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
