"""Headless Chromium (the distribution's package) driven through selenium and the system chromedriver: for the
browser test and the README screenshot. Needs ``apt-get install chromium chromium-driver`` and the ``dev`` extra.
Nothing is downloaded: the driver is given explicitly, so selenium's own driver manager never runs."""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

CHROMIUM_CANDIDATES = ("chromium", "chromium-browser", "/usr/bin/chromium")
DRIVER_CANDIDATES = ("chromedriver", "/usr/bin/chromedriver", "/usr/lib/chromium/chromedriver")
INSTALL_HINT = "apt-get install chromium chromium-driver"
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-dev-shm-usage", "--hide-scrollbars")


def _find(candidates: tuple[str, ...]) -> str | None:
    for name in candidates:
        found = shutil.which(name) or (name if Path(name).is_file() else None)
        if found:
            return found
    return None


def missing() -> str | None:
    """Why a headless browser cannot be driven here (with the fix), or None when it can."""
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "selenium is not installed (pip install -e '.[dev]')"
    if _find(CHROMIUM_CANDIDATES) is None:
        return f"Chromium is not installed ({INSTALL_HINT})"
    if _find(DRIVER_CANDIDATES) is None:
        return f"chromedriver is not installed ({INSTALL_HINT})"
    return None


@contextmanager
def chromium(width: int = 1400, height: int = 1000) -> Iterator[Any]:
    """A selenium WebDriver on headless Chromium with a fresh profile; quits and removes the profile after."""
    problem = missing()
    if problem is not None:
        raise RuntimeError(problem)
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    profile = tempfile.mkdtemp(prefix="fedrl-chromium-")
    options = webdriver.ChromeOptions()
    options.binary_location = _find(CHROMIUM_CANDIDATES) or ""
    for flag in (*FLAGS, f"--user-data-dir={profile}", f"--window-size={width},{height}"):
        options.add_argument(flag)
    driver = webdriver.Chrome(options=options, service=Service(executable_path=_find(DRIVER_CANDIDATES)))
    try:
        yield driver
    finally:
        try:
            driver.quit()
        finally:
            shutil.rmtree(profile, ignore_errors=True)


def page_state(driver: Any) -> dict[str, Any]:
    """What the page shows, read from its DOM: workers (id -> state, points), points drawn, rounds, rigs."""
    return driver.execute_script("""
        const rows = Array.from(document.querySelectorAll('#workers tbody tr'));
        const canvas = document.getElementById('curves');
        return {
          workers: Object.fromEntries(rows.map(r => [r.dataset.worker,
                     {state: r.dataset.state, points: Number(r.dataset.points)}])),
          drawn: Number(canvas.dataset.points || 0),
          rounds: document.querySelectorAll('#rounds tbody tr').length,
          transfers: document.querySelectorAll('#transfers tbody tr').length,
          rigs: Array.from(document.querySelectorAll('#rigs tbody tr')).map(r => r.dataset.rig),
          phase: document.getElementById('run-phase').textContent,
          connected: document.getElementById('conn').classList.contains('on'),
          probe: window.fedrlDashboard || null,
        };""")
