"""The documentation site as built by ``python -m sphinx -W -b html docs docs/_build/html``.

Building the site executes every notebook (minutes), so the tests here do not build it: they check the built
site where it exists (``docs/_build/html``, or the folder named by ``LABKIT_DOCS_HTML``) and skip otherwise -
unless ``LABKIT_REQUIRE_DOCS=1`` (CI, after its docs build step), where a missing site fails. They check that
every public name of ``labkit.__all__`` has its page, that every notebook is a page with its figures and its
solutions folded, that the course and guide pages speak without internal references, and - in Debian's
chromium, driven by Playwright - that the front page and a notebook page render with their figures loaded.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from html.parser import HTMLParser
from pathlib import Path

import pytest

import labkit

ROOT = Path(__file__).resolve().parents[1]
SITE = Path(os.environ.get("LABKIT_DOCS_HTML", ROOT / "docs" / "_build" / "html"))
NOTEBOOKS = sorted((ROOT / "notebooks").glob("[0-9][0-9]-*.ipynb"))
CHROMIUM = shutil.which("chromium") or ("/usr/bin/chromium" if Path("/usr/bin/chromium").exists() else None)
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync"]


@pytest.fixture(scope="module")
def site():
    if not (SITE / "index.html").exists():
        if os.environ.get("LABKIT_REQUIRE_DOCS") == "1":
            pytest.fail(f"no built site at {SITE}: run python -m sphinx -W -b html docs docs/_build/html")
        pytest.skip(f"no built site at {SITE} (python -m sphinx -W -b html docs docs/_build/html builds it)")
    return SITE


class _Text(HTMLParser):
    """The visible text of a page (no scripts or styles) and its <img> sources."""

    def __init__(self):
        super().__init__()
        self.text, self.images, self._skip = [], [], 0

    def handle_starttag(self, tag, attrs):
        if tag in ("script", "style"):
            self._skip += 1
        if tag == "img":
            self.images.append(dict(attrs).get("src", ""))

    def handle_endtag(self, tag):
        if tag in ("script", "style"):
            self._skip -= 1

    def handle_data(self, data):
        if not self._skip:
            self.text.append(data)


def _parse(path: Path) -> _Text:
    parser = _Text()
    parser.feed(path.read_text(encoding="utf-8"))
    return parser


def test_every_public_name_has_a_page(site):
    missing = [n for n in labkit.__all__ if not n.startswith("_")
               and not (site / "api" / "generated" / f"labkit.{n}.html").exists()]
    assert not missing, f"no API page for {missing}"
    index = _parse(site / "api" / "index.html")
    assert "gauss_helmert_model" in " ".join(index.text)


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem[:2] for p in NOTEBOOKS])
def test_every_notebook_is_a_page_with_its_figures(site, path):
    page = site / "notebooks" / f"{path.stem}.html"
    assert page.exists(), f"{path.name} has no page on the site"
    parsed = _parse(page)
    figures = [s for s in parsed.images if s.endswith(".png") or s.startswith("data:image/png")]
    assert len(figures) >= 3, f"{path.name}: {len(figures)} figures on its page"
    for src in figures:
        if not src.startswith("data:"):
            assert (page.parent / src).exists(), f"{path.name}: figure {src} missing from the site"
    cells = json.loads(path.read_text(encoding="utf-8"))["cells"]
    n_solutions = sum("solution" in c["metadata"].get("tags", []) for c in cells)
    folded = len(re.findall(r'<details class="[^"]*\bhide\b', page.read_text(encoding="utf-8")))
    assert folded >= n_solutions, f"{n_solutions} solutions, {folded} folded on the page"


def test_site_speaks_without_internal_references(site):
    pages = sorted(site.rglob("*.html"))  # the front page, the guide, the course and the API reference
    assert len(pages) > 100
    bad = {}
    for page in pages:
        text = " ".join(_parse(page).text)
        hits = re.findall(r"\bissue \d+|\bthe seed\b", text, re.IGNORECASE)
        if hits:
            bad[str(page.relative_to(site))] = sorted(set(hits))
    assert not bad, f"internal references on the site: {bad}"


def test_site_loads_nothing_from_the_internet(site):
    """Scripts, style sheets and MathJax come with the site, so it works offline (links may point out)."""
    loaded = re.compile(r'<(?:script[^>]*\ssrc|link[^>]*rel="(?:stylesheet|preload)"[^>]*\shref)="(https?:[^"]*)"')
    bad = {}
    for page in site.rglob("*.html"):
        hits = loaded.findall(page.read_text(encoding="utf-8"))
        if hits:
            bad[str(page.relative_to(site))] = sorted(set(hits))
    assert not bad, f"pages that load from the internet: {dict(list(bad.items())[:3])}"
    assert (site / "_static" / "mathjax" / "tex-chtml.js").exists()


def test_front_page_and_a_notebook_render_in_chromium(site, tmp_path):
    if CHROMIUM is None:
        pytest.skip("no chromium: install Debian's 'chromium' package (apt-get install chromium)")
    sync_api = pytest.importorskip("playwright.sync_api", reason="the 'playwright' Python package is not installed")
    notebook = next((p for p in NOTEBOOKS if p.name.startswith("01-")), NOTEBOOKS[0])
    artifacts = [tmp_path] + ([Path(os.environ["LABKIT_ARTIFACTS"])] if os.environ.get("LABKIT_ARTIFACTS") else [])
    for folder in artifacts:
        folder.mkdir(parents=True, exist_ok=True)
    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1300, "height": 1600})
            # offline, as in a course room without internet: every request that leaves the site fails
            outside = []
            page.route("**/*", lambda route: (route.continue_() if route.request.url.startswith("file:")
                                              else (outside.append(route.request.url), route.abort())))
            # the front page: title, the three ways in, the navigation to the course and the API reference
            page.goto((site / "index.html").as_uri(), wait_until="domcontentloaded", timeout=60_000)
            assert "labkit" in page.title()
            body = page.inner_text("main")
            assert "course" in body and "API reference" in body, body[:500]
            hrefs = page.eval_on_selector_all("a", "els => els.map(e => e.getAttribute('href') || '')")
            assert any(h.startswith("course") for h in hrefs) and any(h.startswith("api/") for h in hrefs), hrefs
            for folder in artifacts:
                page.screenshot(path=str(folder / "docs-front.png"), full_page=False)

            # a notebook page: its figures are decoded images of real size, its solutions folded
            page.goto((site / "notebooks" / f"{notebook.stem}.html").as_uri(), wait_until="domcontentloaded",
                      timeout=60_000)
            page.wait_for_function(
                "() => [...document.querySelectorAll('main img')].some(i => i.complete && i.naturalWidth > 200)",
                timeout=60_000)
            sizes = page.eval_on_selector_all(
                "main img", "els => els.map(i => [i.naturalWidth, i.naturalHeight])")
            assert sum(w > 200 and h > 100 for w, h in sizes) >= 3, sizes
            opened = page.eval_on_selector_all("main details.hide", "els => els.filter(e => e.open).length")
            assert opened == 0, "a solution is open on the page"
            # its equations typeset by MathJax from the site's own files: no raw LaTeX left in the text
            page.wait_for_function("() => document.querySelectorAll('main mjx-container').length > 10",
                                   timeout=60_000)
            raw = page.inner_text("main")
            assert "\\begin{" not in raw and "\\mathbf" not in raw, "math left as raw LaTeX"
            assert not outside, f"the site asked the internet for {outside[:3]}"
            for folder in artifacts:
                page.screenshot(path=str(folder / "docs-notebook.png"), full_page=False)
            assert (tmp_path / "docs-notebook.png").stat().st_size > 10_000
        finally:
            browser.close()
