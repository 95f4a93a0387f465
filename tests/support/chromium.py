"""Headless Chromium for the tests that look at MLflow's UI: the page a link renders."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
HEADLESS = [  # as the machine notes start it: no sandbox as root, no calls to Google's hosts
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--window-size=1400,900",
]


def rendered(link: str, profile: Path, budget: int = 15000) -> str:
    """The DOM headless Chromium renders at ``link``, with a new browser profile, after
    ``budget`` ms of the page's virtual time (to let the UI's JavaScript fetch and render
    the runs)."""
    time_budget, user = f"--virtual-time-budget={budget}", f"--user-data-dir={profile}"
    page = subprocess.run(
        [CHROMIUM, *HEADLESS, time_budget, user, "--dump-dom", link],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert page.returncode == 0, page.stderr[-2000:]
    return page.stdout
