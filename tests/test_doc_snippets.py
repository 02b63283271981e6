"""Every code block of README.md and docs/ runs as written (python), or says why it does not.

The blocks of one page run in order in one namespace, as a reader would type them.  The pages'
own claims (convergence, shapes, agreements) are checked by the page-specific tests
(tests/test_readme*.py); this test makes sure nothing in the documentation is left unrun.
"""

from __future__ import annotations

import pytest

from .readme_snippets import ROOT, doc_blocks, doc_pages, page_namespace

PAGES = doc_pages()


def _param(page):
    blocks = doc_blocks(page.read_text())
    marks = [pytest.mark.slow] if any(b.marker == "slow" for b in blocks) else []
    return pytest.param(page, id=page.relative_to(ROOT).as_posix(), marks=marks)


def test_every_page_found():
    names = {p.relative_to(ROOT).as_posix() for p in PAGES}
    assert {"README.md", "docs/index.md", "docs/tutorial.md", "docs/concepts.md"} <= names


@pytest.mark.parametrize("page", [_param(p) for p in PAGES])
def test_every_block_runs_or_states_why_not(page):
    blocks = doc_blocks(page.read_text())
    for b in blocks:
        if b.lang != "python" or b.marker == "skip":
            assert b.marker == "skip" and b.reason, f"{page.name}:{b.line}: a ```{b.lang} block needs '<!-- snippet: skip (reason) -->'"
    page_namespace(page.relative_to(ROOT).as_posix())


def test_markers_are_parsed():
    text = "x\n<!-- snippet: skip (needs data) -->\n```python\n1/0\n```\n\n```bash\nls\n```\n"
    a, b = doc_blocks(text)
    assert (a.lang, a.marker, a.reason, a.line) == ("python", "skip", "needs data", 3)
    assert (b.lang, b.marker) == ("bash", None)
