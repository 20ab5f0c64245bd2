"""A real headless browser for the studio's tests: Debian's chromium driven by Playwright. One browser per use,
its page's script errors collected and checked when it closes."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]
TIMEOUT_MS = 60_000
"""Longest wait of a page action: a first compilation of the S environment on a busy 2-core machine."""


def missing_browser() -> str | None:
    """Why the browser cannot run here (no chromium, no Playwright), or None when it can."""
    if not Path(CHROMIUM).exists() or shutil.which(CHROMIUM) is None:
        return f"no {CHROMIUM}: install Debian's chromium (apt-get install chromium) to run the browser tests"
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "playwright is not installed (pip install -e '.[dev]')"
    return None


@contextmanager
def browser_page(url: str) -> Iterator[Any]:
    """A page of a fresh headless chromium opened at `url`; on leaving, fails if the page's script raised."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": 1180, "height": 760})
        page.set_default_timeout(TIMEOUT_MS)
        errors: list[str] = []
        page.on("pageerror", lambda error: errors.append(str(error)))
        page.goto(url)
        try:
            yield page
        finally:
            browser.close()
        assert errors == [], f"the page raised: {errors}"
