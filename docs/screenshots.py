"""Screenshots of the documentation site as a reader sees it, taken with headless Chromium.

``python docs/screenshots.py [--site DIR] [--out DIR]`` builds the site with ``mkdocs build
--strict`` (unless ``--site`` names one already built) and writes one PNG per page of
:data:`PAGES` to ``--out`` (default ``out/screenshots``): the front page and a how-to, at a
laptop's window size. Chromium runs without its sandbox, which needs a user namespace that a
container or a root shell does not give it.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: page (its source under docs/) → the PNG's name
PAGES = {"index.md": "front-page.png", "howto/motion-capture.md": "howto-motion-capture.png"}
WINDOW = (1280, 1600)


def chromium() -> str | None:
    """The Chromium executable on the path (Debian's ``chromium``, or ``chromium-browser``)."""
    return shutil.which("chromium") or shutil.which("chromium-browser")


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


def screenshot(browser: str, html: Path, png: Path, window: tuple[int, int] = WINDOW) -> None:
    """One PNG of ``html`` as Chromium draws it in a ``window``-sized viewport."""
    with tempfile.TemporaryDirectory() as profile:  # no state from, or left for, another run
        subprocess.run(
            [
                browser,
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--hide-scrollbars",
                f"--user-data-dir={profile}",
                f"--window-size={window[0]},{window[1]}",
                f"--screenshot={png}",
                html.as_uri(),
            ],
            check=True,
            capture_output=True,
            timeout=120,
        )


def take(site: Path, out: Path, browser: str) -> list[Path]:
    """Screenshots of :data:`PAGES` of the built ``site`` into ``out``; returns their paths."""
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for source, name in PAGES.items():
        html = page_file(site, source)
        if not html.is_file():
            raise SystemExit(f"{html}: not in the built site (is {source} in mkdocs.yml's nav?)")
        screenshot(browser, html, out / name)
        written.append(out / name)
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--site", type=Path, help="a site already built (default: build one)")
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "screenshots")
    args = parser.parse_args(argv)
    browser = chromium()
    if browser is None:
        print("screenshots: no chromium on the path (Debian: apt-get install chromium)", file=sys.stderr)
        return 1
    with tempfile.TemporaryDirectory() as tmp:
        site = args.site or Path(tmp) / "site"
        if args.site is None:
            build_site(site)
        for png in take(site, args.out, browser):
            print(png)
    return 0


if __name__ == "__main__":
    sys.exit(main())
