"""Check the report site in a real browser: open `<reports>/index.html` in headless Chromium, follow every
link to a local page (breadth first, each page once), and fail on a linked page that does not exist, an
image that did not load (`naturalWidth == 0`) or whose longer side is below 256 px (a thumbnail no one can
read), a table without a row, text cut by a box that hides its overflow, a console error (or an uncaught
exception), or a page wider than a 1280 px window (a wide table must scroll inside the page).

    python scripts/check_site.py reports [--screenshots DIR]

Prints one line per problem and exits 1 when there is any, else prints what it checked and exits 0; exit 2
when the folder has no index.html or no browser can be started. The browser is the system's Chromium
(Debian's `chromium` package; `.ci/run` installs it), driven by the `playwright` package (a dev
dependency): no browser is downloaded. `--screenshots DIR` also saves a full-page PNG of the index and of
the first report page it reaches.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from collections import deque
from pathlib import Path
from urllib.parse import unquote, urldefrag, urlparse

#: The images of a page that did not load: not complete, or complete with no pixels (a broken src).
BROKEN_IMAGES = """() => Array.from(document.images)
    .filter(img => !img.complete || img.naturalWidth === 0)
    .map(img => (img.getAttribute('src') || '').slice(0, 120))"""
LINKS = "() => Array.from(document.querySelectorAll('a[href]')).map(a => a.href)"
IMAGE_COUNT = "() => document.images.length"
#: How far the page reaches past the window's right edge: a table that does not fit must scroll in its box.
OVERFLOW = "() => document.documentElement.scrollWidth - window.innerWidth"
WIDTH = 1280
#: The smallest figure a reader can look at: an image whose longer side is below it is a thumbnail.
MIN_IMAGE_PX = 256
SMALL_IMAGES = f"""() => Array.from(document.images)
    .filter(img => img.complete && img.naturalWidth > 0
                   && Math.max(img.naturalWidth, img.naturalHeight) < {MIN_IMAGE_PX})
    .map(img => (img.getAttribute('alt') || img.getAttribute('src') || '').slice(0, 80)
                + ' (' + img.naturalWidth + 'x' + img.naturalHeight + ' px)')"""
#: Tables without a body row: a page never shows an empty table (it says why there is none instead).
EMPTY_TABLES = """() => Array.from(document.querySelectorAll('table'))
    .filter(t => t.querySelectorAll('tbody tr').length === 0)
    .map(t => (t.querySelector('thead') || t).innerText.replace(/\\s+/g, ' ').slice(0, 80))"""
#: Text cut by its box: an element that hides its overflow (CSS overflow hidden or clip) while its content
#: is wider or taller than it (a box that scrolls, like the tables' `.scroll`, shows all of it).
CLIPPED = """() => Array.from(document.querySelectorAll('body *'))
    .filter(el => { const s = getComputedStyle(el);
                    const hides = v => v === 'hidden' || v === 'clip';
                    return (hides(s.overflowX) && el.scrollWidth > el.clientWidth + 1)
                        || (hides(s.overflowY) && el.scrollHeight > el.clientHeight + 1); })
    .map(el => el.tagName.toLowerCase() + ': ' + (el.innerText || '').replace(/\\s+/g, ' ').slice(0, 60))"""


def local_path(url: str, root: Path) -> Path | None:
    """The file a `file://` link points to when it lies under `root` (without its #fragment), else None
    (another scheme, or outside the site)."""
    url, _ = urldefrag(url)
    parsed = urlparse(url)
    if parsed.scheme != "file":
        return None
    path = Path(unquote(parsed.path)).resolve()
    return path if path.is_relative_to(root) else None


def check_site(root: Path, screenshots: Path | None = None) -> tuple[list[str], dict[str, int]]:
    """(problems, counts of pages, links and images checked) of the site under `root`."""
    from playwright.sync_api import sync_playwright

    root = root.resolve()
    start = root / "index.html"
    problems: list[str] = []
    counts = {"pages": 0, "links": 0, "images": 0}
    executable = shutil.which("chromium") or shutil.which("chromium-browser")
    if executable is None:
        raise RuntimeError("no chromium on PATH (apt-get install -y --no-install-recommends chromium)")
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=executable, headless=True)
        page = browser.new_page(viewport={"width": WIDTH, "height": 900})
        errors: list[str] = []
        page.on("console", lambda msg: errors.append(msg.text) if msg.type == "error" else None)
        page.on("pageerror", lambda err: errors.append(str(err)))
        queue, seen, shot_report = deque([start]), {start}, False
        while queue:
            path = queue.popleft()
            name = path.relative_to(root).as_posix()
            errors.clear()
            page.goto(path.as_uri(), wait_until="load")
            counts["pages"] += 1
            counts["images"] += page.evaluate(IMAGE_COUNT)
            problems += [f"{name}: image did not load: {src}" for src in page.evaluate(BROKEN_IMAGES)]
            problems += [f"{name}: console error: {text}" for text in errors]
            if (overflow := page.evaluate(OVERFLOW)) > 0:
                problems.append(f"{name}: page {overflow} px wider than a {WIDTH} px window")
            problems += [
                f"{name}: image below {MIN_IMAGE_PX} px: {text}" for text in page.evaluate(SMALL_IMAGES)
            ]
            problems += [f"{name}: empty table: {text}" for text in page.evaluate(EMPTY_TABLES)]
            problems += [f"{name}: clipped text: {text}" for text in page.evaluate(CLIPPED)]
            if screenshots is not None and (path == start or (not shot_report and path.parent != root)):
                screenshots.mkdir(parents=True, exist_ok=True)
                target = "index.png" if path == start else "report.png"
                page.screenshot(path=str(screenshots / target), full_page=True)
                shot_report = shot_report or path != start
            for href in page.evaluate(LINKS):
                target = local_path(href, root)
                if target is None:
                    continue
                counts["links"] += 1
                if not target.exists():
                    problems.append(f"{name}: link to a missing page: {target.relative_to(root).as_posix()}")
                elif target.suffix == ".html" and target not in seen:
                    seen.add(target)
                    queue.append(target)
        browser.close()
    return problems, counts


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("reports", type=Path, help="the reports folder (report.out_dir), with index.html")
    parser.add_argument("--screenshots", type=Path, default=None, help="save index.png and report.png here")
    args = parser.parse_args(argv)
    if not (args.reports / "index.html").is_file():
        print(f"check_site: {args.reports}/index.html: no such file (build a report or the ledger first)")
        return 2
    try:
        problems, counts = check_site(args.reports, args.screenshots)
    except Exception as err:  # no browser, no playwright: cannot check, which is not a pass
        print(f"check_site: cannot run the browser ({type(err).__name__}: {str(err).splitlines()[0]})")
        return 2
    for problem in problems:
        print(f"check_site: {problem}")
    summary = f"{counts['pages']} pages, {counts['links']} local links, {counts['images']} images"
    if problems:
        print(f"check_site: FAILED, {len(problems)} problems in {summary}")
        return 1
    print(f"check_site: ok, {summary}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
