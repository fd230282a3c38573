"""Headless Chromium for the browser tests (Debian's package; .ci/run installs it)."""

from __future__ import annotations

import shutil


def chromium() -> str | None:
    """The Chromium binary, or None when it is not installed."""
    for name in ("/usr/bin/chromium", "chromium", "chromium-browser"):
        found = shutil.which(name)
        if found:
            return found
    return None
