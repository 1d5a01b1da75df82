"""The formulas of the documentation render: typeset by the site's own KaTeX in a real browser.

The docs write mathematics as LaTeX (``$...$`` inline, ``$$...$$`` display);
``pymdownx.arithmatex`` wraps each formula in an ``.arithmatex`` element and the vendored
KaTeX (``docs/assets/vendor/katex``) typesets it when the page loads. Here the site built by
``mkdocs build --strict`` (once per test run, shared with ``tests/docs/test_docs.py``) is opened
in headless Chromium and the DOM after its scripts ran is read (``--dump-dom``). A page
fails on raw or broken maths: TeX left in the visible text (``$``-delimited, ``\\(``,
``\\frac``-style control words), a KaTeX error node (``.katex-error``, ``merror``), or fewer
typeset formulas than its Markdown source has. A page must also load nothing from another
host (no CDN script, stylesheet or web font): the site works offline.

Chromium is a system package (Debian: ``chromium``); without it the browser tests skip,
unless ``TWINFALSIFY_REQUIRE_BROWSER=1`` (CI sets it), when they fail.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import pytest
from helpers.docs import build_site, require_mkdocs
from helpers.paths import ROOT
from helpers.workflow import built_once

DOCS = ROOT / "docs"

# pages whose formulas the test reads in the browser, with the fewest formulas each must
# have (a floor, so that a page whose maths went back to plain text fails)
PAGES = {
    "explanation/statistics.md": 150,
    "explanation/sequential.md": 100,
    "explanation/method.md": 20,
    "explanation/calibration.md": 5,
    "explanation/implementation.md": 5,
    "how-to/twins.md": 5,
    "how-to/mimic3.md": 1,
}

_FENCE = re.compile(r"^(```|~~~).*?^\1[ \t]*$", re.MULTILINE | re.DOTALL)
_INLINE_CODE = re.compile(r"(`+)(?:.+?)\1", re.DOTALL)
_DISPLAY = re.compile(r"(?<!\\)\$\$(.+?)(?<!\\)\$\$", re.DOTALL)
# arithmatex's "smart dollar" rule: no space just inside the dollars, no escaped dollar
_INLINE = re.compile(r"(?<![\\$])\$(?![\s$])((?:\\.|[^\\$])+?)(?<![\s\\])\$(?!\$)")


def formulas_in_markdown(text: str) -> int:
    """How many formulas a Markdown page holds: ``$$...$$`` blocks and ``$...$`` spans
    outside code (fenced blocks and inline code are not maths)."""
    text = _FENCE.sub("", text)
    text = _INLINE_CODE.sub("", text)
    n_display = len(_DISPLAY.findall(text))
    text = _DISPLAY.sub(" ", text)
    return n_display + len(_INLINE.findall(text))


_SKIP_TEXT = {"code", "pre", "script", "style", "kbd", "samp", "annotation", "math"}
_VOID = {"area", "base", "br", "col", "embed", "hr", "img", "input", "link", "meta", "source",
         "track", "wbr"}  # fmt: skip


class _MathsDom(HTMLParser):
    """Counts the formulas of a rendered page and collects its visible non-maths text."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.stack: list[tuple[str, set[str]]] = []
        self.formulas = 0  # .arithmatex elements
        self.typeset = 0  # .arithmatex elements holding KaTeX output
        self.errors: list[str] = []
        self.text: list[str] = []
        self._open_formula: list[int] = []  # stack depth of each open .arithmatex
        self._typeset_flag: list[bool] = []
        self.remote: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        classes = set((a.get("class") or "").split())
        for key in ("src", "href"):
            url = a.get(key) or ""
            if tag in {"script", "link", "img"} and re.match(r"(https?:)?//", url) \
                    and (tag != "link" or (a.get("rel") or "") in {"stylesheet", "preload"}):
                self.remote.append(f"<{tag} {key}={url}>")
        if "katex-error" in classes or tag == "merror":
            self.errors.append(a.get("title") or tag)
        if "katex" in classes and self._typeset_flag:
            self._typeset_flag[-1] = True
        if tag in _VOID:
            return
        self.stack.append((tag, classes))
        if "arithmatex" in classes:
            self.formulas += 1
            self._open_formula.append(len(self.stack))
            self._typeset_flag.append(False)

    def handle_endtag(self, tag: str) -> None:
        if tag in _VOID:
            return
        while self.stack:
            depth = len(self.stack)
            open_tag, _ = self.stack.pop()
            if self._open_formula and self._open_formula[-1] == depth:
                self._open_formula.pop()
                self.typeset += self._typeset_flag.pop()
            if open_tag == tag:
                break

    def handle_data(self, data: str) -> None:
        if any(t in _SKIP_TEXT or "katex" in c for t, c in self.stack):
            return
        self.text.append(data)


