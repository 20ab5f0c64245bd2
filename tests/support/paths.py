"""Where things are, for every test: the checkout, the shared Kinetix level files beside it, the test fixtures."""

from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
"""The checkout's root."""
SHARED_LEVELS = REPO.parent / "shared" / "kinetix-levels"
"""Kinetix's own level files (MIT licence), kept outside the repository; tests that need them skip without them."""
FIXTURES = REPO / "tests" / "fixtures"
