"""Screenshots of the documentation site as a reader sees it, taken with headless Chromium.

``python docs/screenshots.py [--site DIR] [--out DIR]`` builds the site with ``mkdocs build
--strict`` (unless ``--site`` names one already built) and writes one PNG per page of
:data:`PAGES` to ``--out`` (default ``out/screenshots``): the front page and a how-to, at a
laptop's window size, through the tests' own Chromium driver (``tests/browser.py``).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the checkout's tests/browser.py: one way to drive Chromium, the tests' too

from tests.browser import browser, screenshot  # noqa: E402 (the checkout joins sys.path first)

#: page (its source under docs/) → the PNG's name
PAGES = {"index.md": "front-page.png", "howto/motion-capture.md": "howto-motion-capture.png"}
WINDOW = (1280, 1600)


def build_site(site: Path) -> None:
    """``mkdocs build --strict`` of the checkout into ``site``."""
    subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet", "--site-dir", str(site)],
        cwd=ROOT,
        check=True,
    )


def page_file(site: Path, source: str) -> Path:
    """The HTML file mkdocs writes for ``source`` (directory URLs: ``howto/x.md`` → ``howto/x/index.html``)."""
    stem = source.removesuffix(".md")
    return site / "index.html" if stem == "index" else site / stem / "index.html"


def take(site: Path, out: Path) -> list[Path]:
    """Screenshots of :data:`PAGES` of the built ``site`` into ``out``; returns their paths."""
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for source, name in PAGES.items():
        html = page_file(site, source)
        if not html.is_file():
            raise SystemExit(f"{html}: not in the built site (is {source} in mkdocs.yml's nav?)")
        screenshot(html, out / name, *WINDOW)
        written.append(out / name)
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--site", type=Path, help="a site already built (default: build one)")
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "screenshots")
    args = parser.parse_args(argv)
    if browser() is None:
        print("screenshots: no chromium on the path (Debian: apt-get install chromium)", file=sys.stderr)
        return 1
    with tempfile.TemporaryDirectory() as tmp:
        site = args.site or Path(tmp) / "site"
        if args.site is None:
            build_site(site)
        for png in take(site, args.out):
            print(png)
    return 0


if __name__ == "__main__":
    sys.exit(main())