def problems_in_rendered_page(dom: str, expected: int) -> list[str]:
    """Everything wrong with the maths of one rendered page (empty when it is right)."""
    parser = _MathsDom()
    parser.feed(dom)
    parser.close()
    out = []
    text = re.sub(r"\s+", " ", " ".join(parser.text))
    for m in re.finditer(r"\$\$|\$[^\s$][^$\n]*\$|\\[()\[\]]|\\[A-Za-z]{2,}", text):
        start = max(0, m.start() - 40)
        out.append(f"raw TeX in the text: ...{text[start:m.end() + 40]}...")
    out += [f"KaTeX error: {e}" for e in parser.errors]
    if parser.typeset < parser.formulas:
        out.append(f"{parser.formulas - parser.typeset} of {parser.formulas} formulas not "
                   f"typeset")
    if parser.typeset < expected:
        out.append(f"{parser.typeset} formulas typeset, the Markdown source has {expected}")
    out += [f"loads from another host: {r}" for r in parser.remote]
    return out


def _chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        if path := shutil.which(name):
            return path
    return None


def _dump_dom(browser: str, page: Path, profile: Path) -> str:
    out = subprocess.run(
        [browser, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
         "--no-first-run", "--disable-background-networking", "--disable-component-update",
         "--disable-sync", f"--user-data-dir={profile}", "--virtual-time-budget=5000",
         "--dump-dom", page.as_uri()],
        capture_output=True, text=True, timeout=120)  # fmt: skip
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout


@pytest.fixture(scope="module")
def browser() -> str:
    path = _chromium()
    if path is None:
        if os.environ.get("TWINFALSIFY_REQUIRE_BROWSER") == "1":
            pytest.fail("TWINFALSIFY_REQUIRE_BROWSER=1 but no Chromium on PATH "
                        "(Debian: apt-get install chromium)")
        pytest.skip("no Chromium on PATH (Debian: apt-get install chromium); "
                    "set TWINFALSIFY_REQUIRE_BROWSER=1 to fail instead")
    return path


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    require_mkdocs()
    return built_once(tmp_path_factory, "docs-site", build_site)


@pytest.mark.parametrize("page", sorted(PAGES))
def test_formulas_render_in_a_browser(page, browser, site, tmp_path):
    expected = formulas_in_markdown((DOCS / page).read_text())
    assert expected >= PAGES[page], f"{page} has {expected} formulas, fewer than {PAGES[page]}"
    html = site / page.removesuffix(".md") / "index.html"
    assert html.is_file(), html
    dom = _dump_dom(browser, html, tmp_path / "profile")
    problems = problems_in_rendered_page(dom, expected)
    assert not problems, f"{page}:\n" + "\n".join(problems[:20])


def test_every_page_with_formulas_is_checked():
    """A page that gains formulas must join PAGES, so its rendering is read too."""
    with_maths = {p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*.md")
                  if formulas_in_markdown(p.read_text()) > 0}  # fmt: skip
    assert with_maths <= set(PAGES), f"pages with formulas not in PAGES: {with_maths - set(PAGES)}"


# The checker itself, on small pages: it must catch each kind of failure.

_GOOD = ('<p>a <span class="arithmatex"><span class="katex"><math><annotation>\\frac{1}{2}'
         '</annotation></math></span></span> b</p>')


def test_the_source_count_skips_code_and_counts_both_kinds():
    md = ("Inline $a_1$ and $b^*$, a price of 5 $ or $ 6.\n\n$$\n\\frac{1}{2}\n$$\n\n"
          "`$HOME` and\n\n```sh\necho $x$\n```\n")
    assert formulas_in_markdown(md) == 3


def test_the_checker_accepts_typeset_maths():
    assert problems_in_rendered_page(_GOOD, 1) == []


@pytest.mark.parametrize(
    "dom, what",
    [
        ('<p>p = 2 j*/B where $\\theta^*_{(j)}$ holds</p>', "raw TeX"),
        ('<p><span class="arithmatex">\\(\\hat n\\)</span></p>', "not typeset"),
        ('<p><span class="arithmatex"><span class="katex-error" title="Undefined control '
         'sequence">\\foo</span></span></p>', "KaTeX error"),
        ("<p>the bound \\sqrt{n} in plain text</p>", "raw TeX"),
        (_GOOD.replace("arithmatex", "x"), "the Markdown source has 1"),
        ('<script src="https://cdn.example.org/katex.min.js"></script>' + _GOOD,
         "another host"),
    ],
)
def test_the_checker_catches_broken_maths(dom, what):
    problems = problems_in_rendered_page(dom, 1)
    assert any(what in p for p in problems), problems
