"""Static pages in a headless Chromium, for the tests: a screenshot of a page as an RGB array."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np


def browser() -> str | None:
    """The installed Chromium (or Chrome), or None: the tests that need it skip."""
    return next(
        (path for name in ("chromium", "chromium-browser", "google-chrome") if (path := shutil.which(name))), None
    )


def screenshot(page: Path, shot: Path, width: int, height: int) -> np.ndarray:
    """``(height, width, 3)`` RGB [0–255] of ``page`` opened from the file system in a window of that size."""
    from PIL import Image

    subprocess.run(
        [
            browser(),
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--hide-scrollbars",
            f"--window-size={width},{height}",
            f"--screenshot={shot}",
            page.as_uri(),
        ],
        check=True,
        capture_output=True,
        timeout=120,
    )
    return np.asarray(Image.open(shot).convert("RGB"), dtype=float)
