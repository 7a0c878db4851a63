"""The documentation site as a reader sees it (mkdocs.yml; docs/screenshots.py, docs/griffe_rst.py).

`.ci/run` builds the site with ``mkdocs build --strict`` after the tests; here, where the docs
extra and Chromium are installed, the front page and a how-to are photographed in headless
Chromium and the pictures checked for what a reader must see: the theme's header, a page of text.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "docs" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def test_sphinx_roles_and_literal_markers_read_as_markdown():
    pytest.importorskip("griffe")
    rst = _load("griffe_rst")
    text = (
        "Use :class:`~stewart_calib.workflows.online.OnlineCalibrator` and :func:`.base.residual`;"
        " :meth:`x.y` too.\n\nFor users::\n\n    calib.update(sample)\n\n::\n\n    code\n"
    )
    assert rst.markdown(text) == (
        "Use `OnlineCalibrator` and `.base.residual`; `x.y` too.\n\nFor users:\n\n    calib.update(sample)\n\n\n\n"
        "    code\n"
    )
    assert rst.markdown("a C++ name a::b stays") == "a C++ name a::b stays"


def test_screenshots_show_the_front_page_and_a_howto(tmp_path):
    pytest.importorskip("mkdocs")
    pytest.importorskip("material")
    PIL = pytest.importorskip("PIL.Image")
    from tests.browser import browser

    if browser() is None:
        pytest.skip("no chromium on the path (Debian: apt-get install chromium)")
    screenshots = _load("screenshots")
    assert screenshots.main(["--out", str(tmp_path)]) == 0
    for name in screenshots.PAGES.values():
        pixels = np.asarray(PIL.open(tmp_path / name).convert("RGB")).astype(int)
        assert pixels.shape == (screenshots.WINDOW[1], screenshots.WINDOW[0], 3), name
        # the header bar in the theme's indigo (#3f51b5): the stylesheet loaded from the site itself
        assert np.abs(pixels[10, 10] - [63, 81, 181]).max() <= 2, (name, pixels[10, 10])
        # below it, a page of text: dark glyphs on white, neither a blank page nor an error page
        body = pixels[100:]
        dark = (body.max(axis=2) < 100).mean()
        white = (body.min(axis=2) > 245).mean()
        assert 0.01 < dark < 0.3 and white > 0.5, (name, dark, white)
